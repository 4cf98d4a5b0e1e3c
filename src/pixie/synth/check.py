"""A photo of your own part with a known pose: the data behind ``pixie render`` ("check your setup first").

>>> scene = check_scene(mesh, K, 480, 640, seed=0)                 # a random pose facing the camera
>>> scene.rgb, scene.mask, scene.bbox_xywh, scene.T_cam_from_obj   # photo, mask, box, ground truth (mm)
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from pixie.geometry.camera import make_T, validate_K, validate_pose
from pixie.eval.pose_error import add, rotation_error_deg, translation_error
from pixie.geometry.mesh import Mesh
from pixie.geometry.render import Renderer
from pixie.synth.photo import LightRig, Material, box_renderer, degrade, random_background, render_rgb

__all__ = ["CheckScene", "BACKGROUNDS", "check_scene", "random_facing_pose", "pose_error"]

BACKGROUNDS = ("plain", "gradient", "noise", "texture", "clutter")


@dataclass(kw_only=True)
class CheckScene:
    """The rendered photo and its ground truth: RGB uint8, visible-object mask, box (x, y, w, h; w, h counting
    pixels), pose (mm, OpenCV camera), K, the share of the object that is visible."""

    rgb: np.ndarray
    mask: np.ndarray
    bbox_xywh: tuple[int, int, int, int]
    T_cam_from_obj: np.ndarray
    K: np.ndarray
    visib_fract: float


def random_facing_pose(mesh: Mesh, K: np.ndarray, width: int, height: int, rng: np.random.Generator,
                       distance_factor: float = 3.0) -> np.ndarray:
    """A uniformly random rotation, the object's centre ``distance_factor`` diameters away and within the middle
    half of the image."""
    from scipy.spatial.transform import Rotation

    R = Rotation.random(random_state=int(rng.integers(1 << 31))).as_matrix()
    z = distance_factor * mesh.diameter
    u, v = rng.uniform(0.35, 0.65) * width, rng.uniform(0.35, 0.65) * height
    c = np.array([(u - K[0, 2]) / K[0, 0] * z, (v - K[1, 2]) / K[1, 1] * z, z])
    return make_T(R, c - R @ mesh.center)


def check_scene(mesh: Mesh, K: np.ndarray, height: int, width: int, T: np.ndarray | None = None, seed: int = 0,
                colour=None, background: str | np.ndarray = "clutter", noise: bool = False, blur: bool = False,
                distractors: int = 0, distance_factor: float = 3.0) -> CheckScene:
    """Render ``mesh`` at ``T`` (random and facing the camera when None) in camera ``K``.

    Parameters
    ----------
    colour : RGB (0-1 floats or 0-255) of the part; None = a random plastic / metal-like material
    background : one of :data:`BACKGROUNDS`, or an (H, W, 3) uint8 RGB image (resized to the photo)
    noise, blur : sensor noise / defocus blur (:func:`pixie.synth.photo.degrade`)
    distractors : boxes about the part's size placed around it (clutter that may occlude it)
    """
    K = validate_K(K)
    rng = np.random.default_rng(seed)
    T = random_facing_pose(mesh, K, width, height, rng, distance_factor) if T is None else validate_pose(T)
    if isinstance(background, np.ndarray):
        bg = cv2.resize(np.ascontiguousarray(background[..., :3]), (width, height), interpolation=cv2.INTER_AREA)
    elif background == "plain":
        bg = np.full((height, width, 3), 128, np.uint8)
    elif background in BACKGROUNDS:
        bg = random_background(height, width, rng, background)
    else:
        raise ValueError(f"background must be one of {', '.join(BACKGROUNDS)} or an image, got {background!r}")
    mat = Material.random(rng) if colour is None else Material(color=colour, roughness=0.5, specular=0.3)
    rens, poses, mats = [Renderer(mesh)], [T], [mat]
    if distractors:
        c = T[:3, :3] @ mesh.center + T[:3, 3]
        for _ in range(int(distractors)):
            rens.append(box_renderer(rng.uniform(0.3, 0.8, 3) * mesh.diameter))
            off = rng.normal(0.0, 0.6, 2) * mesh.diameter
            poses.append(make_T(cv2.Rodrigues(rng.normal(size=3))[0],
                                c + np.array([off[0], off[1], rng.uniform(-0.3, 0.8) * mesh.diameter])))
            mats.append(Material.random(rng))
    ph = render_rgb(rens, poses, K, height, width, mats, rng, background=bg, lights=LightRig.random(rng), shadows=True)
    rgb = ph.rgb
    if noise or blur:
        rgb = degrade(rgb, rng, blur=blur, noise=noise, jpeg=False, resample=False)
    m = ph.masks_visib[0]
    if not m.any():
        raise ValueError("the part is not visible at this pose (outside the image or hidden): choose another pose")
    ys, xs = np.nonzero(m)
    box = (int(xs.min()), int(ys.min()), int(xs.max() - xs.min() + 1), int(ys.max() - ys.min() + 1))
    return CheckScene(rgb=rgb, mask=m, bbox_xywh=box, T_cam_from_obj=T, K=K, visib_fract=ph.visib_fract(0))


def pose_error(T_est: np.ndarray, T_gt: np.ndarray, vertices: np.ndarray) -> dict[str, float]:
    """Rotation error (deg), translation error (mm), depth error (% of the true depth) and ADD (mm, mean distance
    of the model's vertices under the two poses) of an estimate."""
    v = np.asarray(vertices, np.float64)
    if len(v) > 5000:
        v = v[np.linspace(0, len(v) - 1, 5000).astype(int)]
    return {"rot_deg": rotation_error_deg(T_est, T_gt), "trans_mm": translation_error(T_est, T_gt),
            "depth_pct": float(100 * abs(T_est[2, 3] - T_gt[2, 3]) / abs(T_gt[2, 3])), "add_mm": add(T_est, T_gt, v)}
