"""Test ordering for the two xdist workers (pyproject's addopts: ``-n 2 --dist loadfile``).

Each test file goes whole to one worker, in collection order, so the file that takes longest
(``test_flows.py``: the scene flow and its reruns, ~9 of the run's ~15 minutes) is collected
first and starts at once on one worker while the other works through the rest.
"""

from __future__ import annotations

# The test processes pin their CPU kernels as the CLI does (before anything
# loads numpy: cropcraft_core.kernels), whichever test file a worker happens to import first.
import flows  # noqa: F401

#: Files started first, longest first (measured with ``--durations=0``, session 57).
FIRST = ("test_flows.py", "test_fit.py")


def pytest_collection_modifyitems(items) -> None:
    rank = {name: i for i, name in enumerate(FIRST)}
    items.sort(key=lambda item: rank.get(item.path.name, len(FIRST)))  # stable: keeps the rest
