"""Per-plant random streams that do not depend on which part of the field is generated.

Every plant is addressed by its (row, slot) position on the planting grid. Its random numbers come
from an explicit ``numpy.random.Generator`` (PCG64) seeded by ``SeedSequence([seed, row])`` and
advanced to the plant's slot, so

* the same seed gives the same plant wherever the generated region starts or ends (the plot's
  plants are identical in a small view-culled canopy and in a large one built for gap fractions);
* the number of draws per plant is fixed (``n``), never dependent on the parameters, so two
  canopies with different parameters and the same seed share their random numbers (common random
  numbers, which the optimiser relies on).
"""

from __future__ import annotations

import numpy as np

_SLOT_OFFSET = 1 << 24  # slots may be negative: shift them into the non-negative range
_ROW_OFFSET = 1 << 20


def plant_uniforms(seed: int, row: int, first_slot: int, n_plants: int, n: int) -> np.ndarray:
    """(n_plants, n) float64 uniforms in (0, 1) for plants ``first_slot .. first_slot+n_plants-1``
    of ``row``."""
    if n_plants <= 0:
        return np.zeros((0, n))
    bitgen = np.random.PCG64(np.random.SeedSequence([int(seed) & 0xFFFFFFFF, row + _ROW_OFFSET]))
    bitgen.advance((first_slot + _SLOT_OFFSET) * n)
    u = np.random.Generator(bitgen).random((n_plants, n))
    # keep away from exactly 0 so that inverse CDFs stay finite
    return np.clip(u, 1e-12, 1 - 1e-12)


def normals_from_uniforms(u: np.ndarray) -> np.ndarray:
    """Standard normal deviates from uniforms by the inverse CDF (one uniform each)."""
    from scipy.special import ndtri

    return ndtri(u)
