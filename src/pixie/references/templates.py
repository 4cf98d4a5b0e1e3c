"""Contour templates from geometry: the object's silhouette and crease edges as oriented 2D points.

The shape of an object is what a photo of it shares with its CAD model whatever the paint, finish or light:
the outline (depth > 0 boundary) and the creases (where the surface normal turns sharply). For every view of
a set of viewpoints (each camera looks at the mesh centre, as the reference views do) this module renders
depth and normals at low resolution, finds those edges and keeps a spread subset of oriented points
``(x, y, orientation, kind)`` with the object point under each. In-plane rolls cost nothing: rolling the
camera about its optical axis (which passes through the object centre) turns the image about the principal
point, so a view's points are simply rotated (:meth:`ContourTemplates.rolled`).

Points are stored relative to the principal point of the template camera, in template pixels; the box of the
full silhouette (per roll) fixes scale and position against a query box (:mod:`pixie.cues.edges`).

>>> tpl = build_templates(mesh, n_views=300, size=128)
>>> xy, ori, kind = tpl.rolled(np.radians([0, 10, 20]))   # (V, 3, N, 2), (V, 3, N), (V, N)
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass
from typing import Callable

import cv2
import numpy as np

from pixie.geometry.camera import backproject, invert_T, make_K, transform_points
from pixie.geometry.mesh import Mesh
from pixie.geometry.render import Renderer
from pixie.references.views import camera_distance, fibonacci_sphere, look_at, up_vector

SILHOUETTE, CREASE = 0, 1


def _rotate2d(pts: np.ndarray, angles: np.ndarray) -> np.ndarray:
    """Points (V, N, 2) turned by each angle (A,) radians: (V, A, N, 2) float32, ``[c -s; s c] @ p``.

    Written out per coordinate (float32, as the points): a batched 2x2 product that an einsum over (V, A, N)
    would run ~30x slower.
    """
    c = np.cos(angles).astype(np.float32)[None, :, None]
    s = np.sin(angles).astype(np.float32)[None, :, None]
    x, y = pts[:, None, :, 0].astype(np.float32), pts[:, None, :, 1].astype(np.float32)
    return np.stack([c * x + (-s) * y, s * x + c * y], axis=-1)


@dataclass
class ContourTemplates:
    """Oriented contour points of V views (roll 0), N points each.

    Attributes
    ----------
    poses : (V, 4, 4) T_cam_from_obj of each view's camera (looks at the mesh centre, roll 0)
    K : (3, 3) intrinsics of the template renders (principal point at the image centre)
    xy : (V, N, 2) float32, point offsets from the principal point, template px
    ori : (V, N) float32, unsigned edge orientation (gradient direction) in [0, pi), radians
    kind : (V, N) int8, SILHOUETTE or CREASE; padding points (views with fewer edges) have kind -1
    xyz : (V, N, 3) float32, object point under each contour point (mm)
    outline : (V, M, 2) float32, the outer silhouette boundary as an ordered polygon of M points, its box the\n        mask's box (boxes of rolled views, region masks)
    size : int, side of the template renders, px
    build_seconds : float
    """

    poses: np.ndarray
    K: np.ndarray
    xy: np.ndarray
    ori: np.ndarray
    kind: np.ndarray
    xyz: np.ndarray
    outline: np.ndarray
    size: int
    build_seconds: float = 0.0

    @property
    def n_views(self) -> int:
        return self.poses.shape[0]

    @property
    def n_points(self) -> int:
        return self.xy.shape[1]

    @property
    def valid(self) -> np.ndarray:
        """(V, N) bool: real points (not padding)."""
        return self.kind >= 0

    def rolled(self, angles: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Points and orientations of every view turned by each roll angle (radians, camera rolled by +a).

        Returns
        -------
        xy : (V, A, N, 2) offsets from the principal point
        ori : (V, A, N) orientations in [0, pi)
        boxes : (V, A, 4) x0, y0, x1, y1 of the rolled outline grown by half a pixel (pixel-count extent),
            offsets from the principal point
        """
        a = np.asarray(angles, np.float64).reshape(-1)
        xy = _rotate2d(self.xy, a)
        ori = np.mod(self.ori[:, None, :] + a[None, :, None].astype(np.float32), np.pi).astype(np.float32)
        out = _rotate2d(self.outline, a)
        # outline points are pixel centres: the silhouette covers half a pixel more on every side (pixie boxes
        # count pixels, w = last - first + 1)
        boxes = np.concatenate([out.min(axis=2) - 0.5, out.max(axis=2) + 0.5], axis=-1)
        return xy.astype(np.float32), ori, boxes.astype(np.float32)

    def pose(self, view: int, angle: float) -> np.ndarray:
        """T_cam_from_obj of template ``view`` rolled by ``angle`` (radians) about the optical axis."""
        c, s = np.cos(angle), np.sin(angle)
        Rz = np.eye(4)
        Rz[:2, :2] = [[c, -s], [s, c]]
        return Rz @ self.poses[view]

    def rotations(self, angles: np.ndarray) -> np.ndarray:
        """(V, A, 3, 3) rotations of every view rolled by each angle."""
        a = np.asarray(angles, np.float64)
        c, s = np.cos(a), np.sin(a)
        Rz = np.zeros((len(a), 3, 3))
        Rz[:, 0, 0], Rz[:, 0, 1], Rz[:, 1, 0], Rz[:, 1, 1], Rz[:, 2, 2] = c, -s, s, c, 1.0
        return np.einsum("aij,vjk->vaik", Rz, self.poses[:, :3, :3])

    def to_arrays(self) -> dict[str, np.ndarray]:
        """Every field as an array (for .npz storage)."""
        return {f.name: np.asarray(getattr(self, f.name)) for f in dataclasses.fields(self)}

    @classmethod
    def from_arrays(cls, arrays: dict) -> "ContourTemplates":
        """Inverse of :meth:`to_arrays`."""
        kw = {}
        for f in dataclasses.fields(cls):
            v = np.asarray(arrays[f.name])
            kw[f.name] = v.item() if v.ndim == 0 else v
        kw["size"] = int(kw["size"])
        return cls(**kw)

    def nbytes(self) -> int:
        return int(sum(a.nbytes for a in (self.poses, self.xy, self.ori, self.kind, self.xyz, self.outline)))


def distinct_by_rotation(R: np.ndarray, order: np.ndarray, k: int, min_deg: float) -> list[int]:
    """The first ``k`` indices of ``order`` whose rotations ``R[i]`` are more than ``min_deg`` from every one kept."""
    kept: list[int] = []
    cmin = np.cos(np.radians(min_deg))
    for i in order:
        if kept:
            tr = np.einsum("kij,ij->k", R[kept], R[i])
            if np.any((tr - 1) / 2 > cmin):
                continue
        kept.append(int(i))
        if len(kept) >= k:
            break
    return kept


def template_view_poses(mesh: Mesh, n_views: int, focal_px: float, size: int, fill: float = 0.8) -> np.ndarray:
    """Roll-0 cameras on a Fibonacci sphere of ``n_views`` directions, looking at the mesh centre."""
    dist = camera_distance(mesh.bounding_radius, focal_px, size, fill=fill)
    dirs = fibonacci_sphere(n_views)
    return np.stack([look_at(mesh.center + dist * d, mesh.center, up_vector(d)) for d in dirs])


def edge_map(depth: np.ndarray, normals: np.ndarray, crease_deg: float = 35.0,
             depth_jump: float = 0.03) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Silhouette and crease/depth-discontinuity edges of one render.

    Parameters
    ----------
    depth : (S, S) z-depth, 0 on background
    normals : (S, S, 3) unit camera-frame normals
    crease_deg : normal turn between neighbouring pixels that counts as a crease
    depth_jump : relative depth step between neighbours that counts as an inner occluding edge

    Returns
    -------
    sil : (S, S) bool, silhouette pixels (object pixels with a background 4-neighbour)
    crease : (S, S) bool, inner edge pixels (not on the silhouette)
    ori : (S, S) float32, unsigned gradient orientation in [0, pi)
    strength : (S, S) float32, edge strength (1 on the silhouette, the normal turn's cosine gap on creases)

    Only the mask's box and a margin wider than every filter's reach are computed (the rest is background:
    no edge, orientation 0, strength 0), which gives the same maps as the whole image at a fraction of the cost.
    """
    mask = depth > 0
    H, W = mask.shape
    rows, cols = np.flatnonzero(mask.any(axis=1)), np.flatnonzero(mask.any(axis=0))
    out = (np.zeros((H, W), bool), np.zeros((H, W), bool), np.zeros((H, W), np.float32), np.zeros((H, W), np.float32))
    if len(rows) == 0:
        return out
    m = _EDGE_MARGIN
    y0, y1 = max(rows[0] - m, 0), min(rows[-1] + m + 1, H)
    x0, x1 = max(cols[0] - m, 0), min(cols[-1] + m + 1, W)
    if (y1 - y0) * (x1 - x0) >= H * W:
        return _edge_map_full(depth, normals, crease_deg, depth_jump)
    sub = _edge_map_full(depth[y0:y1, x0:x1], normals[y0:y1, x0:x1], crease_deg, depth_jump)
    for o, a in zip(out, sub):
        o[y0:y1, x0:x1] = a
    return out


_EDGE_MARGIN = 8  # px around the mask's box: > the reach of the blurs (radius 4, 3) + Sobel (1) + neighbours (1)


def _edge_map_full(depth: np.ndarray, normals: np.ndarray, crease_deg: float,
                   depth_jump: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """:func:`edge_map` computed over the whole of ``depth``."""
    mask = depth > 0
    m8 = mask.astype(np.uint8)
    sil = mask & (cv2.erode(m8, np.ones((3, 3), np.uint8), borderType=cv2.BORDER_CONSTANT, borderValue=0) == 0)
    # silhouette orientation: gradient of the smoothed mask
    mf = cv2.GaussianBlur(mask.astype(np.float32), (0, 0), 1.0)
    gx_m, gy_m = cv2.Sobel(mf, cv2.CV_32F, 1, 0, ksize=3), cv2.Sobel(mf, cv2.CV_32F, 0, 1, ksize=3)
    # creases: largest normal turn / relative depth step to any 8-neighbour (both pixels of a pair marked)
    n = normals.astype(np.float32)
    d = depth.astype(np.float32)
    turn = np.zeros(mask.shape, np.float32)
    dz = np.zeros(mask.shape, np.float32)
    H, W = mask.shape
    for dy, dx in ((0, 1), (1, 0), (1, 1), (1, -1)):
        sa = (slice(dy, H), slice(max(dx, 0), W + min(dx, 0)))  # pixel
        sb = (slice(0, H - dy), slice(max(-dx, 0), W - max(dx, 0)))  # its neighbour
        both = mask[sa] & mask[sb]
        t = np.where(both, 1.0 - np.einsum("ijk,ijk->ij", n[sa], n[sb]), 0.0).astype(np.float32)
        rel = np.where(both, np.abs(d[sa] - d[sb]) / np.maximum(np.minimum(d[sa], d[sb]), 1e-6), 0.0).astype(np.float32)
        for s_ in (sa, sb):
            turn[s_] = np.maximum(turn[s_], t)
            dz[s_] = np.maximum(dz[s_], rel)
    cos_gap = 1.0 - np.cos(np.radians(crease_deg))
    crease = mask & ~sil & ((turn > cos_gap) | (dz > depth_jump))
    # crease orientation: gradient of the normals / depth image, channel of largest magnitude
    chans = [n[..., 0], n[..., 1], n[..., 2], np.where(mask, d / max(float(d[mask].mean()) if mask.any() else 1.0, 1e-6), 0) * 5]
    best_mag = np.zeros(mask.shape, np.float32)
    gx_c = np.zeros(mask.shape, np.float32)
    gy_c = np.zeros(mask.shape, np.float32)
    for ch in chans:
        ch = cv2.GaussianBlur(ch.astype(np.float32), (0, 0), 0.8)
        gx, gy = cv2.Sobel(ch, cv2.CV_32F, 1, 0, ksize=3), cv2.Sobel(ch, cv2.CV_32F, 0, 1, ksize=3)
        mag = gx * gx + gy * gy
        upd = mag > best_mag
        best_mag = np.where(upd, mag, best_mag)
        gx_c, gy_c = np.where(upd, gx, gx_c), np.where(upd, gy, gy_c)
    gx = np.where(sil, gx_m, gx_c)
    gy = np.where(sil, gy_m, gy_c)
    ori = np.mod(np.arctan2(gy, gx), np.pi).astype(np.float32)
    strength = np.where(sil, 1.0, np.where(crease, np.clip(turn / (2 * cos_gap), 0.0, 1.0) * 0.5 + 0.5 * (dz > depth_jump), 0.0))
    return sil, crease, ori, strength.astype(np.float32)


def spread_points(pts: np.ndarray, score: np.ndarray, n: int, min_dist: float, min_dist_floor: float | None = None) -> np.ndarray:
    """Indices of up to ``n`` points, strongest first, about ``min_dist`` apart (the strongest point of each
    ``min_dist`` grid cell; the cell shrinks x0.75 until ``n`` points are found or it falls below
    ``min_dist_floor``, default min_dist / 2)."""
    if len(pts) == 0 or n <= 0:
        return np.zeros(0, dtype=int)
    d = float(min_dist)
    floor = 0.5 * d if min_dist_floor is None else float(min_dist_floor)
    order = np.argsort(-score, kind="stable")
    while True:
        cell = np.floor(pts[order] / d).astype(np.int64)
        key = cell[:, 0] * 1_000_003 + cell[:, 1]
        _, first = np.unique(key, return_index=True)  # first = strongest point of each cell
        chosen = order[np.sort(first)]
        if len(chosen) >= n or d * 0.75 < floor:
            return chosen[:n]
        d *= 0.75


def view_points(depth: np.ndarray, normals: np.ndarray, K: np.ndarray, T: np.ndarray, n_points: int = 96,
                crease_share: float = 0.35, n_outline: int = 128, crease_deg: float = 35.0) -> dict:
    """Oriented contour points of one rendered view (see :class:`ContourTemplates` for the fields)."""
    sil, crease, ori, strength = edge_map(depth, normals, crease_deg)
    # silhouette: evenly along the boundary curves (outer outline and holes), by arc length
    cs, _ = cv2.findContours((depth > 0).astype(np.uint8), cv2.RETR_LIST, cv2.CHAIN_APPROX_NONE)
    cs = [c[:, 0, :] for c in cs if len(c) >= 8]
    pts_s = np.concatenate(cs).astype(np.float64) if cs else np.zeros((0, 2))
    yc, xc = np.nonzero(crease)
    n_cr = min(int(round(n_points * crease_share)), len(yc) // 2)
    n_si = min(n_points - n_cr, len(pts_s))
    idx_s = np.linspace(0, len(pts_s), n_si, endpoint=False).astype(int) if n_si else np.zeros(0, int)
    pts_c = np.stack([xc, yc], 1).astype(np.float64)
    idx_c = spread_points(pts_c, strength[yc, xc], n_cr, 4.0, 3.0) if n_cr else np.zeros(0, int)
    P = np.concatenate([pts_s[idx_s], pts_c[idx_c]]).astype(np.float64)
    kind = np.concatenate([np.full(len(idx_s), SILHOUETTE), np.full(len(idx_c), CREASE)]).astype(np.int8)
    r, c = P[:, 1].astype(int), P[:, 0].astype(int)
    z = depth[r, c].astype(np.float64)
    X = transform_points(invert_T(T), backproject(K, P, z))
    # the outline: the largest outer boundary, ordered (a polygon), evenly resampled with its four extreme
    # points in place (so the polygon's box is the mask's box)
    outer, _ = cv2.findContours((depth > 0).astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    if outer:
        ring = max(outer, key=len)[:, 0, :].astype(np.float64)
        oi = np.linspace(0, len(ring), n_outline, endpoint=False).astype(int)
        for e in (np.argmin(ring[:, 0]), np.argmax(ring[:, 0]), np.argmin(ring[:, 1]), np.argmax(ring[:, 1])):
            oi[np.argmin(np.abs(oi - e))] = e
        lo, hi = pts_s.min(axis=0), pts_s.max(axis=0)  # all boundaries: holes and parts are inside / beside
        outline = ring[np.sort(oi)]
        outline[np.argmin(outline[:, 0]), 0] = lo[0]
        outline[np.argmax(outline[:, 0]), 0] = hi[0]
        outline[np.argmin(outline[:, 1]), 1] = lo[1]
        outline[np.argmax(outline[:, 1]), 1] = hi[1]
    else:
        outline = np.zeros((n_outline, 2))
    pp = K[:2, 2]
    return {"xy": P - pp, "ori": ori[r, c], "kind": kind, "xyz": X, "outline": outline - pp}


def build_templates(mesh: Mesh, n_views: int = 300, size: int = 128, n_points: int = 96, crease_share: float = 0.35,
                    n_outline: int = 128, focal_factor: float = 4.0, renderer: Renderer | None = None,
                    crease_deg: float = 35.0,
                    progress: Callable[[int, int], None] | None = None) -> ContourTemplates:
    """Render depth/normals of ``n_views`` roll-0 views at ``size`` px and extract their contour points.

    Parameters
    ----------
    mesh : Mesh
    n_views : Fibonacci directions (300: nearest-view gap ~7°)
    size : render side, px (the object's bounding sphere fills 80 %)
    n_points : oriented points kept per view (silhouette + ``crease_share`` of creases when the view has them)
    """
    t0 = time.perf_counter()
    f = focal_factor * size
    K = make_K(f, f, (size - 1) / 2.0, (size - 1) / 2.0)
    poses = template_view_poses(mesh, n_views, f, size)
    renderer = renderer or Renderer(mesh, smooth_normals=True)
    V, N = len(poses), int(n_points)
    xy = np.zeros((V, N, 2), np.float32)
    ori = np.zeros((V, N), np.float32)
    kind = np.full((V, N), -1, np.int8)
    xyz = np.zeros((V, N, 3), np.float32)
    outline = np.zeros((V, n_outline, 2), np.float32)
    for i, T in enumerate(poses):
        if progress is not None:
            progress(i + 1, len(poses))
        r = renderer.render(T, K, size, size)
        vp = view_points(r.depth, r.normals, K, T, N, crease_share, n_outline, crease_deg)
        k = len(vp["kind"])
        xy[i, :k], ori[i, :k], kind[i, :k], xyz[i, :k] = vp["xy"], vp["ori"], vp["kind"], vp["xyz"]
        if k < N and k > 0:  # pad by repeating points (weight kept out by kind -1)
            xy[i, k:], ori[i, k:], xyz[i, k:] = vp["xy"][0], vp["ori"][0], vp["xyz"][0]
        outline[i] = vp["outline"]
    return ContourTemplates(poses, K, xy, ori, kind, xyz, outline, int(size), time.perf_counter() - t0)
