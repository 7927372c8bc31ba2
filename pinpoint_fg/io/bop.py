"""Import a BOP-format scene (e.g. the AMBF needle dataset) as a recorded run, format v1.

The BOP layout (bop_toolkit's ``docs/bop_datasets_format.md``) of one scene directory::

    SCENE_DIR/scene_camera.json   {"im_id": {"cam_K": [9, row-major], "depth_scale": s, ...}, ...}
    SCENE_DIR/scene_gt.json       {"im_id": [{"obj_id": i, "cam_R_m2c": [9, row-major], "cam_t_m2c": [3, mm]}, ...]}
    SCENE_DIR/rgb/ or gray/       {im_id:06d}.png / .jpg / .tif
    SCENE_DIR/mask_visib/, mask/  {im_id:06d}_{gt_idx:06d}.png, one binary mask per gt instance

becomes ``RUN/recording.json``, ``frames.csv``, ``masks/``, ``images/`` written by
:class:`pinpoint_fg.io.recording.RecordingWriter` (the one writer of the format).

Decisions (the BOP format and the recording format are silent on them):

* **Frames**: one per ``im_id`` of ``scene_camera.json``, sorted; ``frame = im_id`` (so a frame
  names its BOP files) and ``t_s = im_id / fps`` (``fps`` default 30, the recording's
  ``frame_rate_hz``). An ``im_id`` in ``scene_gt.json`` without a camera entry is an error.
* **Camera**: ``cam_K`` must be the same for every image (a run has one camera; compared to
  1e-9 relative), without skew. BOP images are undistorted: distortion is zeros. The image size
  is the first frame's image (or its mask with ``images=False``); every file must match it.
* **Ground truth**: the gt entry with ``obj_id`` of the frame; several entries with that id in
  one image are an error unless ``instance`` picks the K-th (0-based, in file order; an image
  with K or fewer entries of the object does not show instance K). An image without the object
  (or the instance) gets empty gt cells (and no mask). ``cam_R_m2c`` must be a rotation to
  1e-3 (BOP stores ~7 significant digits) and is projected onto SO(3) by SVD;
  ``cam_t_m2c`` is in mm. ``cam_T_needle = cam_T_model @ model_T_needle`` with ``model_T_needle``
  fitted to the PLY model by :func:`pinpoint_fg.io.needle_mesh.fit_needle_mesh`.
* **Masks**: ``mask_dir`` (relative to SCENE_DIR, default ``mask_visib``) holds one binary mask
  per gt instance (nonzero = object), read at the chosen instance's index. With ``mask_color``
  (R, G, B) it holds instead one colour-label image per frame ``{im_id:06d}.png`` in which the
  needle has exactly that colour; the colour must occur in at least one of them. A mask with no
  needle pixel is recorded as "no segmentation" (the trackers use no negative evidence).
* **Keypoints**: BOP has none; the tip/tail columns stay empty unless ``keypoints_sigma_px`` is
  given: then the tip and tail of the ground-truth pose are projected and perturbed by
  N(0, σ²) per axis (``seed``), kept only when in front of the camera and inside the image.
  These are **synthetic** and ``recording.json`` says so (``bop_import.keypoints``).
* ``recording.json`` gets an extra key ``bop_import`` (allowed by the format) with the scene,
  object, model, ``model_T_needle`` and the fit's figures, so the conversion can be retraced.

Every malformed input raises :class:`InputError` naming the file and the JSON key path
(``"12[0].cam_R_m2c"``: image 12, gt entry 0) or the image file. The JSON files, the model and
the existence of every image and mask file are checked before anything is written; an image or
mask that exists but does not decode is found while writing, and leaves the frames before it
(a valid, shorter run) in ``out``.
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from factors.geometry import PinholeCamera
from factors.lie import homogeneous
from pinpoint_fg.errors import InputError, path_argument
from pinpoint_fg.io.needle_mesh import NeedleMeshFit, fit_needle_mesh, read_ply_vertices
from pinpoint_fg.io.outdir import check_output_dir, staged_output_dir
from pinpoint_fg.io.recording.png import PNG_SIGNATURE, check_png
from pinpoint_fg.io.recording.schema import MAX_ABS_METRES, FrameRecord, RecordingInfo, gt_depth_problem
from pinpoint_fg.io.recording.writer import RecordingWriter, check_recording_info

SCENE_CAMERA = "scene_camera.json"
SCENE_GT = "scene_gt.json"
#: Image directories tried in this order, and the image extensions tried in this order.
IMAGE_DIRS = ("rgb", "gray")
IMAGE_EXTENSIONS = (".png", ".jpg", ".jpeg", ".tif", ".tiff")
#: Largest accepted deviation of cam_R_m2c from a rotation, max |R^T R - I|.
ROTATION_TOL = 1e-3


@dataclass(frozen=True)
class BopImportConfig:
    """What to import from a BOP scene and how."""

    obj_id: int
    """BOP object id of the needle."""
    mask_dir: str = "mask_visib"
    """Mask directory relative to the scene (binary per-instance masks, or colour labels with mask_color)."""
    mask_color: tuple[int, int, int] | None = None
    """(R, G, B) of the needle in colour-label masks; None: binary per-instance masks."""
    model_units: str = "mm"
    """Length unit of the PLY model's vertices (BOP: mm)."""
    instance: int | None = None
    """Which gt entry of the object to use when an image has several (0-based); None: error then."""
    fps: float = 30.0
    """Frame rate, Hz: t_s = im_id / fps."""
    tip_end: str | None = None
    """Tip end of the model (``+x`` … ``-z``) when the mesh shows no taper; None: from the taper."""
    grasp_angle_rad: float | None = None
    """Grasp angle in the needle frame; None: a third of the arc from the tail."""
    keypoints_sigma_px: float | None = None
    """Synthetic keypoints: project tip/tail from the ground truth with this noise, px; None: none."""
    seed: int = 0
    """Seed of the synthetic keypoint noise."""
    images: bool = True
    """Copy the scene's images into the run (as PNG)."""
    name: str | None = None
    """Run name; None: the scene directory's name."""


@dataclass(frozen=True)
class BopImportSummary:
    """What an import wrote."""

    out: Path
    """The run directory."""
    frames: int
    """Frames written."""
    with_gt: int
    """Frames with the object's ground truth."""
    with_mask: int
    """Frames with a (non-empty) mask."""
    with_keypoints: int
    """Frames with at least one synthetic keypoint."""
    fit: NeedleMeshFit
    """The needle circle fitted to the model."""

    def describe(self) -> str:
        """A short human-readable report."""
        return (f"wrote {self.out}: {self.frames} frames, ground truth in {self.with_gt}, masks in {self.with_mask}, "
                f"synthetic keypoints in {self.with_keypoints}\n{self.fit.describe()}")


# --------------------------------------------------------------------------------------------
# JSON helpers: every problem names the file and the key path
# --------------------------------------------------------------------------------------------


def _load_json(path: Path, what: str) -> Any:
    if not path.is_file():
        raise InputError(f"file not found (a BOP scene needs {what})", file=path)
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(f"cannot read: {exc}", file=path) from None
    try:
        return json.loads(text)
    except json.JSONDecodeError as exc:
        raise InputError(f"not valid JSON: {exc.msg} at line {exc.lineno}, column {exc.colno}", file=path) from None


def _im_id(key: str, path: Path) -> int:
    if not (isinstance(key, str) and key.isdigit()):
        raise InputError("image ids (top-level keys) must be non-negative integers", file=path, column=str(key))
    return int(key)


def _numbers(value: Any, count: int, path: Path, key: str) -> np.ndarray:
    ok = isinstance(value, list) and len(value) == count and all(
        isinstance(v, int | float) and not isinstance(v, bool) for v in value)
    if not ok:
        raise InputError(f"must be a list of {count} numbers, got {json.dumps(value)[:80]}", file=path, column=key)
    a = np.asarray(value, dtype=float)
    if not np.all(np.isfinite(a)):
        raise InputError("contains NaN or infinite values", file=path, column=key)
    return a


def _camera_entries(path: Path) -> dict[int, np.ndarray]:
    """``im_id -> K (3, 3)`` of scene_camera.json, every K checked; the same K for every image."""
    doc = _load_json(path, SCENE_CAMERA)
    if not isinstance(doc, dict) or not doc:
        raise InputError("the top level must be a non-empty JSON object {im_id: {cam_K: ...}}", file=path)
    out: dict[int, np.ndarray] = {}
    first: tuple[str, np.ndarray] | None = None
    for key, entry in doc.items():
        im = _im_id(key, path)
        if not isinstance(entry, dict):
            raise InputError(f"must be an object with cam_K, got {json.dumps(entry)[:60]}", file=path, column=key)
        if "cam_K" not in entry:
            raise InputError("missing required key", file=path, column=f"{key}.cam_K")
        K = _numbers(entry["cam_K"], 9, path, f"{key}.cam_K").reshape(3, 3)
        if K[0, 0] <= 0 or K[1, 1] <= 0 or np.any(K[1:, 0] != 0) or K[2, 1] != 0 or K[2, 2] != 1:
            raise InputError(f"not an intrinsic matrix [fx 0 cx; 0 fy cy; 0 0 1]: {K.ravel().tolist()}",
                             file=path, column=f"{key}.cam_K")
        if K[0, 1] != 0:
            raise InputError(f"skew {K[0, 1]} is not supported (must be 0)", file=path, column=f"{key}.cam_K")
        if first is None:
            first = (key, K)
        elif not np.allclose(K, first[1], rtol=1e-9, atol=0.0):
            raise InputError(f"differs from image {first[0]}'s {first[1].ravel().tolist()}: a run has one camera",
                             file=path, column=f"{key}.cam_K")
        out[im] = K
    return out


def _rotation(value: Any, path: Path, key: str) -> np.ndarray:
    R = _numbers(value, 9, path, key).reshape(3, 3)
    err = float(np.max(np.abs(R.T @ R - np.eye(3))))
    if err > ROTATION_TOL or np.linalg.det(R) <= 0:
        raise InputError(f"not a rotation matrix (max |R^T R - I| = {err:.2g}, det {np.linalg.det(R):.3g})",
                         file=path, column=key)
    U, _, Vt = np.linalg.svd(R)
    return U @ Vt


def _gt_entries(path: Path, obj_id: int, instance: int | None) -> dict[int, tuple[int, np.ndarray]]:
    """``im_id -> (gt_idx, cam_T_model in metres)`` of the object's entry in each image that has one."""
    doc = _load_json(path, SCENE_GT)
    if not isinstance(doc, dict):
        raise InputError("the top level must be a JSON object {im_id: [gt entries]}", file=path)
    out: dict[int, tuple[int, np.ndarray]] = {}
    seen_ids: set[int] = set()
    for key, entries in doc.items():
        im = _im_id(key, path)
        if not isinstance(entries, list):
            raise InputError(f"must be a list of gt entries, got {json.dumps(entries)[:60]}", file=path, column=key)
        hits = []
        for idx, e in enumerate(entries):
            where = f"{key}[{idx}]"
            if not isinstance(e, dict):
                raise InputError(f"must be an object, got {json.dumps(e)[:60]}", file=path, column=where)
            if "obj_id" not in e:
                raise InputError("missing required key", file=path, column=f"{where}.obj_id")
            oid = e["obj_id"]
            if not isinstance(oid, int) or isinstance(oid, bool):
                raise InputError(f"must be an integer, got {json.dumps(oid)}", file=path, column=f"{where}.obj_id")
            seen_ids.add(oid)
            if oid != obj_id:
                continue
            for k in ("cam_R_m2c", "cam_t_m2c"):
                if k not in e:
                    raise InputError("missing required key", file=path, column=f"{where}.{k}")
            R = _rotation(e["cam_R_m2c"], path, f"{where}.cam_R_m2c")
            t_m = _numbers(e["cam_t_m2c"], 3, path, f"{where}.cam_t_m2c") * 1e-3
            hits.append((idx, homogeneous(R, t_m)))
        if len(hits) > 1 and instance is None:
            raise InputError(f"{len(hits)} entries of obj_id {obj_id} in one image; choose one with --instance K",
                             file=path, column=key)
        k = 0 if instance is None else instance
        if k < len(hits):  # an image with fewer entries does not show instance k
            out[im] = hits[k]
    if not out:
        ids = ", ".join(str(i) for i in sorted(seen_ids)) or "none"
        which = f"obj_id {obj_id}" if instance is None else f"instance {instance} of obj_id {obj_id}"
        raise InputError(f"no entry has {which} (obj_ids present: {ids})", file=path)
    return out


# --------------------------------------------------------------------------------------------
# Images and masks
# --------------------------------------------------------------------------------------------


def _check_gt_depths(gts: dict[int, tuple[int, np.ndarray]], model_T_needle: np.ndarray, path: Path) -> None:
    """:class:`InputError` naming the ``cam_t_m2c`` of the first entry whose needle lies behind the camera or beyond
    the format's :data:`MAX_ABS_METRES`, before anything is written
    (:func:`~pinpoint_fg.io.recording.schema.gt_depth_problem`: the run's reader refuses it; the writer named the
    run's frames.csv, a file never written, for the distance)."""
    for im, (gt_idx, cam_T_model) in sorted(gts.items()):
        cam_T_needle = cam_T_model @ model_T_needle
        problem = gt_depth_problem(cam_T_needle)
        far = float(np.max(np.abs(cam_T_needle[:3, 3])))
        if problem is None and far > MAX_ABS_METRES:
            problem = f"the needle lies {far:.6g} m from the camera, beyond the format's {MAX_ABS_METRES:g} m"
        if problem is not None:
            raise InputError(problem, file=path,
                             column=f"{im}[{gt_idx}].cam_t_m2c")


def _find_image(scene: Path, im: int) -> Path:
    for d in IMAGE_DIRS:
        if (scene / d).is_dir():
            for ext in IMAGE_EXTENSIONS:
                p = scene / d / f"{im:06d}{ext}"
                if p.is_file():
                    return p
            raise InputError(f"no image for im_id {im} ({'/'.join(IMAGE_EXTENSIONS)})", file=scene / d / f"{im:06d}.*")
    raise InputError(f"no image directory ({' or '.join(d + '/' for d in IMAGE_DIRS)})", file=scene)


def _read(path: Path, flags: int, size: tuple[int, int] | None) -> np.ndarray:
    if not path.is_file():
        raise InputError("file not found", file=path)
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise InputError(f"cannot read: {exc.strerror or exc}", file=path) from None
    if data.startswith(PNG_SIGNATURE):
        try:  # a corrupt PNG made OpenCV print its own "[ERROR] ... readHeader" line before ours
            check_png(data)
        except ValueError as exc:
            raise InputError(f"not a readable image: {exc}", file=path) from None
    img = cv2.imdecode(np.frombuffer(data, dtype=np.uint8), flags) if data else None
    if img is None:
        raise InputError("not a readable image", file=path)
    if size is not None and (img.shape[1], img.shape[0]) != size:
        raise InputError(f"image is {img.shape[1]}x{img.shape[0]} px but the scene's images are "
                         f"{size[0]}x{size[1]} px (width x height)", file=path)
    return img


def _mask_reader(scene: Path, cfg: BopImportConfig) -> Callable[[int, int, tuple[int, int] | None], np.ndarray]:
    """``(im_id, gt_idx, size) -> bool (H, W)`` mask of the needle, per the configured mask kind."""
    root = scene / cfg.mask_dir
    if not root.is_dir():
        raise InputError("mask directory not found (choose one with --mask-dir)", file=root)
    if cfg.mask_color is None:
        def binary(im: int, gt_idx: int, size: tuple[int, int] | None) -> np.ndarray:
            m = _read(root / f"{im:06d}_{gt_idx:06d}.png", cv2.IMREAD_UNCHANGED, size)
            return (m != 0) if m.ndim == 2 else np.any(m != 0, axis=2)
        return binary
    bgr = np.array(cfg.mask_color[::-1])

    def colour(im: int, gt_idx: int, size: tuple[int, int] | None) -> np.ndarray:
        m = _read(root / f"{im:06d}.png", cv2.IMREAD_COLOR, size)
        return np.all(m == bgr, axis=2)
    return colour


# --------------------------------------------------------------------------------------------
# The import
# --------------------------------------------------------------------------------------------


#: Largest accepted standard deviation of synthetic keypoints (``--keypoints-from-gt``), pixels.
MAX_KEYPOINT_SIGMA_PX = 1000.0


def _check_config(cfg: BopImportConfig) -> None:
    if not math.isfinite(cfg.fps) or cfg.fps <= 0:
        raise InputError(f"fps (--fps) must be > 0, got {cfg.fps}")
    if cfg.keypoints_sigma_px is not None and not (math.isfinite(cfg.keypoints_sigma_px)
                                                   and 0 <= cfg.keypoints_sigma_px <= MAX_KEYPOINT_SIGMA_PX):
        # beyond the bound every synthetic keypoint lands off the image: 1e308 imported a run with none, exit 0
        raise InputError(f"keypoint noise (--keypoints-from-gt) must lie in 0 .. {MAX_KEYPOINT_SIGMA_PX:g} px, "
                         f"got {cfg.keypoints_sigma_px}")
    if cfg.instance is not None and cfg.instance < 0:
        raise InputError(f"instance (--instance) must be >= 0, got {cfg.instance}")
    if cfg.mask_color is not None and (len(cfg.mask_color) != 3 or any(not 0 <= c <= 255 for c in cfg.mask_color)):
        raise InputError(f"mask colour (--mask-color) must be three integers 0..255 (R,G,B), got {cfg.mask_color}")


def import_bop(scene_dir: str | Path, model_path: str | Path, out: str | Path,
               config: BopImportConfig, overwrite: bool = False) -> BopImportSummary:
    """Convert one BOP scene of the needle ``config.obj_id`` into the run ``out`` (module docstring).

    Everything that can be checked before writing is checked first (JSON files, the model fit,
    the existence of every image and mask file); ``out`` must not exist or be empty unless ``overwrite``
    (:func:`pinpoint_fg.io.outdir.check_output_dir`). The run is written into a hidden sibling of ``out`` and moved
    into place at the end (:func:`pinpoint_fg.io.outdir.staged_output_dir`): a file that fails half-way (a corrupt
    mask PNG) leaves no partial run behind (it was a valid run of the frames before it).
    """
    # "" was the current directory (an unset variable): the run was written into it
    scene, model_path = path_argument("scene_dir", scene_dir), path_argument("model_path", model_path)
    out = path_argument("out", out)
    cfg = config
    _check_config(cfg)
    if not scene.is_dir():
        raise InputError("not a directory (the BOP scene)", file=scene)
    check_output_dir(out, overwrite, "run", inputs=(scene,))
    fit = fit_needle_mesh(read_ply_vertices(model_path, cfg.model_units), tip_end=cfg.tip_end, source=model_path)
    try:
        needle = fit.needle_model(cfg.grasp_angle_rad)
    except ValueError as exc:
        raise InputError(f"needle fitted to the mesh with --grasp-angle-rad {cfg.grasp_angle_rad}: {exc}",
                         file=model_path) from None
    cams = _camera_entries(scene / SCENE_CAMERA)
    gts = _gt_entries(scene / SCENE_GT, cfg.obj_id, cfg.instance)
    _check_gt_depths(gts, fit.model_T_needle, scene / SCENE_GT)
    orphans = sorted(set(gts) - set(cams))
    if orphans:
        raise InputError(f"has ground truth for im_id {orphans[0]}, which {SCENE_CAMERA} does not list",
                         file=scene / SCENE_GT, column=str(orphans[0]))
    ids = sorted(cams)
    read_mask = _mask_reader(scene, cfg)
    image_paths = {im: _find_image(scene, im) for im in ids} if cfg.images else {}
    if cfg.mask_color is None:
        mask_files = [scene / cfg.mask_dir / f"{im:06d}_{gt_idx:06d}.png" for im, (gt_idx, _) in sorted(gts.items())]
    else:
        mask_files = [scene / cfg.mask_dir / f"{im:06d}.png" for im in ids]
    for p in mask_files:
        if not p.is_file():
            raise InputError("file not found (a mask the scene's ground truth calls for)", file=p)
    if cfg.mask_color is not None:  # the colour must occur somewhere (usually in the first file)
        bgr = np.array(cfg.mask_color[::-1])
        if not any(np.all(_read(p, cv2.IMREAD_COLOR, None) == bgr, axis=2).any() for p in mask_files):
            raise InputError(f"no pixel has the needle's colour (R,G,B) = {tuple(cfg.mask_color)} in any mask",
                             file=scene / cfg.mask_dir)
    has_images = any((scene / d).is_dir() for d in IMAGE_DIRS)
    first = _read(_find_image(scene, ids[0]) if has_images or cfg.images else mask_files[0],
                  cv2.IMREAD_UNCHANGED, None)
    size = (int(first.shape[1]), int(first.shape[0]))
    K = cams[ids[0]]
    camera = PinholeCamera(fx=K[0, 0], fy=K[1, 1], cx=K[0, 2], cy=K[1, 2], width=size[0], height=size[1],
                           distortion=(0.0,) * 5)
    keypoints = ({"source": "none"} if cfg.keypoints_sigma_px is None else
                 {"source": "synthetic: tip and tail of the ground-truth pose, projected, plus Gaussian noise",
                  "sigma_px": float(cfg.keypoints_sigma_px), "seed": int(cfg.seed)})
    extra = {"bop_import": {
        "scene_dir": str(scene), "obj_id": int(cfg.obj_id), "instance": cfg.instance, "model": str(model_path),
        "model_units": cfg.model_units, "model_T_needle": fit.model_T_needle.tolist(),
        "tip_from": fit.tip_from, "end_taper_tail_tip": list(fit.end_taper), "tube_p95_m": fit.tube_p95_m,
        "mask_dir": cfg.mask_dir, "mask_color_rgb": None if cfg.mask_color is None else list(cfg.mask_color),
        "keypoints": keypoints,
    }}
    info = RecordingInfo(name=cfg.name or scene.resolve().name, frame_rate_hz=float(cfg.fps), camera=camera,
                         needle=needle, extra=extra)
    # before anything is written; the camera's values came from scene_camera.json: name it
    check_recording_info(info, out / "recording.json", camera_source=(scene / SCENE_CAMERA, f"{ids[0]}.cam_K"))
    rng = np.random.default_rng(cfg.seed)
    n_gt = n_mask = n_kp = 0
    with staged_output_dir(out, overwrite, "run", inputs=(scene,)) as stage, RecordingWriter(stage, info) as writer:
        for im in ids:
            gt = gts.get(im)
            cam_T_needle = None if gt is None else gt[1] @ fit.model_T_needle
            mask = None
            if cfg.mask_color is not None:
                m = read_mask(im, 0, size)
                mask = m if m.any() else None  # an observation, with or without gt
            elif gt is not None:
                m = read_mask(im, gt[0], size)
                mask = m if m.any() else None
            tip = tail = None
            if cam_T_needle is not None and cfg.keypoints_sigma_px is not None:
                pts = np.stack([needle.tip_m, needle.tail_m]) @ cam_T_needle[:3, :3].T + cam_T_needle[:3, 3]
                noise = rng.normal(0.0, cfg.keypoints_sigma_px, (2, 2))  # drawn for every gt frame: reproducible
                px = camera.project(pts) + noise
                keep = (pts[:, 2] > 0) & camera.in_image(px)
                tip = px[0] if keep[0] else None
                tail = px[1] if keep[1] else None
            image = _read(image_paths[im], cv2.IMREAD_UNCHANGED, size) if cfg.images else None
            if image is not None and image.dtype not in (np.uint8, np.uint16):
                raise InputError(f"image type {image.dtype} is not supported (8 or 16 bit)", file=image_paths[im])
            writer.add(FrameRecord(frame=im, t_s=im / cfg.fps, tip_px=tip, tail_px=tail,
                                   cam_T_needle_gt=cam_T_needle), mask=mask, image=image)
            n_gt += gt is not None
            n_mask += mask is not None
            n_kp += tip is not None or tail is not None
    return BopImportSummary(out=out, frames=len(ids), with_gt=n_gt, with_mask=n_mask, with_keypoints=n_kp, fit=fit)

