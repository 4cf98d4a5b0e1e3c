"""Edge-based 6-DoF alignment (pixie.cues.edge_align): photo edges, box-side depth, flips, convergence on rendered photos."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from pixie.config import PixieConfig
from pixie.cues.edge_align import align, edge_fit, flip_twins, photo_edges
from pixie.geometry.camera import crop_intrinsics, make_K, make_T, project, rotation_angle_deg, transform_points
from pixie.geometry.mesh import from_arrays
from pixie.geometry.render import Renderer
from pixie.pipeline.query import check_bbox
from pixie.pose.solve import depth_from_box, depth_from_visible_sides, projected_box
from pixie.synth.photo import Material, random_background, render_rgb

K = make_K(600.0, 605.0, 321.5, 238.0)
_A = PixieConfig().align
ALIGN = dict(schedule=tuple(_A.schedule), iters=_A.iters, crease_weight=_A.crease_weight, search=_A.search,
             min_contrast=_A.min_contrast, w_box=_A.w_box)  # the shipped defaults


def turned(T: np.ndarray, centre: np.ndarray, deg: float, dz: float, shift_px: float,
           rng: np.random.Generator) -> np.ndarray:
    """``T`` turned ``deg`` about a random axis through the object centre, depth x (1 + dz), centre shifted."""
    axis = rng.normal(size=3)
    R = cv2.Rodrigues(axis / np.linalg.norm(axis) * np.radians(deg))[0]
    c = T[:3, :3] @ centre + T[:3, 3]
    phi = rng.uniform(0, 2 * np.pi)
    u = K[0, 0] * c[0] / c[2] + K[0, 2] + shift_px * np.cos(phi)
    v = K[1, 1] * c[1] / c[2] + K[1, 2] + shift_px * np.sin(phi)
    z = c[2] * (1.0 + dz)
    cn = np.array([(u - K[0, 2]) / K[0, 0] * z, (v - K[1, 2]) / K[1, 1] * z, z])
    R0 = R @ T[:3, :3]
    return make_T(R0, cn - R0 @ centre)


def photo(renderers, poses, seed: int):
    """A 640 x 480 photo (2x supersampled: edges are anti-aliased like a camera's) with random colours, a cluttered
    background and lights (no cast shadows: cheaper); returns the image and the first object's visible box (x0, y0, x1, y1)."""
    rng = np.random.default_rng(seed)
    K2 = K.copy()
    K2[:2, :2] *= 2
    K2[0, 2], K2[1, 2] = 2 * K[0, 2] + 0.5, 2 * K[1, 2] + 0.5
    ph = render_rgb(renderers, poses, K2, 960, 1280, [Material.random(rng) for _ in poses], rng,
                    background=random_background(960, 1280, rng), shadows=False)
    img = cv2.resize(ph.rgb, (640, 480), interpolation=cv2.INTER_AREA)
    vis = cv2.resize(ph.masks_visib[0].astype(np.float32), (640, 480), interpolation=cv2.INTER_AREA) > 0.5
    full = cv2.resize(ph.masks[0].astype(np.float32), (640, 480), interpolation=cv2.INTER_AREA) > 0.5
    ys, xs = np.nonzero(vis)
    return img, np.array([xs.min(), ys.min(), xs.max() + 1, ys.max() + 1], np.float64), vis.sum() / full.sum()


@pytest.fixture(scope="module")
def part(proc_mesh):
    return proc_mesh, Renderer(proc_mesh)


@pytest.fixture(scope="module")
def plate():
    """A flat 200 x 200 x 10 mm plate: the distractor that covers half of the part."""
    import trimesh

    b = trimesh.creation.box(extents=[200.0, 200.0, 10.0])
    return Renderer(from_arrays(np.asarray(b.vertices), np.asarray(b.faces), name="plate"))


def convergence(part, make_pose, plate=None, n: int = 12) -> list[tuple[float, float]]:
    mesh, ren = part
    out = []
    for seed in range(n):
        T = make_pose(mesh, 100 + seed, distance_factor=3.5, offset_px=60, K=K)
        rng = np.random.default_rng(1000 + seed)
        if plate is None:
            img, box, _ = photo([ren], [T], seed)
        else:  # a plate 60 mm in front of the part's centre, shifted sideways to cover about half of it
            c = T[:3, :3] @ mesh.center + T[:3, 3]
            side = 1.0 if seed % 2 else -1.0
            img, box, _ = photo([ren, plate], [T, make_T(np.eye(3), c + [side * 105.0, 0.0, -60.0])], seed)
        T0 = turned(T, mesh.center, 10.0, 0.05, 3.0, rng)
        res = align(ren, photo_edges(img, K, box), T0, hull=mesh.hull_vertices, **ALIGN)
        Ta = res.T_cam_from_obj
        out.append((rotation_angle_deg(Ta[:3, :3], T[:3, :3]), abs(Ta[2, 3] - T[2, 3]) / T[2, 3]))
    return out


# ------------------------------------------------------------------------------------------ photo side


def test_photo_edges_find_a_square_boundary_to_subpixel():
    img = np.full((240, 320, 3), 40, np.uint8)
    # a square of pixels [100, 180) x [60, 140): its boundary lies at 99.5 / 179.5 in pixel-centre coordinates
    img[60:140, 100:180] = 200
    img = cv2.GaussianBlur(img, (0, 0), 0.8)
    Kp = make_K(300.0, 300.0, 159.5, 119.5)
    pe = photo_edges(img, Kp, np.array([100.0, 60.0, 180.0, 140.0]), object_px=160)
    photo_xy = pe.crop.to_original(pe.edge_xy)
    left = (np.abs(photo_xy[:, 0] - 99.5) < 1.5) & (np.abs(photo_xy[:, 1] - 100.0) < 30)  # away from the corners
    assert left.sum() > 40
    assert np.median(np.abs(photo_xy[left, 0] - 99.5)) < 0.25  # sub-pixel, in photo px
    assert np.all(np.abs(pe.edge_dir[left, 0]) > 0.9)  # the gradient points across the vertical side
    # box sides in crop px map back to the photo's pixel edges
    back = pe.crop.to_original(pe.box_sides.reshape(2, 2))
    np.testing.assert_allclose(back, [[99.5, 59.5], [179.5, 139.5]], atol=1e-9)


def test_crop_intrinsics_project_like_the_photo_camera_then_the_crop_map():
    pe = photo_edges(np.zeros((480, 640, 3), np.uint8), K, np.array([200.0, 150.0, 330.0, 260.0]))
    X = np.array([[10.0, -20.0, 700.0], [-35.0, 5.0, 650.0]])
    uv_crop = project(pe.K, X)
    np.testing.assert_allclose(pe.crop.to_original(uv_crop), project(K, X), atol=1e-9)
    np.testing.assert_allclose(crop_intrinsics(K, pe.crop.A), pe.K)


# ------------------------------------------------------------------------------------------ box depth, flips


def test_visible_sides_recover_depth_when_one_side_is_occluded(part, make_pose):
    mesh, _ = part
    T = make_pose(mesh, 3, distance_factor=4.0, K=K)
    pb = projected_box(T, K, mesh.hull_vertices)
    occluded = pb.copy()
    occluded[2] -= 0.3 * (pb[2] - pb[0])  # the right 30 % hidden: the visible box ends early
    far = T.copy()
    far[:3, 3] *= 1.04
    z = T[2, 3]
    # the classic rule (larger of the width / height ratios) is fooled by the cut width only when the height
    # ratio is also affected; the visible-sides rule ignores the cut side and matches the three others
    Ts = depth_from_visible_sides(far, K, mesh.hull_vertices, occluded)
    assert abs(Ts[2, 3] - z) / z < 0.002
    np.testing.assert_allclose(projected_box(Ts, K, mesh.hull_vertices)[[0, 1, 3]], pb[[0, 1, 3]], atol=0.3)
    # with every side visible it agrees with the box rule
    Tb = depth_from_box(far, K, mesh.hull_vertices, pb)
    Tv = depth_from_visible_sides(far, K, mesh.hull_vertices, pb)
    assert abs(Tb[2, 3] - Tv[2, 3]) / z < 0.002 and abs(Tv[2, 3] - z) / z < 0.002


def test_flip_twins_turn_half_a_turn_about_the_object_centre(part, make_pose):
    mesh, _ = part
    T = make_pose(mesh, 5, K=K)
    c = transform_points(T, mesh.center[None])[0]
    for F in flip_twins(T, mesh.center):
        assert rotation_angle_deg(F[:3, :3], T[:3, :3]) == pytest.approx(180.0, abs=1e-6)
        np.testing.assert_allclose(transform_points(F, mesh.center[None])[0], c, atol=1e-9)


# ------------------------------------------------------------------------------------------ alignment


def test_alignment_from_the_true_pose_stays_and_fits(part, make_pose):
    mesh, ren = part
    T = make_pose(mesh, 7, distance_factor=3.5, offset_px=40, K=K)
    img, box, _ = photo([ren], [T], 7)
    pe = photo_edges(img, K, box)
    res = align(ren, pe, T, hull=mesh.hull_vertices, **ALIGN)
    assert rotation_angle_deg(res.T_cam_from_obj[:3, :3], T[:3, :3]) < 0.5
    assert abs(res.T_cam_from_obj[2, 3] - T[2, 3]) / T[2, 3] < 0.005
    # the fit at the true pose is high and drops for a pose 8 % too far
    far = T.copy()
    far[:3, 3] *= 1.08
    assert res.fit.share > 0.6
    assert edge_fit(ren, pe, far).share < res.fit.share - 0.3


def test_matcher_correspondences_pull_a_turned_start_to_the_pose(part, make_pose):
    """2D–3D correspondences as residuals (``matches``, ``w_matches``): 80 surface points seen at the true pose,
    1 px noise and 25 % wrong matches, bring a start 10° / 5 % off to the pose on a photo with clutter (without
    them this start stays 10° off on seed 0); they are mapped from photo px into the crop (a wrong mapping would
    pull the pose off). The Tukey scale is wide here (30 crop px) because the start is far from the matches; in
    the pipeline they are the start's own PnP inliers, within the RANSAC threshold of it."""
    mesh, ren = part
    for seed in (0, 1, 2):
        T = make_pose(mesh, 100 + seed, distance_factor=3.5, offset_px=60, K=K)
        img, box, _ = photo([ren], [T], seed)
        rng = np.random.default_rng(seed)
        r = ren.render(T, K, 480, 640)
        ys, xs = np.nonzero(r.mask)
        pick = rng.choice(len(xs), 80, replace=False)
        xyz = r.xyz[ys[pick], xs[pick]].astype(np.float64)
        uv = project(K, transform_points(T, xyz)) + rng.normal(0.0, 1.0, (80, 2))
        uv[:20] = rng.uniform([box[0], box[1]], [box[2], box[3]], (20, 2))  # outliers inside the box
        T0 = turned(T, mesh.center, 10.0, 0.05, 3.0, rng)
        res = align(ren, photo_edges(img, K, box), T0, hull=mesh.hull_vertices, **ALIGN, matches=(uv, xyz),
                    w_matches=3.0, match_px=30.0)
        Ta = res.T_cam_from_obj
        assert rotation_angle_deg(Ta[:3, :3], T[:3, :3]) < 1.0, seed
        assert abs(Ta[2, 3] - T[2, 3]) / T[2, 3] < 0.01, seed


@pytest.mark.slow
def test_alignment_converges_from_10_degrees_and_5_percent(part, make_pose):
    """Measured (these 12 seeds, procedural part, random colours, clutter, shipped align defaults): 5/12 end within
    1° and 1 % depth, 9/12 within 5° and 3 % (issue 22 asks for 90 % within 1° / 1 %: not reached yet)."""
    errs = convergence(part, make_pose)
    assert sum(r < 1.0 and dz < 0.01 for r, dz in errs) >= 3, errs
    assert sum(r < 5.0 and dz < 0.03 for r, dz in errs) >= 7, errs


@pytest.mark.slow
def test_alignment_with_half_the_part_covered(part, make_pose, plate):
    """Measured (12 seeds, a plate covering 25-75 % of the part): 4/12 within 1° / 1 %, 7/12 within 5° / 3 %
    (issue 22 asks for 80 % within 1° / 1 %: not reached yet)."""
    errs = convergence(part, make_pose, plate)
    assert sum(r < 1.0 and dz < 0.01 for r, dz in errs) >= 2, errs
    assert sum(r < 5.0 and dz < 0.03 for r, dz in errs) >= 5, errs


def test_alignment_on_real_lmo_crops_returns_finite_poses(lmo_dataset, lmo_meshes):
    ds = lmo_dataset
    t = next(t for t in ds.targets() if t.obj_id in lmo_meshes)
    g = next(g for g in ds.instances(t.scene_id, t.im_id) if g.obj_id == t.obj_id)
    img = ds.load_rgb(t.scene_id, t.im_id)
    Kc = ds.camera(t.scene_id, t.im_id).K
    box = check_bbox(g.box_visib, img.shape[:2])
    mesh = lmo_meshes[t.obj_id]
    ren = Renderer(mesh)
    res = align(ren, photo_edges(img, Kc, box), g.T_cam_from_obj, hull=mesh.hull_vertices, **ALIGN)
    assert np.all(np.isfinite(res.T_cam_from_obj))
    assert 0.0 <= res.fit.share <= 1.0
    assert rotation_angle_deg(res.T_cam_from_obj[:3, :3], g.T_cam_from_obj[:3, :3]) < 20.0
