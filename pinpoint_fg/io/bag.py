"""ROS bags <-> recorded runs (format v1), through ``rosbags`` (pure Python; ROS 1 and ROS 2 bags).

:func:`import_bag` turns a bag into a run directory (written with
:class:`~pinpoint_fg.io.recording.RecordingWriter`); :func:`export_bag` writes a run as a bag
(read with :func:`~pinpoint_fg.io.recording.read_recording`). Default topics (:class:`BagTopics`):

=====================  =============================  ===============================================
topic                  type                           meaning
=====================  =============================  ===============================================
``/camera/camera_info``  ``sensor_msgs/CameraInfo``   one frame per message; intrinsics ``K``, ``D``
``/needle/mask``       ``sensor_msgs/Image``          segmentation, ``mono8`` (or ``8UC1``), nonzero = needle
``/needle/tip_px``     ``geometry_msgs/PointStamped``  tip keypoint: ``x`` = u, ``y`` = v, distorted pixels
``/needle/tail_px``    ``geometry_msgs/PointStamped``  tail keypoint, same convention
``/grasper/pose``      ``geometry_msgs/PoseStamped``   ``cam_T_grasper`` (kinematics)
``/needle/gt_pose``    ``geometry_msgs/PoseStamped``   ``cam_T_needle`` ground truth (optional)
=====================  =============================  ===============================================

Decisions (the issue leaves them open; import and export agree on every one):

* **Needle.** A bag carries no needle geometry: ``NEEDLE.json`` is the ``needle`` object of
  ``recording.json`` (``radius_m``, ``tail_angle_rad``, ``tip_angle_rad``, ``grasp_angle_rad``,
  ``wire_diameter_m``); a whole ``recording.json`` (an object with a ``needle`` key) is accepted too,
  so ``export-bag RUN`` then ``import-bag --needle RUN/recording.json`` round-trips.
* **Frames.** One frame per ``camera_info`` message, ordered by header stamp, indexed 0, 1, ...
  (a run's own frame indices are not carried by a bag). Two camera_info messages with the same
  stamp are an error. ``t_s`` is the header stamp **relative to the first camera_info stamp**
  (so the first frame has ``t_s = 0``): absolute epoch times as float64 seconds would keep only
  ~0.2 us, relative ones keep the nanosecond. The first stamp (the time origin) is kept in
  ``recording.json`` under ``"ros_bag": {"time_origin_ns": ..., "camera_frame_id": ...}``;
  the export writes the stamp ``time_origin_ns + round(t_s * 1e9)`` (origin 0 when absent).
* **frame_rate_hz** = 1 / median of the camera_info stamp differences (robust to a dropped
  frame), rounded to 1e-6 Hz: nanosecond stamps quantise a 30 Hz period by ~1e-6 Hz, so the
  rounding gives back the nominal rate (30 Hz -> 33333333 ns -> 30.0 Hz) instead of 30.0000003.
  A bag with a single frame needs ``frame_rate_hz`` given explicitly.
* **Camera.** From the first camera_info: ``fx = K[0]``, ``fy = K[4]``, ``cx = K[2]``, ``cy = K[5]``,
  image ``width``/``height``; ``K`` must have zero skew and the form ``[fx 0 cx; 0 fy cy; 0 0 1]``.
  ``K`` and ``D`` are the raw (distorted) image's, as the keypoints and masks are distorted pixels;
  ``R`` and ``P`` (rectification) are not used. ``distortion_model`` ``plumb_bob`` is OpenCV's
  ``(k1, k2, p1, p2, k3)`` (an empty ``D`` means no distortion); ``rational_polynomial`` (8
  coefficients, OpenCV's ``k1 k2 p1 p2 k3 k4 k5 k6``) is accepted too; any other model
  (``equidistant``, ...) is rejected. Every later camera_info must have the same size, K, D and
  model (one run has one camera). Binning or a region of interest is rejected.
* **Matching** the other topics "by header stamp": each frame takes the message of that topic
  whose header stamp is nearest to the frame's stamp, if within ``stamp_tolerance_s`` (default
  1 ms; 0 = exact match only); otherwise the frame's cells stay empty ("not observed"). The
  tolerance must be below half the median frame period, so a message can match one frame only.
  Two messages of one topic with the same stamp are an error (which one is the observation?).
  Messages that match no frame are counted in :class:`BagImportSummary`, not imported.
* **Keypoints.** ``PointStamped.point.x`` = u, ``.y`` = v; ``z`` is ignored (the export writes 0).
  Non-finite coordinates are an error, not "not observed" (publish nothing instead).
* **Poses.** ``position`` in metres, ``orientation`` (x, y, z, w) -> ``wxyz``; the quaternion must
  be unit within :data:`~pinpoint_fg.io.recording.schema.QUAT_NORM_TOL` and is normalised. A pose whose
  ``header.frame_id`` is set and differs from the camera_info's (when that is set) is rejected:
  the format's poses are in the camera frame and this module does no tf lookups.
* **Masks.** ``sensor_msgs/Image`` with encoding ``mono8`` or ``8UC1``, the camera's width and
  height, ``step >= width`` (row padding is dropped); nonzero = needle backbone. Other encodings are
  rejected. The export writes 0/255 ``mono8`` with ``step = width``.
* **Topics.** ``camera_info``, ``mask``, ``tip``, ``tail`` and ``grasper`` must be in the bag (a
  missing one is most often a misspelt name, which would silently empty a column): set a topic
  to None (CLI: ``none``) to skip it deliberately. ``gt`` is optional. A topic of the wrong
  message type is an error.
* **Not carried** by a bag, so not exported: camera images, occlusion labels, extra
  ``recording.json`` keys other than ``ros_bag``. The run's name comes from ``name`` (default:
  the bag's file name without suffix).
* **Export over an existing ``out``.** Refused unless ``overwrite`` (CLI ``--overwrite``), as every ``--out``; an
  empty directory counts as new (ROS 2). ``overwrite`` replaces a bag only: for ROS 2 a directory holding
  ``metadata.yaml`` (a rosbag2 one) and nothing but ``.db3``/``.mcap`` storage files, for ROS 1 a regular file that
  starts with ``#ROSBAG V2.0``. Anything else (a directory holding other files, a run directory, a file that is no
  bag) is refused with or without ``overwrite``, and so is a symbolic link (replacing the link would leave its
  target; writing through it would replace a bag elsewhere). The new bag is written into a hidden sibling and
  swapped in once complete (:func:`~pinpoint_fg.io.outdir.staged_replacement`): the old bag is replaced whole
  (no ``.db3`` left beside a new ``.mcap``), and kept as it was when writing fails (sqlite's own errors, a full
  disk under the default storage, included). An ``out`` that is the run or lies inside it is refused, as every
  command's output inside its input is.
* **Export format.** ROS 2 (rosbag2 version 9, ``sqlite3`` storage by default, ``mcap`` on request;
  CDR, ``ROS2_HUMBLE`` type store) or ROS 1 (``.bag`` version 2.0, ``ROS1_NOETIC`` type store).
  The bag's receive time of every message is its header stamp. All messages have
  ``header.frame_id`` = the recording's ``ros_bag.camera_frame_id`` or ``"camera"``.

Any problem raises :class:`~pinpoint_fg.errors.InputError` naming the bag (or NEEDLE.json) and the
topic/field; malformed bags that ``rosbags`` cannot parse are reported the same way.
"""

from __future__ import annotations

import json
import math
import os
import sqlite3
import struct
from collections.abc import Iterator
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any

import numpy as np

from factors.geometry import NeedleModel, PinholeCamera, pose_from_xyz_quat, xyz_quat_from_pose
from pinpoint_fg.errors import InputError, path_argument
from pinpoint_fg.io.outdir import (
    check_not_an_input,
    check_output_dir,
    shown_entries,
    staged_output_dir,
    staged_replacement,
)
from pinpoint_fg.io.recording.reader import read_recording
from pinpoint_fg.io.recording.schema import (
    MAX_ABS_ANGLE_RAD,
    MAX_NEEDLE_M,
    MIN_NEEDLE_M,
    QUAT_NORM_TOL,
    FrameRecord,
    Recording,
    RecordingInfo,
)
from pinpoint_fg.io.recording.writer import RecordingWriter, check_recording_info, frame_cells

#: recording.json key holding what a bag import knows beyond the format (time origin, frame id).
ROS_BAG_KEY = "ros_bag"
#: header.frame_id written by the export when the recording names none.
DEFAULT_CAMERA_FRAME_ID = "camera"
#: Default tolerance of the header-stamp matching, seconds.
DEFAULT_STAMP_TOLERANCE_S = 1e-3

_NS_PER_S = 1_000_000_000
_NEEDLE_KEYS = tuple(f.name for f in fields(NeedleModel))
_MSGTYPES = {
    "camera_info": "sensor_msgs/msg/CameraInfo",
    "mask": "sensor_msgs/msg/Image",
    "tip": "geometry_msgs/msg/PointStamped",
    "tail": "geometry_msgs/msg/PointStamped",
    "grasper": "geometry_msgs/msg/PoseStamped",
    "gt": "geometry_msgs/msg/PoseStamped",
}
_DISTORTION_MODELS = {"plumb_bob": (0, 5), "rational_polynomial": (8,)}
_MASK_ENCODINGS = ("mono8", "8UC1")
#: Exceptions rosbags (and the sqlite3 / struct / zstd layers under it) raise on a malformed bag.
_BAG_ERRORS: tuple[type[BaseException], ...] = (
    sqlite3.Error, struct.error, OSError, EOFError, ValueError, KeyError, IndexError, TypeError,
    UnicodeDecodeError, AssertionError,
)


@dataclass(frozen=True)
class BagTopics:
    """Topic names of a bag; None skips a topic (``camera_info`` cannot be skipped)."""

    camera_info: str = "/camera/camera_info"
    """sensor_msgs/CameraInfo: one frame per message, the intrinsics."""
    mask: str | None = "/needle/mask"
    """sensor_msgs/Image mono8: the needle segmentation."""
    tip: str | None = "/needle/tip_px"
    """geometry_msgs/PointStamped: tip keypoint (x = u, y = v, distorted pixels)."""
    tail: str | None = "/needle/tail_px"
    """geometry_msgs/PointStamped: tail keypoint (x = u, y = v, distorted pixels)."""
    grasper: str | None = "/grasper/pose"
    """geometry_msgs/PoseStamped: cam_T_grasper from the kinematics."""
    gt: str | None = "/needle/gt_pose"
    """geometry_msgs/PoseStamped: ground-truth cam_T_needle (optional in a bag)."""

    def __post_init__(self) -> None:
        if not self.camera_info:
            raise ValueError("the camera_info topic cannot be skipped: it defines the frames")
        for f in fields(self):
            v = getattr(self, f.name)
            if v is not None and (not isinstance(v, str) or not v.startswith("/")):
                raise ValueError(f"topic {f.name} must be an absolute ROS topic name ('/...'), got {v!r}")
        used = [v for v in (getattr(self, f.name) for f in fields(self)) if v is not None]
        if len(set(used)) != len(used):
            raise ValueError(f"two roles share one topic: {used}")

    def items(self) -> list[tuple[str, str]]:
        """``(role, topic)`` of the topics not skipped, camera_info first."""
        return [(f.name, getattr(self, f.name)) for f in fields(self) if getattr(self, f.name) is not None]


@dataclass(frozen=True)
class BagImportSummary:
    """What :func:`import_bag` found: frames, and per role the frames matched and messages unused."""

    run_dir: Path
    """The run directory written."""
    frames: int
    """Number of frames (camera_info messages)."""
    matched: dict[str, int] = field(default_factory=dict)
    """Role -> frames that got a message of that topic."""
    unmatched: dict[str, int] = field(default_factory=dict)
    """Role -> messages of that topic that matched no frame (not imported)."""

    def describe(self) -> str:
        """One line per role."""
        lines = [f"wrote {self.run_dir}: {self.frames} frames"]
        for role, n in self.matched.items():
            lines.append(f"  {role:8s} {n:6d} frames matched, {self.unmatched.get(role, 0)} messages unmatched")
        return "\n".join(lines)


# --------------------------------------------------------------------------------------------
# NEEDLE.json
# --------------------------------------------------------------------------------------------


def read_needle_json(path: str | Path) -> NeedleModel:
    """The needle of ``NEEDLE.json``: the ``needle`` object of recording.json, or a whole recording.json.

    Every key of the needle object is required and a finite number within the recording format's bounds
    (``radius_m`` and ``wire_diameter_m`` in [:data:`MIN_NEEDLE_M`, :data:`MAX_NEEDLE_M`], angles within
    ±:data:`MAX_ABS_ANGLE_RAD`);
    unknown keys are ignored. Errors name the file and the key.
    """
    path = Path(path)
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise InputError("file not found (the needle geometry: the 'needle' object of recording.json)",
                         file=path) from None
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(f"cannot read: {exc}", file=path) from None
    except json.JSONDecodeError as exc:
        raise InputError(f"not valid JSON: {exc.msg} at line {exc.lineno}, column {exc.colno}", file=path) from None
    prefix = ""
    if isinstance(doc, dict) and "needle" in doc:
        doc, prefix = doc["needle"], "needle."
    if not isinstance(doc, dict):
        raise InputError(f"must be a JSON object with the needle keys {', '.join(_NEEDLE_KEYS)}",
                         file=path, column=prefix.rstrip(".") or None)
    values: dict[str, float] = {}
    for key in _NEEDLE_KEYS:
        if key not in doc:
            raise InputError("missing required key", file=path, column=prefix + key)
        v = doc[key]
        if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v):
            raise InputError(f"must be a finite number, got {json.dumps(v)}", file=path, column=prefix + key)
        # the recording format's bounds, named here: beyond them the run's own recording.json was blamed at writing
        low, high = (MIN_NEEDLE_M[key], MAX_NEEDLE_M) if key in MIN_NEEDLE_M else (-MAX_ABS_ANGLE_RAD,
                                                                                  MAX_ABS_ANGLE_RAD)
        if not low <= v <= high:
            raise InputError(f"out of range: {v:g} (accepted {low:g} .. {high:g})", file=path, column=prefix + key)
        values[key] = float(v)
    try:
        return NeedleModel(**values)
    except ValueError as exc:
        raise InputError(str(exc), file=path, column=prefix.rstrip(".") or None) from None


# --------------------------------------------------------------------------------------------
# reading a bag
# --------------------------------------------------------------------------------------------


def _bag_paths(bag: Path) -> list[Path]:
    """What AnyReader opens: a ROS 1 ``.bag`` file or a ROS 2 directory (a ``.db3``/``.mcap`` file -> its dir)."""
    if not bag.exists():
        raise InputError("no such file or directory (a ROS 1 .bag file or a ROS 2 bag directory)", file=bag)
    if bag.is_file() and bag.suffix != ".bag":
        if bag.suffix in (".db3", ".mcap") and (bag.parent / "metadata.yaml").is_file():
            return [bag.parent]
        raise InputError("not a bag: a ROS 1 bag is a '.bag' file, a ROS 2 bag a directory with metadata.yaml",
                         file=bag)
    if bag.is_dir() and not (bag / "metadata.yaml").is_file():
        raise InputError("not a ROS 2 bag: the directory has no metadata.yaml", file=bag)
    return [bag]


def _stamp_ns(msg: Any) -> int:
    st = msg.header.stamp
    return int(st.sec) * _NS_PER_S + int(st.nanosec)


def _field(msg: Any, name: str) -> Any:
    """A CameraInfo array field: ROS 2 spells it ``k``, ROS 1 ``K``."""
    return getattr(msg, name) if hasattr(msg, name) else getattr(msg, name.upper())


@dataclass
class _TopicData:
    """The deserialised messages of one role: stamps (ns) and per-message payloads."""

    topic: str
    stamps: list[int] = field(default_factory=list)
    values: list[Any] = field(default_factory=list)


def _read_bag(bag: Path, topics: BagTopics) -> tuple[dict[str, _TopicData], dict[str, Any]]:
    """Every message of the wanted topics, deserialised and converted (per role), plus camera facts."""
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    paths = _bag_paths(bag)
    store = get_typestore(Stores.ROS1_NOETIC if paths[0].suffix == ".bag" else Stores.ROS2_HUMBLE)
    wanted = dict(topics.items())
    data = {role: _TopicData(topic) for role, topic in wanted.items()}
    cam: dict[str, Any] = {}
    try:
        with AnyReader(paths, default_typestore=store) as reader:
            by_topic: dict[str, list] = {}
            for conn in reader.connections:
                by_topic.setdefault(conn.topic, []).append(conn)
            for role, topic in wanted.items():
                conns = by_topic.get(topic)
                if not conns:
                    if role == "gt":
                        continue
                    present = ", ".join(sorted(by_topic)) or "none"
                    raise InputError(
                        f"topic {topic} ({role}) is not in the bag (topics present: {present}); "
                        f"name the right one with --topic-{role.replace('_', '-')} or skip it with 'none'",
                        file=bag, column=topic)
                bad = {c.msgtype for c in conns} - {_MSGTYPES[role]}
                if bad:
                    raise InputError(f"has message type {', '.join(sorted(bad))}, expected {_MSGTYPES[role]}",
                                     file=bag, column=topic)
            conns = [c for c in reader.connections if c.topic in wanted.values()]
            role_of = {topic: role for role, topic in wanted.items()}
            # conns holds camera_info at least (checked above): an empty list would mean "every topic"
            for conn, _t, raw in reader.messages(connections=conns):
                role = role_of[conn.topic]
                msg = reader.deserialize(raw, conn.msgtype)
                stamp = _stamp_ns(msg)
                value = _CONVERT[role](msg, bag, conn.topic, stamp, cam)
                data[role].stamps.append(stamp)
                data[role].values.append(value)
    except InputError:
        raise
    except _BAG_ERRORS as exc:
        raise InputError(f"cannot read the bag: {type(exc).__name__}: {_one_line(exc)}", file=bag) from None
    except Exception as exc:  # rosbags' own error classes (ReaderError, AnyReaderError, SerdeError, ...)
        if not type(exc).__module__.startswith("rosbags"):
            raise
        raise InputError(f"cannot read the bag: {_one_line(exc)}", file=bag) from None
    return data, cam


def _where(topic: str, stamp: int) -> str:
    """Location of a message within its topic (the topic itself is the error's column)."""
    return f"message stamped {stamp // _NS_PER_S}.{stamp % _NS_PER_S:09d} s"


def _one_line(exc: BaseException) -> str:
    """An exception's text on one line (YAML and sqlite messages span several)."""
    return " ".join(str(exc).split())


def _convert_camera_info(msg: Any, bag: Path, topic: str, stamp: int, cam: dict[str, Any]) -> None:
    def fail(what: str) -> InputError:
        return InputError(f"{what} ({_where(topic, stamp)})", file=bag, column=topic)

    model = str(msg.distortion_model)
    if model not in _DISTORTION_MODELS:
        raise fail(f"distortion_model {model!r} is not supported; use plumb_bob (OpenCV k1 k2 p1 p2 k3) "
                   f"or rational_polynomial")
    d = np.asarray(_field(msg, "d"), dtype=float).reshape(-1)
    if d.size not in _DISTORTION_MODELS[model]:
        raise fail(f"D has {d.size} coefficients; {model} needs {' or '.join(map(str, _DISTORTION_MODELS[model]))}")
    k = np.asarray(_field(msg, "k"), dtype=float).reshape(-1)
    if not (np.all(np.isfinite(k)) and np.all(np.isfinite(d))):
        raise fail("K or D contains NaN or infinite values")
    if k[1] != 0.0 or k[3] != 0.0 or k[6] != 0.0 or k[7] != 0.0 or k[8] != 1.0:
        raise fail(f"K must be [fx 0 cx; 0 fy cy; 0 0 1] (no skew), got {k.tolist()}")
    if int(msg.binning_x) > 1 or int(msg.binning_y) > 1:
        raise fail("binning is not supported (the intrinsics would describe another image size)")
    roi = msg.roi
    if int(roi.width) or int(roi.height) or int(roi.x_offset) or int(roi.y_offset):
        raise fail("a region of interest is not supported")
    now = {
        "width": int(msg.width), "height": int(msg.height), "fx": float(k[0]), "fy": float(k[4]),
        "cx": float(k[2]), "cy": float(k[5]),
        "distortion": tuple(float(x) for x in d) if d.size else (0.0,) * 5, "model": model,
    }
    if not cam:
        try:
            PinholeCamera(**{k_: v for k_, v in now.items() if k_ != "model"})
        except ValueError as exc:
            raise fail(str(exc)) from None
        cam.update(now)
        cam["frame_id"] = str(msg.header.frame_id)
    elif any(cam[key] != now[key] for key in now):
        changed = [key for key in now if cam[key] != now[key]]
        raise fail(f"the camera changed within the bag ({', '.join(changed)}); a run has one camera")


def _convert_point(msg: Any, bag: Path, topic: str, stamp: int, cam: dict[str, Any]) -> np.ndarray:
    uv = np.array([float(msg.point.x), float(msg.point.y)])
    if not np.all(np.isfinite(uv)):
        raise InputError(f"point x/y is not finite: {uv.tolist()} ({_where(topic, stamp)}); "
                         "publish nothing when the keypoint is not detected", file=bag, column=topic)
    return uv


def _convert_pose(msg: Any, bag: Path, topic: str, stamp: int, cam: dict[str, Any]) -> tuple[np.ndarray, str]:
    p, o = msg.pose.position, msg.pose.orientation
    xyz = np.array([float(p.x), float(p.y), float(p.z)])
    q = np.array([float(o.w), float(o.x), float(o.y), float(o.z)])
    if not (np.all(np.isfinite(xyz)) and np.all(np.isfinite(q))):
        raise InputError(f"pose contains NaN or infinite values ({_where(topic, stamp)})", file=bag, column=topic)
    norm = float(np.linalg.norm(q))
    if abs(norm - 1.0) > QUAT_NORM_TOL:
        raise InputError(f"orientation quaternion has norm {norm:.6g}; it must be 1 within {QUAT_NORM_TOL:g} "
                         f"({_where(topic, stamp)})", file=bag, column=topic)
    return pose_from_xyz_quat(xyz, q / norm), str(msg.header.frame_id)


def _convert_mask(msg: Any, bag: Path, topic: str, stamp: int, cam: dict[str, Any]) -> tuple[np.ndarray, tuple]:
    def fail(what: str) -> InputError:
        return InputError(f"{what} ({_where(topic, stamp)})", file=bag, column=topic)

    if str(msg.encoding) not in _MASK_ENCODINGS:
        raise fail(f"mask encoding {str(msg.encoding)!r} is not supported; use mono8 (nonzero = needle)")
    h, w, step = int(msg.height), int(msg.width), int(msg.step)
    if step < w:
        raise fail(f"step {step} is smaller than the width {w}")
    raw = np.asarray(msg.data, dtype=np.uint8).reshape(-1)
    if raw.size < step * h:
        raise fail(f"data has {raw.size} bytes, height x step needs {h * step}")
    mask = raw[: step * h].reshape(h, step)[:, :w] != 0
    # kept bit-packed until written: a long run's masks would otherwise fill the memory
    return np.packbits(mask, axis=None), (h, w)


_CONVERT = {
    "camera_info": _convert_camera_info,
    "mask": _convert_mask,
    "tip": _convert_point,
    "tail": _convert_point,
    "grasper": _convert_pose,
    "gt": _convert_pose,
}


def _match(frame_ns: np.ndarray, stamps: list[int], tol_ns: int) -> tuple[np.ndarray, int]:
    """Index of the message nearest each frame within ``tol_ns`` (-1: none) and the number of unused messages."""
    out = np.full(frame_ns.size, -1, dtype=np.int64)
    if not stamps:
        return out, 0
    s = np.asarray(stamps, dtype=np.int64)
    order = np.argsort(s, kind="stable")
    ss = s[order]
    pos = np.searchsorted(ss, frame_ns)
    for i, (f, p) in enumerate(zip(frame_ns, pos, strict=True)):
        best, best_d = -1, tol_ns + 1
        for j in (p - 1, p):  # the neighbours; ties go to the earlier message
            if 0 <= j < ss.size and abs(int(ss[j]) - int(f)) < best_d:
                best, best_d = j, abs(int(ss[j]) - int(f))
        if best >= 0:
            out[i] = order[best]
    return out, int(s.size - np.unique(out[out >= 0]).size)


def import_bag(
    bag: str | Path,
    out: str | Path,
    needle: NeedleModel | str | Path,
    topics: BagTopics | None = None,
    stamp_tolerance_s: float = DEFAULT_STAMP_TOLERANCE_S,
    name: str | None = None,
    frame_rate_hz: float | None = None,
    overwrite: bool = False,
) -> BagImportSummary:
    """Convert a ROS 1/2 bag into the run directory ``out`` (module docstring for every rule).

    ``needle`` is a :class:`NeedleModel` or the path of ``NEEDLE.json``. Everything is read and
    validated before the first file is written. Raises :class:`InputError` on any problem.
    """
    bag, out = path_argument("bag", bag), path_argument("out", out)  # "" was the current directory
    topics = topics or BagTopics()
    if not math.isfinite(stamp_tolerance_s) or not 0 <= stamp_tolerance_s <= 1e9:  # 1e308 overflowed the ns
        raise InputError(f"must be a finite number in [0, 1e9], got {stamp_tolerance_s}", column="--stamp-tolerance-s")
    needle_model = needle if isinstance(needle, NeedleModel) else read_needle_json(needle)
    check_output_dir(out, overwrite, "run", inputs=(bag,))  # a ROS 2 bag is a directory
    data, cam = _read_bag(bag, topics)

    ci = data["camera_info"]
    if not ci.stamps:
        raise InputError("no camera_info messages: a run needs at least one frame", file=bag, column=ci.topic)
    frame_ns = np.sort(np.asarray(ci.stamps, dtype=np.int64))
    dup = frame_ns[1:][np.diff(frame_ns) == 0]
    if dup.size:
        raise InputError(f"two camera_info messages have the same stamp ({_where(ci.topic, int(dup[0]))})",
                         file=bag, column=ci.topic)
    if frame_rate_hz is None:
        if frame_ns.size < 2:
            raise InputError("one camera_info message only: the frame rate cannot be measured; give it "
                             "(--frame-rate-hz)", file=bag, column=ci.topic)
        frame_rate_hz = round(_NS_PER_S / float(np.median(np.diff(frame_ns))), 6)
    elif not (math.isfinite(frame_rate_hz) and frame_rate_hz > 0):
        raise InputError(f"must be > 0, got {frame_rate_hz}", column="--frame-rate-hz")
    tol_ns = int(round(stamp_tolerance_s * _NS_PER_S))
    if frame_ns.size >= 2 and 2 * tol_ns >= float(np.median(np.diff(frame_ns))):
        raise InputError(f"{stamp_tolerance_s} s is not below half the frame period "
                         f"({0.5 / frame_rate_hz:.6g} s): one message could match two frames",
                         column="--stamp-tolerance-s")

    matched: dict[str, int] = {}
    unmatched: dict[str, int] = {}
    picks: dict[str, np.ndarray] = {}
    for role, td in data.items():
        if role == "camera_info":
            continue
        s = np.asarray(td.stamps, dtype=np.int64)
        u, c = np.unique(s, return_counts=True)
        if np.any(c > 1):
            raise InputError(f"two messages have the same stamp ({_where(td.topic, int(u[c > 1][0]))}): "
                             "which one is the observation?", file=bag, column=td.topic)
        picks[role], unmatched[role] = _match(frame_ns, td.stamps, tol_ns)
        matched[role] = int(np.sum(picks[role] >= 0))

    frame_id = cam["frame_id"]
    for role in ("grasper", "gt"):
        if role not in picks:
            continue
        for i in picks[role][picks[role] >= 0]:
            fid = data[role].values[i][1]
            if fid and frame_id and fid != frame_id:
                raise InputError(
                    f"pose is in frame {fid!r} but the camera frame is {frame_id!r} "
                    f"({_where(data[role].topic, data[role].stamps[i])}); transform it to the camera frame first",
                    file=bag, column=data[role].topic)
    for i in picks.get("mask", np.array([], dtype=np.int64)):
        if i >= 0:
            h, w = data["mask"].values[i][1]
            if (w, h) != (cam["width"], cam["height"]):
                raise InputError(f"mask is {w}x{h} px but the camera is {cam['width']}x{cam['height']} px "
                                 f"({_where(data['mask'].topic, data['mask'].stamps[i])})",
                                 file=bag, column=data["mask"].topic)

    camera = PinholeCamera(fx=cam["fx"], fy=cam["fy"], cx=cam["cx"], cy=cam["cy"], width=cam["width"],
                           height=cam["height"], distortion=cam["distortion"])
    origin = int(frame_ns[0])
    info = RecordingInfo(
        name=name or (bag.stem if bag.is_file() else bag.name), frame_rate_hz=float(frame_rate_hz),
        camera=camera, needle=needle_model,
        extra={ROS_BAG_KEY: {"time_origin_ns": origin, "camera_frame_id": frame_id}},
    )
    # before anything is written; the camera's values came from the bag's camera_info: name that topic
    check_recording_info(info, out / "recording.json", camera_source=(Path(bag), ci.topic))

    def pick(role: str, k: int) -> Any:
        idx = picks.get(role)
        return None if idx is None or idx[k] < 0 else data[role].values[idx[k]]

    n_pixels = cam["width"] * cam["height"]
    records = []
    for k, ns in enumerate(frame_ns):
        grasper, gt = pick("grasper", k), pick("gt", k)
        rec = FrameRecord(
            frame=k, t_s=(int(ns) - origin) / _NS_PER_S, tip_px=pick("tip", k), tail_px=pick("tail", k),
            cam_T_grasper=None if grasper is None else grasper[0],
            cam_T_needle_gt=None if gt is None else gt[0],
        )
        try:  # every row as the reader will check it, before the first file (was: a run cut at the bad frame)
            frame_cells(rec, cam["width"], cam["height"])
        except InputError as exc:
            role = str(exc.column).split("_")[0]  # tip_u_px -> tip, grasper_x_m -> grasper, gt_x_m -> gt
            raise InputError(f"{exc.reason} ({exc.column})", file=bag,
                             column=data[role].topic if role in data else exc.column) from None
        records.append(rec)
    with staged_output_dir(out, overwrite, "run", inputs=(bag,)) as stage, RecordingWriter(stage, info) as writer:
        for k, rec in enumerate(records):
            mask = pick("mask", k)
            mask_arr = None
            if mask is not None:
                mask_arr = np.unpackbits(mask[0], count=n_pixels).reshape(cam["height"], cam["width"])
            writer.add(rec, mask=mask_arr)
    return BagImportSummary(run_dir=out, frames=int(frame_ns.size), matched=matched, unmatched=unmatched)


# --------------------------------------------------------------------------------------------
# writing a bag
# --------------------------------------------------------------------------------------------


def _ros_bag_meta(recording: Recording) -> tuple[int, str]:
    """(time origin ns, camera frame id) from recording.json's ``ros_bag`` key (defaults 0, "camera")."""
    meta = recording.info.extra.get(ROS_BAG_KEY)
    origin, frame_id = 0, DEFAULT_CAMERA_FRAME_ID
    if isinstance(meta, dict):
        o = meta.get("time_origin_ns")
        if isinstance(o, int) and not isinstance(o, bool) and o >= 0:
            origin = o
        elif o is not None:
            raise InputError(f"must be a non-negative integer, got {json.dumps(o)}",
                             file=recording.root / "recording.json", column=f"{ROS_BAG_KEY}.time_origin_ns")
        f = meta.get("camera_frame_id")
        if isinstance(f, str) and f:
            frame_id = f
    return origin, frame_id


def _ros_distortion(recording: Recording) -> tuple[str, list[float]]:
    d = list(recording.info.camera.distortion or (0.0,) * 5)
    if len(d) == 4:
        d.append(0.0)  # OpenCV's 4-coefficient model is plumb_bob with k3 = 0
    if len(d) == 5:
        return "plumb_bob", d
    if len(d) == 8:
        return "rational_polynomial", d
    raise InputError(f"{len(d)} distortion coefficients have no ROS distortion model (plumb_bob: 5, "
                     "rational_polynomial: 8)", file=recording.root / "recording.json", column="camera.distortion")


class _BagWriter:
    """One writer interface over rosbags' ROS 1 and ROS 2 writers (messages built from the type store)."""

    def __init__(self, path: Path, fmt: str, storage: str) -> None:
        from rosbags.typesys import Stores, get_typestore

        self.ros1 = fmt == "ros1"
        self.store = get_typestore(Stores.ROS1_NOETIC if self.ros1 else Stores.ROS2_HUMBLE)
        if self.ros1:
            from rosbags.rosbag1 import Writer

            self.writer = Writer(path)
        else:
            from rosbags.rosbag2 import StoragePlugin, Writer

            plugin = StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3
            self.writer = Writer(path, version=9, storage_plugin=plugin)
        self.conns: dict[str, Any] = {}
        self.T = self.store.types

    def __enter__(self) -> _BagWriter:
        self.writer.open()
        return self

    def __exit__(self, exc_type: object, *rest: object) -> None:
        if exc_type is None:
            self.writer.close()
        else:
            self.writer.abort() if hasattr(self.writer, "abort") else self.writer.close()

    def header(self, ns: int, frame_id: str, seq: int) -> Any:
        stamp = self.T["builtin_interfaces/msg/Time"](sec=ns // _NS_PER_S, nanosec=ns % _NS_PER_S)
        kw = {"seq": seq} if self.ros1 else {}
        return self.T["std_msgs/msg/Header"](stamp=stamp, frame_id=frame_id, **kw)

    def write(self, topic: str, msg: Any, ns: int) -> None:
        t = msg.__msgtype__
        if topic not in self.conns:
            self.conns[topic] = self.writer.add_connection(topic, t, typestore=self.store)
        raw = self.store.serialize_ros1(msg, t) if self.ros1 else self.store.serialize_cdr(msg, t)
        self.writer.write(self.conns[topic], ns, raw)

    def camera_info(self, h: Any, cam: PinholeCamera, model: str, d: list[float]) -> Any:
        T = self.T
        K = np.array([cam.fx, 0.0, cam.cx, 0.0, cam.fy, cam.cy, 0.0, 0.0, 1.0])
        R = np.eye(3).reshape(-1)
        P = np.array([cam.fx, 0.0, cam.cx, 0.0, 0.0, cam.fy, cam.cy, 0.0, 0.0, 0.0, 1.0, 0.0])
        roi = T["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0, do_rectify=False)
        arrays = {"d": np.asarray(d, dtype=float), "k": K, "r": R, "p": P}
        if self.ros1:
            arrays = {k.upper(): v for k, v in arrays.items()}
        return T["sensor_msgs/msg/CameraInfo"](header=h, height=int(cam.height), width=int(cam.width),
                                               distortion_model=model, binning_x=0, binning_y=0, roi=roi, **arrays)

    def mask(self, h: Any, mask: np.ndarray) -> Any:
        data = np.ascontiguousarray(np.where(mask, 255, 0).astype(np.uint8)).reshape(-1)
        return self.T["sensor_msgs/msg/Image"](header=h, height=int(mask.shape[0]), width=int(mask.shape[1]),
                                               encoding="mono8", is_bigendian=0, step=int(mask.shape[1]), data=data)

    def point(self, h: Any, uv: np.ndarray) -> Any:
        p = self.T["geometry_msgs/msg/Point"](x=float(uv[0]), y=float(uv[1]), z=0.0)
        return self.T["geometry_msgs/msg/PointStamped"](header=h, point=p)

    def pose(self, h: Any, T_: np.ndarray) -> Any:
        xyz, q = xyz_quat_from_pose(T_)
        T = self.T
        pose = T["geometry_msgs/msg/Pose"](
            position=T["geometry_msgs/msg/Point"](x=float(xyz[0]), y=float(xyz[1]), z=float(xyz[2])),
            orientation=T["geometry_msgs/msg/Quaternion"](x=float(q[1]), y=float(q[2]), z=float(q[3]), w=float(q[0])),
        )
        return T["geometry_msgs/msg/PoseStamped"](header=h, pose=pose)


def _frame_stamps(recording: Recording, origin: int) -> Iterator[tuple[FrameRecord, int]]:
    prev: tuple[int, FrameRecord] | None = None
    for rec in recording.frames:
        ns = origin + int(round(rec.t_s * _NS_PER_S))
        where = dict(file=recording.csv_path, row=recording.row_of(rec), column="t_s")
        if ns < 0 or ns >= 2**31 * _NS_PER_S:
            raise InputError(f"stamp {ns} ns (time origin {origin} + t_s) is outside the ROS time range "
                             f"(frame {rec.frame})", **where)
        if prev is not None and ns <= prev[0]:
            raise InputError(f"t_s does not increase from frame {prev[1].frame} to frame {rec.frame} at "
                             "nanosecond resolution; bag frames are ordered by stamp", **where)
        prev = (ns, rec)
        yield rec, ns


#: What a ROS 2 bag directory holds besides ``metadata.yaml``: storage files with these suffixes.
_ROS2_STORAGE_SUFFIXES = (".db3", ".mcap")
#: The first line of a ROS 1 bag (format 2.0, the one rosbags reads and writes).
_ROS1_MAGIC = b"#ROSBAG V2.0\n"
#: The top-level key of a rosbag2 ``metadata.yaml``.
_ROS2_METADATA_KEY = b"rosbag2_bagfile_information:"


def _not_a_bag(out: Path, fmt: str) -> str | None:
    """Why the existing ``out`` is not a ``fmt`` bag that ``--overwrite`` may replace (module docstring), or None
    (an empty directory too, for ROS 2). The text follows ``--out``."""
    try:
        if fmt == "ros1":
            if out.is_dir():
                return "is a directory, not a ROS 1 bag file"
            if not out.is_file():
                return "is not a regular file, so not a ROS 1 bag"
            with open(out, "rb") as fh:
                head = fh.read(len(_ROS1_MAGIC))
            return None if head == _ROS1_MAGIC else "is not a ROS 1 bag (it does not start with '#ROSBAG V2.0')"
        if not out.is_dir():
            return "is a file, not a ROS 2 bag directory"
        entries = sorted(os.scandir(out), key=lambda e: e.name)
        if not entries:
            return None
        other = [e.name for e in entries if not e.is_file(follow_symlinks=False)
                 or not (e.name == "metadata.yaml" or e.name.endswith(_ROS2_STORAGE_SUFFIXES))]
        if other:
            shown = shown_entries(other)
            return (f"holds {len(other)} entr{'y' if len(other) == 1 else 'ies'} a ROS 2 bag does not ({shown}; a bag "
                    "holds metadata.yaml and its .db3 or .mcap files only)")
        meta = out / "metadata.yaml"
        if not meta.is_file():
            return "holds no metadata.yaml, so it is not a ROS 2 bag"
        with open(meta, "rb") as fh:
            head = fh.read(4096).lstrip()
        if not head.startswith(_ROS2_METADATA_KEY):
            return "has a metadata.yaml that is not a rosbag2 one (no 'rosbag2_bagfile_information')"
        return None
    except OSError as exc:
        return f"cannot be inspected: {exc.strerror or type(exc).__name__}"


def _check_bag_out(out: Path, fmt: str, overwrite: bool) -> None:
    """Refuse an existing ``out`` that is not a bag, or a bag without ``overwrite`` (module docstring)."""
    if out.is_symlink():
        raise InputError("--out is a symbolic link; name the bag's own path (export-bag writes a bag, or with "
                         "--overwrite replaces one, never a link)", file=out)
    if not out.exists():
        return
    why = _not_a_bag(out, fmt)
    if why is not None:
        raise InputError(f"--out {why}; --overwrite replaces only a bag: choose another --out", file=out)
    if not overwrite and not (out.is_dir() and not any(out.iterdir())):
        kind = "a ROS 1 bag" if fmt == "ros1" else "a ROS 2 bag"
        raise InputError(f"--out exists ({kind}); pass --overwrite to replace it, or choose another --out", file=out)


def export_bag(
    run: str | Path,
    out: str | Path,
    fmt: str = "ros2",
    storage: str = "sqlite3",
    topics: BagTopics | None = None,
    overwrite: bool = False,
) -> Path:
    """Write the run ``run`` as a bag at ``out``; returns ``out`` (module docstring for every rule).

    ``fmt`` ``ros2`` writes a rosbag2 directory (``storage`` ``sqlite3`` or ``mcap``), ``ros1`` a
    ``.bag`` file (``out`` must end in ``.bag``: readers tell the two formats apart by it). Topics
    set to None are not written. Masks are read through :meth:`Recording.load_mask`. An existing ``out`` is
    refused unless ``overwrite`` and a bag; it is then replaced once the new bag is complete.
    """
    run, out = path_argument("run", run), path_argument("out", out)  # "" was the current directory
    topics = topics or BagTopics()
    if fmt not in ("ros1", "ros2"):
        raise InputError(f"unknown bag format {fmt!r}; choose ros1 or ros2", column="--format")
    if storage not in ("sqlite3", "mcap"):
        raise InputError(f"unknown ROS 2 storage {storage!r}; choose sqlite3 or mcap", column="--storage")
    if (fmt == "ros1") != (out.suffix == ".bag"):
        need = "must end in .bag" if fmt == "ros1" else "must not end in .bag (that names a ROS 1 bag)"
        raise InputError(f"a {fmt} bag path {need}", file=out)
    check_not_an_input(out, (run,), "bag")
    try:
        _check_bag_out(out, fmt, overwrite)
    except OSError as exc:
        raise InputError(f"--out cannot be used for the bag: {exc.strerror or type(exc).__name__}", file=out) from None
    recording = read_recording(run)
    origin, frame_id = _ros_bag_meta(recording)
    model, d = _ros_distortion(recording)
    stamps = list(_frame_stamps(recording, origin))  # validate every stamp before writing
    cam = recording.info.camera
    staged: list[Path] = []

    def failed(exc: BaseException) -> InputError:
        text = _one_line(exc)
        for target in staged:  # name the bag as the user knows it, not its hidden staging path
            text = text.replace(str(target), str(out))
        return InputError(f"cannot write the bag: {text}", file=out)

    try:
        with staged_replacement(out, "bag") as target, _BagWriter(target, fmt, storage) as w:
            staged.append(target)
            for seq, (rec, ns) in enumerate(stamps):
                h = w.header(ns, frame_id, seq)
                w.write(topics.camera_info, w.camera_info(h, cam, model, d), ns)
                if topics.mask and rec.mask is not None:
                    w.write(topics.mask, w.mask(h, recording.load_mask(rec)), ns)
                for role, uv in (("tip", rec.tip_px), ("tail", rec.tail_px)):
                    topic = getattr(topics, role)
                    if topic and uv is not None:
                        w.write(topic, w.point(h, uv), ns)
                for role, T_ in (("grasper", rec.cam_T_grasper), ("gt", rec.cam_T_needle_gt)):
                    topic = getattr(topics, role)
                    if topic and T_ is not None:
                        w.write(topic, w.pose(h, T_), ns)
    except InputError:
        raise
    except (OSError, sqlite3.Error) as exc:  # sqlite3: a full disk or quota under the default storage
        raise failed(exc) from None
    except Exception as exc:  # rosbags' writer errors
        if not type(exc).__module__.startswith("rosbags"):
            raise
        raise failed(exc) from None
    return out
