"""The spread-scale file: per-method factors for the reported q95 bounds (``calibrate-spread`` writes it).

A :class:`SpreadScale` holds, per tracking method, the factors ``kappa_trans`` and ``kappa_rot`` by
which the q95 bounds of that method must be multiplied to cover ``level`` (95 %) of the frames; they are
fitted on training results with ground truth by :func:`pinpoint_fg.eval.spread_calibration.fit_spread_scale`
(the fit and its decisions are documented there). ``evaluate --spread-scale`` applies them to results
when it scores them, ``track --spread-scale`` to the q95 columns it writes and to the covariances of
``modes.csv`` (:func:`scaled_cov_xi`), and records that in ``result.json``'s ``settings.spread_scale``
(see :func:`recorded_scale`).

File format (JSON, UTF-8)::

    {"format": "pinpoint-spread-scale", "version": 1, "level": 0.95, "mode_gate_rad": 0.5236,
     "methods": {"svn": {"kappa_trans": 1.8, "kappa_rot": 1.6, "frames": 730, "skipped_frames": 0,
                         "wrong_mode_frames": 20, "coverage_raw_trans": 0.71, "coverage_raw_rot": 0.64}, ...},
     "unfitted": {"pf": "why it could not be fitted"},
     "results": ["/path/of/a/training/result", ...]}

Required: ``format``, ``version``, ``level`` in (0, 1), ``mode_gate_rad`` in (0, pi], a non-empty
``methods`` with ``kappa_trans`` and ``kappa_rot`` in [1e-6, 1e6] per method. Optional: the counts
(non-negative integers, default 0), ``coverage_raw_*`` (the training coverage before scaling, in [0, 1]
or null), ``unfitted`` (method -> reason; such a method is refused when applied, naming the reason) and
``results`` (the training results, provenance only). Unknown keys are ignored (forward compatibility).
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from pinpoint_fg.errors import InputError, path_argument
from pinpoint_fg.io.jsonfile import json_shown, load_json

SPREAD_SCALE_FORMAT = "pinpoint-spread-scale"
SPREAD_SCALE_VERSION = 1
LEVEL = 0.95
"""Coverage the scaled bound is fitted to: the trackers report a 95 % bound."""
PARTS = ("trans", "rot")
MODE_GATE_RAD = math.radians(30.0)
"""Default training gate: a frame whose MAP rotation error exceeds 30° is in another mode (the fit's docstring)."""


@dataclass(frozen=True)
class MethodScale:
    """The fitted factors of one method (and their training statistics, for the record)."""

    kappa_trans: float
    """Factor applied to ``q95_trans_m`` (dimensionless, > 0)."""
    kappa_rot: float
    """Factor applied to ``q95_rot_rad`` (dimensionless, > 0)."""
    frames: int = 0
    """Training frames both factors were fitted on."""
    skipped_frames: int = 0
    """Training frames with ground truth left out because a q95 was not finite (no claim)."""
    wrong_mode_frames: int = 0
    """Training frames left out because the MAP was in another mode (rotation error beyond the gate)."""
    coverage_raw_trans: float = float("nan")
    """Share of the training frames whose translation error is within the raw q95."""
    coverage_raw_rot: float = float("nan")
    """Share of the training frames whose rotation error is within the raw q95."""


@dataclass(frozen=True)
class SpreadScale:
    """Per-method q95 factors fitted by :func:`fit_spread_scale` (the file of ``calibrate-spread``)."""

    methods: dict[str, MethodScale]
    """Method name (``result.json``'s ``method``) -> its factors."""
    level: float = LEVEL
    """The coverage the factors were fitted to."""
    mode_gate_rad: float = math.pi
    """Training frames whose MAP rotation error exceeded this were left out (another mode), radians."""
    results: tuple[str, ...] = ()
    """The training result directories (provenance)."""
    unfitted: dict[str, str] = field(default_factory=dict)
    """Methods of the training results that could not be fitted -> why (e.g. a collapsed particle filter)."""
    source: str | None = None
    """The file it was read from (None when built in memory)."""

    def for_method(self, method: str) -> MethodScale:
        """The factors of ``method``; :class:`InputError` when the file has none (never a silent 1.0), or when they
        were fitted for another coverage than :data:`LEVEL`: applied to the q95 columns (95 % bounds by the result
        format), a 90 % file's factors would label a 90 % bound q95."""
        if not math.isclose(self.level, LEVEL, rel_tol=0.0, abs_tol=1e-12):
            raise InputError(f"the factors were fitted for {100 * self.level:g} % coverage; the q95 columns they "
                             f"scale are {100 * LEVEL:g} % bounds (refit with `pinpoint-fg calibrate-spread`)",
                             file=self.source, column="level")
        if method in self.unfitted:
            raise InputError(f"no scale for method {method!r}: it could not be fitted ({self.unfitted[method]})",
                             file=self.source, column=f"methods.{method}")
        if method not in self.methods:
            have = ", ".join(sorted(self.methods)) or "none"
            raise InputError(f"no scale for method {method!r} (the file has: {have}); fit one with "
                             "`pinpoint-fg calibrate-spread` on results of that method", file=self.source,
                             column=f"methods.{method}")
        return self.methods[method]

    def to_json(self) -> dict[str, Any]:
        """The file's JSON document (NaN statistics written as null)."""
        def num(x: float) -> float | None:
            return float(x) if math.isfinite(x) else None

        return {
            "format": SPREAD_SCALE_FORMAT, "version": SPREAD_SCALE_VERSION, "level": self.level,
            "mode_gate_rad": self.mode_gate_rad,
            "methods": {m: {"kappa_trans": s.kappa_trans, "kappa_rot": s.kappa_rot, "frames": s.frames,
                            "skipped_frames": s.skipped_frames, "wrong_mode_frames": s.wrong_mode_frames,
                            "coverage_raw_trans": num(s.coverage_raw_trans),
                            "coverage_raw_rot": num(s.coverage_raw_rot)}
                        for m, s in sorted(self.methods.items())},
            "unfitted": dict(sorted(self.unfitted.items())),
            "results": list(self.results),
        }

    def save(self, path: str | Path) -> Path:
        """Write the JSON file; returns its path."""
        path = Path(path)
        path.write_text(json.dumps(self.to_json(), indent=2, allow_nan=False) + "\n", encoding="utf-8")
        return path

    @classmethod
    def load(cls, path: str | Path) -> SpreadScale:
        """Read and validate a spread-scale file; every problem is one :class:`InputError` naming the key."""
        path = path_argument("path", path)  # None was pathlib's TypeError; "" read the current directory
        doc = load_json(path)
        if not isinstance(doc, dict):
            raise InputError("the top level must be a JSON object", file=path)
        if doc.get("format") != SPREAD_SCALE_FORMAT:
            raise InputError(f"must be {SPREAD_SCALE_FORMAT!r}, got {json_shown(doc.get('format'))}", file=path,
                             column="format")
        version = doc.get("version")
        if version != SPREAD_SCALE_VERSION or isinstance(version, bool):
            raise InputError(f"unsupported version {json_shown(version)} (this reader knows "
                             f"{SPREAD_SCALE_VERSION})", file=path, column="version")
        level = _number(doc, "level", path, "level")
        if not 0.0 < level < 1.0:
            raise InputError(f"must lie in (0, 1), got {level!r}", file=path, column="level")
        gate = _number(doc, "mode_gate_rad", path, "mode_gate_rad")
        if not 0.0 < gate <= math.pi:
            raise InputError(f"must lie in (0, pi], got {gate!r}", file=path, column="mode_gate_rad")
        methods = doc.get("methods")
        if not isinstance(methods, dict) or not methods:
            raise InputError(f"must be a non-empty object of method -> factors, got {json_shown(methods)}",
                             file=path, column="methods")
        parsed = {}
        for name, entry in methods.items():
            key = f"methods.{name}"
            if not isinstance(entry, dict):
                raise InputError(f"must be an object, got {json_shown(entry)}", file=path, column=key)
            kappa = {}
            for part in PARTS:
                kappa[part] = _kappa(entry, f"kappa_{part}", path, f"{key}.kappa_{part}")
            counts = {c: _count(entry, c, path, f"{key}.{c}") for c in ("frames", "skipped_frames",
                                                                        "wrong_mode_frames")}
            cover = {}
            for part in PARTS:
                c = f"coverage_raw_{part}"
                v = entry.get(c)
                if v is None:
                    cover[part] = float("nan")
                    continue
                v = _number(entry, c, path, f"{key}.{c}")
                if not 0.0 <= v <= 1.0:
                    raise InputError(f"must lie in [0, 1], got {v!r}", file=path, column=f"{key}.{c}")
                cover[part] = v
            parsed[str(name)] = MethodScale(kappa["trans"], kappa["rot"], **counts, coverage_raw_trans=cover["trans"],
                                            coverage_raw_rot=cover["rot"])
        results = doc.get("results", [])
        if not isinstance(results, list) or not all(isinstance(r, str) for r in results):
            raise InputError("must be a list of strings (the training results)", file=path, column="results")
        unfitted = doc.get("unfitted", {})
        if not isinstance(unfitted, dict) or not all(isinstance(v, str) for v in unfitted.values()):
            raise InputError("must be an object of method -> reason (strings)", file=path, column="unfitted")
        both = sorted(set(unfitted) & set(parsed))
        if both:
            raise InputError(f"method {both[0]!r} is both fitted and unfitted", file=path, column=f"unfitted.{both[0]}")
        return cls(methods=parsed, level=level, mode_gate_rad=gate, results=tuple(results), unfitted=dict(unfitted),
                   source=str(path))


#: Accepted range of a factor ``kappa``: beyond it the file is a mistake, and ``kappa^2`` times a covariance
#: overflowed ``track --spread-scale`` (``1e308``: numpy's "Eigenvalues did not converge") while
#: ``evaluate --spread-scale`` silently reported infinite bounds.
KAPPA_RANGE = (1e-6, 1e6)


def _kappa(doc: dict, key: str, path: Path, column: str) -> float:
    """A required factor of ``doc`` in :data:`KAPPA_RANGE`."""
    k = _number(doc, key, path, column)
    if not k > 0.0:
        raise InputError(f"must be positive, got {k!r}", file=path, column=column)
    if not KAPPA_RANGE[0] <= k <= KAPPA_RANGE[1]:
        raise InputError(f"must lie in [{KAPPA_RANGE[0]:g}, {KAPPA_RANGE[1]:g}], got {k!r}", file=path, column=column)
    return k


def _number(doc: dict, key: str, path: Path, column: str) -> float:
    """A required finite JSON number (not a boolean) of ``doc``."""
    if key not in doc:
        raise InputError("missing required key", file=path, column=column)
    v = doc[key]
    if isinstance(v, bool) or not isinstance(v, int | float):
        raise InputError(f"must be a number, got {json_shown(v)}", file=path, column=column)
    v = float(v)
    if not math.isfinite(v):
        raise InputError(f"must be finite, got {v!r}", file=path, column=column)
    return v


def _count(doc: dict, key: str, path: Path, column: str) -> int:
    """An optional non-negative JSON integer (default 0)."""
    v = doc.get(key, 0)
    if isinstance(v, bool) or not isinstance(v, int) or v < 0:
        raise InputError(f"must be a non-negative integer, got {json_shown(v)}", file=path, column=column)
    return int(v)


def format_scale(scale: SpreadScale) -> str:
    """The fitted factors as a text table (one row per method)."""
    lines = [f"spread scale for {100 * scale.level:g} % coverage, fitted on {len(scale.results)} result(s), "
             f"frames with a rotation error beyond {math.degrees(scale.mode_gate_rad):g} deg left out",
             "method  frames  other mode  raw cover t/r   kappa t/r"]
    for m, s in sorted(scale.methods.items()):
        lines.append(f"{m:<6} {s.frames:7d} {s.wrong_mode_frames:11d}  {100 * s.coverage_raw_trans:5.1f}/"
                     f"{100 * s.coverage_raw_rot:5.1f} %  {s.kappa_trans:5.2f}/{s.kappa_rot:5.2f}")
    for m, why in sorted(scale.unfitted.items()):
        lines.append(f"{m:<6} not fitted: {why}")
    return "\n".join(lines)


# ----------------------------------------------------------------------------- scaled at tracking time


def scaled_cov_xi(cov_xi: np.ndarray, kappa_trans: float, kappa_rot: float) -> np.ndarray:
    """A (6, 6) covariance in GTSAM's chart ``[omega; v]`` with the q95 factors applied: ``K C K``,
    ``K = diag(kappa_rot x3, kappa_trans x3)``.

    The rotation block is multiplied by ``kappa_rot^2``, the translation block by ``kappa_trans^2``, the
    cross blocks by ``kappa_rot kappa_trans``: the covariance of ``K xi`` for ``xi`` with covariance ``C``,
    whose ``|omega|`` and ``|v|`` are ``kappa_rot |omega|`` and ``kappa_trans |v|``. So the Gaussian's 95 %
    quantiles of ``|omega|`` and ``|v|`` (what q95 reports) grow by exactly the factors, the particle methods'
    deviations scale alike, and the correlations are unchanged. Elementwise (one product per entry), so a
    symmetric input stays exactly symmetric.
    """
    k = np.array([kappa_rot] * 3 + [kappa_trans] * 3, dtype=float)
    return np.asarray(cov_xi, dtype=float) * np.outer(k, k)


def settings_entry(scale: SpreadScale, method: str) -> dict[str, Any]:
    """What ``track --spread-scale`` records in ``result.json``'s ``settings.spread_scale``.

    ``{"file": the scale file, "kappa_trans": ..., "kappa_rot": ...}``: the q95 columns of that result are
    ``kappa · q95`` of the tracker's own bound, so the raw bound is ``q95 / kappa``.
    """
    s = scale.for_method(method)
    source = None if scale.source is None else str(Path(scale.source).resolve())
    return {"file": source, "kappa_trans": s.kappa_trans, "kappa_rot": s.kappa_rot}


def recorded_scale(settings: dict, file: str | Path) -> tuple[float, float] | None:
    """``(kappa_trans, kappa_rot)`` a result's q95 columns were scaled by when tracked, None when raw.

    ``settings``: ``result.json``'s ``settings`` (``file`` names that result.json in errors); a malformed
    ``spread_scale`` entry raises :class:`InputError` naming the key.
    """
    entry = settings.get("spread_scale") if isinstance(settings, dict) else None
    if entry is None:
        return None
    path = Path(file)
    if not isinstance(entry, dict):
        raise InputError(f"must be an object, got {json_shown(entry)}", file=path, column="settings.spread_scale")
    out = []
    for part in PARTS:
        out.append(_kappa(entry, f"kappa_{part}", path, f"settings.spread_scale.kappa_{part}"))
    return out[0], out[1]
