"""Noise models of the residuals: bias (sample mean) and covariance per residual type.

Defaults are the paper's Table I (standard deviations, diagonal); ``pinpoint-fg calibrate``
writes a file of the same shape from residuals at ground-truth poses, and
``pinpoint-fg track --noise FILE`` reads it.

File format (JSON)::

    {"format": "pinpoint-noise", "version": 1,
     "residuals": {"tip": {"mean": [du, dv], "cov": [[...], [...]], "count": n}, ...}}

with one entry per residual type in :data:`RESIDUAL_DIMS`, and optionally (same version; a file
without it keeps :data:`DEFAULT_ROBUST`)::

     "robust": {"conic": {"loss": "huber", "k": 1.345}, "tip": {"loss": "none"}, ...}

the robust loss of each measurement residual (:mod:`factors.robust`, thresholds in whitened units), and
optionally ``"conic_correlation_px": ell`` (default 0): the correlation length of the backbone residuals along
the arc (:mod:`factors.conic_correlation`; 0 = independent pixels, the paper's model), and
``"conic_distance": "sampson" | "geometric"``: the backbone distance the conic noise was calibrated for
(``calibrate --conic-distance``; absent in files written before it was recorded, and then any distance is
accepted). ``track`` tracks with the file's distance unless told otherwise, and refuses another one: a sigma
fitted to one distance does not describe the other (their residuals differ most near edge-on, where it matters).
Units are those of the residual:
pixels (tip, tail, conic), metres (grasp_position, camera axes), unitless
(grasp_perpendicular), and the tangent ``[omega (rad); v (m)]`` of the motion residual
(per camera frame, in the needle frame: it is GTSAM's right-perturbation chart).

Decision (not in the paper): the calibrated mean is treated as a measurement bias and
subtracted from the residual before whitening, so ``whitened = L^-1 (r - mean)`` with
``cov = L L^T``.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from factors.robust import NO_LOSS, RobustLoss
from pinpoint_fg.errors import InputError, path_argument
from pinpoint_fg.io.jsonfile import json_shown, load_json

#: Residual types and their dimensions.
RESIDUAL_DIMS: dict[str, int] = {
    "tip": 2,
    "tail": 2,
    "conic": 1,
    "grasp_position": 3,
    "grasp_perpendicular": 1,
    "motion": 6,
}

#: Paper Table I standard deviations; motion is this project's choice (see DEFAULT_MOTION_SIGMA).
TABLE_I_SIGMA: dict[str, tuple[float, ...]] = {
    "tip": (1.006, 1.012),
    "tail": (0.921, 0.680),
    "conic": (1.235,),
    "grasp_position": (0.41e-3, 0.44e-3, 1.00e-3),
    "grasp_perpendicular": (0.138,),
}

#: Per-frame (30 Hz) process noise of the motion residual, [omega (rad) x3, v (m) x3].
#: The paper gives no value. The grasper's measured motion is accurate frame to frame, but the
#: needle can turn inside the grasp (external forces) and the robot can slip in tissue; 0.02 rad
#: (~1.1 deg) and 0.3 mm per frame admit ~35 deg/s and ~9 mm/s of unmodelled motion at 1 sigma.
DEFAULT_MOTION_SIGMA: tuple[float, ...] = (0.02, 0.02, 0.02, 0.3e-3, 0.3e-3, 0.3e-3)


#: Largest accepted correlation length of the backbone residuals (px): far beyond any image's size, a larger one
#: is a unit mistake (the whitening would treat a whole mask as one pixel).
MAX_CORRELATION_PX = 1e4

#: Residual types that take a robust loss (the motion residual stays Gaussian).
ROBUST_RESIDUALS: tuple[str, ...] = ("tip", "tail", "conic", "grasp_position", "grasp_perpendicular")

#: Default robust loss per residual (unlisted: none), chosen by measurement (README "Robust losses").
#: Mean translation (mm) / rotation (deg) error, seed 1, GTSAM MAP, 300 frames, each loss alone:
#:
#: ==========================  ===========  ===========  ============  ============
#: loss                        rotation     suturing     normal        normal+spurs
#: ==========================  ===========  ===========  ============  ============
#: none                        0.92 / 15.3  0.77 / 3.46  0.39 / 3.55   0.99 / 12.3
#: perpendicularity huber      0.87 / 13.8  0.77 / 3.48
#: perpendicularity cauchy 1   0.84 / 13.7  3.31 / 99.3  (flipped pose chosen at seeding)
#: conic huber 1.345           0.91 / 15.2  0.77 / 3.45                0.53 / 4.36
#: conic cauchy 1              1.12 / 18.4                             0.47 / 3.57
#: conic cauchy 3              0.91 / 15.2  0.77 / 3.43                0.52 / 4.15
#: grasp position huber        1.42 / 24.6
#: keypoints huber             0.93 / 15.1
#: old default (cauchy 3)      0.86 / 13.8  0.77 / 3.45  0.38 / 3.49   0.52 / 4.15
#: these defaults (gm 3)       0.86 / 13.9  0.77 / 3.41  0.38 / 3.44   0.50 / 3.84
#: the same with gm 2          0.97 / 15.4  0.78 / 3.35  0.37 / 3.33   0.48 / 3.65
#: the same with gm 4          0.86 / 13.8  0.77 / 3.44  0.38 / 3.49   0.51 / 3.96
#: ==========================  ===========  ===========  ============  ============
#:
#: The conic's default is Geman-McClure (k = 3) since the twenty-third round, Cauchy 3 before. The two
#: measure alike on clean masks (last two rows, each with perpendicularity huber; also SVN, MAP and MHT on
#: the benchmark's nine scenarios at seeds 1-8, README "Robust losses"), but a suture thread drawn into
#: every mask of normal-01 pulls a Cauchy conic 63-66 deg off for SVN, MAP and MHT alike, where
#: Geman-McClure, whose cost of a far pixel is bounded by k^2/2, stays at 3.9-4.5 deg. A real needle
#: always trails its thread, so the redescending loss is the safer default. k = 3 is a compromise, and near
#: an edge: on that thread run MAP gives 3.3 deg at k = 2, 3.9 at k = 3 and 72 at k = 4 (the thread pulls
#: again), while k = 2 costs the model-violating rotation run 1.5 deg (rows above). Measured again for SVN,
#: MAP and MHT on the nine benchmark scenarios at seeds 1-8 (twenty-fourth round, README "Robust losses"): k = 2
#: gains 0.1-0.2 deg on the clear runs but loses rotation (SVN 14.6 -> 16.4, MAP 15.1 -> 16.6 deg), drive (SVN
#: 28.0 -> 31.3) and MAP's snapshots (36.4 -> 49.4), so k = 3 stays.
DEFAULT_ROBUST: dict[str, RobustLoss] = {
    "conic": RobustLoss("gm", 3.0),
    "grasp_perpendicular": RobustLoss("huber", 1.345),
}


def parse_robust_spec(text: str) -> dict[str, RobustLoss]:
    """``--robust`` text -> loss per residual: ``none`` or ``NAME=LOSS[:K],...``.

    ``NAME`` is a residual of :data:`ROBUST_RESIDUALS` (``-`` or ``_``; ``keypoints`` means tip and
    tail), ``LOSS`` one of none/huber/cauchy/gm, ``K`` the threshold in standard deviations (default
    1.345 for Huber, 1.0 for Cauchy and Geman-McClure). The result is the complete setting: unlisted residuals get
    ``none``. Raises ValueError naming the bad item; a residual given twice (``conic=huber,conic=cauchy``, or
    ``keypoints`` beside ``tip``) is refused rather than the last entry silently winning.
    """
    out = {name: NO_LOSS for name in ROBUST_RESIDUALS}
    given: dict[str, str] = {}
    text = text.strip()
    if text.lower() in ("none", "off", ""):
        return out
    for item in text.split(","):
        if not item.strip():
            continue
        name, eq, loss = item.partition("=")
        if not eq:
            raise ValueError(f"robust item {item.strip()!r} must be NAME=LOSS[:K]")
        name = name.strip().replace("-", "_")
        names = ("tip", "tail") if name == "keypoints" else (name,)
        if names[0] not in ROBUST_RESIDUALS:
            raise ValueError(f"robust item {item.strip()!r}: unknown residual {name!r}; choose from "
                             + ", ".join(n.replace("_", "-") for n in ROBUST_RESIDUALS) + ", keypoints")
        try:
            rl = RobustLoss.parse(loss)
        except ValueError as exc:
            raise ValueError(f"robust item {item.strip()!r}: {exc}") from exc
        for n in names:
            if n in given:
                raise ValueError(f"robust item {item.strip()!r}: {n.replace('_', '-')} was already set by "
                                 f"{given[n]!r}; give each residual once")
            given[n] = item.strip()
            out[n] = rl
    return out


def format_robust(robust: dict[str, RobustLoss]) -> str:
    """The ``--robust`` text of a setting (``none`` when no loss is active)."""
    items = [f"{n.replace('_', '-')}={robust[n]}" for n in ROBUST_RESIDUALS if robust[n].active]
    return ",".join(items) if items else "none"


def _default_robust() -> dict[str, RobustLoss]:
    out = {name: NO_LOSS for name in ROBUST_RESIDUALS}
    out.update(DEFAULT_ROBUST)
    return out


@dataclass(frozen=True)
class ResidualNoise:
    """Bias and covariance of one residual type."""

    mean: np.ndarray
    """Sample mean (bias), shape (d,); subtracted before whitening."""
    cov: np.ndarray
    """Covariance, shape (d, d), symmetric positive definite."""
    count: int = 0
    """Number of residual samples it was estimated from (0: a default)."""

    def __post_init__(self) -> None:
        mean = np.asarray(self.mean, dtype=float).reshape(-1)
        cov = np.atleast_2d(np.asarray(self.cov, dtype=float))
        d = mean.shape[0]
        if cov.shape != (d, d):
            raise ValueError(f"cov must have shape ({d}, {d}) to match mean, got {cov.shape}")
        if not (np.all(np.isfinite(mean)) and np.all(np.isfinite(cov))):
            raise ValueError("noise mean/cov contain NaN or infinite values")
        cov = 0.5 * (cov + cov.T)
        if np.min(np.linalg.eigvalsh(cov)) <= 0:
            raise ValueError("noise covariance must be positive definite")
        object.__setattr__(self, "mean", mean)
        object.__setattr__(self, "cov", cov)

    @classmethod
    def from_sigma(cls, sigma: tuple[float, ...] | np.ndarray) -> ResidualNoise:
        """Zero-mean, diagonal noise with the given standard deviations."""
        s = np.asarray(sigma, dtype=float)
        return cls(mean=np.zeros_like(s), cov=np.diag(s**2))

    @property
    def dim(self) -> int:
        """Residual dimension."""
        return int(self.mean.shape[0])

    @property
    def sigma(self) -> np.ndarray:
        """Marginal standard deviations, shape (d,)."""
        return np.sqrt(np.diag(self.cov))

    @property
    def sqrt_information(self) -> np.ndarray:
        """``W`` with ``W^T W = cov^-1`` (upper triangular), so the whitened residual is ``W (r - mean)``.

        Computed once per covariance value (every frame's likelihood asks for it; the result is a copy of the
        kept one, which is recomputed if ``cov`` is ever changed in place).
        """
        key = self.cov.tobytes()
        kept = self.__dict__.get("_sqrt_information")
        if kept is None or kept[0] != key:
            kept = (key, np.linalg.inv(np.linalg.cholesky(self.cov)))
            object.__setattr__(self, "_sqrt_information", kept)
        return kept[1].copy()

    def gtsam_model(self):  # noqa: ANN201 - gtsam type
        """The matching zero-mean gtsam noise model (Diagonal when the covariance is diagonal)."""
        import gtsam

        off = self.cov - np.diag(np.diag(self.cov))
        if np.allclose(off, 0.0):
            return gtsam.noiseModel.Diagonal.Sigmas(self.sigma)
        return gtsam.noiseModel.Gaussian.Covariance(self.cov)


def _default_residuals() -> dict[str, ResidualNoise]:
    out = {k: ResidualNoise.from_sigma(v) for k, v in TABLE_I_SIGMA.items()}
    out["motion"] = ResidualNoise.from_sigma(DEFAULT_MOTION_SIGMA)
    return out


#: The backbone distances a conic noise can be calibrated for
#: (:attr:`pinpoint_fg.likelihood.MeasurementModel.conic_distance`).
CONIC_DISTANCES = ("sampson", "geometric")


@dataclass(frozen=True)
class NoiseConfig:
    """Noise of every residual type (defaults: the paper's Table I plus DEFAULT_MOTION_SIGMA)."""

    residuals: dict[str, ResidualNoise] = field(default_factory=_default_residuals)
    """Residual type -> its noise; keys are those of RESIDUAL_DIMS."""
    robust: dict[str, RobustLoss] = field(default_factory=_default_robust)
    """Residual type -> its robust loss; keys are those of ROBUST_RESIDUALS (missing ones: DEFAULT_ROBUST)."""
    conic_correlation_px: float = 0.0
    """Correlation length (px) of the backbone residuals along the arc (:mod:`factors.conic_correlation`); 0 =
    independent pixels."""
    conic_distance: str | None = None
    """The backbone distance the conic noise was calibrated for (one of :data:`CONIC_DISTANCES`); None: not
    recorded (the defaults, older files), any distance."""

    def __post_init__(self) -> None:
        if self.conic_distance is not None and self.conic_distance not in CONIC_DISTANCES:
            raise ValueError(f"conic_distance must be one of {', '.join(CONIC_DISTANCES)} or None, "
                             f"got {self.conic_distance!r}")
        ell = self.conic_correlation_px
        if isinstance(ell, bool) or not isinstance(ell, (int, float)) or not (0.0 <= ell <= MAX_CORRELATION_PX):
            raise ValueError(f"conic_correlation_px must be a number of pixels in [0, {MAX_CORRELATION_PX:g}], "
                             f"got {ell!r}")
        object.__setattr__(self, "conic_correlation_px", float(ell))
        rob = _default_robust()
        rob.update(self.robust)
        for k, v in rob.items():
            if k not in ROBUST_RESIDUALS:
                raise ValueError(f"no robust loss for residual type {k!r}; expected one of {ROBUST_RESIDUALS}")
            if not isinstance(v, RobustLoss):
                raise ValueError(f"robust loss of {k!r} must be a RobustLoss, got {type(v).__name__}")
        object.__setattr__(self, "robust", rob)
        merged = _default_residuals()
        merged.update(self.residuals)
        for k, v in merged.items():
            if k not in RESIDUAL_DIMS:
                raise ValueError(f"unknown residual type {k!r}; expected one of {sorted(RESIDUAL_DIMS)}")
            if v.dim != RESIDUAL_DIMS[k]:
                raise ValueError(f"noise for {k!r} has dimension {v.dim}, expected {RESIDUAL_DIMS[k]}")
        object.__setattr__(self, "residuals", merged)

    def __getitem__(self, key: str) -> ResidualNoise:
        return self.residuals[key]

    def loss(self, key: str) -> RobustLoss:
        """The robust loss of residual type ``key`` (``none`` for motion)."""
        return self.robust.get(key, NO_LOSS)

    def with_robust(self, robust: dict[str, RobustLoss]) -> NoiseConfig:
        """A copy with the robust losses replaced by ``robust`` (unlisted residuals: DEFAULT_ROBUST)."""
        return NoiseConfig(residuals=dict(self.residuals), robust=dict(robust),
                           conic_correlation_px=self.conic_correlation_px, conic_distance=self.conic_distance)

    def with_conic_correlation(self, length_px: float) -> NoiseConfig:
        """A copy with the backbone residuals' correlation length set to ``length_px`` (0: independent)."""
        return NoiseConfig(residuals=dict(self.residuals), robust=dict(self.robust), conic_correlation_px=length_px,
                           conic_distance=self.conic_distance)

    def with_conic_distance(self, distance: str) -> NoiseConfig:
        """A copy recording that its conic noise was calibrated for the backbone distance ``distance``."""
        return NoiseConfig(residuals=dict(self.residuals), robust=dict(self.robust),
                           conic_correlation_px=self.conic_correlation_px, conic_distance=distance)

    @property
    def process_cov(self) -> np.ndarray:
        """Per-frame process noise ``Q`` (6x6, ``[omega; v]``) of the motion residual."""
        return self.residuals["motion"].cov

    def to_json(self) -> dict:
        """The JSON object written by ``calibrate``."""
        return {
            "format": "pinpoint-noise",
            "version": 1,
            "residuals": {
                k: {"mean": v.mean.tolist(), "cov": v.cov.tolist(), "count": int(v.count)}
                for k, v in self.residuals.items()
            },
            "robust": {k: ({"loss": v.kind, "k": v.k} if v.active else {"loss": "none"})
                       for k, v in self.robust.items()},
            "conic_correlation_px": self.conic_correlation_px,
            **({} if self.conic_distance is None else {"conic_distance": self.conic_distance}),
        }

    def save(self, path: str | Path) -> None:
        """Write the JSON file; :class:`InputError` (nothing written) for a variance :meth:`load` would refuse
        (e.g. ``calibrate`` on noise-free data)."""
        for k, noise in self.residuals.items():
            problem = _variance_problem(k, noise.cov)
            if problem is not None:
                raise InputError(f"residual {k!r}: {problem}; a noise file may not hold it", file=Path(path))
        Path(path).write_text(json.dumps(self.to_json(), indent=2) + "\n")

    @classmethod
    def load(cls, path: str | Path) -> NoiseConfig:
        """Read and validate a noise file; residual types it omits keep their defaults."""
        path = path_argument("path", path)  # None was pathlib's TypeError; "" read the current directory
        doc = load_json(path)  # bounded nesting and integer size; InputError naming the file
        if not isinstance(doc, dict) or doc.get("format") != "pinpoint-noise":
            raise InputError('key "format" must be "pinpoint-noise"', file=path)
        if doc.get("version") != 1:
            raise InputError(f'key "version": unsupported version {doc.get("version")!r}', file=path)
        res = doc.get("residuals")
        if not isinstance(res, dict):
            raise InputError('key "residuals" must be an object', file=path)
        parsed: dict[str, ResidualNoise] = {}
        for k, entry in res.items():
            if k not in RESIDUAL_DIMS:
                continue  # forward compatibility: unknown residual types are ignored
            where = f'key "residuals.{k}"'
            if not isinstance(entry, dict) or "cov" not in entry:
                raise InputError(f'{where} must be an object with "cov" (and optionally "mean")', file=path)
            d = RESIDUAL_DIMS[k]
            _check_entry_types(entry, where, path, d)
            try:
                mean = np.asarray(entry.get("mean", [0.0] * d), dtype=float).reshape(-1)
                cov = np.atleast_2d(np.asarray(entry["cov"], dtype=float))
            except (TypeError, ValueError) as exc:
                raise InputError(f"{where}: {exc}", file=path) from exc
            _check_cov_asymmetry(cov, where, path)
            _check_magnitudes(mean, cov, where, path)
            try:
                parsed[k] = ResidualNoise(mean=mean, cov=cov, count=entry.get("count", 0))
            except (TypeError, ValueError) as exc:
                raise InputError(f"{where}: {exc}", file=path) from exc
            if parsed[k].dim != d:
                raise InputError(f"{where}: dimension {parsed[k].dim}, expected {d}", file=path)
            problem = _variance_problem(k, parsed[k].cov)
            if problem is not None:
                raise InputError(f"{where}: {problem}", file=path)
        ell = doc.get("conic_correlation_px", 0.0)
        if isinstance(ell, bool) or not isinstance(ell, (int, float)) or not (0.0 <= ell <= MAX_CORRELATION_PX):
            raise InputError(f'key "conic_correlation_px" must be a number of pixels in [0, {MAX_CORRELATION_PX:g}], '
                             f"got {ell!r}", file=path)
        distance = doc.get("conic_distance")
        if distance is not None and distance not in CONIC_DISTANCES:
            raise InputError(f'key "conic_distance" must be one of {", ".join(CONIC_DISTANCES)}, got {distance!r}',
                             file=path)
        return cls(residuals=parsed, robust=_load_robust(doc.get("robust", {}), path), conic_correlation_px=ell,
                   conic_distance=distance)

    def process_variance_whitened(self, scale: np.ndarray) -> float:
        """``tr(S^-1 Q S^-1) / 6``: the mean per-axis process variance in the kernel's whitened units."""
        s = np.asarray(scale, dtype=float)
        return float(np.trace(self.process_cov / np.outer(s, s)) / 6.0)


#: Accepted range of a noise file's variances (eigenvalues of ``cov``), in the residual's unit squared (px, m,
#: rad): a standard deviation of 1e-7 to 1e6. Below it no measurement is that exact and the whitened residuals
#: overflowed SVN's log posterior (variance 1e-16: ``log_posterior contains NaN or +inf``); above it, or a
#: ``|mean|`` beyond :data:`MAX_NOISE_ABS_MEAN`, the file is a unit mistake (``1e308`` gave NaN poses).
NOISE_VARIANCE_RANGE = (1e-14, 1e12)
#: Unit of each residual type's standard deviation (error messages).
RESIDUAL_UNITS: dict[str, str] = {"tip": "px", "tail": "px", "conic": "px", "grasp_position": "m",
                                  "grasp_perpendicular": "(unitless)", "motion": "rad / m"}
#: Smallest accepted variance per residual type, in its unit squared: a standard deviation of 0.01 px for the
#: pixel residuals, 10 µm for the grasp position, 1e-4 for perpendicularity (no detector, kinematic chain or
#: grasp is that exact), :data:`NOISE_VARIANCE_RANGE`'s 1e-14 for the motion. Below these, GTSAM's MAP
#: baseline met an indeterminate linear system on the simulator's normal run (tip at a variance of 1e-7 px^2
#: while 1e-6 tracked; grasp position at 1e-14 m^2 while 1e-12 tracked; perpendicularity at 1e-14 while 1e-10
#: tracked; motion tracked at 1e-14), so each floor lies 100x above the smallest variance seen to track.
NOISE_VARIANCE_FLOOR: dict[str, float] = {"tip": 1e-4, "tail": 1e-4, "conic": 1e-4, "grasp_position": 1e-10,
                                          "grasp_perpendicular": 1e-8, "motion": NOISE_VARIANCE_RANGE[0]}
#: Largest accepted ``|mean|`` (bias) of a noise file's residual, in the residual's unit.
MAX_NOISE_ABS_MEAN = 1e6
#: Largest accepted ``|cov - cov^T|`` relative to ``max |cov|`` (rounding; a larger asymmetry is a typo that
#: symmetrising would silently turn into another covariance).
NOISE_COV_ASYMMETRY_TOL = 1e-9


def _variance_problem(name: str, cov: np.ndarray) -> str | None:
    """Why residual ``name``'s ``cov`` may not be in a noise file (a variance outside its floor ..
    :data:`NOISE_VARIANCE_RANGE`'s top), or None: the one check :meth:`NoiseConfig.load` and ``save`` share."""
    lo, hi = NOISE_VARIANCE_FLOOR.get(name, NOISE_VARIANCE_RANGE[0]), NOISE_VARIANCE_RANGE[1]
    w = np.linalg.eigvalsh(cov)
    if w[0] >= lo and w[-1] <= hi:
        return None
    return (f"'cov' has a variance of {w[0] if w[0] < lo else w[-1]:.3g}, accepted {lo:g} .. {hi:g} (a standard "
            f"deviation of {np.sqrt(lo):g} to 1e6 {RESIDUAL_UNITS.get(name, 'in its unit')})")


def _array_problem(value: object, shape: tuple[int, ...], at: str = "") -> str | None:
    """Why ``value`` (parsed JSON) is not nested lists of ``shape`` holding finite numbers (not booleans); None if
    it is. The element is named (``[1][0]``), so NumPy's "inhomogeneous shape" never reaches the user."""
    if not isinstance(value, list) or len(value) != shape[0]:
        what = (f"a list of {shape[0]} number{'s' if shape[0] != 1 else ''}" if len(shape) == 1
                else f"a {shape[0]}x{shape[1]} array (rows of numbers)")
        return f"{at + ' ' if at else ''}must be {what}, got {json_shown(value)}"
    for i, v in enumerate(value):
        if len(shape) > 1:
            why = _array_problem(v, shape[1:], f"{at}[{i}]")
            if why is not None:
                return why
        elif isinstance(v, bool) or not isinstance(v, int | float):
            return f"{at}[{i}] must be a number, got {json_shown(v)}"
        elif not math.isfinite(v):
            return f"{at}[{i}] must be finite, got {v!r} (JSON Infinity/NaN, or beyond a double)"
    return None


def _check_entry_types(entry: dict, where: str, path: Path, dim: int) -> None:
    """JSON types of one ``residuals`` entry: ``mean`` a list of ``dim`` finite numbers (optional), ``cov`` a
    ``dim x dim`` array of them (numbers, not booleans; for ``dim`` 1 also a bare number or a one-element list),
    a non-negative integer count."""
    for key, shape in (("mean", (dim,)), ("cov", (dim, dim))):
        if key == "mean" and key not in entry:
            continue
        value = entry[key]
        if dim == 1:  # a 1-D residual's scalar forms, as the loader reads them: 0.25, [0.25] or [[0.25]]
            flat = value
            while isinstance(flat, list) and len(flat) == 1 and isinstance(flat[0], list):
                flat = flat[0]
            if not isinstance(flat, list):
                flat = [flat]
            value = flat if key == "mean" else [flat]
        why = _array_problem(value, shape)
        if why is not None:
            raise InputError(f"{where}: {key!r}: {why}", file=path)
    count = entry.get("count", 0)
    if isinstance(count, bool) or not isinstance(count, int) or count < 0:
        raise InputError(f"{where}: 'count' must be a non-negative integer, got {count!r}", file=path)


def _check_cov_asymmetry(cov: np.ndarray, where: str, path: Path) -> None:
    """Refuse a square ``cov`` that is not symmetric up to rounding."""
    if cov.ndim != 2 or cov.shape[0] != cov.shape[1] or not np.all(np.isfinite(cov)):
        return  # ResidualNoise names these problems
    scale = float(np.max(np.abs(cov))) if cov.size else 0.0
    if float(np.max(np.abs(cov - cov.T), initial=0.0)) > NOISE_COV_ASYMMETRY_TOL * scale:
        raise InputError(f"{where}: 'cov' is not symmetric", file=path)


def _check_magnitudes(mean: np.ndarray, cov: np.ndarray, where: str, path: Path) -> None:
    """Refuse entries too large for the maths before they are used (the eigenvalue range is checked after
    :class:`ResidualNoise` validated the shape): ``|mean|`` above :data:`MAX_NOISE_ABS_MEAN`, ``|cov|`` above
    the largest accepted variance."""
    if mean.size and np.all(np.isfinite(mean)) and float(np.max(np.abs(mean))) > MAX_NOISE_ABS_MEAN:
        raise InputError(f"{where}: 'mean' beyond {MAX_NOISE_ABS_MEAN:g} in absolute value", file=path)
    hi = NOISE_VARIANCE_RANGE[1]
    if cov.size and np.all(np.isfinite(cov)) and float(np.max(np.abs(cov))) > hi:
        raise InputError(f"{where}: 'cov' has an entry beyond {hi:g} (a standard deviation above 1e6 in the "
                         "residual's unit)", file=path)


def _load_robust(rob: object, path: Path) -> dict[str, RobustLoss]:
    """The optional ``robust`` object of a noise file (unknown residual types are ignored)."""
    if not isinstance(rob, dict):
        raise InputError('key "robust" must be an object', file=path)
    out: dict[str, RobustLoss] = {}
    for k, entry in rob.items():
        if k not in ROBUST_RESIDUALS:
            continue
        where = f'key "robust.{k}"'
        if not isinstance(entry, dict) or not isinstance(entry.get("loss"), str):
            raise InputError(f'{where} must be an object with "loss" (none, huber, cauchy, gm) and optionally "k"',
                             file=path)
        kind = entry["loss"]
        default_k = 1.345 if kind == "huber" else 1.0
        k_value = entry.get("k", default_k)
        if isinstance(k_value, bool) or not isinstance(k_value, int | float):
            raise InputError(f'{where}: "k" must be a number, got {k_value!r}', file=path)
        try:
            out[k] = RobustLoss(kind, float(k_value))
        except (TypeError, ValueError) as exc:
            raise InputError(f"{where}: {exc}", file=path) from exc
    return out


def degrees(rad: float) -> float:
    """Radians to degrees (small helper for reports)."""
    return rad * 180.0 / math.pi
