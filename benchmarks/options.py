"""Command-line values the benchmarks share, checked when the command line is read: a bad
``--scenes``, ``--budget`` or ``--json`` stops the run before any work with argparse's one-line
message (exit status 2), not after an hour of fitting with a traceback.
"""

from __future__ import annotations

import argparse
import json
import math
import os
from collections.abc import Callable
from pathlib import Path
from typing import Any


def at_least(low: int) -> Callable[[str], int]:
    """An argparse type: a whole number >= ``low``."""

    def parse(text: str) -> int:
        try:
            v = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{text!r} is not a whole number") from None
        if v < low:
            raise argparse.ArgumentTypeError(f"{v} is below {low}")
        return v

    parse.__name__ = f"whole number >= {low}"
    return parse


def positive(text: str) -> float:
    """An argparse type: a finite number > 0."""
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None
    if not (math.isfinite(v) and v > 0):
        raise argparse.ArgumentTypeError(f"{text} is not a finite number > 0")
    return v


def non_negative(text: str) -> float:
    """An argparse type: a finite number >= 0 (a noise's standard deviation)."""
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None
    if not (math.isfinite(v) and v >= 0):
        raise argparse.ArgumentTypeError(f"{text} is not a finite number >= 0")
    return v


def seeds_by_evals(text: str) -> str:
    """An argparse type: ``SEEDSxEVALS`` (e.g. ``10x500``), at least 1 seed of 5 evaluations
    (a fit's random start takes 2/5 of them, at least 5); returned as written, lower case."""
    parts = text.lower().split("x")
    try:
        seeds, evals = (int(p) for p in parts)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not SEEDSxEVALS, e.g. 10x500") from None
    if seeds < 1 or evals < 5:
        raise argparse.ArgumentTypeError(f"{text!r}: need at least 1 seed of 5 evaluations")
    return text.lower()


def output_file(text: str) -> str:
    """An argparse type: a file that can be written once the run ends (its folder exists and
    is writable, and it is no folder itself)."""
    p = Path(text)
    folder = p.parent
    if p.is_dir():
        raise argparse.ArgumentTypeError(f"{text} is a folder")
    if not folder.is_dir():
        raise argparse.ArgumentTypeError(f"{text}: folder {folder} does not exist")
    if not os.access(folder, os.W_OK):
        raise argparse.ArgumentTypeError(f"{text}: folder {folder} is not writable")
    return text


def json_file(text: str) -> str:
    """An argparse type: a JSON file that exists and parses (a missing or malformed ``--load``
    or ``--truth`` ended in a traceback)."""
    p = Path(text)
    if not p.is_file():
        raise argparse.ArgumentTypeError(f"{text}: no such file")
    try:
        json.loads(p.read_text())
    except (OSError, UnicodeDecodeError, ValueError) as e:
        raise argparse.ArgumentTypeError(f"{text}: not a JSON file ({e})") from None
    return text


def folder(text: str) -> str:
    """An argparse type: a folder, or a path one can be made at (not a file: a
    ``--checkpoint-dir`` naming a file failed after the scenes were built)."""
    p = Path(text)
    if p.exists() and not p.is_dir():
        raise argparse.ArgumentTypeError(f"{text} is a file, not a folder")
    parent = next((q for q in p.absolute().parents if q.exists()), None)
    if parent is not None and not p.exists() and not parent.is_dir():
        raise argparse.ArgumentTypeError(f"{text}: {parent} is a file, not a folder")
    return text


def existing_folder(*needs: str) -> Callable[[str], str]:
    """An argparse type: an existing folder holding the files ``needs`` (a scene's
    ``scene.json``, a train half's ``row.json``)."""

    def parse(text: str) -> str:
        p = Path(text)
        if not p.is_dir():
            raise argparse.ArgumentTypeError(f"{text}: no such folder")
        missing = [n for n in needs if not (p / n).is_file()]
        if missing:
            raise argparse.ArgumentTypeError(f"{text}: holds no {missing[0]}")
        return text

    parse.__name__ = "folder"
    return parse


def _json_safe(x: Any) -> Any:
    """``x`` with every non-finite number as None (JSON has no NaN) and numpy values as
    Python's."""
    if isinstance(x, dict):
        return {k: _json_safe(v) for k, v in x.items()}
    if isinstance(x, list | tuple):
        return [_json_safe(v) for v in x]
    if hasattr(x, "tolist") and not isinstance(x, str):  # numpy arrays and scalars
        return _json_safe(x.tolist())
    if isinstance(x, float) and not math.isfinite(x):
        return None
    return x


def write_json(path: str | os.PathLike, data: Any) -> Path:
    """``data`` as strict JSON (NaN and infinities written as null) to ``path``, atomically."""
    from cropcraft_core.export.atomic import atomic_write_text

    text = json.dumps(_json_safe(data), indent=2, default=float, allow_nan=False) + "\n"
    return atomic_write_text(path, text)


def parse_kv(items: list[str]) -> dict:
    """``["a=1", "b=text"]`` → ``{"a": 1, "b": "text"}`` (values are JSON, else strings)."""
    out = {}
    for kv in items:
        k, sep, v = kv.partition("=")
        if not sep or not k:
            raise SystemExit(f"expected KEY=VALUE, got {kv!r}")
        try:
            out[k] = json.loads(v)
        except json.JSONDecodeError:
            out[k] = v
    return out
