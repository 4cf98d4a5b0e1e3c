"""Pose-error metrics against hand-computable cases."""

from __future__ import annotations

import math

import numpy as np
import pytest
import trimesh

from pixie import metrics as M
from pixie.camera import make_K, make_T
from pixie.mesh import from_arrays
from pixie.render import Renderer

K = make_K(500.0, 500.0, 160.0, 120.0)
H, W = 240, 320


def _box(extents, center=(0.0, 0.0, 0.0)):
    b = trimesh.creation.box(extents=extents)
    b.apply_translation(center)
    return from_arrays(b.vertices, b.faces, name="box")


def _rot(axis, deg):
    from scipy.spatial.transform import Rotation

    return Rotation.from_rotvec(np.radians(deg) * np.asarray(axis, float) / np.linalg.norm(axis)).as_matrix()


@pytest.fixture(scope="module")
def pts():
    rng = np.random.default_rng(0)
    return rng.uniform(-50, 50, (500, 3))


T_GT = make_T(_rot([1, 2, 3], 40), [10.0, -20.0, 600.0])


# ---------------------------------------------------------------------------- point metrics


def test_identity_pose_gives_zero_everywhere(pts):
    syms = np.stack([np.eye(4), np.diag([-1.0, -1.0, 1.0, 1.0])])
    assert M.add(T_GT, T_GT, pts) == 0.0
    assert M.adds(T_GT, T_GT, pts) == pytest.approx(0.0, abs=1e-9)
    assert M.add_s(T_GT, T_GT, pts, symmetric=True) == pytest.approx(0.0, abs=1e-9)
    assert M.mssd(T_GT, T_GT, pts, syms) == pytest.approx(0.0, abs=1e-9)
    assert M.mspd(T_GT, T_GT, K, pts, syms) == pytest.approx(0.0, abs=1e-9)
    assert M.rotation_error_deg(T_GT, T_GT) == pytest.approx(0.0, abs=1e-6)
    assert M.translation_error(T_GT, T_GT) == 0.0


def test_known_translation_offset(pts):
    off = np.array([3.0, -4.0, 12.0])  # |off| = 13
    T = T_GT.copy()
    T[:3, 3] += off
    assert M.add(T, T_GT, pts) == pytest.approx(13.0, abs=1e-9)
    assert M.mssd(T, T_GT, pts) == pytest.approx(13.0, abs=1e-9)
    assert M.translation_error(T, T_GT) == pytest.approx(13.0)
    assert M.adds(T, T_GT, pts) <= 13.0 + 1e-9


def test_rotation_about_origin_add_and_mssd(pts):
    """Rotating by 180° about the object z axis: MSSD = max 2·r_xy, ADD = mean 2·r_xy."""
    T = T_GT @ make_T(_rot([0, 0, 1], 180.0), np.zeros(3))
    r = 2 * np.linalg.norm(pts[:, :2], axis=1)
    assert M.add(T, T_GT, pts) == pytest.approx(r.mean(), rel=1e-9)
    assert M.mssd(T, T_GT, pts) == pytest.approx(r.max(), rel=1e-9)
    # ...and zero once that rotation is declared a symmetry.
    syms = np.stack([np.eye(4), make_T(_rot([0, 0, 1], 180.0), np.zeros(3))])
    assert M.mssd(T, T_GT, pts, syms) == pytest.approx(0.0, abs=1e-9)
    assert M.mspd(T, T_GT, K, pts, syms) == pytest.approx(0.0, abs=1e-7)


def test_mspd_known_pixel_shift():
    """A planar fronto-parallel point set at depth Z shifted by dx moves by fx·dx/Z pixels."""
    g = np.stack(np.meshgrid(np.linspace(-40, 40, 9), np.linspace(-30, 30, 7), indexing="ij"), -1).reshape(-1, 2)
    pts = np.column_stack([g, np.zeros(len(g))])
    Z, dx = 800.0, 8.0
    Tg = make_T(np.eye(3), [0.0, 0.0, Z])
    Te = make_T(np.eye(3), [dx, 0.0, Z])
    assert M.mspd(Te, Tg, K, pts) == pytest.approx(500.0 * dx / Z, rel=1e-12)  # = 5 px
    Te2 = make_T(np.eye(3), [0.0, -dx, Z])
    assert M.mspd(Te2, Tg, K, pts) == pytest.approx(5.0, rel=1e-12)
    behind = make_T(np.eye(3), [0.0, 0.0, -10.0])
    assert M.mspd(behind, Tg, K, pts) == math.inf


@pytest.mark.parametrize("obj_id", [10, 11])
def test_symmetric_lmo_object_rotated_by_its_symmetry(lmo_dataset, obj_id):
    from pixie.datasets import symmetry_transforms
    from pixie.mesh import load_mesh

    ds = lmo_dataset
    info = ds.model_info(obj_id, eval=True)
    d = info["diameter"]
    syms = symmetry_transforms(info)
    v = load_mesh(ds.model_path(obj_id, eval=True)).vertices
    Tg = next(g for g in ds.instances(2, 3) if g.obj_id == obj_id).T_cam_from_obj
    Te = Tg @ syms[1]
    assert M.mssd(Te, Tg, v, syms) == pytest.approx(0.0, abs=1e-9)
    assert M.mspd(Te, Tg, ds.camera(2, 3).K, v, syms) == pytest.approx(0.0, abs=1e-6)
    assert M.adds(Te, Tg, v) < 0.02 * d  # the symmetry maps the surface onto itself
    assert M.add_s(Te, Tg, v, symmetric=True) == M.adds(Te, Tg, v)
    assert M.add(Te, Tg, v) > 0.25 * d  # but every point moved: ADD is large
    assert M.mssd(Te, Tg, v, None) > 0.4 * d  # without the symmetry set MSSD is large too


# ---------------------------------------------------------------------------- matching, recall


def test_count_matches_greedy_bop_rules():
    # Two estimates (sorted by score) and two GT instances.
    err = np.array([[1.0, 2.0], [1.5, 9.0]])
    valid = np.array([True, True])
    # th 3: est0 takes gt0 (smaller error), est1 then can only take gt1 with 9 -> no.
    # th 10: est1 takes gt1.  th 1.2: only est0/gt0.  th 0.5: nothing. Strictly below.
    np.testing.assert_array_equal(M.count_matches(err, valid, [0.5, 1.0, 1.2, 3.0, 10.0]), [0, 0, 1, 1, 2])
    # An invalid GT cannot be matched.
    np.testing.assert_array_equal(M.count_matches(err, np.array([False, True]), [3.0, 10.0]), [1, 1])
    # A GT is not consumed by an estimate above the threshold.
    err2 = np.array([[5.0], [1.0]])
    np.testing.assert_array_equal(M.count_matches(err2, np.array([True]), [2.0]), [1])
    assert M.count_matches(np.zeros((0, 1)), np.array([True]), [1.0]).tolist() == [0]


def test_recall_and_average_recall():
    e = np.array([0.01, 0.12, 0.26, np.inf])
    r = M.recall_at(e, M.MSSD_THRESHOLDS)
    np.testing.assert_allclose(r, [0.25, 0.25, 0.5, 0.5, 0.5, 0.75, 0.75, 0.75, 0.75, 0.75])
    assert M.average_recall(r) == pytest.approx(0.575)
    np.testing.assert_allclose(M.mspd_thresholds(1280), np.arange(10, 101, 10))


# ---------------------------------------------------------------------------- VSD


@pytest.fixture(scope="module")
def box_scene():
    mesh = _box([80.0, 60.0, 40.0])
    r = Renderer(mesh)
    Tg = make_T(_rot([1, 1, 0], 30.0), [5.0, -5.0, 500.0])
    depth_test = r.render(Tg, K, H, W).depth
    return mesh, r, Tg, depth_test


def test_vsd_gt_pose_is_zero_and_far_pose_is_one(box_scene):
    mesh, r, Tg, depth_test = box_scene
    d = mesh.diameter
    e = M.vsd_poses(r, Tg, Tg, depth_test, K, d)
    assert e.shape == (10,)
    np.testing.assert_array_equal(e, 0.0)
    far = Tg.copy()
    far[:3, 3] += [300.0, 0.0, 0.0]  # projected elsewhere in the image
    np.testing.assert_array_equal(M.vsd_poses(r, far, Tg, depth_test, K, d), 1.0)
    # Same silhouette region but 0.3·d too far: misaligned for taus ≤ 0.3, fine above.
    back = Tg.copy()
    back[:3, 3] *= 1.0 + 0.3 * d / np.linalg.norm(Tg[:3, 3])  # move along the viewing ray
    e = M.vsd_poses(r, back, Tg, depth_test, K, d)
    assert np.all(e[:5] > 0.9) and e[-1] < 0.5
    assert np.all(np.diff(e) <= 1e-12)  # non-increasing in tau


def test_vsd_occlusion_and_missing_depth(box_scene):
    mesh, r, Tg, depth_test = box_scene
    d = mesh.diameter
    occluded = depth_test.copy()
    occluded[:, :160] = np.where(occluded[:, :160] > 0, 300.0, 300.0)  # a wall in front of the left half
    np.testing.assert_array_equal(M.vsd_poses(r, Tg, Tg, occluded, K, d), 0.0)
    missing = np.zeros_like(depth_test)  # no depth at all: everything rendered counts as visible
    np.testing.assert_array_equal(M.vsd_poses(r, Tg, Tg, missing, K, d), 0.0)
    # The pure-depth function: identical renders, no pixel -> 1.
    z = np.zeros((4, 4), np.float32)
    np.testing.assert_array_equal(M.vsd(z, z, z, K, diameter=d), 1.0)


def test_depth_to_distance():
    z = np.full((3, 3), 100.0)
    Kc = make_K(100.0, 100.0, 1.0, 1.0)
    dist = M.depth_to_distance(z, Kc)
    assert dist[1, 1] == pytest.approx(100.0)
    assert dist[0, 0] == pytest.approx(100.0 * math.sqrt(1 + 1e-4 + 1e-4))


# ---------------------------------------------------------------------------- APS


def test_aps_identical_models_at_gt_is_one(box_scene):
    mesh, r, Tg, _ = box_scene
    assert M.aps(r, r, Tg, Tg, K, H, W) == pytest.approx(1.0)
    res = M.aps_from_depth(r.render(Tg, K, H, W).depth, r.render(Tg, K, H, W).depth)
    assert res.iou == 1.0 and res.depth_agreement == 1.0 and res.n_covisible > 100


def test_aps_part_removed_is_below_one():
    full = trimesh.util.concatenate(
        [trimesh.creation.box(extents=[80, 60, 40]), trimesh.creation.box(extents=[30, 30, 30], transform=make_T(np.eye(3), [55, 0, 0]))]
    )
    target = from_arrays(full.vertices, full.faces)  # box with a block attached
    defective = _box([80.0, 60.0, 40.0])  # the block is missing
    rt, rd = Renderer(target), Renderer(defective)
    Tg = make_T(_rot([1, 0, 0], 20.0), [0.0, 0.0, 500.0])
    s = M.aps(rt, rd, Tg, Tg, K, H, W)
    assert 0.5 < s < 0.95
    res = M.aps_from_depth(rt.render(Tg, K, H, W).depth, rd.render(Tg, K, H, W).depth)
    assert res.iou < 0.95 and res.aps == pytest.approx(s)
    # An estimate off by 20 mm in depth lowers the depth term too.
    Te = Tg.copy()
    Te[2, 3] += 20.0
    assert M.aps(rd, rd, Te, Tg, K, H, W) < 0.99
    # No co-visible pixel: 0.
    Tf = Tg.copy()
    Tf[0, 3] += 400.0
    assert M.aps(rd, rd, Tf, Tg, K, H, W) == 0.0


# ---------------------------------------------------------------------------- IoU3D


def test_iou3d_cube_vs_half_cube():
    cube = _box([100.0, 100.0, 100.0], [50.0, 50.0, 50.0])
    half = _box([100.0, 100.0, 50.0], [50.0, 50.0, 25.0])
    for vs in (10.0, 5.0, 3.0):
        assert M.iou3d(cube, half, vs) == pytest.approx(0.5, abs=vs / 100.0)
    assert M.iou3d(cube, cube, 5.0) == 1.0
    # Poses place the meshes: the half cube lifted by 50 mm overlaps the cube's top half.
    assert M.iou3d(cube, half, 5.0, T_b=make_T(np.eye(3), [0, 0, 50.0])) == pytest.approx(0.5, abs=0.05)


def test_iou3d_non_watertight_mesh():
    b = trimesh.creation.box(extents=[100, 100, 100])
    keep = b.triangles_center[:, 2] < 49.0  # drop the top face: an open box
    open_box = from_arrays(b.vertices, b.faces[keep])
    closed = from_arrays(b.vertices, b.faces)
    assert M.iou3d(open_box, closed, 4.0) == pytest.approx(1.0, abs=0.02)


def test_iou3d_convergence_towards_analytic_value():
    """Two 100 mm cubes offset by a non-grid-aligned vector: exact IoU known in closed form."""
    b = trimesh.creation.box(extents=[100.0, 100.0, 100.0])
    a = from_arrays(b.vertices, b.faces)
    c = from_arrays(b.vertices + [33.3, 17.7, 0.0], b.faces)
    inter = 66.7 * 82.3 * 100.0
    exact = inter / (2e6 - inter)
    conv = M.iou3d_convergence(a, c, [10.0, 5.0, 2.5, 1.25])
    assert [v for v, _ in conv] == [10.0, 5.0, 2.5, 1.25]
    for vs, iou in conv:
        assert abs(iou - exact) < 0.01 * vs  # error bounded by the voxel size
    assert abs(conv[-1][1] - exact) < 0.005


def test_iou3d_spheres_close_to_lens_volume():
    s = trimesh.creation.icosphere(subdivisions=4, radius=50.0)
    a = from_arrays(s.vertices, s.faces)
    b = from_arrays(s.vertices + [20.0, 0.0, 0.0], s.faces)
    r, dd = 50.0, 20.0
    inter = math.pi * (4 * r + dd) * (2 * r - dd) ** 2 / 12.0  # lens of two true spheres
    exact = inter / (2 * (4.0 / 3.0) * math.pi * r**3 - inter)
    assert M.iou3d(a, b, 2.5) == pytest.approx(exact, abs=0.01)
