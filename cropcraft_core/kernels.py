"""The CPU kernels numpy and OpenBLAS run, pinned alike on every x86-64 host with AVX2.

numpy and OpenBLAS choose their kernels by the CPU they find: numpy its widest SIMD loops
(AVX-512 where the CPU has it), OpenBLAS a core type (SkylakeX, Haswell, Zen, ...). Different
kernels round differently in the last bits, and the fit's optimiser is chaotic in its input, so
with the same code and the same locked libraries the demo's LAI read −1.8 %, +19.6 % and
+16.2 % on three machines, and a season processed on a mixed pool would mix such draws.

:func:`pin` therefore adds the two environment variables that make every host with AVX2 and
FMA (x86-64-v3: Intel since 2013, AMD since 2015) choose the same kernels: numpy's dispatch
capped at ``X86_V3`` and OpenBLAS's Haswell kernels. The libraries read them when they load,
so the pin is made before numpy is imported, by importing ``flows`` (the CLI, the tests); the
processes they spawn (the process pools, Dask's nannies) inherit it. A Prefect worker loads a
deployment's flow file by path, which imports numpy before ``flows``, so ``deploy/prefect.yaml``
gives every deployment the same two variables as job variables, and ``deploy/dask`` gives them
to a cluster's workers. A user's own value of either variable wins; ``CROPCRAFT_KERNELS=native``
keeps each host's own choice.

Measured on one AVX-512 machine (benchmarks/RESULTS.md *#portable-kernels*): each of the two
alone moved a demo seed's losses (numpy's from its first GP step, OpenBLAS's SkylakeX kernels
from its first evaluation), while what numba compiles for (the project's kernels use no
fastmath, so LLVM may neither reorder nor fuse their arithmetic) and OpenCV's and IPP's
dispatch moved none; the whole demo pinned, and again with numba and OpenCV set as a machine
without AVX-512 would run them, gave the same answer to the bit, no slower. Every stage record
names the kernels that ran (``numpy-simd``, ``openblas-core``:
:func:`cropcraft_core.store.numeric_kernels`).
"""

from __future__ import annotations

import os
import platform
import sys
from collections.abc import Mapping

#: The environment variable that turns the pinning off (``native``) or on (anything else).
SWITCH = "CROPCRAFT_KERNELS"

#: numpy's dispatch targets above x86-64-v3 (numpy 2.4's names); disabling them leaves X86_V3.
NUMPY_ABOVE_V3 = ("X86_V4", "AVX512_ICL", "AVX512_SPR")

#: What :func:`pin` sets on an x86-64-v3 host.
PORTABLE: dict[str, str] = {
    "NPY_DISABLE_CPU_FEATURES": " ".join(NUMPY_ABOVE_V3),
    "OPENBLAS_CORETYPE": "Haswell",
}

#: /proc/cpuinfo flags of x86-64-v3 (what numpy's X86_V3 loops and OpenBLAS's Haswell kernels
#: need); ``abm`` is how Linux names LZCNT.
X86_V3_FLAGS = frozenset({"avx", "avx2", "fma", "bmi1", "bmi2", "f16c", "movbe", "abm", "xsave"})


def host_is_x86_v3(cpuinfo: str = "/proc/cpuinfo") -> bool:
    """Whether this machine is x86-64 with every x86-64-v3 feature (read from ``cpuinfo``, so
    without importing numpy); false where that cannot be read."""
    if platform.machine().lower() not in ("x86_64", "amd64"):
        return False
    try:
        with open(cpuinfo, encoding="ascii", errors="replace") as f:
            for line in f:
                if line.startswith("flags"):
                    return X86_V3_FLAGS <= set(line.partition(":")[2].split())
    except OSError:
        return False
    return False


def portable_environ(
    environ: Mapping[str, str] | None = None, cpuinfo: str = "/proc/cpuinfo"
) -> dict[str, str]:
    """What :func:`pin` adds to ``environ`` (``os.environ`` by default): :data:`PORTABLE` on an
    x86-64-v3 host, less the variables ``environ`` sets already (a user's own value wins);
    nothing with ``CROPCRAFT_KERNELS=native`` or on another CPU."""
    environ = os.environ if environ is None else environ
    if environ.get(SWITCH, "").strip().lower() == "native" or not host_is_x86_v3(cpuinfo):
        return {}
    return {k: v for k, v in PORTABLE.items() if k not in environ}


def pin() -> dict[str, str]:
    """Add :func:`portable_environ` to ``os.environ``, if numpy is not loaded yet in this
    process; return the variables it added.

    Only before numpy: the libraries read them when they load, and a process whose numpy
    already runs the host's own kernels must not hand other ones to the workers it spawns (they
    inherit ``os.environ``), or a seed fitted in a worker would differ from the same seed fitted
    in the process. So a process and its workers always run the same kernels; the entry points
    (``flows``, which the CLI imports first) pin them."""
    if "numpy" in sys.modules:
        return {}
    add = portable_environ()
    os.environ.update(add)
    return add


__all__ = ["PORTABLE", "SWITCH", "host_is_x86_v3", "pin", "portable_environ"]
