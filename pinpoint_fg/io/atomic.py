"""Atomic file replacement with the permissions an ordinary ``open`` would give.

Files that readers must always find whole (``recording.json``, ``result.json``, ``particles.npz``, a
``frames.csv`` rewritten in place) are written to a temporary file in the same directory and moved over the
target with ``os.replace``. ``tempfile.mkstemp`` creates that file with mode 0600 whatever the umask, so the
replaced file was unreadable to other users (a Dask worker or a colleague reading a shared disk).
:func:`atomic_write` creates it as ``open(path, "w")`` creates a file, with ``os.open(..., 0o666)``: the kernel
applies the umask (and a directory's default ACL), with no chmod that a file system might refuse and no
process-wide umask read. When the target exists its mode is kept, as ``open(path, "w")`` keeps it (best effort:
a file system without modes keeps its own).
"""

from __future__ import annotations

import os
import secrets
import stat
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import IO

_FLAGS = os.O_WRONLY | os.O_CREAT | os.O_EXCL | getattr(os, "O_CLOEXEC", 0) | getattr(os, "O_BINARY", 0)


def _create_beside(path: Path) -> tuple[int, Path]:
    """A new file ``.NAME.<random>.tmp`` beside ``path``, opened for writing: ``(descriptor, its path)``."""
    while True:
        tmp = path.parent / f".{path.name}.{secrets.token_hex(6)}.tmp"
        try:
            return os.open(tmp, _FLAGS, 0o666), tmp
        except FileExistsError:  # another writer's temporary file: draw another name
            continue


@contextmanager
def atomic_write(path: Path, binary: bool = False) -> Iterator[IO]:
    """Open a temporary file beside ``path`` for writing; on a clean exit it replaces ``path``.

    Permissions as ``open(path, "w")`` would leave them (module docstring). On an exception the temporary file is
    removed and ``path`` is left as it was. Text mode is UTF-8 with ``newline=""`` (the caller chooses the line ends).
    """
    path = Path(path)
    try:
        kept = stat.S_IMODE(path.stat().st_mode) if path.is_file() else None
    except OSError:
        kept = None
    fd, tmp = _create_beside(path)
    try:
        fh = os.fdopen(fd, "wb") if binary else os.fdopen(fd, "w", encoding="utf-8", newline="")
    except BaseException:
        os.close(fd)
        tmp.unlink(missing_ok=True)
        raise
    try:
        with fh:
            if kept is not None and hasattr(os, "fchmod"):
                try:
                    os.fchmod(fh.fileno(), kept)
                except OSError:
                    pass  # a file system without modes (vfat): the write matters, not the mode
            yield fh
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
