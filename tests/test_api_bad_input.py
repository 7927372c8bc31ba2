"""A GTSAM user's or a researcher's bad arguments to the Python API (third audit): each case here was an inf/NaN
error value, a silently wrong number, a truncated argument or an obscure NumPy/pybind traceback before its fix.
Each must now raise one ValueError (InputError for the readers and metrics) naming the argument, at construction
or before any work."""

from __future__ import annotations

from pathlib import Path

import gtsam
import numpy as np
import pytest

from factors import (
    ConicFactor,
    GraspPerpendicularFactor,
    GraspPositionFactor,
    KeypointFactor,
    MotionFactor,
    PinholeCamera,
    PosePriorFactor,
)
from factors.geometry import NeedleModel
from factors.gtsam_factors import ConicPixelFactor, _ConicCache, conic_pixel_factors
from factors.robust import RobustLoss
from pinpoint_fg.errors import InputError
from pinpoint_fg.eval.metrics import breakdown_by_label, interval_score, nll_score, pose_errors, summarize_errors
from pinpoint_fg.io.recording.reader import read_recording
from pinpoint_fg.io.result.reader import read_result
from pinpoint_fg.posterior.spread import tangent_spread
from pinpoint_fg.track import track_recording

CAM = PinholeCamera(900.0, 900.0, 320.0, 240.0)
NEEDLE = NeedleModel()
S = gtsam.noiseModel.Isotropic.Sigma
T0 = np.eye(4)
T0[2, 3] = 0.05
PTS = CAM.project(NEEDLE.arc_points(10) + T0[:3, 3])


def _scaled(s: float) -> np.ndarray:
    M = T0.copy()
    M[:3, :3] *= s
    return M


def _skewed_K() -> np.ndarray:
    K = CAM.K
    K[0, 1] = 50.0
    return K


def _cache() -> _ConicCache:
    return _ConicCache(CAM.K, NEEDLE.radius_m, PTS, 0.0)


def _huge_point() -> np.ndarray:
    p = PTS.copy()
    p[0] = 1e200
    return p


FACTOR_CASES = {
    # inf error and inf/NaN Jacobian, silently
    "sigma 0": (lambda: KeypointFactor(0, CAM, NEEDLE.tip_m, [300, 200], S(2, 0.0)), "zero or NaN sigma"),
    "NaN sigma": (lambda: KeypointFactor(0, CAM, NEEDLE.tip_m, [300, 200],
                                         gtsam.noiseModel.Diagonal.Sigmas(np.array([np.nan, 1.0]))), "sigma"),
    "zero covariance": (lambda: MotionFactor(0, 1, T0, gtsam.noiseModel.Gaussian.Covariance(np.zeros((6, 6)))),
                        "sigma"),
    "robust over sigma 0": (lambda: GraspPositionFactor(0, NEEDLE.grasp_m, [0, 0, 0.05],
                                                        RobustLoss("huber", 1.0).gtsam_model(S(3, 0.0))), "sigma"),
    "pixel factors sigma 0": (lambda: conic_pixel_factors(0, CAM, NEEDLE.radius_m, PTS, S(1, 0.0)), "sigma"),
    # pybind's "incompatible constructor arguments" listing the whole signature
    "key -1": (lambda: KeypointFactor(-1, CAM, NEEDLE.tip_m, [300, 200], S(2, 1)), "key"),
    "key 2**64": (lambda: KeypointFactor(2**64, CAM, NEEDLE.tip_m, [300, 200], S(2, 1)), "key"),
    # a singular / skewed / mis-scaled K: a silently wrong error (65000 px for all zeros, conic 0.0)
    "K zeros": (lambda: KeypointFactor(0, np.zeros((3, 3)), NEEDLE.tip_m, [300, 200], S(2, 1)), "camera K"),
    "conic K zeros": (lambda: ConicFactor(0, np.zeros((3, 3)), NEEDLE.radius_m, PTS, S(10, 1)), "camera K"),
    "K skew": (lambda: KeypointFactor(0, _skewed_K(), NEEDLE.tip_m, [300, 200], S(2, 1)), "camera K"),
    "K[2,2] = 2": (lambda: KeypointFactor(0, 2 * CAM.K, NEEDLE.tip_m, [300, 200], S(2, 1)), "camera K"),
    "focal 1e308": (lambda: KeypointFactor(0, PinholeCamera(1e308, 1e308, 0, 0), NEEDLE.tip_m, [300, 200], S(2, 1)),
                    "camera K"),
    "camera a string": (lambda: KeypointFactor(0, "cam", NEEDLE.tip_m, [1, 2], S(2, 1)), "camera"),
    # overflow: inf or NaN errors, or OverflowError without a name
    "measured 1e308": (lambda: KeypointFactor(0, CAM, NEEDLE.tip_m, [1e308, 200], S(2, 1)), "measured_px"),
    "needle point 1e300": (lambda: KeypointFactor(0, CAM, [1e300, 0, 0], [300, 200], S(2, 1)), "needle_point_m"),
    "backbone pixel 1e200": (lambda: ConicFactor(0, CAM, NEEDLE.radius_m, _huge_point(), S(10, 1)), "points_px"),
    "radius 1e200": (lambda: ConicFactor(0, CAM, 1e200, PTS, S(10, 1)), "radius_m"),
    "grasp 1e300": (lambda: GraspPositionFactor(0, NEEDLE.grasp_m, [1e300, 0, 0], S(3, 1)), "measured_cam_m"),
    "delta translation 1e300": (lambda: MotionFactor(0, 1, np.r_[np.c_[np.eye(3), [1e300, 0, 0]], [[0, 0, 0, 1]]],
                                                     S(6, 1)), "cam_delta"),
    # normalised to zero: a perpendicularity residual of 0 whatever the pose
    "tangent 1e200": (lambda: GraspPerpendicularFactor(0, [1e200, 0, 0], [0, 1, 0], S(1, 1)), "needle_tangent"),
    # NumPy's "could not convert string to float", naming nothing
    "radius a string": (lambda: ConicFactor(0, CAM, "abc", PTS, S(10, 1)), "radius_m"),
    "bias a string": (lambda: ConicFactor(0, CAM, NEEDLE.radius_m, PTS, S(10, 1), bias="x"), "bias"),
    "measured a string": (lambda: KeypointFactor(0, CAM, NEEDLE.tip_m, "ab", S(2, 1)), "measured_px"),
    "robust k a string": (lambda: RobustLoss("huber", "abc"), "threshold k"),
    # read no row: "cannot reshape array of size 0" at every error()
    "pixel index -1": (lambda: ConicPixelFactor(0, _cache(), -1, S(1, 1)), "index"),
    "pixel index past the end": (lambda: ConicPixelFactor(0, _cache(), 10, S(1, 1)), "index"),
    # gtsam.Rot3 keeps any 3x3: a scaled or zero rotation was a silently wrong error
    "prior scaled rotation": (lambda: PosePriorFactor(0, _scaled(2.0), S(6, 1)), "cam_T_mean"),
    "prior zero rotation": (lambda: PosePriorFactor(0, _scaled(0.0), S(6, 1)), "cam_T_mean"),
    "motion sheared": (lambda: MotionFactor(0, 1, np.r_[np.c_[[[1, 1, 0], [0, 1, 0], [0, 0, 1]], np.zeros(3)],
                                                        [[0, 0, 0, 1]]], S(6, 1)), "cam_delta"),
}


@pytest.mark.parametrize("case", list(FACTOR_CASES))
def test_factor_constructors_refuse_bad_arguments_by_name(case: str) -> None:
    make, says = FACTOR_CASES[case]
    with pytest.raises(ValueError, match=says):
        make()


def test_factors_keep_accepting_what_gtsam_users_pass() -> None:
    """The new checks leave valid models alone: a hard constraint, an infinite sigma (no information on a row), a
    robust model, a K given as a matrix, and a rotation rounded to nine digits."""
    v = gtsam.Values()
    v.insert(0, gtsam.Pose3(T0))
    v.insert(1, gtsam.Pose3(T0))
    rounded = np.round(T0 @ np.r_[np.c_[gtsam.Rot3.Rz(0.3).matrix(), np.zeros(3)], [[0, 0, 0, 1]]], 9)
    factors = [
        KeypointFactor(0, CAM.K, NEEDLE.tip_m, [300, 200], gtsam.noiseModel.Constrained.All(2)),
        KeypointFactor(0, CAM, NEEDLE.tip_m, [300, 200], gtsam.noiseModel.Diagonal.Sigmas(np.array([np.inf, 1.0]))),
        ConicFactor(0, CAM, NEEDLE.radius_m, PTS, RobustLoss("cauchy", 2.0).gtsam_model(S(10, 1.0))),
        PosePriorFactor(0, rounded, S(6, 1)),
        MotionFactor(0, 1, rounded, S(6, 1)),
        *conic_pixel_factors(0, CAM, NEEDLE.radius_m, PTS, S(1, 1.0)),
    ]
    assert all(np.isfinite(f.error(v)) for f in factors)


# --- the library functions a researcher calls ---------------------------------------------------------------

@pytest.fixture(scope="module")
def run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    from pinpoint_fg.cli import main

    out = tmp_path_factory.mktemp("api") / "run"
    assert main(["simulate", "--scenario", "normal", "--frames", "4", "--seed", "2", "--out", str(out)]) == 0
    return out


@pytest.mark.parametrize(("kwargs", "says"), [
    ({"max_frames": -1}, "max_frames"),       # tracked every frame but the last (a slice), silently
    ({"max_frames": 0}, "max_frames"),        # was "the recording has no frames"
    ({"seed": 2**64}, "seed"),                # wrote a result.json its own reader refuses
    ({"seed": -1}, "seed"),                   # NumPy's "expected non-negative integer"
    ({"particles": 10.5}, "particles"),       # tracked with 10
    ({"disable": "tip"}, "disable"),          # split into the switches 't', 'i', 'p'
    ({"blas_threads": 0}, "blas_threads"),
    ({"method": "bogus"}, "method"),
    ({"particles": 10**11}, "particles"),     # NumPy's "Unable to allocate 11.6 TiB" MemoryError, after reading the run
])
def test_track_recording_refuses_bad_arguments_before_any_work(kwargs: dict, says: str, run: Path,
                                                               tmp_path: Path) -> None:
    out = tmp_path / "r"
    with pytest.raises(ValueError, match=says):
        track_recording(run, **{"method": "map", **kwargs}, out=out, progress=False)
    assert not out.exists()


@pytest.mark.parametrize("bad", [None, 5, b"run", ""])
def test_readers_name_an_argument_that_is_not_a_path(bad: object, tmp_path: Path,
                                                     monkeypatch: pytest.MonkeyPatch) -> None:
    """None, a number or bytes was pathlib's TypeError; "" read the current directory (here: a valid run)."""
    monkeypatch.chdir(tmp_path)
    with pytest.raises(InputError, match="run must be a path"):
        read_recording(bad)  # type: ignore[arg-type]
    with pytest.raises(InputError, match="out_dir must be a path"):
        read_result(bad)  # type: ignore[arg-type]
    with pytest.raises(InputError, match="run must be a path"):
        track_recording(bad, "map", tmp_path / "r", progress=False)  # type: ignore[arg-type]
    assert not (tmp_path / "r").exists()


def test_metrics_name_bad_arguments() -> None:
    T = np.stack([T0, T0])
    with pytest.raises(InputError, match="no particles"):  # was ZeroDivisionError
        tangent_spread(T0, np.zeros((0, 4, 4)))
    with pytest.raises(InputError, match="sigma"):  # was scored as a confident 0.01
        nll_score(1.0, -1.0)
    with pytest.raises(InputError, match="alpha"):  # was TypeError of '<'
        interval_score(1.0, 0.0, 1.0, alpha="0.05")  # type: ignore[arg-type]
    with pytest.raises(InputError, match="T_est"):  # a scaled rotation was an error of 0 rad
        pose_errors(_scaled(3.0), T0)
    errors = pose_errors(T, T)
    with pytest.raises(InputError, match="mask"):  # every string read as True: all frames kept
        summarize_errors(errors, mask=np.array(["no", "no"]))
    with pytest.raises(InputError, match="labels"):  # split into one label per character
        breakdown_by_label(np.ones(3), "abc")
    assert summarize_errors(errors, mask=np.array([True, False]))["frames"] == 1
    assert nll_score(1.0, 0.0) == nll_score(1.0, 1e-3)  # zero spread is still floored, not refused


def test_every_factor_stays_finite_at_degenerate_poses() -> None:
    """A guard (it passed before this audit too): behind the camera, edge-on, the tip in the camera plane, the
    needle centre at the camera centre and a rotation of pi give a finite error and linearisation, never NaN."""
    from factors.lie import se3_exp

    in_plane = np.eye(4)
    in_plane[:3, 3] = -NEEDLE.tip_m + [0.01, 0.0, 0.0]
    poses = [se3_exp(np.r_[0, 0, 0, 0, 0, -0.05]), se3_exp(np.r_[np.pi / 2, 0, 0, 0, 0, 0.05]), in_plane,
             np.eye(4), se3_exp(np.r_[np.pi, 0, 0, 0, 0, 0.05])]
    factors = [KeypointFactor(0, CAM, NEEDLE.tip_m, [300, 200], S(2, 1)), ConicFactor(0, CAM, NEEDLE.radius_m, PTS,
               S(10, 1)), *conic_pixel_factors(0, CAM, NEEDLE.radius_m, PTS, S(1, 1))[:2],
               GraspPositionFactor(0, NEEDLE.grasp_m, [0, 0, 0.05], S(3, 1)),
               GraspPerpendicularFactor(0, NEEDLE.grasp_tangent, [0, 0, 1], S(1, 1)), PosePriorFactor(0, T0, S(6, 1)),
               MotionFactor(1, 0, np.eye(4), S(6, 1))]
    for P in poses:
        v = gtsam.Values()
        v.insert(0, gtsam.Pose3(P))
        v.insert(1, gtsam.Pose3(T0))
        for f in factors:
            A, b = f.linearize(v).jacobian()
            assert np.isfinite(f.error(v)) and np.isfinite(A).all() and np.isfinite(b).all()


def test_batched_residuals_refuse_a_degenerate_radius_or_direction() -> None:
    """``factors.residuals`` called directly: a NaN radius and a zero tangent were NaN residuals, radius 0 a
    degenerate conic (checked where the constants are built, so the trackers' hot path is unchanged)."""
    from factors import residuals

    for radius in (np.nan, 0.0, -1.0, 1e200):
        with pytest.raises(ValueError, match="radius_m"):
            residuals.conic_residual(T0, CAM.K, radius, PTS)
    with pytest.raises(ValueError, match="direction"):
        residuals.grasp_perpendicular_residual(T0, [0.0, 0.0, 0.0], [0.0, 0.0, 1.0])
    with pytest.raises(ValueError, match="direction"):
        residuals.grasp_perpendicular_residual(T0, [1.0, 0.0, 0.0], [np.inf, 0.0, 1.0])


@pytest.mark.parametrize("fmt", ["ros2", "ros1"])
@pytest.mark.parametrize(("role", "says"), [("tip", "outside the accepted"), ("grasper", "10 m")])
def test_import_bag_checks_every_row_before_writing(fmt: str, role: str, says: str, tmp_path: Path) -> None:
    """A tip at 1e308 px was imported (exit 0) into a run the reader refused; a grasper 100 km away stopped the
    import at its frame and left the frames before it as a run that validated (half the bag, silently)."""
    from pinpoint_fg.io.bag import BagTopics, import_bag
    from tests.test_io_bag import T0 as STAMP0
    from tests.test_io_bag import _camera_frames, _needle, _observations, _write_bag

    frame2 = STAMP0 + 80_000_000

    def build(w):
        yield from _camera_frames(w)
        yield from _observations(w, {0: 0})
        if role == "tip":
            yield "/needle/tip_px", w.point(w.header(frame2, "cam", 2), np.array([1e308, 2.0])), frame2
        else:
            far = np.eye(4)
            far[0, 3] = 1e5
            yield "/grasper/pose", w.pose(w.header(frame2, "cam", 2), far), frame2

    bag = _write_bag(tmp_path / ("b.bag" if fmt == "ros1" else "b"), fmt, build)
    with pytest.raises(InputError, match=says) as exc:
        import_bag(bag, tmp_path / "run", _needle(tmp_path), topics=BagTopics(gt=None))
    assert exc.value.file == str(bag) and exc.value.column == ("/needle/tip_px" if role == "tip" else "/grasper/pose")
    assert "frame 2" in str(exc.value)
    assert not (tmp_path / "run").exists()


def test_one_path_where_a_list_of_paths_is_expected_is_named(run: Path, tmp_path: Path) -> None:
    """A str was split into one "path" per character ("/: run given twice", "/result.json: file not found"), a
    Path was "'PosixPath' object is not iterable"."""
    from pinpoint_fg.eval.calibrate import calibrate_runs
    from pinpoint_fg.eval.report import evaluate_results
    from pinpoint_fg.eval.spread_calibration import fit_spread_scale
    from pinpoint_fg.experiments.ablate import ablation_jobs
    from pinpoint_fg.experiments.batch import run_batch
    from pinpoint_fg.io.result.reader import expand_result_dirs

    calls = [(lambda x: calibrate_runs(x), "runs"), (lambda x: ablation_jobs(x, tmp_path / "a"), "runs"),
             (lambda x: run_batch(x, "map", tmp_path / "b"), "runs"), (lambda x: fit_spread_scale(x), "results"),
             (lambda x: evaluate_results(x, out=tmp_path / "e"), "results"), (lambda x: expand_result_dirs(x), "paths")]
    for one in (str(run), run):
        for call, name in calls:
            with pytest.raises(InputError, match=f"{name} must be a list of paths, got the single path"):
                call(one)
    assert not any(tmp_path.iterdir())


# --- fourth audit -------------------------------------------------------------------------------------------

def test_notebook_calls_with_none_or_a_number_name_the_argument(run: Path, tmp_path: Path) -> None:
    """``evaluate_results(None)`` was "'NoneType' object is not iterable", ``[None]`` and ``out=None`` pathlib's
    "expected str, bytes or os.PathLike object", ``read_modes(None)`` / ``read_modes(3)`` the same: no argument
    named. Now each is an InputError naming it, before anything is written."""
    from pinpoint_fg.eval.calibrate import calibrate_runs
    from pinpoint_fg.eval.report import evaluate_results
    from pinpoint_fg.io.result.reader import read_modes

    result = track_recording(run, "map", tmp_path / "res", progress=False)
    with pytest.raises(InputError, match=r"results must be a list of paths, got NoneType"):
        evaluate_results(None, out=tmp_path / "e")  # type: ignore[arg-type]
    with pytest.raises(InputError, match=r"results\[1\] must be a path"):
        evaluate_results([result, None], out=tmp_path / "e")  # type: ignore[list-item]
    with pytest.raises(InputError, match=r"runs must be a list of paths, got int"):
        calibrate_runs(5)  # type: ignore[arg-type]
    with pytest.raises(InputError, match=r"^out must be a path"):
        evaluate_results([result], out=None)  # type: ignore[arg-type]
    for bad in (None, 3):
        with pytest.raises(InputError, match=r"^out_dir must be a path"):
            read_modes(bad)  # type: ignore[arg-type]
    assert not (tmp_path / "e").exists()
    assert read_modes(result).frame.size > 0  # a valid call still reads


@pytest.mark.parametrize("side_px", [1, 3, 8, 14, 23])
def test_detect_board_on_an_image_too_small_for_the_board_is_none(side_px: int) -> None:
    """An image under 15 px a side was OpenCV's "(-215:Assertion failed) blockSize % 2 == 1 && blockSize > 1" cv2.error
    (a traceback from ``groundtruth`` on a run of tiny images); an image too small to show the board finds none."""
    from pinpoint_fg.checkerboard import BoardSpec, detect_board

    camera = PinholeCamera(fx=600.0, fy=600.0, cx=side_px / 2, cy=side_px / 2, width=side_px, height=side_px)
    rng = np.random.default_rng(side_px)
    for image in (np.zeros((side_px, side_px), np.uint8), rng.integers(0, 256, (side_px, 640), dtype=np.uint8)):
        assert detect_board(image, camera, BoardSpec()) is None


@pytest.mark.parametrize("change", ["str", "record", "complex", "no particles"])
def test_particles_npz_of_the_wrong_dtype_or_no_particles_is_located(change: str, run: Path, tmp_path: Path) -> None:
    """``xyz_m`` saved as strings or a record dtype was NumPy's "ufunc 'isfinite' not supported" TypeError, as complex
    numbers a ComplexWarning (imaginary parts dropped), and zero particles per frame was read (a "truth kept by
    some particle" share of 0 %). The other arrays were already required to be float."""
    import warnings

    result = track_recording(run, "map", tmp_path / "res", progress=False)
    with np.load(result / "particles.npz") as z:
        arrays = {k: z[k] for k in z.files}
    xyz = arrays["xyz_m"]
    arrays["xyz_m"] = {"str": xyz.astype(str), "record": np.zeros(xyz.shape, dtype=[("a", "f8")]),
                       "complex": xyz.astype(complex), "no particles": xyz[:, :0]}[change]
    if change == "no particles":
        for k in ("quat_wxyz", "log_posterior"):
            arrays[k] = arrays[k][:, :0]
    np.savez(result / "particles.npz", **arrays)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with pytest.raises(InputError, match=r"particles\.npz: column 'xyz_m': must be a float array"):
            read_result(result)


@pytest.mark.parametrize(("kwargs", "says"), [
    ({"noise_file": 5}, "noise_file must be a path"),           # pathlib's TypeError, naming no argument
    ({"noise_file": ""}, "noise_file must be a path"),          # read the current directory as the noise file
    ({"spread_scale": 3}, "spread_scale must be a path"),       # pathlib's TypeError
    ({"robust": "conic=cauchy:3"}, "robust must be a dict"),    # "dictionary update sequence element #0 has length 1"
    ({"disable": None}, "disable must be a list"),              # "'NoneType' object is not iterable"
    ({"disable": ["bogus"]}, "unknown likelihood switch"),      # refused only after OUT had been created
])
def test_track_recording_names_more_bad_arguments_before_any_work(kwargs: dict, says: str, run: Path,
                                                                   tmp_path: Path) -> None:
    out = tmp_path / "r"
    with pytest.raises(ValueError, match=says):
        track_recording(run, "map", out, progress=False, **kwargs)
    assert not out.exists()


# --- sixth audit --------------------------------------------------------------------------------------------

@pytest.mark.parametrize("bad", ["", None])
@pytest.mark.parametrize("call", ["simulate", "import_bag", "import_bop", "export_bag", "run_batch"])
def test_writers_refuse_an_out_that_is_not_a_path(call: str, bad: object, run: Path, tmp_path: Path,
                                                  monkeypatch: pytest.MonkeyPatch) -> None:
    """``out=""`` (an unset variable in a notebook) was pathlib's ``Path("")``, the current directory: ``simulate``
    wrote its run into it (replacing a frames.csv or recording.json there), ``import_bag`` / ``import_bop`` too when
    it was empty; ``out=None`` was pathlib's TypeError, naming no argument. Now an InputError naming ``out``."""
    from pinpoint_fg.experiments.batch import run_batch
    from pinpoint_fg.io.bag import export_bag, import_bag
    from pinpoint_fg.io.bop import BopImportConfig, import_bop
    from pinpoint_fg.sim.scenarios import simulate
    from tests.bop_scene import write_bop_scene

    if call == "import_bag":
        bag = export_bag(run, tmp_path / "b.bag", fmt="ros1")
    if call == "import_bop":
        write_bop_scene(tmp_path / "bop", n_images=2, without_needle=())
    cwd = tmp_path / "cwd"
    cwd.mkdir()
    monkeypatch.chdir(cwd)
    calls = {
        "simulate": lambda: simulate("normal", 2, out=bad),
        "import_bag": lambda: import_bag(bag, bad, run / "recording.json"),
        "import_bop": lambda: import_bop(tmp_path / "bop" / "000001", tmp_path / "bop" / "models" / "obj_000007.ply",
                                         bad, BopImportConfig(obj_id=7)),
        "export_bag": lambda: export_bag(run, bad, fmt="ros2"),
        "run_batch": lambda: run_batch([run], "map", bad, workers=1),
    }
    name = "out_dir" if call == "run_batch" else "out"
    with pytest.raises(InputError, match=f"^{name} must be a path"):
        calls[call]()
    assert not any(cwd.iterdir())


@pytest.mark.parametrize(("kwargs", "says"), [
    ({"frames": 2.5}, "frames must be a whole number"),   # tracked the first 2 frames, silently
    ({"frames": "3"}, "frames must be a whole number"),   # int("3"): a string taken as a count
    ({"frames": True}, "frames must be a whole number"),  # tracked 1 frame
    ({"out": None}, "^out must be a path"),               # pathlib's TypeError, naming no argument
])
def test_ablate_names_a_frame_count_or_out_that_is_not_one(kwargs: dict, says: str, run: Path,
                                                           tmp_path: Path) -> None:
    from pinpoint_fg.experiments.ablate import ablate

    with pytest.raises(InputError, match=says):
        ablate(**{"runs": [run], "out": tmp_path / "a", "jobs": 1, **kwargs})
    assert not (tmp_path / "a").exists()


@pytest.mark.parametrize(("call", "kwargs", "says"), [
    ("demo", {"frames": 0}, "n_frames"),
    ("demo", {"frames": 2.5}, "n_frames"),
    ("demo", {"seed": -1}, "seed"),
    ("benchmark", {"frames": 0}, "n_frames"),
    ("benchmark", {"seed": -1}, "seed"),
    ("benchmark", {"grid_frames": 0}, "n_frames"),
    ("benchmark", {"unseen_seeds": (-1,)}, "seed"),
])
def test_demo_and_benchmark_refuse_bad_sizes_before_creating_out(call: str, kwargs: dict, says: str,
                                                                 tmp_path: Path) -> None:
    """Each was refused by the simulator only after ``out`` had been created: an empty ``out`` was left behind."""
    from pinpoint_fg.experiments.benchmark import run_benchmark
    from pinpoint_fg.experiments.demo import run_demo

    out = tmp_path / "out"
    with pytest.raises(ValueError, match=says):
        if call == "demo":
            run_demo(out=out, **{"frames": 2, "jobs": 1, **kwargs})
        else:
            run_benchmark(out=out, **{"frames": 2, "jobs": 1, **kwargs})
    assert not out.exists()


@pytest.mark.parametrize("bad", ["", None])
@pytest.mark.parametrize("call", ["NoiseConfig.load", "SpreadScale.load", "read_board_to_needle", "read_ply_vertices"])
def test_loaders_name_a_path_argument_that_is_not_one(call: str, bad: object, tmp_path: Path,
                                                      monkeypatch: pytest.MonkeyPatch) -> None:
    """``None`` was pathlib's TypeError (no argument named), ``""`` read the current directory (". cannot read: Is a
    directory"); both are an InputError naming ``path`` (the audit's "left alone" list, closed after it)."""
    from pinpoint_fg.groundtruth import read_board_to_needle
    from pinpoint_fg.io.needle_mesh import read_ply_vertices
    from pinpoint_fg.io.spread_scale import SpreadScale
    from pinpoint_fg.noise import NoiseConfig

    monkeypatch.chdir(tmp_path)
    calls = {"NoiseConfig.load": NoiseConfig.load, "SpreadScale.load": SpreadScale.load,
             "read_board_to_needle": read_board_to_needle, "read_ply_vertices": read_ply_vertices}
    with pytest.raises(InputError, match="^path must be a path"):
        calls[call](bad)
