"""Atomic file replacement with the permissions an ordinary ``open`` would give.

Files that readers must always find whole (``recording.json``, ``result.json``, ``particles.npz``, a
``frames.csv`` rewritten in place) are written to a temporary file in the same directory and moved over the
target with ``os.replace``. ``tempfile.mkstemp`` creates that file with mode 0600 whatever the umask, so the
replaced file would be unreadable to other users (a Dask worker or a colleague reading a shared disk);
:func:`atomic_write` gives it ``0666 & ~umask``, as ``open(path, "w")`` does.
"""

from __future__ import annotations

import os
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import IO


def _process_umask() -> int:
    # os.umask can only be read by setting it; done once, at import, before any worker thread runs
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


_UMASK = _process_umask()
#: Mode of a file created by ``open(path, "w")`` under this process's umask.
FILE_MODE = 0o666 & ~_UMASK


@contextmanager
def atomic_write(path: Path, binary: bool = False) -> Iterator[IO]:
    """Open a temporary file beside ``path`` for writing; on a clean exit it replaces ``path``.

    The file gets :data:`FILE_MODE`. On an exception the temporary file is removed and ``path`` is left as it was.
    Text mode is UTF-8 with ``newline=""`` (the caller chooses the line ends).
    """
    path = Path(path)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        os.fchmod(fd, FILE_MODE)
        with (os.fdopen(fd, "wb") if binary else os.fdopen(fd, "w", encoding="utf-8", newline="")) as fh:
            yield fh
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
