"""A window's hypotheses as rows: subsets, write-backs, resampling, copies, shared books (:mod:`pinpoint_fg.window`).

Every per-hypothesis array of a :class:`~pinpoint_fg.window.Window` — poses, window prior, evidence,
the oldest-pose terms' memo (:mod:`pinpoint_fg.window_memo`) and the older part's anchored model
(:mod:`pinpoint_fg.relinearize`) — follows its hypothesis here, so a tracker that copies, drops or
polishes hypotheses never re-evaluates the ones that did not change.
"""

from __future__ import annotations

import copy
from typing import Protocol, TypeVar

import numpy as np

from factors import residuals as res
from pinpoint_fg.elimination import whiten_prior
from pinpoint_fg.relinearize import ChainAnchor
from pinpoint_fg.window_memo import OldestTermsMemo


class Rows(Protocol):
    """What these functions use of a :class:`~pinpoint_fg.window.Window` (its per-hypothesis state)."""

    poses: np.ndarray | None
    prior_mean: np.ndarray | None
    prior_W: np.ndarray | None
    evidence: np.ndarray | None
    kin: object
    frames: list
    deltas: list
    delta_W: list
    _memo: OldestTermsMemo
    _anchor: ChainAnchor

    def _prior_key(self, T: np.ndarray) -> tuple: ...


Window = TypeVar("Window", bound=Rows)


def subset(window: Window, index: np.ndarray | list[int]) -> Window:
    """A window over hypotheses ``index`` only: copies of their poses, priors and evidence, the same frames.

    Work on a few hypotheses (polishing the MAP, trial poses) then costs what those few cost,
    not what all N cost; write the result back with ``poses[:, index] = sub.poses``.
    """
    assert window.poses is not None and window.prior_mean is not None and window.prior_W is not None
    index = np.asarray(index)
    sub = copy.copy(window)
    sub.poses = window.poses[:, index].copy()
    sub.prior_mean = window.prior_mean[index].copy()
    sub.prior_W = window.prior_W[index].copy()
    sub.evidence = None if window.evidence is None else window.evidence[index].copy()
    sub.kin = None if window.kin is None else window.kin.rows(index)
    sub.frames, sub.deltas, sub.delta_W = list(window.frames), list(window.deltas), list(window.delta_W)
    sub._memo = OldestTermsMemo()
    sub._anchor = window._anchor.subset(index)
    return sub


def adopt(window: Window, sub: Window, index: np.ndarray | list[int]) -> None:
    """Write a :func:`subset`'s poses back to hypotheses ``index``, keeping the prior-term memo valid.

    The memo of the oldest frame's terms (all hypotheses) gets the subset's rows where the
    subset holds them for its current poses, so the next marginalisation need not
    re-evaluate the hypotheses that did not move (equal to a fresh evaluation to round-off:
    the subset's rows were computed in a smaller batch).
    """
    assert window.poses is not None and sub.poses is not None
    index = np.asarray(index)
    valid = window._memo.holds(window._prior_key(window.poses[0])) and sub._memo.holds(sub._prior_key(sub.poses[0]))
    window.poses[:, index] = sub.poses
    window._anchor.copy_rows(index, sub._anchor, np.arange(index.shape[0]))
    if not valid:
        window._memo.clear()
        return
    window._memo.with_rows(window._prior_key(window.poses[0]), sub._memo.entry[1], index)


def resample(window: Window, index: np.ndarray) -> None:
    """Keep hypotheses ``index`` (N',): poses and priors follow (used by re-seeding and the PF).

    The memo of the oldest frame's terms follows too (its rows are reindexed, as :func:`adopt`
    merges rows), so the next marginalisation need not re-evaluate the kept hypotheses.
    """
    assert window.poses is not None and window.prior_mean is not None and window.prior_W is not None
    valid = window._memo.holds(window._prior_key(window.poses[0]))
    window.poses = window.poses[:, index]
    window.prior_mean = window.prior_mean[index]
    window.prior_W = window.prior_W[index]
    if window.evidence is not None:
        window.evidence = window.evidence[index]
    if window.kin is not None:
        window.kin = window.kin.rows(index)
    window._anchor = window._anchor.subset(index)
    if valid:
        window._memo.reindexed(window._prior_key(window.poses[0]), index)
    else:
        window._memo.clear()


def copy_hypotheses(window: Window, index: np.ndarray | list[int], source: Window,
                    source_index: np.ndarray | list[int]) -> None:
    """Hypotheses ``index`` of ``window`` become copies of ``source``'s ``source_index``: poses, prior, evidence.

    ``source`` shares the window's frames (the window itself, or a :meth:`Window.subset` of it).
    """
    assert window.poses is not None and source.poses is not None and window.evidence is not None
    index, source_index = np.asarray(index), np.asarray(source_index)
    window.poses[:, index] = source.poses[:, source_index]
    window.prior_mean[index] = source.prior_mean[source_index]
    window.prior_W[index] = source.prior_W[source_index]
    window.evidence[index] = source.evidence[source_index]
    if window.kin is not None and source.kin is not None:
        window.kin.set_rows(index, source.kin, source_index)
    window._memo.clear()
    window._anchor.copy_rows(index, source._anchor, source_index)


def share_books(window: Window, index: np.ndarray | list[int], source_index: np.ndarray | list[int]) -> None:
    """Hypotheses ``index`` take the window prior and evidence of ``source_index``, keeping their own poses.

    The books of one mode (:func:`pinpoint_fg.trackers.svn_modes.book_sources`). The memo of the
    oldest frame's terms stays valid: only the prior's share of the changed rows is re-evaluated
    (equal to a fresh evaluation to round-off).
    """
    assert window.poses is not None and window.evidence is not None
    index, source_index = np.asarray(index, dtype=int), np.asarray(source_index, dtype=int)
    if index.size == 0:
        return
    valid = window._memo.holds(window._prior_key(window.poses[0]))
    T0 = window.poses[0, index]
    old_prior = (window.prior_mean[index], window.prior_W[index])
    # the old prior's share, to patch the memo (at L = 1 right after a push no memo holds: nothing to patch)
    old = whiten_prior(*res.pose_prior_residual(T0, old_prior[0]), old_prior[1]) if valid else None
    window.prior_mean[index] = window.prior_mean[source_index]
    window.prior_W[index] = window.prior_W[source_index]
    window.evidence[index] = window.evidence[source_index]
    if window.kin is not None:
        window.kin.set_rows(index, window.kin, source_index)
    # the older part's anchored model holds the prior: its share is swapped, the frames' terms are kept
    new_prior = (window.prior_mean[index], window.prior_W[index])
    window._anchor.replace_prior(window.frames[:-1], index, old_prior, new_prior)
    if not valid:
        window._memo.clear()
        return
    new = whiten_prior(*res.pose_prior_residual(T0, window.prior_mean[index]), window.prior_W[index])
    patched = tuple(a + (n - o) for a, n, o in zip(window._memo.rows(index), new, old, strict=True))
    window._memo.with_rows(window._prior_key(window.poses[0]), patched, index)
