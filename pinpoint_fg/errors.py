"""The one exception type for bad input: it names the file, the row and the column (and one check shared by the
commands that pool several inputs)."""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path


class InputError(ValueError):
    """Malformed or unusable input, located as precisely as the reader knows.

    The message reads ``FILE: row R: column C: what is wrong`` with the parts that are known (``option '--x'``
    instead of ``column`` when ``column`` names a command-line option).
    """

    def __init__(
        self,
        message: str,
        file: str | Path | None = None,
        row: int | None = None,
        column: str | None = None,
    ) -> None:
        self.file = None if file is None else str(file)
        self.row = row
        self.column = column
        self.reason = message
        parts = []
        if self.file is not None:
            parts.append(self.file)
        if row is not None:
            parts.append(f"row {row}")
        if column is not None:
            shown = repr(column)
            if len(shown) > 80:  # a mangled header can hold a 4000-character name: keep the line readable
                shown = f"{shown[:60]}...{shown[-12:]} ({len(column)} characters)"
            # a command-line option (``column="--workers"``) is not a column of a file
            parts.append(f"{'option' if column.startswith('--') else 'column'} {shown}")
        parts.append(message)
        super().__init__(": ".join(parts))


def refuse_repeated(paths: Sequence[str | Path], what: str) -> None:
    """:class:`InputError` naming the second mention when two of ``paths`` are the same file or directory (after
    resolving symbolic links): pooled twice, its samples or frames would silently weigh double. A path that cannot
    be resolved (a symlink loop) is left to the reader, which names it."""
    seen: dict[Path, Path] = {}
    for p in paths:
        key = Path(os.path.realpath(p))  # not Path.resolve: a symlink loop was its RuntimeError traceback
        if key in seen:
            raise InputError(f"{what} given twice (also as {seen[key]})", file=p)
        seen[key] = Path(p)


def path_argument(name: str, value: object) -> Path:
    """``value`` as a Path, or :class:`InputError` naming the argument ``name``: ``None``, a number or bytes was
    pathlib's "expected str, bytes or os.PathLike object" TypeError, and ``""`` read the current directory."""
    if not isinstance(value, (str, os.PathLike)) or os.fspath(value) in ("", b""):
        shown = "an empty string" if isinstance(value, str) and value == "" else type(value).__name__
        raise InputError(f"{name} must be a path (a non-empty str or os.PathLike), got {shown}")
    return Path(value)


def path_list(name: str, value: object) -> list:
    """``value`` as a list, or :class:`InputError` naming ``name`` when it is one path (a ``str``, bytes or
    ``os.PathLike``) where a list of paths is expected: a str was split into one "path" per character
    (``calibrate_runs("RUN")``: "/: run given twice"), a Path was "'PosixPath' object is not iterable". Each item
    must be a path too (:func:`path_argument`)."""
    if isinstance(value, (str, bytes, os.PathLike)):
        raise InputError(f"{name} must be a list of paths, got the single path {os.fsdecode(value)!r} "
                         f"(write [{os.fsdecode(value)!r}])")
    try:
        items = list(value)  # type: ignore[call-overload]
    except TypeError:  # None or a number: was "'NoneType' object is not iterable", naming no argument
        raise InputError(f"{name} must be a list of paths, got {type(value).__name__}") from None
    for i, item in enumerate(items):  # None inside: pathlib's "expected str, bytes or os.PathLike" TypeError
        path_argument(f"{name}[{i}]", item)
    return items
