"""Test data for the BOP importer: a needle tube mesh (PLY) and a small BOP scene, written by the tests.

The mesh is a wire of radius ``wire_mm`` around an arc of a circle of radius ``radius_mm``: in
its own construction frame (the needle frame of DESIGN.md) the centre line is
``r (cos θ, sin θ, 0)``, θ from 0 (tail, flat end face) to ``arc_rad`` (tip). Over the last
``taper`` fraction of the arc the wire narrows linearly to a point. The model frame is this
frame moved by ``model_T_needle`` (a tilted plane, an arc starting at a non-zero angle, an offset
centre), so the importer has to find all of it.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from plyfile import PlyData, PlyElement

from factors.geometry import NeedleModel, PinholeCamera
from factors.lie import homogeneous, se3_inverse, so3_exp
from pinpoint_fg.sim.render import draw_needle, render_mask, tissue_background

CAMERA = PinholeCamera(fx=600.0, fy=610.0, cx=319.5, cy=241.0, width=640, height=480)
NEEDLE_OBJ_ID = 7
OTHER_OBJ_ID = 3
#: R, G, B of the needle in the colour-label masks (and of the other object).
NEEDLE_RGB = (255, 0, 128)
OTHER_RGB = (0, 200, 0)


@dataclass(frozen=True)
class MeshTruth:
    """The construction of a test mesh."""

    radius_m: float
    wire_m: float
    arc_rad: float
    model_T_needle: np.ndarray
    """Needle frame (tail at θ=0, tip at arc_rad, normal +z) -> model frame, metres."""

    @property
    def needle(self) -> NeedleModel:
        return NeedleModel(radius_m=self.radius_m, tail_angle_rad=0.0, tip_angle_rad=self.arc_rad,
                           grasp_angle_rad=self.arc_rad / 3, wire_diameter_m=2 * self.wire_m)


def default_model_T_needle() -> np.ndarray:
    """A tilted circle plane, the arc starting at 1.1 rad about it, the centre off the origin (metres)."""
    R = so3_exp(np.array([0.7, -0.4, 0.25])) @ so3_exp(np.array([0.0, 0.0, 1.1]))
    return homogeneous(R, np.array([3.2e-3, -1.7e-3, 2.4e-3]))


def tube_mesh(radius_mm: float = 4.5, wire_mm: float = 0.2, arc_rad: float = 0.75 * math.pi,
              taper: float = 0.2, rings: int = 160, sides: int = 12,
              model_T_needle: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, MeshTruth]:
    """Vertices ``(V, 3)`` in mm (model frame), triangles ``(F, 3)`` and the truth."""
    T = default_model_T_needle() if model_T_needle is None else model_T_needle
    theta = np.linspace(0.0, arc_rad, rings)
    frac = theta / arc_rad
    w = wire_mm * np.clip((1.0 - frac) / taper, 0.0, 1.0) if taper > 0 else np.full(rings, wire_mm)
    phi = 2 * np.pi * np.arange(sides) / sides
    er = np.stack([np.cos(theta), np.sin(theta), np.zeros(rings)], axis=1)
    ez = np.array([0.0, 0.0, 1.0])
    centre = radius_mm * er
    ring = centre[:, None, :] + w[:, None, None] * (np.cos(phi)[None, :, None] * er[:, None, :]
                                                    + np.sin(phi)[None, :, None] * ez)
    verts = np.concatenate([ring.reshape(-1, 3), centre[:1]])  # + the tail face's centre
    faces = []
    for i in range(rings - 1):
        for k in range(sides):
            a, b = i * sides + k, i * sides + (k + 1) % sides
            faces += [(a, b, a + sides), (b, b + sides, a + sides)]
    tail_c = rings * sides
    faces += [(tail_c, (k + 1) % sides, k) for k in range(sides)]
    verts_model = verts @ T[:3, :3].T + T[:3, 3] * 1e3
    truth = MeshTruth(radius_m=radius_mm * 1e-3, wire_m=wire_mm * 1e-3, arc_rad=arc_rad, model_T_needle=T)
    return verts_model, np.asarray(faces, dtype=np.int32), truth


def write_ply(path: Path, verts: np.ndarray, faces: np.ndarray | None = None, text: bool = False) -> Path:
    """A PLY file with float32 vertices (and triangles) through plyfile."""
    v = np.array([tuple(p) for p in verts], dtype=[("x", "f4"), ("y", "f4"), ("z", "f4")])
    elements = [PlyElement.describe(v, "vertex")]
    if faces is not None:
        f = np.empty(len(faces), dtype=[("vertex_indices", "i4", (3,))])
        f["vertex_indices"] = faces
        elements.append(PlyElement.describe(f, "face"))
    PlyData(elements, text=text).write(str(path))
    return path


def needle_trajectory(n: int) -> np.ndarray:
    """``(n, 4, 4)`` smooth ``cam_T_needle`` about 45 mm in front of the camera, seen obliquely."""
    out = []
    for k in range(n):
        R = so3_exp(np.array([0.9 + 0.02 * k, -0.3 + 0.015 * k, 0.4 + 0.03 * k]))
        t = np.array([-2e-3 + 0.3e-3 * k, 1e-3 - 0.2e-3 * k, 0.045 + 0.4e-3 * k])
        out.append(homogeneous(R, t))
    return np.asarray(out)


def write_bop_scene(root: Path, n_images: int = 8, without_needle: tuple[int, ...] = (5,),
                    taper: float = 0.2) -> dict:
    """A BOP scene under ``root``: models/obj_000007.ply, 000001/{scene_camera,scene_gt}.json, rgb/, masks.

    Image ``k`` holds the needle (obj 7, gt index 1) at ``needle_trajectory(n)[k]`` unless
    ``k in without_needle``, and another object (obj 3, gt index 0). Masks: ``mask_visib/`` (binary,
    per instance, rendered with the project's renderer without noise) and ``labels/`` (colour labels).
    Returns the truth: mesh, poses, paths.
    """
    verts, faces, truth = tube_mesh(taper=taper)
    (root / "models").mkdir(parents=True, exist_ok=True)
    model = write_ply(root / "models" / f"obj_{NEEDLE_OBJ_ID:06d}.ply", verts, faces)
    scene = root / "000001"
    for d in ("rgb", "mask_visib", "labels"):
        (scene / d).mkdir(parents=True, exist_ok=True)
    poses = needle_trajectory(n_images)
    needle = truth.needle
    theta = needle.arc_angles(271)
    visible = np.ones(theta.shape, bool)
    K = CAMERA.K.ravel().tolist()
    scene_camera, scene_gt = {}, {}
    other_T = homogeneous(so3_exp(np.array([0.1, 0.2, 0.3])), np.array([0.01, 0.008, 0.06]))
    for k in range(n_images):
        scene_camera[str(k)] = {"cam_K": K, "depth_scale": 1.0}
        entries = [{"obj_id": OTHER_OBJ_ID, "cam_R_m2c": other_T[:3, :3].ravel().tolist(),
                    "cam_t_m2c": (other_T[:3, 3] * 1e3).tolist()}]
        img = tissue_background(CAMERA.width, CAMERA.height, seed=k)
        labels = np.zeros((CAMERA.height, CAMERA.width, 3), np.uint8)
        other = np.zeros((CAMERA.height, CAMERA.width), np.uint8)
        cv2.circle(other, (560, 80), 30, 255, -1)
        labels[other > 0] = OTHER_RGB[::-1]
        cv2.imwrite(str(scene / "mask_visib" / f"{k:06d}_000000.png"), other)
        if k not in without_needle:
            cam_T_model = poses[k] @ se3_inverse(truth.model_T_needle)
            entries.append({"obj_id": NEEDLE_OBJ_ID, "cam_R_m2c": cam_T_model[:3, :3].ravel().tolist(),
                            "cam_t_m2c": (cam_T_model[:3, 3] * 1e3).tolist()})
            mask, _ = render_mask(CAMERA, poses[k], needle, theta, visible, np.random.default_rng(k),
                                  0.0, 0.0, 20.0, 0.5, 0.0, (5.0, 10.0), 20.0)
            cv2.imwrite(str(scene / "mask_visib" / f"{k:06d}_000001.png"), mask)
            labels[mask > 0] = NEEDLE_RGB[::-1]
            draw_needle(img, CAMERA, poses[k], needle, theta, visible)
        scene_gt[str(k)] = entries
        cv2.imwrite(str(scene / "rgb" / f"{k:06d}.png"), img)
        cv2.imwrite(str(scene / "labels" / f"{k:06d}.png"), labels)
    (scene / "scene_camera.json").write_text(json.dumps(scene_camera, indent=2))
    (scene / "scene_gt.json").write_text(json.dumps(scene_gt, indent=2))
    return {"scene": scene, "model": model, "truth": truth, "poses": poses, "without_needle": without_needle}
