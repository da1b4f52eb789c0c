"""The CPU kernels pinned alike on every x86-64-v3 host (``cropcraft_core.kernels``), in real
child interpreters: what a process that imports the flows first runs, what its spawned workers
run, and that what the pin leaves to the host (numba's target CPU, OpenCV's and IPP's SIMD
dispatch) does not move a fit by a bit."""

from __future__ import annotations

import json
import os
import platform
import subprocess
import sys

import pytest

from cropcraft_core.kernels import PORTABLE, SWITCH, host_is_x86_v3, portable_environ

X86 = platform.machine().lower() in ("x86_64", "amd64")
V3_FLAGS = "fpu sse sse2 ssse3 sse4_1 sse4_2 avx avx2 fma bmi1 bmi2 f16c movbe abm xsave"

needs_v3 = pytest.mark.skipif(not host_is_x86_v3(), reason="needs an x86-64-v3 CPU (AVX2, FMA)")


def _cpuinfo(tmp_path, name: str, flags: str):
    p = tmp_path / name
    p.write_text(f"processor\t: 0\nvendor_id\t: AuthenticAMD\nflags\t\t: {flags}\n\n")
    return str(p)


def test_the_portable_kernels_are_added_on_a_v3_host_unless_the_user_chose(tmp_path):
    v3 = _cpuinfo(tmp_path, "v3", V3_FLAGS)
    old = _cpuinfo(tmp_path, "old", "fpu sse sse2 ssse3 sse4_1 sse4_2 avx xsave")  # no AVX2
    if X86:
        assert portable_environ({}, v3) == PORTABLE
        assert PORTABLE == {
            "NPY_DISABLE_CPU_FEATURES": "X86_V4 AVX512_ICL AVX512_SPR",
            "OPENBLAS_CORETYPE": "Haswell",
        }
        # a user's own value wins; the other variable is still added
        assert portable_environ({"OPENBLAS_CORETYPE": "Zen"}, v3) == {
            "NPY_DISABLE_CPU_FEATURES": "X86_V4 AVX512_ICL AVX512_SPR"
        }
        assert portable_environ({SWITCH: " Native "}, v3) == {}
        assert portable_environ({SWITCH: "portable"}, v3) == PORTABLE
    else:
        assert portable_environ({}, v3) == {}
    # a CPU without AVX2 (the Haswell kernels would not run), or no cpuinfo: nothing is set
    assert portable_environ({}, old) == {}
    assert portable_environ({}, str(tmp_path / "missing")) == {}


def _child(code: str, **env: str):
    """What ``code`` prints (JSON) in a fresh interpreter whose environment holds none of the
    pinned variables, plus ``env``."""
    base = {k: v for k, v in os.environ.items() if k not in PORTABLE and k != SWITCH}
    out = subprocess.run(
        [sys.executable, "-c", code],
        env={**base, **env},
        capture_output=True,
        text=True,
        check=True,
        timeout=600,
    )
    return json.loads(out.stdout.strip().splitlines()[-1])


PINNED = {"numpy-simd": "X86_V3", "openblas-core": "Haswell"}


@needs_v3
def test_a_process_that_imports_the_flows_first_and_its_workers_run_the_portable_kernels():
    """The CLI's process and the spawned workers that fit its seeds read X86_V3 and Haswell in
    their stage records (a deployment's flow run gets the same from ``deploy/prefect.yaml``);
    a process whose numpy was loaded before the flows (a notebook) keeps its own kernels and
    hands none to its workers, so that the two agree; ``CROPCRAFT_KERNELS=native`` keeps the
    host's."""
    code = (
        "import flows, json\n"
        "from cropcraft_core.parallel import pool\n"
        "from cropcraft_core.store import numeric_kernels\n"
        "ex = pool(2)\n"
        "w = ex.submit(numeric_kernels).result()\n"
        "ex.shutdown()\n"
        "print(json.dumps([numeric_kernels(), w]))\n"
    )
    main, worker = _child(code)
    assert main == worker == PINNED
    set_vars = "import json, os; print(json.dumps([os.environ.get(k) for k in {!r}]))"
    names = sorted(PORTABLE)
    assert _child("import numpy, flows; " + set_vars.format(names)) == [None, None]
    assert _child("import flows; " + set_vars.format(names), **{SWITCH: "native"}) == [None, None]
    assert _child("import flows; " + set_vars.format(names)) == [PORTABLE[k] for k in names]


FIT = """
import flows, json
from cropcraft_core.config import default_layout
from cropcraft_core.fit import FitConfig, fit_seed, observe_canopy
from cropcraft_core.observe import preset
from cropcraft_core.procedural import generate_canopy
from cropcraft_core.store import numeric_kernels
truth = {"leaf_length": 1.2, "petiole_length": 1.0, "petiole_angle": 2.0,
         "internode_length": 1.2, "num_nodes": 8.0}
canopy = generate_canopy("soybean", truth, default_layout("soybean"), seed=11)
obs = observe_canopy(canopy, preset("soybean", image_width=248, image_height=184))
res = fit_seed(obs, 0, FitConfig(n_evals=40, n_initial=20))
print(json.dumps({"y": [float(v).hex() for v in res.y], "kernels": numeric_kernels()}))
"""


@needs_v3
def test_under_the_pin_what_numba_and_opencv_compile_for_does_not_move_a_fit():
    """The pin fixes numpy's and OpenBLAS's kernels; numba (which compiles for the host's CPU)
    and OpenCV with IPP (which dispatch by it) are left to the host. One soybean seed (20
    random and 20 GP evaluations) fitted here, and again with numba compiling for a Haswell
    and OpenCV and IPP held to AVX2 — what a machine without AVX-512 runs — gives every loss to
    the bit: the project's numba kernels use no fastmath, so LLVM may not reorder or fuse their
    arithmetic for a wider CPU."""
    here = _child(FIT)
    avx2_host = _child(
        FIT,
        NUMBA_CPU_NAME="haswell",
        NUMBA_CPU_FEATURES="",
        OPENCV_CPU_DISABLE="AVX512-SKX",
        OPENCV_IPP="avx2",
    )
    assert here["kernels"] == avx2_host["kernels"] == PINNED
    assert len(here["y"]) == 40
    assert here["y"] == avx2_host["y"]
