"""Shape agreement (pixie.eval.shape_metrics): APS and IoU3D against cases with known answers."""

from __future__ import annotations

import math

import numpy as np
import pytest
import trimesh
from conftest import box_mesh, rotvec

from pixie.geometry.camera import make_K, make_T
from pixie.eval import shape_metrics as M
from pixie.geometry.mesh import from_arrays
from pixie.geometry.render import Renderer

K = make_K(500.0, 500.0, 160.0, 120.0)
H, W = 240, 320




@pytest.fixture(scope="module")
def box_scene():
    mesh = box_mesh([80.0, 60.0, 40.0])
    r = Renderer(mesh)
    Tg = make_T(rotvec([1, 1, 0], 30.0), [5.0, -5.0, 500.0])
    return mesh, r, Tg, r.render(Tg, K, H, W).depth


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
    defective = box_mesh([80.0, 60.0, 40.0])  # the block is missing
    rt, rd = Renderer(target), Renderer(defective)
    Tg = make_T(rotvec([1, 0, 0], 20.0), [0.0, 0.0, 500.0])
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
    cube = box_mesh([100.0, 100.0, 100.0], [50.0, 50.0, 50.0])
    half = box_mesh([100.0, 100.0, 50.0], [50.0, 50.0, 25.0])
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
