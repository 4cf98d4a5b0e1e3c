"""Labelled query/reference pairs for training cross-modality matchers.

One sample (deterministic from its seed, :func:`make_pair`):

* **query**: a photo-like 640x480 frame (:func:`pixie.synth.photo.render_rgb`: random material,
  1-3 lights + ambient, shadows, procedural background, 2-5 distractor parts some of which occlude the
  target, then :func:`pixie.synth.photo.degrade`) of a procedural part (:mod:`pixie.synth.parts`) seen
  40-120 px large, cropped like :func:`pixie.pipeline.query.square_crop` (square of ``pad`` x the visible box,
  resampled to ``size`` px, so small objects are upsampled like real LM-O crops);
* **reference**: geometry encodings (``shade3_edges``, ``depth``, ``normal``; :func:`pixie.references.encode.encode`)
  of the same part rendered like a reference view (``K_start`` focal, :func:`pixie.references.views.square_crop_K`
  object-centred crop of ``size`` px) from a nearby viewpoint: viewing direction within ``max_view_deg``
  of the query's and an in-plane roll within ``max_roll_deg`` (180 = any);
* **ground truth**: object XYZ of every query-crop pixel (rendered exactly at the crop intrinsics with
  all objects, so occluders hide the target) and the reference depth; :meth:`Pair.correspond` maps query
  pixels to reference pixels (same surface point, visible in both: depth check).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from pixie.geometry.camera import backproject, invert_T, make_T, rot_z
from pixie.references.encode import encode
from pixie.geometry.rotations import nearest_pixel, rodrigues, rotation_between
from pixie.geometry.mesh import Mesh
from pixie.pipeline.query import square_crop
from pixie.geometry.render import Renderer, composite
from pixie.synth import photo
from pixie.synth.parts import random_part
from pixie.geometry.camera import crop_K
from pixie.references.views import camera_distance, square_crop_K, start_K

ENCODINGS = ("shade3_edges", "depth", "normal")
IMAGE_W, IMAGE_H = 640, 480


@dataclass
class PairConfig:
    size: int = 512  # crop side (query and reference), px
    crop_pad: float = 1.2  # as RefsConfig.crop_pad / QueryConfig.crop_pad
    focal_factor: float = 4.0  # reference K_start focal = focal_factor * size
    object_px: tuple[float, float] = (40.0, 120.0)  # projected diameter of the target in the 640x480 frame
    max_view_deg: float = 15.0  # angle between query and reference viewing directions
    max_roll_deg: float = 22.5  # in-plane roll of the reference: half the 45° step of the reference rolls (180: any)
    n_distractors: tuple[int, int] = (2, 5)
    occluder_prob: float = 0.5  # probability that one distractor is put in front of the target
    min_visib: float = 0.35
    encodings: tuple[str, ...] = ENCODINGS
    box_jitter: float = 0.05  # relative jitter of the visible box (detector noise)
    degrade: bool = True


@dataclass
class Pair:
    """One labelled query/reference pair (all images ``size`` x ``size``)."""

    seed: int
    mesh: Mesh
    query: np.ndarray  # (S, S, 3) uint8 photo crop
    query_owner: np.ndarray  # (S, S) int32: 0 target, >0 distractor, -1 background
    query_xyz: np.ndarray  # (S, S, 3) float32 object XYZ of the target's visible pixels (0 elsewhere)
    query_K: np.ndarray  # intrinsics of the crop
    query_T: np.ndarray  # T_cam_from_obj of the target
    refs: dict[str, np.ndarray]  # encoding -> (S, S[, 3]) uint8
    ref_depth: np.ndarray  # (S, S) float32
    ref_K: np.ndarray
    ref_T: np.ndarray
    visib_fract: float = 1.0
    info: dict = field(default_factory=dict)

    @property
    def ref_mask(self) -> np.ndarray:
        return self.ref_depth > 0

    @property
    def query_mask(self) -> np.ndarray:
        return self.query_owner == 0

    def correspond(self, kp_q: np.ndarray, depth_tol: float | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Reference pixel (x, y) of each query keypoint, and whether it is a valid correspondence.

        Valid: the keypoint's nearest query pixel shows the target, its surface point projects inside the
        reference and is not hidden there (reference depth within ``depth_tol`` mm of the point's depth;
        default 1.5 % of the part's diameter).
        """
        kp_q = np.asarray(kp_q, np.float64).reshape(-1, 2)
        ix, iy = nearest_pixel(kp_q, self.query_owner.shape)
        on = self.query_owner[iy, ix] == 0
        X = self.query_xyz[iy, ix].astype(np.float64)
        Xc = X @ self.ref_T[:3, :3].T + self.ref_T[:3, 3]
        z = np.maximum(Xc[:, 2], 1e-6)
        uv = np.stack([self.ref_K[0, 0] * Xc[:, 0] / z + self.ref_K[0, 2],
                       self.ref_K[1, 1] * Xc[:, 1] / z + self.ref_K[1, 2]], 1)
        H, W = self.ref_depth.shape
        rx, ry = np.rint(uv[:, 0]).astype(int), np.rint(uv[:, 1]).astype(int)
        inside = (rx >= 0) & (rx < W) & (ry >= 0) & (ry < H)
        d = np.zeros(len(kp_q))
        d[inside] = self.ref_depth[ry[inside], rx[inside]]
        tol = 0.015 * self.mesh.diameter if depth_tol is None else depth_tol
        valid = on & inside & (d > 0) & (np.abs(d - z) < tol)
        return uv.astype(np.float32), valid


    def correspond_ref(self, kp_r: np.ndarray, tol: float | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Query-crop pixel (x, y) of each reference keypoint, and whether it is a valid correspondence.

        Valid: the keypoint's nearest reference pixel is on the part, its surface point projects into the
        query crop onto a pixel that shows the target with (nearly) the same object XYZ (within ``tol`` mm,
        default 1.5 % of the diameter: the point is not occluded in the query).
        """
        kp_r = np.asarray(kp_r, np.float64).reshape(-1, 2)
        H, W = self.ref_depth.shape
        ix, iy = nearest_pixel(kp_r, self.ref_depth.shape)
        z = self.ref_depth[iy, ix].astype(np.float64)
        Xc = backproject(self.ref_K, np.stack([ix, iy], 1).astype(np.float64), z)
        Ti = invert_T(self.ref_T)
        X = Xc @ Ti[:3, :3].T + Ti[:3, 3]
        Xq = X @ self.query_T[:3, :3].T + self.query_T[:3, 3]
        zq = np.maximum(Xq[:, 2], 1e-6)
        uv = np.stack([self.query_K[0, 0] * Xq[:, 0] / zq + self.query_K[0, 2],
                       self.query_K[1, 1] * Xq[:, 1] / zq + self.query_K[1, 2]], 1)
        S = self.query_owner.shape[0]
        qx, qy = np.rint(uv[:, 0]).astype(int), np.rint(uv[:, 1]).astype(int)
        inside = (qx >= 0) & (qx < S) & (qy >= 0) & (qy < S) & (z > 0)
        valid = np.zeros(len(kp_r), bool)
        tol = 0.015 * self.mesh.diameter if tol is None else tol
        qi = np.flatnonzero(inside)
        on = self.query_owner[qy[qi], qx[qi]] == 0
        dist = np.linalg.norm(self.query_xyz[qy[qi], qx[qi]] - X[qi], axis=1)
        valid[qi] = on & (dist < tol)
        return uv.astype(np.float32), valid


def _random_rotation(rng: np.random.Generator) -> np.ndarray:
    q = rng.standard_normal(4)
    q /= np.linalg.norm(q)
    w, x, y, z = q
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ])


def _centre_on_axis(R: np.ndarray, t: np.ndarray, center: np.ndarray) -> np.ndarray:
    """Rotation turning the camera so the object centre lies on the optical axis (like a query crop)."""
    c = R @ center + t
    return rotation_between(c / np.linalg.norm(c), np.array([0.0, 0.0, 1.0])) @ R


def reference_pose(mesh: Mesh, R_query: np.ndarray, t_query: np.ndarray, rng: np.random.Generator,
                   cfg: PairConfig) -> tuple[np.ndarray, np.ndarray]:
    """A reference pose near the query's view and its ``size`` px square-crop intrinsics."""
    S = int(cfg.size)
    K0 = start_K(S, cfg.focal_factor)
    dist = camera_distance(mesh.bounding_radius, K0[0, 0], S, fill=1.0 / cfg.crop_pad)
    R = _centre_on_axis(R_query, t_query, mesh.center)
    ang = np.radians(cfg.max_view_deg) * np.sqrt(rng.random())  # uniform over the spherical cap (approx.)
    axis = rng.standard_normal(3)
    axis[2] = 0.0  # tilt about an axis in the image plane: the viewing direction changes by `ang`
    R = rodrigues(axis, ang) @ R
    R = rot_z(np.radians(cfg.max_roll_deg) * rng.uniform(-1, 1)) @ R
    T = make_T(R, np.array([0.0, 0.0, dist]) - R @ mesh.center)
    K, _ = square_crop_K(K0, T, mesh.vertices, S, cfg.crop_pad)
    return T, K


def make_pair(seed: int, cfg: PairConfig | None = None, part_seed: int | None = None,
              parts_fn=None) -> Pair:
    """Build one labelled pair from ``seed`` (the target part is ``parts_fn(part_seed)``, default seed)."""
    cfg = cfg or PairConfig()
    parts_fn = parts_fn or random_part
    rng = np.random.default_rng([int(seed), 424242])
    S = int(cfg.size)
    mesh = parts_fn(int(seed if part_seed is None else part_seed))
    n_dis = int(rng.integers(cfg.n_distractors[0], cfg.n_distractors[1] + 1))
    distractors = [parts_fn(int(rng.integers(1 << 30))) for _ in range(n_dis)]
    meshes = [mesh] + distractors
    renderers = [Renderer(m) for m in meshes]
    f = float(rng.uniform(520, 620))
    K = np.array([[f, 0, IMAGE_W / 2 + rng.uniform(-10, 10)], [0, f, IMAGE_H / 2 + rng.uniform(-10, 10)], [0, 0, 1]])

    for attempt in range(20):
        # Target: random rotation, projected diameter object_px, anywhere in the frame.
        px = float(rng.uniform(*cfg.object_px))
        z = f * mesh.diameter / px
        u, v = rng.uniform(0.15, 0.85) * IMAGE_W, rng.uniform(0.15, 0.85) * IMAGE_H
        p_cam = np.array([(u - K[0, 2]) / f * z, (v - K[1, 2]) / f * z, z])
        R = _random_rotation(rng)
        poses = [make_T(R, p_cam - R @ mesh.center)]
        occluder = rng.random() < cfg.occluder_prob
        for k, dm in enumerate(distractors):
            Rd = _random_rotation(rng)
            if k == 0 and occluder:  # in front of the target, offset so it hides part of it
                zd = z * rng.uniform(0.6, 0.9)
                off = rng.uniform(-0.6, 0.6, 2) * (mesh.diameter + dm.diameter) * 0.5 * zd / z
                pd = np.array([p_cam[0] * zd / z + off[0], p_cam[1] * zd / z + off[1], zd])
            else:
                zd = z * rng.uniform(0.7, 1.6)
                ud, vd = u + rng.uniform(-1.5, 1.5) * px, v + rng.uniform(-1.5, 1.5) * px
                pd = np.array([(ud - K[0, 2]) / f * zd, (vd - K[1, 2]) / f * zd, zd])
            poses.append(make_T(Rd, pd - Rd @ dm.center))
        mats = [photo.Material.random(rng) for _ in meshes]
        res = photo.render_rgb(renderers, poses, K, IMAGE_H, IMAGE_W, mats, rng)
        full, vis = res.masks[0], res.masks_visib[0]
        visib = float(vis.sum()) / max(float(full.sum()), 1.0)
        if full.sum() > 0 and visib >= cfg.min_visib and vis.sum() >= 200:
            break
    rgb = photo.degrade(res.rgb, rng) if cfg.degrade else res.rgb

    # Query crop around the (jittered) visible box, exactly like pixie.pipeline.query.square_crop.
    ys, xs = np.nonzero(vis)
    box = np.array([xs.min(), ys.min(), xs.max() + 1, ys.max() + 1], np.float64)
    wh = box[2:] - box[:2]
    box += np.concatenate([wh, wh]) * rng.uniform(-cfg.box_jitter, cfg.box_jitter, 4)
    crop = square_crop(rgb, box, cfg.crop_pad, S)
    centre = 0.5 * np.array([box[0] + box[2], box[1] + box[3]]) - 0.5
    side = max(box[2] - box[0], box[3] - box[1]) * cfg.crop_pad
    Kq = crop_K(K, centre[0] + 0.5 - side / 2, centre[1] + 0.5 - side / 2, side, S)
    qr = [r.render(T, Kq, S, S) for r, T in zip(renderers, poses)]
    _, owner = composite(qr)
    qxyz = np.where((owner == 0)[..., None], qr[0].xyz, 0).astype(np.float32)

    # Reference: a nearby view rendered like a reference-set view.
    Tr, Kr = reference_pose(mesh, R, poses[0][:3, 3], rng, cfg)
    rr = renderers[0].render(Tr, Kr, S, S)
    encs = {e: encode(e, rr.depth, rr.normals, rr.mask) for e in cfg.encodings}
    return Pair(seed=int(seed), mesh=mesh, query=crop.image, query_owner=owner, query_xyz=qxyz, query_K=Kq,
                query_T=poses[0], refs=encs, ref_depth=rr.depth, ref_K=Kr, ref_T=Tr, visib_fract=visib,
                info={"object_px": px, "n_distractors": n_dis, "occluder": bool(occluder), "attempts": attempt + 1,
                      "frame": rgb, "box_xyxy": box, "K": K})
