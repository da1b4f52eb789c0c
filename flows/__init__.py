"""The CropCraft flows and their command line.

Importing this package first pins the CPU kernels that numpy and OpenBLAS run to the same ones
on every x86-64-v3 host (``cropcraft_core.kernels``), before anything loads numpy: the CLI and
the processes it spawns then compute a scene's answer to the same bits on any such machine (a
Prefect worker's flow runs get the same variables from ``deploy/prefect.yaml``).
``CROPCRAFT_KERNELS=native`` keeps each host's own choice.
"""

from cropcraft_core.kernels import pin as _pin

_pin()
