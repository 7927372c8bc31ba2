"""Settings of the simulator: camera, needle, sensor rates and every noise parameter.

Defaults follow the paper (§V, Table I) where it gives a number and are this project's
choice otherwise; each field says which. Noise models are described in
:mod:`pinpoint_fg.sim.kinematics` (robot kinematics) and :mod:`pinpoint_fg.sim.render`
(keypoints and masks).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import asdict, dataclass, field

from factors.geometry import NeedleModel, PinholeCamera


def default_camera() -> PinholeCamera:
    """The simulated endoscope: 1080x1080 px, fx = fy = 900 px, centred principal point.

    Mild barrel distortion (OpenCV k1 = -0.08, k2 = 0.02): at the image corner the radial
    scale is ~0.95, within the central third of the image it is above 0.99. The paper's
    camera is 1080x1080 at 30 Hz; its intrinsics are not published, these are plausible.
    """
    return PinholeCamera(
        fx=900.0, fy=900.0, cx=539.5, cy=539.5, width=1080, height=1080, distortion=(-0.08, 0.02, 0.0, 0.0, 0.0)
    )


def held_out_camera() -> PinholeCamera:
    """A second endoscope no setting of this project was tuned on: 1280x1024 px, fx 1050 / fy 1040 px, the
    principal point about 15 px right of and 12 px above the centre, stronger barrel distortion with a tangential part
    (OpenCV k1 = -0.22, k2 = 0.09, p1 = 0.001, p2 = -0.0015: at the farthest image corner the radial scale is
    ~0.90, against ~0.95 for the default).
    A chip of another size, another lens and an off-centre mount; used by :func:`held_out_config`."""
    return PinholeCamera(
        fx=1050.0, fy=1040.0, cx=655.0, cy=500.0, width=1280, height=1024, distortion=(-0.22, 0.09, 0.001, -0.0015, 0.0)
    )


def held_out_needle() -> NeedleModel:
    """A second needle: a 1/2 circle of radius 5.5 mm (a half circle of ~17 mm, e.g. an RB-1's size class) grasped
    60 degrees from the tail (a third of the way along, as the default 3/8 needle is), wire 0.45 mm."""
    return NeedleModel(radius_m=0.0055, tail_angle_rad=0.0, tip_angle_rad=math.pi, grasp_angle_rad=math.pi / 3.0,
                       wire_diameter_m=0.00045)


def held_out_config() -> SimConfig:
    """:class:`SimConfig` with the held-out camera and needle (``pinpoint-fg simulate --geometry held-out``).

    Every default of the trackers (noise, proposals, thresholds) was chosen on runs of the paper's geometry
    (:func:`default_camera`, the 3/8 needle): runs of this one test the general case, as a user's own camera and
    needle would. The scenarios' motions and every noise parameter are unchanged.
    """
    return SimConfig(camera=held_out_camera(), needle=held_out_needle())


#: ``pinpoint-fg simulate --geometry`` choices and their settings: the paper's camera and 3/8 needle, or the held-out
#: pair.
_GEOMETRY_CONFIGS: dict[str, Callable[[], SimConfig]] = {"paper": lambda: SimConfig(), "held-out": held_out_config}
GEOMETRIES = tuple(_GEOMETRY_CONFIGS)


def geometry_config(name: str) -> SimConfig:
    """The :class:`SimConfig` of a geometry of :data:`GEOMETRIES` (``ValueError`` for another name)."""
    if name not in _GEOMETRY_CONFIGS:
        raise ValueError(f"unknown geometry {name!r}; valid geometries: {', '.join(GEOMETRIES)}")
    return _GEOMETRY_CONFIGS[name]()


def _positive(name: str, value: float) -> None:
    if not (isinstance(value, (int, float)) and math.isfinite(value) and value > 0):
        raise ValueError(f"SimConfig.{name} must be a finite number > 0, got {value!r}")


def _probability(name: str, value: float) -> None:
    if not (isinstance(value, (int, float)) and 0.0 <= value <= 1.0):
        raise ValueError(f"SimConfig.{name} must be a probability in [0, 1], got {value!r}")


@dataclass(frozen=True)
class SimConfig:
    """Everything the simulator draws its runs from (scenario shapes are fixed in scenarios.py)."""

    camera: PinholeCamera = field(default_factory=default_camera)
    """Camera intrinsics, image size and OpenCV distortion (see :func:`default_camera`)."""
    needle: NeedleModel = field(default_factory=NeedleModel)
    """Needle geometry: r = 4.5 mm, 3/8 circle (tail 0, tip 3π/4), grasp at π/4, wire 0.4 mm (paper §V)."""
    frame_rate_hz: float = 30.0
    """Camera frame rate, Hz (paper: 30 Hz)."""
    mask_every: int = 3
    """A segmentation mask on every ``mask_every``-th frame (frames 0, 3, 6, ...): 10 Hz at 30 Hz (paper)."""
    tip_sigma_px: tuple[float, float] = (1.006, 1.012)
    """Tip keypoint noise std (u, v), pixels, added in the distorted image (paper Table I)."""
    tail_sigma_px: tuple[float, float] = (0.921, 0.680)
    """Tail keypoint noise std (u, v), pixels, added in the distorted image (paper Table I)."""
    keypoint_miss_prob: float = 0.03
    """Probability that a visible keypoint is not detected (independent per keypoint and frame)."""
    keypoint_margin_px: float = 2.0
    """A keypoint is only reported when its true pixel lies this far inside the image."""
    mask_miss_prob: float = 0.02
    """Probability that a segmentation frame yields no mask at all (the model failed)."""
    mask_centreline_sigma_px: float = 1.12
    """Std of the smooth sideways displacement of the segmented band (both edges together), pixels."""
    mask_edge_sigma_px: float = 0.7
    """Std of the smooth, independent jitter of each edge of the band, pixels."""
    mask_noise_length_px: float = 20.0
    """Correlation length (along the projected arc) of the mask boundary noise, pixels."""
    mask_min_half_width_px: float = 0.75
    """The rendered band is never thinner than twice this, pixels (a segmenter's minimum stroke)."""
    fp_blob_prob: float = 0.15
    """Probability that a mask contains a false-positive blob (a second one with this probability again)."""
    fp_blob_axes_px: tuple[float, float] = (2.0, 7.0)
    """Range of the semi-axes of false-positive ellipses, pixels (uniform)."""
    fp_blob_min_distance_px: float = 25.0
    """False-positive blobs are placed at least this far from the needle's projection, pixels."""
    mask_spur_prob: float = 0.0
    """Probability that a mask carries a spur (a second one with this probability again); 0 = none (default)."""
    mask_spur_length_px: tuple[float, float] = (20.0, 35.0)
    """Range of spur lengths, pixels (uniform): wire-wide branches off the band, i.e. skeleton outliers."""
    grasp_position_sigma_m: tuple[float, float, float] = (0.41e-3, 0.44e-3, 1.00e-3)
    """Marginal std of the recorded grasp position error, camera axes x, y, z, metres (paper Table I)."""
    perpendicular_sigma: float = 0.138
    """Std of the perpendicularity residual z_g·(R t_g) at the true pose caused by kinematics (Table I)."""
    grasper_rot_sigma_rad: float = 0.035
    """Std of the recorded grasper's tilt about its x and z axes (invisible to z_g·t_g), radians."""
    kin_bias_tau_s: float = 5.0
    """Time constant of the slowly varying (Ornstein-Uhlenbeck) kinematic bias, seconds."""
    kin_white_var_fraction: float = 0.01
    """Share of each kinematic error's variance that is white (frame-independent); the rest is the bias."""
    grasper_tilt_rad: float = math.radians(20.0)
    """Grasper axis z_g: the needle normal tilted by this angle towards the needle centre (⟂ tangent)."""

    def __post_init__(self) -> None:
        if not isinstance(self.camera, PinholeCamera) or self.camera.width is None or self.camera.height is None:
            raise ValueError("SimConfig.camera must be a PinholeCamera with width and height")
        if not isinstance(self.needle, NeedleModel):
            raise ValueError("SimConfig.needle must be a NeedleModel")
        _positive("frame_rate_hz", self.frame_rate_hz)
        if not (isinstance(self.mask_every, int) and self.mask_every >= 1):
            raise ValueError(f"SimConfig.mask_every must be an integer >= 1, got {self.mask_every!r}")
        for name in ("tip_sigma_px", "tail_sigma_px", "fp_blob_axes_px", "mask_spur_length_px"):
            v = tuple(float(x) for x in getattr(self, name))
            if len(v) != 2:
                raise ValueError(f"SimConfig.{name} must have 2 entries, got {len(v)}")
            for x in v:
                _positive(name, x)
            object.__setattr__(self, name, v)
        if self.fp_blob_axes_px[0] > self.fp_blob_axes_px[1]:
            raise ValueError("SimConfig.fp_blob_axes_px must be (min, max)")
        g = tuple(float(x) for x in self.grasp_position_sigma_m)
        if len(g) != 3:
            raise ValueError(f"SimConfig.grasp_position_sigma_m must have 3 entries, got {len(g)}")
        for x in g:
            _positive("grasp_position_sigma_m", x)
        object.__setattr__(self, "grasp_position_sigma_m", g)
        if self.mask_spur_length_px[0] > self.mask_spur_length_px[1]:
            raise ValueError("SimConfig.mask_spur_length_px must be (min, max)")
        for name in ("keypoint_miss_prob", "mask_miss_prob", "fp_blob_prob", "mask_spur_prob"):
            _probability(name, getattr(self, name))
        for name in (
            "keypoint_margin_px", "mask_noise_length_px", "mask_min_half_width_px", "fp_blob_min_distance_px",
            "kin_bias_tau_s",
        ):
            _positive(name, getattr(self, name))
        for name in ("mask_centreline_sigma_px", "mask_edge_sigma_px", "grasper_rot_sigma_rad"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v >= 0):
                raise ValueError(f"SimConfig.{name} must be a finite number >= 0, got {v!r}")
        if not (isinstance(self.perpendicular_sigma, (int, float)) and 0 <= self.perpendicular_sigma < 0.5):
            raise ValueError(f"SimConfig.perpendicular_sigma must be in [0, 0.5), got {self.perpendicular_sigma!r}")
        _probability("kin_white_var_fraction", self.kin_white_var_fraction)
        if not (isinstance(self.grasper_tilt_rad, (int, float)) and abs(self.grasper_tilt_rad) < math.pi / 2):
            raise ValueError(f"SimConfig.grasper_tilt_rad must be in (-pi/2, pi/2), got {self.grasper_tilt_rad!r}")

    @property
    def dt_s(self) -> float:
        """Time between camera frames, seconds."""
        return 1.0 / self.frame_rate_hz

    def to_json(self) -> dict:
        """A JSON-safe description (written under ``simulator.config`` in recording.json)."""
        d = asdict(self)
        d["camera"] = asdict(self.camera)
        d["needle"] = asdict(self.needle)
        return _jsonable(d)


def _jsonable(x: object) -> object:
    if isinstance(x, dict):
        return {k: _jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_jsonable(v) for v in x]
    return x
