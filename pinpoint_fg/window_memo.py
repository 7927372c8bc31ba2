"""The last evaluation of a window's oldest-pose terms, kept across calls (:mod:`pinpoint_fg.window`).

The oldest pose of every hypothesis carries its frame's measurement terms plus the window prior.
Those terms are evaluated by the linearisation, by the safeguard's trial poses and again by the
marginalisation when the window slides; :class:`OldestTermsMemo` keeps the last result, keyed on
the exact values (bytes) of the poses and of the prior, so a repeated evaluation is free and
bitwise identical. When hypotheses are copied, re-indexed or take another prior, their rows are
updated in place of a re-evaluation (equal to a fresh one to round-off; tested in
``tests/test_window.py``).
"""

from __future__ import annotations

import numpy as np

#: The memoised arrays: value (N,), gradient (N, 6), information (N, 6, 6).
Terms = tuple[np.ndarray, np.ndarray, np.ndarray]


def _read_only(arrays: tuple[np.ndarray, ...]) -> tuple[np.ndarray, ...]:
    for a in arrays:
        a.flags.writeable = False
    return arrays


class OldestTermsMemo:
    """The oldest pose's terms (frame + prior) at the poses of the last evaluation (module docstring)."""

    def __init__(self) -> None:
        self.entry: tuple[tuple, Terms] | None = None

    @staticmethod
    def key(frame: object, T: np.ndarray, prior_mean: np.ndarray, prior_W: np.ndarray) -> tuple:
        """The memo key: the frame object and the exact values of the poses and the prior."""
        return (frame, np.ascontiguousarray(T).tobytes(), prior_mean.tobytes(), prior_W.tobytes())

    def get(self, key: tuple) -> Terms | None:
        """The memoised terms when they were evaluated for ``key``, else None."""
        return self.entry[1] if self.entry is not None and self.entry[0] == key else None

    def holds(self, key: tuple) -> bool:
        """Whether the memo is for ``key``."""
        return self.entry is not None and self.entry[0] == key

    def put(self, key: tuple, terms: Terms) -> Terms:
        """Keep ``terms`` (made read-only) for ``key``; returns them."""
        self.entry = (key, _read_only(terms))
        return terms

    def clear(self) -> None:
        """Forget the memo."""
        self.entry = None

    def with_rows(self, key: tuple, part: Terms, index: np.ndarray) -> None:
        """Rows ``index`` replaced by ``part`` (read-only copies), now valid for ``key``."""
        assert self.entry is not None
        merged = []
        for full, p in zip(self.entry[1], part, strict=True):
            a = full.copy()
            a[index] = p
            merged.append(a)
        self.entry = (key, _read_only(tuple(merged)))

    def reindexed(self, key: tuple, index: np.ndarray) -> None:
        """Rows ``index`` only (copies), now valid for ``key``."""
        assert self.entry is not None
        self.entry = (key, _read_only(tuple(a[index] for a in self.entry[1])))

    def rows(self, index: np.ndarray) -> Terms:
        """Copies of rows ``index``."""
        assert self.entry is not None
        return tuple(a[index] for a in self.entry[1])
