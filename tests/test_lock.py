"""The dependency lock (``deploy/constraints.txt``): it satisfies pyproject.toml, pins every
library the numbers are computed with, is what the installers install from, and is what this
environment runs (the fit's answer moves with the numeric libraries: RESULTS.md#demo)."""

from __future__ import annotations

import re
import tomllib
from importlib import metadata
from pathlib import Path

import pytest
from packaging.requirements import Requirement
from packaging.utils import canonicalize_name
from packaging.version import Version

from cropcraft_core.store import NUMERIC_PACKAGES

ROOT = Path(__file__).resolve().parent.parent
LOCK = ROOT / "deploy" / "constraints.txt"


def _lock() -> dict[str, Version]:
    pins: dict[str, Version] = {}
    for n, line in enumerate(LOCK.read_text().splitlines(), 1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        m = re.fullmatch(r"([A-Za-z0-9][A-Za-z0-9._-]*)==([^\s;]+)", line)
        assert m, f"{LOCK.name} line {n}: {line!r} is not an exact 'name==version' pin"
        name = canonicalize_name(m[1])
        assert name not in pins, f"{LOCK.name} line {n}: {m[1]} pinned twice"
        pins[name] = Version(m[2])
    return pins


def _declared() -> list[Requirement]:
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    reqs = list(project["dependencies"])
    for extra in project.get("optional-dependencies", {}).values():
        reqs += extra
    return [Requirement(r) for r in reqs]


def test_lock_pins_every_declared_dependency_within_its_range():
    pins = _lock()
    for req in _declared():
        name = canonicalize_name(req.name)
        assert name in pins, f"{req.name} is in pyproject.toml but not in {LOCK.name}"
        assert req.specifier.contains(pins[name], prereleases=True), (
            f"{LOCK.name} pins {req.name}=={pins[name]}, outside pyproject.toml's {req}"
        )
    assert pins[canonicalize_name("torch")] == Version("2.13.0")  # the CPU build's pin
    assert not pins[canonicalize_name("torch")].local  # matches the index's +cpu build


def test_lock_pins_the_numeric_libraries():
    pins = _lock()
    for names in NUMERIC_PACKAGES:
        assert any(canonicalize_name(n) in pins for n in names), f"{names[0]} is not pinned"


@pytest.mark.parametrize("path", ["deploy/install.sh", "docker/Dockerfile.cpu"])
def test_installers_install_from_the_lock(path):
    text = (ROOT / path).read_text()
    assert re.search(r"pip install[^\n]*-c deploy/constraints\.txt", text), path


def test_this_environment_runs_the_locked_numeric_libraries():
    """The tests (and every figure in README's table) are of the locked versions; a machine
    whose numeric libraries drifted computes other answers: `bash deploy/install.sh` syncs."""
    pins = _lock()
    for names in NUMERIC_PACKAGES:
        for name in names:
            key = canonicalize_name(name)
            if key not in pins:
                continue
            try:
                have = Version(metadata.version(name))
            except metadata.PackageNotFoundError:
                continue
            assert have.public == pins[key].public, (
                f"{name} {have} is installed but {LOCK.name} pins {pins[key]}: run "
                "`bash deploy/install.sh --dev` to install the locked versions"
            )
