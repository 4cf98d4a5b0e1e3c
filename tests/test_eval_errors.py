"""Pose errors (pixie.eval.pose_error) against hand-computable cases."""

from __future__ import annotations

import math

import numpy as np
import pytest
from conftest import box_mesh, rotvec

from pixie.geometry.camera import make_K, make_T
from pixie.eval import pose_error as M
from pixie.geometry.render import Renderer

K = make_K(500.0, 500.0, 160.0, 120.0)
H, W = 240, 320


@pytest.fixture(scope="module")
def pts():
    rng = np.random.default_rng(0)
    return rng.uniform(-50, 50, (500, 3))


T_GT = make_T(rotvec([1, 2, 3], 40), [10.0, -20.0, 600.0])


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
    T = T_GT @ make_T(rotvec([0, 0, 1], 180.0), np.zeros(3))
    r = 2 * np.linalg.norm(pts[:, :2], axis=1)
    assert M.add(T, T_GT, pts) == pytest.approx(r.mean(), rel=1e-9)
    assert M.mssd(T, T_GT, pts) == pytest.approx(r.max(), rel=1e-9)
    # ...and zero once that rotation is declared a symmetry.
    syms = np.stack([np.eye(4), make_T(rotvec([0, 0, 1], 180.0), np.zeros(3))])
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
    from pixie.eval.datasets import symmetry_transforms
    from pixie.geometry.mesh import load_mesh

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


# ---------------------------------------------------------------------------- VSD


@pytest.fixture(scope="module")
def box_scene():
    mesh = box_mesh([80.0, 60.0, 40.0])
    r = Renderer(mesh)
    Tg = make_T(rotvec([1, 1, 0], 30.0), [5.0, -5.0, 500.0])
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
