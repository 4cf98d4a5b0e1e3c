"""Shape-agreement metrics of the pixie paper: APS (Eq. 1, silhouette IoU x depth agreement of two renders)
and volumetric IoU3D of two meshes (defect scenes, :mod:`pixie.synth.scenes`)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np

from pixie.geometry.camera import transform_points
from pixie.geometry.rotations import orthonormalize


# --------------------------------------------------------------------------------------------
# APS (paper Eq. 1)
# --------------------------------------------------------------------------------------------


@dataclass
class APSResult:
    """APS and its two factors."""

    aps: float
    iou: float
    depth_agreement: float  # mean(1 - delta) over co-visible pixels
    n_covisible: int


def aps_from_depth(depth_target: np.ndarray, depth_defective: np.ndarray) -> APSResult:
    """APS from two z-depth renders (0 = background).

    ``delta = min(|D_t - D_d| / D_d, 1)`` on pixels rendered in both;
    ``APS = IoU(silhouettes) * mean(1 - delta)``, 0 when no pixel is co-visible.
    """
    mt, md = depth_target > 0, depth_defective > 0
    both = mt & md
    n = int(both.sum())
    union = int((mt | md).sum())
    if n == 0 or union == 0:
        return APSResult(0.0, 0.0 if union else 0.0, 0.0, 0)
    iou = n / union
    dt = depth_target[both].astype(np.float64)
    dd = depth_defective[both].astype(np.float64)
    delta = np.minimum(np.abs(dt - dd) / dd, 1.0)
    agree = float((1.0 - delta).mean())
    return APSResult(iou * agree, iou, agree, n)


def aps(
    renderer_target,
    renderer_defective,
    T_est: np.ndarray,
    T_gt: np.ndarray,
    K: np.ndarray,
    h: int,
    w: int,
) -> float:
    """Alignment-Precision Score (paper Eq. 1), in [0, 1].

    Renders the target model at the estimate and the defective (actually observed) model
    at the GT pose with :class:`pixie.geometry.render.Renderer` objects, then applies
    :func:`aps_from_depth`. Rotations are snapped to the nearest exact rotation first.
    """
    dt = renderer_target.render(orthonormalize(T_est), K, h, w).depth
    dd = renderer_defective.render(orthonormalize(T_gt), K, h, w).depth
    return aps_from_depth(dt, dd).aps


# --------------------------------------------------------------------------------------------
# IoU3D
# --------------------------------------------------------------------------------------------


@dataclass
class VoxelGrid:
    """Axis-aligned grid of voxel centres ``origin + (i + 0.5) * voxel_size``."""

    origin: np.ndarray  # (3,) corner, mm
    voxel_size: float
    shape: tuple[int, int, int]

    def centers(self, axis: int) -> np.ndarray:
        return self.origin[axis] + (np.arange(self.shape[axis]) + 0.5) * self.voxel_size

    @property
    def voxel_volume(self) -> float:
        return self.voxel_size**3


def grid_for(bounds_min: np.ndarray, bounds_max: np.ndarray, voxel_size: float) -> VoxelGrid:
    """A grid covering the box with one voxel of margin; the corner is offset by a small
    irrational fraction of a voxel so that ray lines avoid mesh edges on round coordinates."""
    jitter = voxel_size * np.array([0.0123457, 0.0234567, 0.0345679])
    origin = np.asarray(bounds_min, dtype=np.float64) - voxel_size + jitter
    shape = np.ceil((np.asarray(bounds_max) + voxel_size - origin) / voxel_size).astype(int)
    return VoxelGrid(origin, float(voxel_size), tuple(int(s) for s in shape))


def _ray_hits(scene, origins: np.ndarray, direction: np.ndarray, eps: float, max_hits: int = 512):
    """All hit distances along parallel rays: returns (ray index, t) arrays."""
    n = len(origins)
    offset = np.zeros(n)
    active = np.arange(n)
    ray_idx, ts = [], []
    d = np.broadcast_to(direction.astype(np.float32), (n, 3))
    for _ in range(max_hits):
        if active.size == 0:
            break
        o = (origins[active] + offset[active, None] * direction).astype(np.float32)
        res = scene.run(o, np.ascontiguousarray(d[: active.size]), output=1)
        hit = (res["primID"] >= 0) & (res["geomID"] >= 0)
        if not hit.any():
            break
        a = active[hit]
        t = offset[a] + res["tfar"][hit].astype(np.float64)
        ray_idx.append(a)
        ts.append(t)
        offset[a] = t + eps
        active = a
    if not ray_idx:
        return np.zeros(0, int), np.zeros(0)
    return np.concatenate(ray_idx), np.concatenate(ts)


def voxelize(vertices: np.ndarray, faces: np.ndarray, grid: VoxelGrid) -> np.ndarray:
    """Inside/outside of each voxel centre: (nx, ny, nz) bool.

    For each axis, rays along +axis through every column of voxel centres are traced with
    Embree collecting every crossing; a centre is inside for that axis when the number of
    crossings before it is odd. The three axes vote (majority), so a hole or a missing face
    that breaks the parity along one axis does not flip the result: non-watertight meshes
    work as long as the defect is not seen along two axes at the same voxel.
    """
    from embreex import rtcore_scene
    from embreex.mesh_construction import TriangleMesh

    scene = rtcore_scene.EmbreeScene()
    TriangleMesh(scene=scene, vertices=np.asarray(vertices, np.float32), indices=np.asarray(faces, np.int32))
    vs = grid.voxel_size
    extent = float(np.max(np.asarray(grid.shape) * vs))
    eps = max(1e-5 * extent, 1e-6)
    votes = np.zeros(grid.shape, dtype=np.uint8)
    for axis in range(3):
        b, c = [a for a in range(3) if a != axis]
        cb, cc = grid.centers(b), grid.centers(c)
        B, C = np.meshgrid(cb, cc, indexing="ij")
        origins = np.zeros((B.size, 3))
        origins[:, b] = B.ravel()
        origins[:, c] = C.ravel()
        start = grid.origin[axis] - vs
        origins[:, axis] = start
        direction = np.zeros(3)
        direction[axis] = 1.0
        ridx, t = _ray_hits(scene, origins, direction, eps)
        n_a = grid.shape[axis]
        # Index of the first voxel centre beyond each crossing.
        k = np.ceil((t + start - grid.origin[axis]) / vs - 0.5).astype(np.int64)
        k = np.clip(k, 0, n_a)
        counts = np.zeros((B.size, n_a + 1), dtype=np.int32)
        np.add.at(counts, (ridx, k), 1)
        inside = (np.cumsum(counts, axis=1)[:, :n_a] % 2).astype(bool)  # (n_b * n_c, n_a)
        inside = inside.reshape(grid.shape[b], grid.shape[c], n_a)
        order = np.argsort([b, c, axis])  # axes of `inside` -> (x, y, z)
        votes += np.transpose(inside, order).astype(np.uint8)
    return votes >= 2


def _posed(mesh, T: np.ndarray | None) -> np.ndarray:
    v = np.asarray(mesh.vertices, dtype=np.float64)
    return v if T is None else transform_points(np.asarray(T, dtype=np.float64), v)


def iou3d(mesh_a, mesh_b, voxel_size: float, T_a: np.ndarray | None = None, T_b: np.ndarray | None = None) -> float:
    """Volumetric IoU of two meshes voxelised on a common grid.

    Parameters
    ----------
    mesh_a, mesh_b : objects with ``vertices`` (mm) and ``faces`` (e.g. :class:`pixie.geometry.mesh.Mesh`)
    voxel_size : float, mm
    T_a, T_b : (4, 4), optional
        Poses placing each mesh in the common frame (identity when omitted).

    Returns
    -------
    float in [0, 1]; the discretisation error shrinks roughly linearly with ``voxel_size``
    (see :func:`iou3d_convergence`).
    """
    va, vb = _posed(mesh_a, T_a), _posed(mesh_b, T_b)
    lo = np.minimum(va.min(0), vb.min(0))
    hi = np.maximum(va.max(0), vb.max(0))
    grid = grid_for(lo, hi, voxel_size)
    n_vox = int(np.prod(grid.shape))
    if n_vox > 200_000_000:
        raise ValueError(f"voxel size {voxel_size} mm gives {n_vox} voxels; use a larger one")
    ia = voxelize(va, mesh_a.faces, grid)
    ib = voxelize(vb, mesh_b.faces, grid)
    union = int((ia | ib).sum())
    return float((ia & ib).sum() / union) if union else 0.0


def iou3d_convergence(
    mesh_a, mesh_b, voxel_sizes: Sequence[float], T_a: np.ndarray | None = None, T_b: np.ndarray | None = None
) -> list[tuple[float, float]]:
    """IoU3D for a sequence of voxel sizes, to see it converge as the voxels shrink.

    Returns
    -------
    list of (voxel_size, iou) in the given order.
    """
    return [(float(s), iou3d(mesh_a, mesh_b, s, T_a, T_b)) for s in voxel_sizes]
