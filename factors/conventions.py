"""The tangent convention of this project, stated as executable code.

GTSAM perturbs a ``Pose3`` on the right, with the rotation first::

    T ⊕ xi  =  T · Exp(xi),        xi = [omega (3); v (3)]

so ``gtsam.Pose3.retract(xi) == T.compose(gtsam.Pose3.Expmap(xi))`` and
``T.localCoordinates(T.retract(xi)) == xi``. Every Jacobian in :mod:`factors` is
``d r(T ⊕ xi) / d xi`` at ``xi = 0`` in exactly this sense; :func:`oplus` below is the
definition the tests differentiate through.

The paper's appendix uses a *left* perturbation ``Exp(delta) · T`` with ``delta = [v; omega]``.
The two are related by the adjoint: ``Exp(Ad_T xi) · T = T · Exp(xi)``, so
``delta_left_wv = Ad_T xi`` and, with ``P`` swapping the two 3-blocks,
``J_right_gtsam = J_left_vw @ P @ Ad_T`` (:func:`left_vw_to_right_jacobian`).
"""

from __future__ import annotations

import gtsam
import numpy as np

from factors.lie import se3_adjoint, se3_exp, se3_inverse

#: Swaps the rotation and translation blocks of a 6-vector: ``[omega; v] <-> [v; omega]``.
P_SWAP = np.block([[np.zeros((3, 3)), np.eye(3)], [np.eye(3), np.zeros((3, 3))]])


def oplus(T: gtsam.Pose3, xi: np.ndarray) -> gtsam.Pose3:
    """The chart every Jacobian is taken in: ``T ⊕ xi = T · Exp(xi)`` (equal to ``T.retract(xi)``)."""
    return T.compose(gtsam.Pose3.Expmap(np.asarray(xi, dtype=float)))


def oplus_matrix(T: np.ndarray, xi: np.ndarray) -> np.ndarray:
    """:func:`oplus` on homogeneous matrices, batched: ``(..., 4, 4), (..., 6) -> (..., 4, 4)``."""
    return np.asarray(T, dtype=float) @ se3_exp(xi)


def left_vw_to_right_jacobian(J_left_vw: np.ndarray, T: np.ndarray) -> np.ndarray:
    """Convert a Jacobian w.r.t. ``Exp([v; omega]) · T`` into GTSAM's ``T · Exp([omega; v])``.

    ``J_right = J_left_vw @ P @ Ad_T`` (batched over leading axes of ``T``, shape ``(..., 4, 4)``).
    """
    return np.asarray(J_left_vw) @ P_SWAP @ se3_adjoint(T)


def right_to_left_vw_jacobian(J_right: np.ndarray, T: np.ndarray) -> np.ndarray:
    """Inverse of :func:`left_vw_to_right_jacobian`: ``J_left_vw = J_right @ Ad_{T^-1} @ P``."""
    return np.asarray(J_right) @ se3_adjoint(se3_inverse(T)) @ P_SWAP


def pose3_to_matrix(T: gtsam.Pose3) -> np.ndarray:
    """A ``gtsam.Pose3`` as a ``(4, 4)`` float array."""
    return np.asarray(T.matrix(), dtype=float)


def matrix_to_pose3(T: np.ndarray) -> gtsam.Pose3:
    """A ``(4, 4)`` homogeneous matrix as a ``gtsam.Pose3`` (rotation re-orthonormalised by GTSAM)."""
    T = np.asarray(T, dtype=float)
    return gtsam.Pose3(gtsam.Rot3(T[:3, :3]), gtsam.Point3(*T[:3, 3]))
