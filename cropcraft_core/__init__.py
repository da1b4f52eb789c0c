"""CropCraft core library: procedural crop canopies, rendering, fitting and metrics.

Pure Python/numpy (with numba kernels); it imports neither Prefect nor the CLI, so every function
here can be called from a notebook, a test, a Prefect task or a Dask worker alike.
"""

__version__ = "0.1.0"
