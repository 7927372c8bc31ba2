"""Spread of a particle set around a reference pose: weighted quantiles and tangent covariance.

Poses are homogeneous ``cam_T_needle`` matrices; a batch of particle sets is ``(F, N, 4, 4)`` (frame axis
first, particle axis next). Tangent vectors follow GTSAM: ``xi = [omega; v]`` with ``T_i = T_ref · Exp(xi)``.
Every tracker reports its uncertainty with :func:`tangent_spread` (the paper's §IV "Uncertainty Estimation"),
and the evaluation (:mod:`pinpoint_fg.eval.metrics`) scores it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from factors.lie import local
from pinpoint_fg.errors import InputError

# ----------------------------------------------------------------------------- validation


def pose_array(name: str, T: np.ndarray, min_batch_dims: int = 0) -> np.ndarray:
    """``T`` as a float array of shape ``(..., 4, 4)`` with at least ``min_batch_dims`` leading axes."""
    try:
        T = np.asarray(T, dtype=float)
    except (TypeError, ValueError) as exc:
        raise InputError(f"{name} must be a numeric array of 4x4 poses ({exc})", column=name) from None
    if T.ndim < 2 + min_batch_dims or T.shape[-2:] != (4, 4):
        want = "(..., N, 4, 4)" if min_batch_dims else "(..., 4, 4)"
        raise InputError(f"{name} must have shape {want}, got {T.shape}", column=name)
    return T


# ----------------------------------------------------------------------------- weighted statistics


def _weights(weights: np.ndarray | None, shape: tuple[int, ...], name: str = "weights") -> np.ndarray:
    """Normalised non-negative weights of ``shape`` (uniform when ``None``); each row sums to 1."""
    if weights is None:
        return np.full(shape, 1.0 / shape[-1])
    w = np.asarray(weights, dtype=float)
    if w.shape != shape:
        try:
            w = np.broadcast_to(w, shape)
        except ValueError:
            raise InputError(f"{name} has shape {w.shape}, expected {shape}", column=name) from None
    if not np.all(np.isfinite(w)) or np.any(w < 0):
        raise InputError(f"{name} must be finite and non-negative", column=name)
    total = w.sum(axis=-1, keepdims=True)
    if np.any(total <= 0):
        raise InputError(f"{name}: a set of weights sums to zero", column=name)
    return w / total


def weighted_quantile(values: np.ndarray, weights: np.ndarray | None, q: float) -> np.ndarray:
    """Weighted ``q``-quantile of ``values`` (..., N) along the last axis -> (...).

    Definition: the inverse of the weighted empirical CDF,
    ``Q(q) = min { x_(k) : W_k >= q · W_N }``, where ``x_(1) <= ... <= x_(N)`` are the sorted values
    and ``W_k`` the cumulative sum of their weights (weights ``None`` = equal). For ``q = 0`` the
    smallest value with positive weight is returned. With equal weights this is exactly numpy's
    ``np.quantile(..., method="inverted_cdf")``: weights are divided by their maximum, so equal
    weights become exact ones, ``W_k = k`` exactly, and the comparison ``k >= q · N`` is the one numpy
    makes. The result is always one of the values (no interpolation).
    """
    v = np.asarray(values, dtype=float)
    if v.ndim == 0 or v.shape[-1] == 0:
        raise InputError("weighted_quantile needs at least one value along the last axis", column="values")
    if not np.all(np.isfinite(v)):
        raise InputError("weighted_quantile: values must be finite", column="values")
    if not (0.0 <= float(q) <= 1.0):
        raise InputError(f"quantile level q must lie in [0, 1], got {q}", column="q")
    w = _weights(weights, v.shape)
    w = w / w.max(axis=-1, keepdims=True)
    order = np.argsort(v, axis=-1, kind="stable")
    v_sorted = np.take_along_axis(v, order, axis=-1)
    w_sorted = np.take_along_axis(w, order, axis=-1)
    cum = np.cumsum(w_sorted, axis=-1)
    target = float(q) * cum[..., -1:]
    hit = (cum >= target) & (w_sorted > 0)
    k = np.argmax(hit, axis=-1)
    return np.take_along_axis(v_sorted, k[..., None], axis=-1)[..., 0]


@dataclass(frozen=True)
class TangentSpread:
    """Spread of a particle set around a reference pose, in the reference's tangent space."""

    q95_trans_m: np.ndarray
    """(...) weighted 95th percentile of ``||v_i||`` (translation part of ``xi_i``), metres."""
    q95_rot_rad: np.ndarray
    """(...) weighted 95th percentile of ``||omega_i||`` (rotation part of ``xi_i``), radians."""
    mean_xi: np.ndarray
    """(..., 6) weighted mean ``sum_i w_i xi_i``, order ``[omega; v]``."""
    cov_xi: np.ndarray
    """(..., 6, 6) weighted covariance ``sum_i w_i (xi_i - mean)(xi_i - mean)^T`` (weights sum to 1)."""


def tangent_spread(
    T_ref: np.ndarray,
    particles_T: np.ndarray,
    weights: np.ndarray | None = None,
    q: float = 0.95,
) -> TangentSpread:
    """Uncertainty of a particle set (paper §IV "Uncertainty Estimation").

    ``xi_i = Log(T_ref^-1 T_i) = [omega_i; v_i]`` (GTSAM order, :func:`factors.lie.local`);
    ``q95_trans_m`` / ``q95_rot_rad`` are the weighted ``q``-quantiles (:func:`weighted_quantile`)
    of ``||v_i||`` and ``||omega_i||``; the covariance is the weighted (biased, normalised-weight)
    second moment about the weighted mean, as the paper writes it.

    Shapes: ``particles_T`` (F, N, 4, 4) with ``T_ref`` (F, 4, 4) or one (4, 4) for every frame;
    a single set (N, 4, 4) with ``T_ref`` (4, 4) gives scalar quantiles. ``weights`` (F, N) or
    (N,), ``None`` = equal; they are normalised per set.
    """
    w, xi = _tangent_vectors(T_ref, particles_T, weights)
    r_rot = np.linalg.norm(xi[..., :3], axis=-1)
    r_trans = np.linalg.norm(xi[..., 3:], axis=-1)
    mean, cov = _moments(w, xi)
    return TangentSpread(
        q95_trans_m=weighted_quantile(r_trans, w, q),
        q95_rot_rad=weighted_quantile(r_rot, w, q),
        mean_xi=mean,
        cov_xi=cov,
    )


def _tangent_vectors(T_ref: np.ndarray, particles_T: np.ndarray, weights: np.ndarray | None
                     ) -> tuple[np.ndarray, np.ndarray]:
    """Checked, normalised weights ``(..., N)`` and tangent vectors ``xi_i = Log(T_ref^-1 T_i)`` ``(..., N, 6)``."""
    P = pose_array("particles_T", particles_T, min_batch_dims=1)
    T_ref = pose_array("T_ref", T_ref)
    mismatch = f"T_ref {T_ref.shape} does not match particles_T {P.shape}"
    if T_ref.ndim > P.ndim - 1:
        raise InputError(mismatch, column="T_ref")
    try:
        batch = np.broadcast_shapes(T_ref.shape[:-2], P.shape[:-3])
    except ValueError:
        raise InputError(mismatch, column="T_ref") from None
    if batch != P.shape[:-3]:
        raise InputError(mismatch, column="T_ref")
    if P.shape[-3] == 0:  # was ZeroDivisionError from the uniform weights
        raise InputError(f"particles_T holds no particles (shape {P.shape})", column="particles_T")
    if not (np.all(np.isfinite(P)) and np.all(np.isfinite(T_ref))):
        raise InputError("tangent_spread: poses must be finite", column="particles_T")
    w = _weights(weights, P.shape[:-2])
    return w, local(T_ref[..., None, :, :], P)  # (..., N, 6)


def _moments(w: np.ndarray, xi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Weighted mean ``(..., 6)`` and (biased) covariance ``(..., 6, 6)`` of tangent vectors ``xi (..., N, 6)``."""
    mean = np.einsum("...n,...nk->...k", w, xi)
    d = xi - mean[..., None, :]
    return mean, np.einsum("...n,...nj,...nk->...jk", w, d, d)


def tangent_covariance(T_ref: np.ndarray, particles_T: np.ndarray, weights: np.ndarray | None = None) -> np.ndarray:
    """:func:`tangent_spread`'s ``cov_xi`` alone (the same numbers), without its quantiles."""
    return _moments(*_tangent_vectors(T_ref, particles_T, weights))[1]
