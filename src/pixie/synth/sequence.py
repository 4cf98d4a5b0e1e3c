"""Rendered photo sequences with smooth object motion: the test and bench data of pose tracking (``pixie track``).

>>> seq = smooth_sequence(mesh, K, 480, 640, n_frames=60, seed=0)
>>> seq.images[i], seq.poses[i], seq.boxes[i]          # RGB uint8, T_cam_from_obj (mm), visible box (x, y, w, h)
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from pixie.geometry.camera import make_T
from pixie.geometry.mesh import Mesh
from pixie.geometry.render import Renderer
from pixie.synth.photo import LightRig, Material, box_renderer, random_background, render_rgb

__all__ = ["Sequence", "smooth_sequence"]


@dataclass(kw_only=True)
class Sequence:
    images: list[np.ndarray]
    poses: list[np.ndarray]
    boxes: list[tuple[float, float, float, float]]
    K: np.ndarray


def _random_pose(mesh: Mesh, rng: np.random.Generator, K: np.ndarray, distance_factor: float) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    R = Rotation.random(random_state=int(rng.integers(1 << 31))).as_matrix()
    z = distance_factor * mesh.diameter
    return make_T(R, np.array([0.0, 0.0, z]) - R @ mesh.center)


def smooth_sequence(mesh: Mesh, K: np.ndarray, height: int, width: int, n_frames: int = 60, seed: int = 0,
                    deg_per_frame: float = 2.0, px_per_frame: float = 2.0, distance_factor: float = 3.5,
                    clutter: bool = True, distractors: int = 0) -> Sequence:
    """The object turning about a fixed random axis (``deg_per_frame``), drifting across the image
    (``px_per_frame``) and slowly approaching/receding (±10 % depth over the sequence), over one textured /
    cluttered background, one material and one light rig (fixed over the sequence, as for a real camera).
    ``distractors`` static boxes sit in the scene (LM-O-like clutter, occluding the object at times)."""
    rng = np.random.default_rng(seed)
    ren = Renderer(mesh)
    T0 = _random_pose(mesh, rng, K, distance_factor)
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    step = cv2.Rodrigues(axis * np.radians(deg_per_frame))[0]
    phi = rng.uniform(0, 2 * np.pi)
    material = Material.random(rng)
    lights = LightRig.random(rng)
    bg = random_background(height, width, rng, "clutter" if clutter else "gradient")
    others, other_poses, other_mats = [], [], []
    f_px = K[0, 0] * mesh.diameter / T0[2, 3]  # the object's size in the image, px
    for j in range(distractors):
        others.append(box_renderer(rng.uniform(0.3, 0.7, 3) * mesh.diameter))
        # the first one in front, beside the path (covers a part of the object at times), the others behind it
        z = T0[2, 3] * (0.75 if j == 0 else rng.uniform(1.2, 1.5))
        side = rng.choice([-1.0, 1.0])
        off = np.array([-np.sin(phi), np.cos(phi)]) * side * 0.6 * f_px if j == 0 else rng.normal(0, 1.0, 2) * f_px
        uv = np.array([K[0, 2], K[1, 2]]) + off
        other_poses.append(make_T(cv2.Rodrigues(rng.normal(size=3))[0],
                                  np.array([(uv[0] - K[0, 2]) / K[0, 0] * z, (uv[1] - K[1, 2]) / K[1, 1] * z, z])))
        other_mats.append(Material.random(rng))
    images, poses, boxes = [], [], []
    R = T0[:3, :3]
    c0 = T0[:3, :3] @ mesh.center + T0[:3, 3]
    for i in range(n_frames):
        R = step @ R if i else R
        z = c0[2] * (1.0 + 0.1 * np.sin(2 * np.pi * i / max(n_frames, 1)))
        u = K[0, 2] + px_per_frame * (i - n_frames / 2) * np.cos(phi)
        v = K[1, 2] + px_per_frame * (i - n_frames / 2) * np.sin(phi)
        c = np.array([(u - K[0, 2]) / K[0, 0] * z, (v - K[1, 2]) / K[1, 1] * z, z])
        T = make_T(R, c - R @ mesh.center)
        ph = render_rgb([ren] + others, [T] + other_poses, K, height, width, [material] + other_mats,
                        np.random.default_rng([seed, i]), background=bg, lights=lights, shadows=False)
        ys, xs = np.nonzero(ph.masks_visib[0])
        box = (float(xs.min()), float(ys.min()), float(xs.max() - xs.min() + 1), float(ys.max() - ys.min() + 1)) \
            if len(xs) else None
        images.append(ph.rgb)
        poses.append(T)
        boxes.append(box)
    return Sequence(images=images, poses=poses, boxes=boxes, K=np.asarray(K, np.float64))
