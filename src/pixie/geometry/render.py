"""CPU geometry renderer: Intel Embree ray casting (via ``embreex``), no GL context needed.

For a pose and intrinsics it produces, per pixel: z-depth (mm), unit normals in the camera frame
(interpolated vertex normals or face normals, flipped to face the camera), object-space XYZ,
a mask and triangle ids. Hit points are recomputed in float64 from the ray/plane intersection,
so back-projecting the depth with K and T⁻¹ reproduces XYZ to float64 precision.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pixie.geometry.camera import invert_T, validate_K, validate_pose
from pixie.errors import CameraError
from pixie.geometry.mesh import Mesh, face_normals


@dataclass
class RenderResult:
    """Per-pixel geometry of one view. Background pixels: depth 0, normals 0, xyz 0, tri -1."""

    depth: np.ndarray  # (H, W) float32, z in mm
    normals: np.ndarray  # (H, W, 3) float32, camera frame, unit, facing the camera
    xyz: np.ndarray  # (H, W, 3) float32, object frame, mm
    tri_ids: np.ndarray  # (H, W) int32
    K: np.ndarray
    T_cam_from_obj: np.ndarray

    @property
    def mask(self) -> np.ndarray:
        return self.tri_ids >= 0

    @property
    def shape(self) -> tuple[int, int]:
        return self.depth.shape


class Renderer:
    """Ray-casts one mesh; the BVH is built once in the object frame and reused for every pose.

    Parameters
    ----------
    mesh : Mesh
    smooth_normals : bool
        Interpolate per-corner normals (True; smooth across edges gentler than ``crease_deg``, sharp
        across creases) or use flat face normals (False).
    crease_deg : float
        Dihedral angle above which an edge is a crease that normals are not averaged across.
    """

    def __init__(self, mesh: Mesh, smooth_normals: bool = True, crease_deg: float = 30.0):
        from embreex import rtcore_scene
        from embreex.mesh_construction import TriangleMesh

        self.mesh = mesh
        self.smooth_normals = smooth_normals
        self._scene = rtcore_scene.EmbreeScene()
        TriangleMesh(
            scene=self._scene,
            vertices=mesh.vertices.astype(np.float32),
            indices=mesh.faces.astype(np.int32),
        )
        self._fn = face_normals(mesh)
        # Plane of each face: n . x = offset (float64, for exact hit points).
        self._offset = np.einsum("ij,ij->i", self._fn, mesh.vertices[mesh.faces[:, 0]])
        self._cn32 = mesh.corner_normals(crease_deg).astype(np.float32) if smooth_normals else None
        # Embree commits (builds the BVH of) a scene on its first ray query; one ray now, so that renders from several
        # threads at once (pixie.threads.map_threads) never race on that first commit.
        self._scene.run(np.zeros((1, 3), np.float32), np.array([[0.0, 0.0, 1.0]], np.float32), output=1)

    def render(
        self,
        T_cam_from_obj: np.ndarray,
        K: np.ndarray,
        height: int,
        width: int,
        roi: tuple[int, int, int, int] | None = "auto",
    ) -> RenderResult:
        """Render depth, normals, XYZ, mask and triangle ids.

        Parameters
        ----------
        T_cam_from_obj : (4, 4)
        K : (3, 3)
        height, width : int
        roi : (x0, y0, x1, y1), 'auto' or None
            Pixels to cast rays for. 'auto' (default) uses the box of the projected convex-hull vertices
            (the bounding sphere's projection when the camera is inside or too close to the hull), which
            is exact and saves most rays; None casts every pixel.
        """
        if height <= 0 or width <= 0:
            raise CameraError(f"image size must be positive, got {width}x{height}")
        K = validate_K(K)
        T = validate_pose(T_cam_from_obj)
        out = _empty(height, width, K, T)
        if roi == "auto":
            roi = self._hull_roi(T, K, height, width)
        x0, y0, x1, y1 = (0, 0, width, height) if roi is None else roi
        if x1 <= x0 or y1 <= y0:
            return out
        v, u = np.mgrid[y0:y1, x0:x1]
        u = u.ravel().astype(np.float64)
        v = v.ravel().astype(np.float64)
        d_cam = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], axis=1)
        T_obj = invert_T(T)
        R_oc, origin = T_obj[:3, :3], T_obj[:3, 3]
        d_obj = np.einsum("ij,kj->ik", d_cam, R_oc)  # tall-thin product: einsum avoids slow multi-threaded BLAS
        hit = self._scene.run(
            np.broadcast_to(origin.astype(np.float32), d_obj.shape).copy(),
            d_obj.astype(np.float32),
            output=1,
        )
        prim = hit["primID"]
        ok = (prim >= 0) & (hit["geomID"] >= 0)
        if not np.any(ok):
            return out
        prim = prim[ok].astype(np.int64)
        d_hit = d_obj[ok]
        n = self._fn[prim]
        # Exact ray/plane intersection in float64 (Embree's float32 t is only the seed).
        denom = np.einsum("ij,ij->i", n, d_hit)
        safe = np.abs(denom) > 1e-12
        t = np.where(safe, (self._offset[prim] - n @ origin) / np.where(safe, denom, 1.0), hit["tfar"][ok])
        p_obj = origin + t[:, None] * d_hit  # d_cam has z = 1, so t is the z-depth
        if self.smooth_normals:
            bu, bv = hit["u"][ok], hit["v"][ok]
            cn = self._cn32[prim]
            nrm = (1 - bu - bv)[:, None] * cn[:, 0] + bu[:, None] * cn[:, 1] + bv[:, None] * cn[:, 2]
            bad = np.einsum("ij,ij->i", nrm, nrm) < 1e-12
            nrm[bad] = n[bad]
        else:
            nrm = n.astype(np.float32)
        nrm_cam = np.einsum("ij,kj->ik", nrm, T[:3, :3].astype(np.float32))
        nrm_cam /= np.maximum(np.sqrt(np.einsum("ij,ij->i", nrm_cam, nrm_cam))[:, None], 1e-30)
        facing = np.einsum("ij,ij->i", nrm_cam, d_cam[ok].astype(np.float32)) > 0  # pointing away
        nrm_cam[facing] *= -1
        rows, cols = v[ok].astype(np.int64), u[ok].astype(np.int64)
        out.depth[rows, cols] = t
        out.normals[rows, cols] = nrm_cam
        out.xyz[rows, cols] = p_obj
        out.tri_ids[rows, cols] = prim
        return out

    def _hull_roi(self, T: np.ndarray, K: np.ndarray, h: int, w: int) -> tuple[int, int, int, int] | None:
        """Pixel box that contains the projection of the mesh: the box of its projected convex-hull vertices
        (a triangle projects inside the hull of its projected corners), one pixel wider on each side.
        Falls back to :meth:`_sphere_roi` when a hull vertex is not in front of the camera."""
        p = self.mesh.hull_vertices @ T[:3, :3].T + T[:3, 3]  # the mesh computes its hull once
        if p[:, 2].min() <= 1e-6:
            return self._sphere_roi(T, K, h, w)
        u = K[0, 0] * p[:, 0] / p[:, 2] + K[0, 2]  # the rays' camera (skew unused, as in render)
        v = K[1, 1] * p[:, 1] / p[:, 2] + K[1, 2]
        u0, u1 = int(np.floor(u.min())) - 1, int(np.ceil(u.max())) + 2
        v0, v1 = int(np.floor(v.min())) - 1, int(np.ceil(v.max())) + 2
        return max(u0, 0), max(v0, 0), min(u1, w), min(v1, h)

    def _sphere_roi(self, T: np.ndarray, K: np.ndarray, h: int, w: int) -> tuple[int, int, int, int] | None:
        """Pixel box that contains the projection of the mesh's bounding sphere."""
        c = T[:3, :3] @ self.mesh.center + T[:3, 3]
        r = self.mesh.bounding_radius * 1.001 + 1e-6
        if c[2] - r <= 1e-6:  # camera inside or too close to the sphere: cast everything
            return None
        # Bound of the projected sphere: project the box corners of the sphere at its nearest depth.
        zn = c[2] - r
        xs = (np.array([c[0] - r, c[0] + r]) / zn, np.array([c[0] - r, c[0] + r]) / (c[2] + r))
        ys = (np.array([c[1] - r, c[1] + r]) / zn, np.array([c[1] - r, c[1] + r]) / (c[2] + r))
        xn = np.concatenate(xs)
        yn = np.concatenate(ys)
        u0 = int(np.floor(K[0, 0] * xn.min() + K[0, 2])) - 1
        u1 = int(np.ceil(K[0, 0] * xn.max() + K[0, 2])) + 2
        v0 = int(np.floor(K[1, 1] * yn.min() + K[1, 2])) - 1
        v1 = int(np.ceil(K[1, 1] * yn.max() + K[1, 2])) + 2
        return max(u0, 0), max(v0, 0), min(u1, w), min(v1, h)


def _empty(h: int, w: int, K: np.ndarray, T: np.ndarray) -> RenderResult:
    return RenderResult(
        depth=np.zeros((h, w), np.float32),
        normals=np.zeros((h, w, 3), np.float32),
        xyz=np.zeros((h, w, 3), np.float32),
        tri_ids=np.full((h, w), -1, np.int32),
        K=K,
        T_cam_from_obj=T,
    )


def composite(renders: list[RenderResult]) -> tuple[np.ndarray, np.ndarray]:
    """Z-buffer several renders of the same camera.

    Returns
    -------
    depth : (H, W) float32, nearest depth (0 = background)
    owner : (H, W) int32, index of the render that owns each pixel, -1 for background
    """
    depth = np.zeros(renders[0].shape, np.float32)
    owner = np.full(renders[0].shape, -1, np.int32)
    for i, r in enumerate(renders):
        closer = r.mask & ((owner < 0) | (r.depth < depth))
        depth[closer] = r.depth[closer]
        owner[closer] = i
    return depth, owner


def render_depth(mesh_or_renderer, T_cam_from_obj: np.ndarray, K: np.ndarray, height: int, width: int) -> np.ndarray:
    """Convenience: z-depth map (H, W) of a mesh or a :class:`Renderer`."""
    r = mesh_or_renderer if isinstance(mesh_or_renderer, Renderer) else Renderer(mesh_or_renderer)
    return r.render(T_cam_from_obj, K, height, width).depth
