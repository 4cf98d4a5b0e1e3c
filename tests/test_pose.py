"""Lifting, PnP + RANSAC (OpenCV and PoseLib) and the box-based depth correction, on synthetic data."""

from __future__ import annotations

import importlib.util
import math

import numpy as np
import pytest

from pixie.geometry.camera import make_K, project, rotation_angle_deg, transform_points
from pixie.errors import ConfigError
from pixie.features import Matches
from pixie.pose.solve import (
    background_similarity,
    box_iou,
    depth_from_box,
    hypothesis_score,
    lift,
    pair_rank_score,
    projected_box,
    solve_pnp_ransac,
)

K = make_K(600.0, 600.0, 319.5, 239.5)
HAS_POSELIB = importlib.util.find_spec("poselib") is not None


def _correspondences(mesh, T, n=300, outlier_frac=0.4, noise_px=0.5, seed=0):
    """2D–3D pairs: surface points projected with noise, a fraction replaced by random image points."""
    rng = np.random.default_rng(seed)
    X = mesh.sample_points(n, seed=seed)
    uv = project(K, transform_points(T, X)) + rng.normal(0.0, noise_px, (n, 2))
    n_out = int(round(outlier_frac * n))
    out = rng.choice(n, n_out, replace=False)
    uv[out] = rng.uniform([0, 0], [640, 480], (n_out, 2))
    is_in = np.ones(n, bool)
    is_in[out] = False
    return uv, X, is_in


def _errors(T_est, T_true):
    return rotation_angle_deg(T_est[:3, :3], T_true[:3, :3]), float(np.linalg.norm(T_est[:3, 3] - T_true[:3, 3]))


SOLVERS = ["opencv", pytest.param("poselib", marks=pytest.mark.skipif(not HAS_POSELIB, reason="poselib missing"))]


@pytest.mark.parametrize("solver", SOLVERS)
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_pnp_recovers_pose_with_outliers(proc_mesh, make_pose, solver, seed):
    T = make_pose(proc_mesh, 100 + seed, distance_factor=5.0, offset_px=100)
    uv, X, is_in = _correspondences(proc_mesh, T, seed=seed)
    res = solve_pnp_ransac(uv, X, K, iterations=1000, threshold_px=5.0, solver=solver, seed=seed)
    assert res.ok, "PnP failed on an easy problem"
    rot, trans = _errors(res.T_cam_from_obj, T)
    assert rot < 0.5, f"rotation error {rot:.3f} deg"
    assert trans < 1.0, f"translation error {trans:.3f} mm"
    inl = np.zeros(len(uv), bool)
    inl[res.inliers] = True
    assert res.n_correspondences == len(uv)
    # every true inlier is found (noise 0.5 px << 5 px); outliers land within 5 px only by chance
    assert inl[is_in].mean() > 0.98
    assert inl[~is_in].mean() < 0.05
    assert res.reprojection_rmse < 1.5
    assert 0.55 < res.n_inliers / res.n_correspondences < 0.65


@pytest.mark.parametrize("solver", SOLVERS)
def test_pnp_fails_cleanly(proc_mesh, make_pose, solver):
    T = make_pose(proc_mesh, 7, distance_factor=5.0)
    uv, X, _ = _correspondences(proc_mesh, T, n=5, outlier_frac=0.0)
    res = solve_pnp_ransac(uv, X, K, solver=solver)
    assert not res.ok and res.T_cam_from_obj is None and res.n_inliers == 0
    assert res.n_correspondences == 5
    none = solve_pnp_ransac(np.zeros((0, 2)), np.zeros((0, 3)), K, solver=solver)
    assert not none.ok
    # pure noise: no consistent pose
    rng = np.random.default_rng(3)
    uv = rng.uniform([0, 0], [640, 480], (200, 2))
    X = proc_mesh.sample_points(200, seed=4)
    res = solve_pnp_ransac(uv, X, K, solver=solver)  # default min_inliers=6
    assert not res.ok, f"a pose from pure noise with {res.n_inliers} inliers"


def test_pnp_unknown_solver(proc_mesh, make_pose):
    T = make_pose(proc_mesh, 0)
    uv, X, _ = _correspondences(proc_mesh, T, n=50, outlier_frac=0.0)
    with pytest.raises(ConfigError, match="solver"):
        solve_pnp_ransac(uv, X, K, solver="magic")


def test_lift_drops_nan_xyz_and_keeps_similarities():
    kq = np.array([[10.0, 20.0], [30.0, 40.0], [50.0, 60.0], [70.0, 80.0]])
    xyz = np.array([[1.0, 2.0, 3.0], [np.nan, np.nan, np.nan], [4.0, 5.0, 6.0], [7.0, np.nan, 9.0]])
    m = Matches(np.array([3, 2, 1, 0]), np.array([0, 1, 2, 3]), np.array([0.9, 0.8, 0.7, 0.6]))
    p2, p3, sims = lift(kq, xyz, m)
    np.testing.assert_array_equal(p2, [[70.0, 80.0], [30.0, 40.0]])
    np.testing.assert_array_equal(p3, [[1.0, 2.0, 3.0], [4.0, 5.0, 6.0]])
    np.testing.assert_allclose(sims, [0.9, 0.7], rtol=1e-6)
    assert p2.dtype == np.float64 and p3.dtype == np.float64 and sims.dtype == np.float64
    e2, e3, es = lift(kq, xyz, Matches.empty())
    assert e2.shape == (0, 2) and e3.shape == (0, 3) and es.shape == (0,)


def test_background_and_pair_ranking():
    """The background is the median of per-pair mean similarities, 0 with too few pairs; 'excess' ranks a
    pair by its similarity above it, 'count' by its number of matches."""
    sims = [np.full(5, 0.5)] * 4 + [np.full(5, 0.6)] * 5 + [np.zeros(0)]
    assert background_similarity(sims) == pytest.approx(0.6)
    assert background_similarity(sims[:7]) == 0.0  # 7 pairs with matches: no background
    strong, many = np.array([0.9, 0.9]), np.full(10, 0.55)
    assert pair_rank_score(strong, 0.5, "excess") > pair_rank_score(many, 0.5, "excess")
    assert pair_rank_score(strong, 0.5, "count") < pair_rank_score(many, 0.5, "count")
    with pytest.raises(ConfigError, match="candidate_ranking"):
        pair_rank_score(strong, 0.5, "votes")


def test_hypothesis_score_terms():
    s_in = np.array([0.8, 0.7, 0.6])
    assert hypothesis_score("inliers", 3, s_in, 0.5, 0.0, 1.0) == 3.0
    assert hypothesis_score("similarity", 3, s_in, 0.5, 0.0, 1.0) == pytest.approx(2.1)
    assert hypothesis_score("excess", 3, s_in, 0.5, 0.0, 1.0) == pytest.approx(0.6 + 0.003)
    # combined: exp(-(35/35)^2) at 35 degrees from the reference view, 0.25 + 0.75 * 0.5 for IoU 0.5
    assert hypothesis_score("combined", 3, s_in, 0.5, 35.0, 0.5) == pytest.approx(3 * math.exp(-1) * 0.625)
    with pytest.raises(ConfigError, match="pose.scoring"):
        hypothesis_score("votes", 3, s_in, 0.5, 0.0, 1.0)


@pytest.mark.parametrize("scale", [1.3, 1 / 1.3])
def test_depth_from_box_restores_distance(proc_mesh, make_pose, scale):
    for seed in range(3):
        T = make_pose(proc_mesh, 50 + seed, distance_factor=6.0, offset_px=80)
        pts = proc_mesh.vertices
        box = projected_box(T, K, pts)
        # the depth ambiguity of PnP on small objects: the object slides along the ray through its centre
        Rc = T[:3, :3] @ (0.5 * (pts.min(0) + pts.max(0)))
        wrong = T.copy()
        wrong[:3, 3] = (Rc + T[:3, 3]) * scale - Rc
        fixed = depth_from_box(wrong, K, pts, box)
        err = np.linalg.norm(fixed[:3, 3] - T[:3, 3]) / np.linalg.norm(T[:3, 3])
        assert err < 0.01, f"seed {seed}: translation still {100 * err:.2f}% off"
        np.testing.assert_allclose(fixed[:3, :3], T[:3, :3])
        assert box_iou(projected_box(fixed, K, pts), box) > 0.97
    # a degenerate observed box leaves the pose unchanged
    np.testing.assert_array_equal(depth_from_box(wrong, K, pts, np.array([10.0, 10.0, 10.0, 50.0])), wrong)


def test_box_iou():
    a = np.array([0.0, 0.0, 10.0, 10.0])
    assert box_iou(a, a) == pytest.approx(1.0)
    assert box_iou(a, np.array([5.0, 0.0, 15.0, 10.0])) == pytest.approx(50 / 150)
    assert box_iou(a, np.array([20.0, 20.0, 30.0, 30.0])) == 0.0


def test_hull_vertices_give_the_exact_projected_box(lmo_meshes, make_pose):
    """The estimator's box points (convex-hull vertices) are fewer than the vertices yet project to exactly
    the same box (a vertex subsample, the old rule, came out smaller and pulled box depth ~0.6 % too close)."""
    from pixie.geometry.mesh import from_arrays

    for oid, mesh in lmo_meshes.items():
        hull = mesh.hull_vertices
        assert 8 <= len(hull) < len(mesh.vertices)
        for seed in range(4):
            T = make_pose(mesh, seed, distance_factor=8.0, offset_px=60)
            np.testing.assert_allclose(projected_box(T, K, hull), projected_box(T, K, mesh.vertices), atol=1e-9)
    # a flat mesh has no 3D hull: all its vertices are used
    g = np.stack(np.meshgrid(np.linspace(0, 50, 12), np.linspace(0, 30, 12)), -1).reshape(-1, 2)
    V = np.c_[g, np.zeros(len(g))]
    F = np.array([[i, i + 1, i + 12] for i in range(len(V) - 13) if (i + 1) % 12])
    flat = from_arrays(V, F)
    assert len(flat.hull_vertices) == len(flat.vertices)
