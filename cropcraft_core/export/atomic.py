"""Crash-safe file writing.

Every exporter writes into a temporary file in the destination directory and ``os.replace``-s it
onto the final name only once the whole file is written and flushed, so a crash, an exception or a
full disk never leaves a truncated file under the final name: readers see either the previous file
or the complete new one. The temporary file lives in the same directory because ``os.replace`` is
atomic only within one file system.

Failures of the output location (the directory cannot be created, is not writable, the target is a
directory, the disk is full) raise ``OutputError`` naming the path.
"""

from __future__ import annotations

import os
import tempfile
from collections.abc import Iterable, Iterator
from contextlib import contextmanager
from pathlib import Path

from cropcraft_core.errors import CropCraftError, OutputError

__all__ = ["atomic_path", "atomic_write_bytes", "atomic_write_text", "publish"]


def _current_umask() -> int:
    """The process umask (``mkstemp`` creates 0600 files; finished files get the usual mode)."""
    try:
        with open("/proc/self/status", encoding="ascii") as f:
            for line in f:
                if line.startswith("Umask:"):
                    return int(line.split()[1], 8)
    except (OSError, ValueError, IndexError):
        pass
    mask = os.umask(0o022)  # not thread-safe, hence only the fallback
    os.umask(mask)
    return mask


_FILE_MODE = 0o666 & ~_current_umask()

#: Characters of the final name's stem kept in its temporary's name (file names end at 255).
_STEM_CHARS = 64


def _prepare_dir(path: Path) -> Path:
    parent = path.parent
    try:
        parent.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise OutputError(
            f"cannot write {path}: its directory {parent} cannot be created ({e.strerror or e})"
        ) from e
    if not parent.is_dir():
        raise OutputError(f"cannot write {path}: {parent} is not a directory")
    if path.is_dir():
        raise OutputError(f"cannot write {path}: a directory of that name exists")
    return parent


def _fsync(path: Path) -> None:
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


@contextmanager
def atomic_path(path: str | os.PathLike[str], *, fsync: bool = True) -> Iterator[Path]:
    """Yield a temporary path next to ``path``; on success move it onto ``path`` atomically.

    The temporary name keeps the suffix of ``path`` (``.canopy-<random>.tmp.ply`` for
    ``canopy.ply``; a long stem cut to 64 characters), so libraries that pick a format from
    the extension work on it. If the body raises, the temporary file is removed, ``path`` is
    left as it was and the exception propagates; an ``OSError`` from the body (disk full, ...)
    is re-raised as ``OutputError`` naming ``path``. With ``fsync`` the data is flushed to
    disk before the rename.
    """
    final = Path(path)
    parent = _prepare_dir(final)
    try:
        fd, tmp_name = tempfile.mkstemp(  # the stem cut short: a 250-character name still fits
            prefix=f".{final.stem[:_STEM_CHARS]}-", suffix=f".tmp{final.suffix}", dir=parent
        )
    except OSError as e:
        raise OutputError(f"cannot write {final}: directory {parent} is not writable ({e})") from e
    os.close(fd)
    tmp = Path(tmp_name)
    try:
        try:
            yield tmp
            if fsync:
                _fsync(tmp)
            os.chmod(tmp, _FILE_MODE)
            os.replace(tmp, final)
        except CropCraftError:
            raise
        except OSError as e:
            raise OutputError(f"cannot write {final}: {e}") from e
    except BaseException:
        try:
            tmp.unlink(missing_ok=True)
        except OSError:
            pass
        raise


def publish(
    staged: str | os.PathLike[str], out: str | os.PathLike[str], names: Iterable[str]
) -> None:
    """Move the entries ``names`` (files or folders) of the complete folder ``staged`` into
    ``out`` as one set: each replaces the entry of its name whole, and a failure part-way puts
    every previous entry back, so ``out`` never holds some files of one run beside others of
    the run before. Names missing from ``staged`` are skipped.

    ``staged`` must be on ``out``'s file system (a temporary folder inside it): the previous
    entries are parked in it and leave with it. Nothing moves, and OutputError names the entry,
    where a folder would replace a file or a file a folder (someone's own folder of that name).
    """
    staged, out = Path(staged), Path(out)
    todo = [n for n in dict.fromkeys(names) if (staged / n).exists()]
    for name in todo:
        dst = out / name
        if os.path.lexists(dst) and (staged / name).is_dir() != dst.is_dir():
            kind = "folder" if dst.is_dir() else "file"
            raise OutputError(f"cannot write {dst}: a {kind} of that name is in the way")
    parked = Path(tempfile.mkdtemp(dir=staged, prefix=".previous-"))
    moved: list[str] = []
    kept: list[str] = []
    try:
        for name in todo:
            if os.path.lexists(out / name):
                os.replace(out / name, parked / name)
                kept.append(name)
            os.replace(staged / name, out / name)
            moved.append(name)
    except OSError as e:
        for name in reversed(moved):  # undo: the new entries back, the previous ones in place
            try:
                os.replace(out / name, staged / name)
            except OSError:
                pass
        for name in kept:
            try:
                os.replace(parked / name, out / name)
            except OSError:
                pass
        raise OutputError(f"cannot write {out}: {e}") from None


def atomic_write_bytes(path: str | os.PathLike[str], data: bytes | bytearray | memoryview) -> Path:
    """Write ``data`` to ``path`` atomically (see ``atomic_path``); return the final path."""
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            f.write(data)
    return Path(path)


def atomic_write_text(path: str | os.PathLike[str], text: str, encoding: str = "utf-8") -> Path:
    """Write ``text`` to ``path`` atomically with ``encoding`` and ``\\n`` line ends."""
    return atomic_write_bytes(path, text.encode(encoding))
