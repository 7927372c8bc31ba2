"""The ΔNLL truth about ambiguity, and the accuracy floor."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from factors.geometry import NeedleModel, PinholeCamera
from factors.lie import se3_exp, so3_exp
from pinpoint_fg.eval.ambiguity import (
    AmbiguityConfig,
    accuracy_floor,
    alternative_circle,
    ambiguity_delta_nll,
    analyse_frame,
    analyse_recording,
    image_conic,
    label_delta_nll,
    label_frames,
)
from pinpoint_fg.io.recording.reader import read_recording
from pinpoint_fg.likelihood import FrameLikelihood, MeasurementModel, Switches
from pinpoint_fg.observation import Observation
from pinpoint_fg.sim.scenarios import simulate

CAM = PinholeCamera(fx=900.0, fy=900.0, cx=539.5, cy=539.5, width=1080, height=1080)
NEEDLE = NeedleModel()


def _pose(depth_m: float, tilt_deg: float, spin_rad: float = 0.3) -> np.ndarray:
    R = so3_exp(np.array([0.0, 0.0, 0.5])) @ so3_exp(np.array([np.radians(tilt_deg), 0.0, 0.0])) @ so3_exp(
        np.array([0.0, 0.0, spin_rad])
    )
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = [0.002, -0.001, depth_m]
    return T


def _observation(T: np.ndarray, tip: bool = True, tail: bool = True, dense: bool = True,
                 grasp: bool = True) -> Observation:
    """Noise-free evidence of a needle at ``T``."""
    R, t = T[:3, :3], T[:3, 3]
    G = np.eye(4)
    G[:3, 3] = R @ NEEDLE.grasp_m + t
    z = np.cross(R @ NEEDLE.grasp_tangent, [0.3, 0.2, 1.0])
    G[:3, 2] = z / np.linalg.norm(z)  # only the grasper's z axis enters the residuals
    return Observation(
        frame=0, t_s=0.0,
        tip_px=CAM.project(R @ NEEDLE.tip_m + t) if tip else None,
        tail_px=CAM.project(R @ NEEDLE.tail_m + t) if tail else None,
        backbone_px=CAM.project(NEEDLE.arc_points(120) @ R.T + t) if dense else None,
        cam_T_grasper=G if grasp else None,
    )


def _lik(obs: Observation, switches: Switches | None = None) -> FrameLikelihood:
    return FrameLikelihood(obs, MeasurementModel(CAM, NEEDLE, switches=switches or Switches()))


def test_image_conic_holds_the_projected_circle_and_so_does_the_alternative() -> None:
    T = _pose(0.04, 45.0)
    C = image_conic(T, CAM.K, NEEDLE.radius_m)
    ang = np.linspace(0, 2 * np.pi, 50)
    circle = NEEDLE.radius_m * np.stack([np.cos(ang), np.sin(ang), 0 * ang], axis=1)
    x = np.c_[CAM.project(circle @ T[:3, :3].T + T[:3, 3]), np.ones(50)]
    scale = np.linalg.norm(C) * np.linalg.norm(x, axis=1) ** 2
    assert np.max(np.abs(np.einsum("ni,ij,nj->n", x, C, x)) / scale) < 1e-12
    centre, normal, sep = alternative_circle(T, CAM.K, NEEDLE.radius_m)
    assert 60.0 < sep < 90.0  # a different plane ...
    u = np.cross(normal, [1.0, 0.0, 0.0])
    u /= np.linalg.norm(u)
    v = np.cross(normal, u)
    alt = centre + NEEDLE.radius_m * (np.cos(ang)[:, None] * u + np.sin(ang)[:, None] * v)
    xa = np.c_[CAM.project(alt), np.ones(50)]
    # ... with the same image: the other circle's points lie on the truth's conic
    assert np.max(np.abs(np.einsum("ni,ij,nj->n", xa, C, xa)) / scale) < 1e-9


def test_backbone_alone_is_genuinely_ambiguous() -> None:
    T = _pose(0.06, 40.0)
    fa = analyse_frame(_lik(_observation(T, tip=False, tail=False, grasp=False)), T)
    assert abs(fa.delta_nll) < 1e-3
    assert fa.normal_separation_deg > 60.0
    # the two modes are different planes, each kept in its own mode by the polish
    assert abs(fa.cam_T_truth_mode[:3, 2] @ T[:3, 2]) > np.cos(np.radians(1.0))
    assert abs(fa.cam_T_alternative[:3, 2] @ T[:3, 2]) < np.cos(np.radians(45.0))


def test_far_needle_with_backbone_and_grasp_position_is_ambiguous() -> None:
    T = _pose(0.10, 40.0)
    lik = _lik(_observation(T, tip=False, tail=False), Switches(grasp_perpendicular=False))
    d = ambiguity_delta_nll(lik, T)
    assert 0.0 <= d < 2.3
    assert label_delta_nll(np.array([d]))[0] == "ambiguous"


def test_two_keypoints_at_30_mm_make_a_clear_frame() -> None:
    T = _pose(0.03, 30.0)
    d = ambiguity_delta_nll(_lik(_observation(T, grasp=False)), T)
    assert d > 10.0
    assert label_delta_nll(np.array([d]))[0] == "clear"


def test_face_on_needle_has_no_second_mode() -> None:
    T = _pose(0.045, 2.0)
    fa = analyse_frame(_lik(_observation(T)), T)
    assert fa.delta_nll == np.inf and fa.cam_T_alternative is None
    assert fa.normal_separation_deg < AmbiguityConfig().min_mode_separation_deg


def test_labels_follow_the_thresholds() -> None:
    d = np.array([-0.1, 0.0, 2.29, 2.31, 9.99, 10.01, np.inf, np.nan])
    assert list(label_delta_nll(d)) == [
        "ambiguous", "ambiguous", "ambiguous", "between", "between", "clear", "clear", "unknown",
    ]


def test_truth_mode_is_the_map_solved_from_the_truth() -> None:
    rng = np.random.default_rng(3)
    T = _pose(0.04, 35.0)
    obs = _observation(T)
    noisy = Observation(
        frame=0, t_s=0.0, tip_px=obs.tip_px + rng.normal(0, 1.0, 2),
        tail_px=obs.tail_px + rng.normal(0, 1.0, 2),
        backbone_px=obs.backbone_px + rng.normal(0, 1.2, obs.backbone_px.shape),
        cam_T_grasper=obs.cam_T_grasper,
    )
    lik = _lik(noisy)
    fa = analyse_frame(lik, T)
    nll_gt = float(lik.nll(T)[0])
    assert fa.nll_truth < nll_gt - 0.5  # noise puts the truth above the minimum
    _, g, H = lik.gauss_newton(fa.cam_T_truth_mode)
    assert 0.5 * g[0] @ np.linalg.solve(H[0], g[0]) < 1e-2  # converged
    # a small perturbation of the solution does not lower the cost
    xi = rng.normal(0, 1e-4, (20, 6))
    assert np.all(lik.nll(fa.cam_T_truth_mode @ se3_exp(xi)) >= fa.nll_truth - 1e-9)


@pytest.fixture(scope="module")
def rotation_run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return simulate("rotation", 12, seed=4, out=tmp_path_factory.mktemp("amb") / "run")


def test_recording_analysis_labels_every_frame_and_gives_the_floor(rotation_run: Path) -> None:
    rec = read_recording(rotation_run)
    model = MeasurementModel(rec.info.camera, rec.info.needle)
    an = analyse_recording(rec, model)
    assert an.delta_nll.shape == (12,) and an.floor_T.shape == (12, 4, 4)
    assert set(an.labels) <= {"ambiguous", "between", "clear"}
    assert np.all(np.isfinite(an.floor_errors.trans_m))
    assert np.mean(an.floor_errors.trans_m) < 3e-3  # a per-frame MAP stays near a truth it starts at
    np.testing.assert_array_equal(label_frames(rec, model), an.labels)
    np.testing.assert_allclose(accuracy_floor(rec, model), an.floor_T)
    sub = analyse_recording(rec, model, frames=[2, 5])
    assert list(np.nonzero(np.isfinite(sub.delta_nll))[0]) == [2, 5]
    assert sub.labels[0] == "unknown"
    np.testing.assert_allclose(sub.delta_nll[[2, 5]], an.delta_nll[[2, 5]])
    assert list(sub.index_of(np.array([5, 2, 99]))) == [5, 2, -1]
