"""CropCraft core library: procedural crop canopies, rendering, fitting and metrics.

Pure Python/numpy (with numba kernels); it imports neither Prefect nor the CLI, so every function
here can be called from a notebook, a test, a Prefect task or a Dask worker alike.
"""

__version__ = "0.1.0"

import os as _os

# numba's parallel kernels (rasteriser, histograms) may be called from several threads at once
# (Prefect's thread runner, Dask workers); the OpenMP layer is thread-safe, and the TBB shipped
# on Debian 12 is too old for numba (it warns and falls back anyway).
_os.environ.setdefault("NUMBA_THREADING_LAYER", "omp")
