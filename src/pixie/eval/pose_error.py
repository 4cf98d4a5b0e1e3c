"""Pose errors as pure functions: ADD, ADD-S, ADD(-S), BOP'19 MSSD / MSPD / VSD, rotation and translation error.

Recall and AR are in :mod:`pixie.eval.scores`, the shape metrics (APS, IoU3D) in :mod:`pixie.eval.shape_metrics`.

Conventions: poses are 4x4 ``T_cam_from_obj`` (mm), points are (N, 3) object-frame mm,
``K`` is 3x3 (OpenCV). Symmetry sets are (S, 4, 4) arrays from
:func:`pixie.eval.datasets.symmetry_transforms` (identity first).

BOP'19 definitions followed (Hodan et al., "BOP Challenge 2020 on 6D Object Localization",
and bop_toolkit): errors are compared with ``error < threshold`` (strict); MSSD is normalised
by the object diameter, MSPD by ``640 / image_width``; VSD uses distance (not z) images,
the 'bop19' visibility rule (missing depth counts as visible), a step cost and errors
normalised by the diameter.
"""

from __future__ import annotations

import math
from typing import Sequence

import numpy as np

from pixie.geometry.camera import project, rotation_angle_deg, transform_points
from pixie.geometry.rotations import orthonormalize

# BOP'19 threshold sets.
MSSD_THRESHOLDS = np.arange(0.05, 0.51, 0.05)  # fraction of the diameter
MSPD_THRESHOLDS = np.arange(5.0, 51.0, 5.0)  # px at a 640 px wide image
VSD_TAUS = np.arange(0.05, 0.51, 0.05)  # misalignment tolerance, fraction of the diameter
VSD_THRESHOLDS = np.arange(0.05, 0.51, 0.05)  # correctness threshold on the VSD error
VSD_DELTA_MM = 15.0  # visibility tolerance of every BOP dataset but those in VSD_DELTAS_MM
VSD_DELTAS_MM = {"itodd": 5.0}  # dataset name -> its own visibility tolerance


def vsd_delta(dataset_name: str) -> float:
    """BOP's VSD visibility tolerance (mm) for a dataset: 5 for ITODD, 15 for every other one."""
    return VSD_DELTAS_MM.get(dataset_name, VSD_DELTA_MM)

_CHUNK = 2_000_000  # points x symmetries processed at once


# --------------------------------------------------------------------------------------------
# Point-based errors
# --------------------------------------------------------------------------------------------


def add(T_est: np.ndarray, T_gt: np.ndarray, pts: np.ndarray) -> float:
    """ADD: mean distance between model points under the two poses (mm).

    Parameters
    ----------
    T_est, T_gt : (4, 4) poses
    pts : (N, 3) model points, mm

    Returns
    -------
    float, mm
    """
    d = transform_points(T_est, pts) - transform_points(T_gt, pts)
    return float(np.linalg.norm(d, axis=1).mean())


def adds(T_est: np.ndarray, T_gt: np.ndarray, pts: np.ndarray, tree=None) -> float:
    """ADD-S: mean over GT-posed points of the distance to the nearest estimate-posed point (mm).

    Parameters
    ----------
    T_est, T_gt : (4, 4)
    pts : (N, 3) model points
    tree : scipy.spatial.cKDTree over ``pts``, optional
        Built once per object and reused: distances are invariant under the rigid map
        that takes the estimate frame to the object frame, so each query only transforms
        the GT-posed points into the estimated object frame.
    """
    from scipy.spatial import cKDTree

    if tree is None:
        tree = cKDTree(pts)
    R_e, t_e = T_est[:3, :3], T_est[:3, 3]
    q = (transform_points(T_gt, pts) - t_e) @ R_e  # = R_e^T (p - t_e), row-wise
    dist, _ = tree.query(q, k=1)
    return float(dist.mean())


def add_s(T_est: np.ndarray, T_gt: np.ndarray, pts: np.ndarray, symmetric: bool, tree=None) -> float:
    """ADD(-S): ADD-S for symmetric objects, ADD otherwise (mm)."""
    return adds(T_est, T_gt, pts, tree) if symmetric else add(T_est, T_gt, pts)


def _sym_gt_poses(T_gt: np.ndarray, syms: np.ndarray | None) -> np.ndarray:
    if syms is None or len(syms) == 0:
        return T_gt[None]
    return np.einsum("ij,sjk->sik", T_gt, np.asarray(syms, dtype=np.float64))


def mssd(T_est: np.ndarray, T_gt: np.ndarray, pts: np.ndarray, syms: np.ndarray | None = None) -> float:
    """Maximum Symmetry-aware Surface Distance (BOP'19), mm.

    ``min over symmetries S of max over points x of |T_est x - T_gt S x|``.

    Parameters
    ----------
    T_est, T_gt : (4, 4)
    pts : (N, 3) model vertices (BOP uses the evaluation models' vertices)
    syms : (S, 4, 4) symmetry transforms, identity included; None = asymmetric
    """
    p_est = transform_points(T_est, pts)
    best = math.inf
    for p_gt in _sym_gt_points(T_gt, syms, pts):
        d = np.sqrt(((p_gt - p_est[None]) ** 2).sum(-1)).max(axis=1)
        best = min(best, float(d.min()))
    return best


def _sym_gt_points(T_gt: np.ndarray, syms: np.ndarray | None, pts: np.ndarray):
    """Model points under the GT pose composed with each symmetry, in chunks of shape (s, N, 3)."""
    poses = _sym_gt_poses(T_gt, syms)
    step = max(1, _CHUNK // max(len(pts), 1))
    for i in range(0, len(poses), step):
        P = poses[i : i + step]
        yield np.einsum("nj,sij->sni", pts, P[:, :3, :3]) + P[:, None, :3, 3]


def mspd(
    T_est: np.ndarray, T_gt: np.ndarray, K: np.ndarray, pts: np.ndarray, syms: np.ndarray | None = None
) -> float:
    """Maximum Symmetry-aware Projection Distance (BOP'19), px.

    ``min over S of max over x of |proj(T_est x) - proj(T_gt S x)|``. Returns inf when a
    point of the estimate lies at or behind the camera plane. Not normalised by the image
    width; BOP compares ``mspd * 640 / width`` with thresholds 5..50 px.
    """
    K = np.asarray(K, dtype=np.float64)
    X_est = transform_points(T_est, pts)
    if np.any(X_est[:, 2] <= 1e-9):
        return math.inf
    uv_est = project(K, X_est)
    best = math.inf
    for X_gt in _sym_gt_points(T_gt, syms, pts):
        uv_gt = project(K, X_gt)
        d = np.sqrt(((uv_gt - uv_est[None]) ** 2).sum(-1)).max(axis=1)
        best = min(best, float(d.min()))
    return best


def rotation_error_deg(T_est: np.ndarray, T_gt: np.ndarray) -> float:
    """Geodesic angle between the two rotations, degrees."""
    return rotation_angle_deg(T_est[:3, :3], T_gt[:3, :3])


def translation_error(T_est: np.ndarray, T_gt: np.ndarray) -> float:
    """Euclidean distance between the translations, mm."""
    return float(np.linalg.norm(T_est[:3, 3] - T_gt[:3, 3]))


# --------------------------------------------------------------------------------------------
# VSD
# --------------------------------------------------------------------------------------------


def depth_to_distance(depth: np.ndarray, K: np.ndarray, x0: int = 0, y0: int = 0) -> np.ndarray:
    """Convert a z-depth image to distances from the camera centre (0 stays 0).

    ``x0, y0`` are the pixel coordinates of ``depth[0, 0]`` when ``depth`` is a crop.
    """
    h, w = depth.shape
    u = (np.arange(x0, x0 + w, dtype=np.float64) - K[0, 2]) / K[0, 0]
    v = (np.arange(y0, y0 + h, dtype=np.float64) - K[1, 2]) / K[1, 1]
    scale = np.sqrt(1.0 + u[None, :] ** 2 + v[:, None] ** 2)
    return depth.astype(np.float64) * scale


def vsd(
    depth_est: np.ndarray,
    depth_gt: np.ndarray,
    depth_test: np.ndarray,
    K: np.ndarray,
    delta: float = VSD_DELTA_MM,
    taus: Sequence[float] = VSD_TAUS,
    diameter: float | None = None,
) -> np.ndarray:
    """Visible Surface Discrepancy (BOP'19 variant, step cost), one error per tau.

    Parameters
    ----------
    depth_est, depth_gt : (H, W) z-depth renders of the model at the estimate / GT (0 = none), mm
    depth_test : (H, W) measured depth of the test image, mm (0 = missing)
    K : (3, 3)
    delta : float
        Visibility tolerance, mm.
    taus : sequence of float
        Misalignment tolerances; fractions of ``diameter`` when it is given, else mm.
    diameter : float, optional
        Object diameter; when given the pixel distances are divided by it (BOP'19).

    Returns
    -------
    (len(taus),) errors in [0, 1]; all 1 when neither model is visible.

    Notes
    -----
    Visibility (bop19 mode): a model pixel is visible when it is rendered and either the
    test depth is missing there or the model is at most ``delta`` behind the test surface.
    The estimate's mask is widened by the GT's visible mask where the estimate is rendered.
    Error = (#pixels of the union that are not in the intersection + #intersection pixels
    whose distance difference is ≥ tau) / #union.
    """
    taus = np.asarray(taus, dtype=np.float64)
    rendered = (depth_est > 0) | (depth_gt > 0)
    if not rendered.any():
        return np.ones(len(taus))
    ys, xs = np.nonzero(rendered)
    y0, y1, x0, x1 = ys.min(), ys.max() + 1, xs.min(), xs.max() + 1
    crop = (slice(y0, y1), slice(x0, x1))
    d_test = depth_to_distance(depth_test[crop], K, x0, y0)
    d_est = depth_to_distance(depth_est[crop], K, x0, y0)
    d_gt = depth_to_distance(depth_gt[crop], K, x0, y0)
    test_missing = d_test == 0
    visib_gt = (d_gt > 0) & ((d_gt - d_test <= delta) | test_missing)
    visib_est = (d_est > 0) & ((d_est - d_test <= delta) | test_missing)
    visib_est |= visib_gt & (d_est > 0)
    inter = visib_gt & visib_est
    union_count = int((visib_gt | visib_est).sum())
    if union_count == 0:
        return np.ones(len(taus))
    comp_count = union_count - int(inter.sum())
    dists = np.abs(d_gt[inter] - d_est[inter])
    if diameter is not None:
        dists = dists / float(diameter)
    bad = (dists[None, :] >= taus[:, None]).sum(axis=1)
    return (bad + comp_count) / float(union_count)


def projections_may_overlap(radius: float, t_a: np.ndarray, t_b: np.ndarray) -> bool:
    """Conservative test whether two spheres of ``radius`` centred at ``t_a``, ``t_b`` (camera
    frame) can have overlapping image projections (compares normalised image coordinates)."""
    if t_a[2] <= 0 or t_b[2] <= 0:
        return True
    pa, pb = t_a[:2] / t_a[2], t_b[:2] / t_b[2]
    return float(np.linalg.norm(pa - pb)) < radius * (1.0 / t_a[2] + 1.0 / t_b[2])


def vsd_poses(
    renderer,
    T_est: np.ndarray,
    T_gt: np.ndarray,
    depth_test: np.ndarray,
    K: np.ndarray,
    diameter: float,
    delta: float = VSD_DELTA_MM,
    taus: Sequence[float] = VSD_TAUS,
    depth_gt: np.ndarray | None = None,
) -> np.ndarray:
    """VSD of a pose pair: renders the model with ``renderer`` (a :class:`pixie.geometry.render.Renderer`)
    at both poses (``depth_gt`` may be passed in when already rendered) and calls :func:`vsd`."""
    h, w = depth_test.shape
    radius = 0.5 * diameter
    # Far-apart poses: errors are 1 whatever the renders (cheap early exit, as in bop_toolkit).
    c_e = T_est[:3, :3] @ renderer.mesh.center + T_est[:3, 3]
    c_g = T_gt[:3, :3] @ renderer.mesh.center + T_gt[:3, 3]
    if not projections_may_overlap(max(radius, renderer.mesh.bounding_radius), c_e, c_g):
        return np.ones(len(taus))
    if depth_gt is None:
        depth_gt = renderer.render(orthonormalize(T_gt), K, h, w).depth
    depth_est = renderer.render(orthonormalize(T_est), K, h, w).depth
    return vsd(depth_est, depth_gt, depth_test, K, delta, taus, diameter)
