"""The relinearisation threshold (pinpoint_fg/relinearize.py): exact when every moved pose is re-evaluated,
second-order close to the exact linearisation below the threshold, and kept row-consistent by subset,
adopt, resample and copy_hypotheses."""

from __future__ import annotations

import copy

import numpy as np
import pytest

from factors.lie import se3_exp
from pinpoint_fg.likelihood import FrameLikelihood
from pinpoint_fg.relinearize import RELIN_SCALE
from pinpoint_fg.window import DEFAULT_RELIN_THRESHOLD, Window
from pinpoint_fg.window_rows import copy_hypotheses
from tests.test_window import MODEL, _observation, _window


def _with_threshold(w: Window, threshold: float) -> Window:
    """An independent copy of ``w`` (same frames, own poses and anchors) with ``threshold``."""
    c = copy.copy(w)
    c.poses, c.prior_mean, c.prior_W = w.poses.copy(), w.prior_mean.copy(), w.prior_W.copy()
    c.evidence = w.evidence.copy()
    c.frames, c.deltas, c.delta_W = list(w.frames), list(w.deltas), list(w.delta_W)
    c._memo.clear()
    c._anchor = type(w._anchor)()
    c.relin_threshold = threshold
    return c


def _assert_lin_close(a, b, rtol: float) -> None:
    for x, y in ((a.value, b.value), (a.grad, b.grad), (a.hess, b.hess), (a.window_value, b.window_value)):
        np.testing.assert_allclose(x, y, rtol=0, atol=rtol * max(1.0, float(np.max(np.abs(y)))))


def _transport_like(w: Window, rng: np.random.Generator, steps: int, size: float) -> list:
    """Linearise and move the newest poses (older ones by back-substitution) ``steps`` times; the models."""
    out = []
    for _ in range(steps):
        lin = w.linearize()
        out.append(lin)
        w.move_newest(rng.normal(size=(w.newest.shape[0], 6)) * size * RELIN_SCALE, lin)
    out.append(w.linearize())
    return out


@pytest.mark.parametrize("L", [2, 4])
def test_tiny_threshold_equals_the_exact_linearisation(L: int) -> None:
    """Every pose that moved at all is re-evaluated: the anchored path is the exact path (to 1e-9)."""
    w, _ = _window(L, 12, np.random.default_rng(1), frames=L + 1)
    exact, anchored = _with_threshold(w, 0.0), _with_threshold(w, 1e-15)
    lin_e = _transport_like(exact, np.random.default_rng(2), 4, 0.3)
    lin_a = _transport_like(anchored, np.random.default_rng(2), 4, 0.3)
    for a, e in zip(lin_a, lin_e, strict=True):
        _assert_lin_close(a, e, 1e-9)
    np.testing.assert_allclose(anchored.poses, exact.poses, rtol=0, atol=1e-12)


def test_threshold_zero_is_the_exact_path_and_negative_is_rejected() -> None:
    w, _ = _window(3, 6, np.random.default_rng(3), frames=4)
    assert w.relin_threshold == 0.0
    assert Window(3, np.eye(6)).relin_threshold == DEFAULT_RELIN_THRESHOLD > 0.0
    with pytest.raises(ValueError, match="relin_threshold"):
        Window(3, np.eye(6), relin_threshold=-0.1)
    zero = _with_threshold(w, 0.0)
    zero.linearize()
    assert zero._anchor.key is None  # the exact path: nothing anchored
    # the same code path as a window without the setting (memo vs fresh batched evaluation: round-off only)
    _assert_lin_close(zero.linearize(), w.linearize(), 1e-12)


def test_reused_terms_are_second_order_close_to_the_exact_ones() -> None:
    """Below the threshold the older frames' terms come from the anchor's quadratic model: the window value's
    error shrinks quadratically with the size of the moves, the gradient's linearly (the Gauss-Newton information
    omits the residuals' curvature, which a re-evaluated gradient includes)."""
    w, _ = _window(4, 10, np.random.default_rng(4), frames=5)
    errors, value_errors = [], []
    for size in (0.2, 0.02):
        exact, anchored = _with_threshold(w, 0.0), _with_threshold(w, 1e3)  # never re-evaluated after the first
        anchored.linearize()  # anchors at the current poses
        move = se3_exp(np.random.default_rng(5).normal(size=w.poses.shape[:2] + (6,)) * size * RELIN_SCALE)
        exact.poses = exact.poses @ move
        anchored.poses = anchored.poses @ move
        a, e = anchored.linearize(), exact.linearize()
        assert np.all(anchored._anchor.arrays["A"] == w.poses[:-1])  # still at the old poses
        assert not np.array_equal(a.grad, e.grad)  # the reuse is an approximation
        errors.append(float(np.max(np.abs(a.grad - e.grad)) / np.max(np.abs(e.grad))))
        value_errors.append(float(np.max(np.abs(a.window_value - e.window_value))))
    assert errors[1] < errors[0] / 5.0 and errors[1] < 1e-3, errors
    assert value_errors[1] < value_errors[0] / 30.0 and value_errors[1] < 1.0, value_errors


def test_subset_adopt_resample_and_copies_keep_anchor_rows() -> None:
    """A subset's model equals the full window's rows; writing back, resampling and copying rows keep the anchors
    attached to their hypotheses (the anchored model equals a fresh anchored window's to 1e-9)."""
    w, _ = _window(3, 8, np.random.default_rng(6), frames=4)
    w = _with_threshold(w, 0.05)
    rng = np.random.default_rng(7)
    _transport_like(w, rng, 2, 0.01)
    full = w.linearize()
    idx = np.array([5, 1, 6])
    sub = w.subset(idx)
    _assert_lin_close(sub.linearize(), full.subset(idx), 1e-9)
    sub.move_newest(rng.normal(size=(3, 6)) * 0.01 * RELIN_SCALE, sub.linearize())
    lin_sub = sub.linearize()
    w.adopt(sub, idx)
    _assert_lin_close(w.linearize().subset(idx), lin_sub, 1e-9)
    order = np.array([7, 7, 0, 1, 2, 3, 4, 5])
    before = w.linearize()
    w.resample(order)
    _assert_lin_close(w.linearize(), before.subset(order), 1e-9)
    copy_hypotheses(w, [0], w.subset([4]), [0])
    _assert_lin_close(w.linearize().subset([0]), w.linearize().subset([4]), 1e-9)
    # the anchored model is a real evaluation at its anchor poses: an exact window there has the same model
    a = w._anchor.arrays
    at_anchor = _with_threshold(w, 0.0)
    at_anchor.poses[:-1] = a["A"]
    _assert_lin_close(_with_threshold(at_anchor, 1e-15).linearize(), at_anchor.linearize(), 1e-9)
    fresh = _with_threshold(at_anchor, 1e3)
    fresh.linearize()
    for k in ("V", "G", "Hd", "Bo"):
        np.testing.assert_allclose(a[k], fresh._anchor.arrays[k], rtol=0, atol=1e-9 * np.max(np.abs(a[k])))


@pytest.mark.parametrize("grow", [False, True])
def test_sliding_keeps_the_anchored_frames_and_the_evidence_exact(grow: bool) -> None:
    """After a push the older part's model is rebuilt from the frames still anchored (the new prior and motion
    terms evaluated anew, the joining frame at its poses): equal to a fresh exact evaluation at the anchor
    poses. Marginalisation (``grow`` False: the window is full) stays exact: the same evidence as the exact path."""
    rng = np.random.default_rng(8)
    w, obs = _window(3, 6, rng, frames=3 if grow else 4)
    w.length = 4 if grow else 3
    exact, anchored = _with_threshold(w, 0.0), _with_threshold(w, 0.5)
    for x in (exact, anchored):
        x.move_newest(np.full((6, 6), 1e-3), x.linearize())
    anchored.linearize()
    before = anchored._anchor.arrays["A"].copy()
    frame = FrameLikelihood(_observation(len(w.frames), rng), MODEL)
    for x in (exact, anchored):
        x.push(frame, se3_exp(np.full(6, 1e-4)), use_motion=True)
    np.testing.assert_allclose(anchored.evidence, exact.evidence, rtol=0, atol=1e-9 * np.max(np.abs(exact.evidence)))
    anchored.linearize()
    a = anchored._anchor.arrays
    kept = before if grow else before[1:]
    np.testing.assert_array_equal(a["A"][: len(kept)], kept)  # the old frames stay at their anchors
    fresh = type(anchored._anchor)()._evaluate(anchored.frames[:-1], a["A"], (anchored.prior_mean, anchored.prior_W),
                                               anchored.deltas[:-1], anchored.delta_W[:-1])
    for k in ("V", "G", "Hd", "Bo", "Hinv", "H_last"):
        np.testing.assert_allclose(a[k], fresh[k], rtol=0, atol=1e-9 * max(1.0, float(np.max(np.abs(fresh[k])))))


def test_rows_copied_from_a_window_without_the_model_are_re_linearised() -> None:
    """copy_hypotheses from a source whose older part is not anchored (or another window) marks the rows stale:
    the next model is the exact one for them."""
    w, _ = _window(3, 5, np.random.default_rng(9), frames=4)
    w = _with_threshold(w, 1e3)
    w.linearize()
    src = _with_threshold(w, 0.0)  # same frames, no anchored model
    src.poses = src.poses @ se3_exp(np.full(src.poses.shape[:2] + (6,), 0.1) * RELIN_SCALE)
    copy_hypotheses(w, [2], src, [4])
    assert not w._anchor.arrays["valid"][2] and w._anchor.arrays["valid"][[0, 1, 3, 4]].all()
    exact = _with_threshold(w, 0.0)
    _assert_lin_close(w.linearize().subset([2]), exact.linearize().subset([2]), 1e-9)
    assert w._anchor.arrays["valid"][2]


def test_shared_books_swap_the_prior_in_the_anchored_model_without_re_evaluating_the_frames() -> None:
    """share_books gives rows another window prior: the prior's share of their anchored older-part model is swapped
    at the anchors (equal to a fresh evaluation there, to 1e-9), the rows stay anchored (no frame is re-evaluated),
    and with the anchors at the current poses the linearisation is the exact one."""
    from pinpoint_fg.window_rows import share_books

    w, _ = _window(3, 10, np.random.default_rng(7), frames=4)
    anchored = _with_threshold(w, DEFAULT_RELIN_THRESHOLD)
    anchored.linearize()  # anchors every row at the current poses
    exact = _with_threshold(anchored, 0.0)
    for win in (anchored, exact):
        share_books(win, [1, 2, 8], [0, 0, 9])
    assert anchored._anchor.arrays["valid"].all()
    _assert_lin_close(anchored.linearize(), exact.linearize(), 1e-9)

    # anchors away from the current poses (moved below the threshold): the model at the anchors is the fresh one
    moved, _ = _window(3, 10, np.random.default_rng(8), frames=4)
    moved = _with_threshold(moved, DEFAULT_RELIN_THRESHOLD)
    moved.linearize()
    moved.move_newest(np.full((10, 6), 0.05) * RELIN_SCALE, moved.linearize())
    moved.linearize()
    calls = []
    original = type(moved._anchor)._evaluate
    type(moved._anchor)._evaluate = lambda self, *a: calls.append(1) or original(self, *a)
    try:
        share_books(moved, [3, 4, 5], [0, 9, 9])
        moved.linearize()
    finally:
        type(moved._anchor)._evaluate = original
    assert not calls  # no older frame was evaluated again
    a = moved._anchor.arrays
    fresh = type(moved._anchor)._evaluate(type(moved._anchor)(), moved.frames[:-1], a["A"],
                                          (moved.prior_mean, moved.prior_W), moved.deltas[:-1], moved.delta_W[:-1])
    for k in ("V", "G", "Hd", "Bo", "Hinv", "H_last"):
        np.testing.assert_allclose(a[k], fresh[k], rtol=0, atol=1e-9 * max(1.0, float(np.max(np.abs(fresh[k])))))
