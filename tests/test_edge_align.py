"""Edge-based 6-DoF alignment (pixie.cues.edge_align): photo edges, box-side depth, flips, convergence on rendered photos."""

from __future__ import annotations

from dataclasses import replace

import cv2
import numpy as np
from scipy.spatial.transform import Rotation
import pytest

from pixie.config import CHOICES, PixieConfig
from pixie.cues.edge_align import (align, align_kwargs, edge_fit, flip_twins, photo_edges, photo_edges_kwargs,
                                   silhouette_outset)
from pixie.geometry.camera import crop_intrinsics, make_K, project, rotation_angle_deg, transform_points
from pixie.geometry.render import Renderer
from pixie.pipeline.query import check_bbox
from pixie.pose.solve import depth_from_box, depth_from_visible_sides, projected_box
from pixie.synth.e2e import K_ALIGN, align_trials, clutter_photo, plate_renderer, turned_pose

K = K_ALIGN
_A = PixieConfig().align
ALIGN = align_kwargs(_A)  # the shipped defaults
PHOTO = photo_edges_kwargs(_A)  # ... and the photo's edges as the estimator makes them (the silhouette inset)


def turned(T: np.ndarray, centre: np.ndarray, deg: float, dz: float, shift_px: float,
           rng: np.random.Generator) -> np.ndarray:
    return turned_pose(T, K, centre, deg, dz, shift_px, rng)


def photo(renderers, poses, seed: int):
    return clutter_photo(renderers, poses, seed, K)


@pytest.fixture(scope="module")
def part(proc_mesh):
    return proc_mesh, Renderer(proc_mesh)


def convergence(part, plate=None, n: int = 12) -> list[tuple[float, float]]:
    return align_trials(part[0], part[1], ALIGN, n=n, plate=plate, photo_kw=PHOTO)


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


def _srgb(lin: np.ndarray) -> np.ndarray:
    """8-bit sRGB of linear light in [0, 1] (the camera's encoding)."""
    e = np.where(lin <= 0.0031308, 12.92 * lin, 1.055 * np.power(lin, 1 / 2.4) - 0.055)
    return np.clip(np.rint(e * 255), 0, 255).astype(np.uint8)


@pytest.mark.parametrize("bright_inside", [True, False])
def test_linear_light_edges_find_a_blurred_step_that_the_encoded_gradient_moves_to_its_dark_side(bright_inside):
    """A camera blurs light (linear), then encodes it (sRGB): the encoded gradient of a bright square on a dark ground
    peaks outside the square (it looks larger), of a dark square on a bright ground inside it. ``linear=True`` puts the
    edges back on the boundary."""
    lin = np.full((240, 320), 0.6 if not bright_inside else 0.03, np.float64)
    lin[60:140, 100:180] = 0.6 if bright_inside else 0.03  # boundary at x = 99.5 / 179.5 (pixel-centre coordinates)
    lin = cv2.GaussianBlur(lin, (0, 0), 1.5)
    img = np.repeat(_srgb(lin)[..., None], 3, axis=2)
    Kp = make_K(300.0, 300.0, 159.5, 119.5)
    box = np.array([100.0, 60.0, 180.0, 140.0])

    def left_offset(linear: bool) -> float:  # median signed x offset of the left side's edges, + = into the square
        pe = photo_edges(img, Kp, box, object_px=160, linear=linear)
        xy = pe.crop.to_original(pe.edge_xy)
        left = (np.abs(xy[:, 0] - 99.5) < 2.0) & (np.abs(xy[:, 1] - 100.0) < 30)
        assert left.sum() > 40
        return float(np.median(xy[left, 0] - 99.5))

    encoded, linear = left_offset(False), left_offset(True)
    assert abs(linear) < 0.12
    assert (encoded < -0.3) if bright_inside else (encoded > 0.3)  # towards the dark side


def test_edpf_edges_find_the_square_boundary_on_a_colour_only_step():
    """detector='edpf' (parameter-free Edge Drawing per colour channel): the square's sides, to sub-pixel, also where
    the square differs from its surroundings in hue only (equal grey level: a grey-image detector sees no step); an
    unknown detector is refused by name."""
    img = np.zeros((240, 320, 3), np.uint8)
    img[...] = (150, 60, 30)
    img[60:140, 100:180] = (30, 90, 150)  # about the same luminance, other hue
    g = cv2.cvtColor(img, cv2.COLOR_RGB2GRAY)
    assert abs(int(g[100, 140]) - int(g[10, 10])) <= 4
    img = cv2.GaussianBlur(img, (0, 0), 0.8)
    Kp = make_K(300.0, 300.0, 159.5, 119.5)
    pe = photo_edges(img, Kp, np.array([100.0, 60.0, 180.0, 140.0]), object_px=160, detector="edpf")
    photo_xy = pe.crop.to_original(pe.edge_xy)
    left = (np.abs(photo_xy[:, 0] - 99.5) < 1.5) & (np.abs(photo_xy[:, 1] - 100.0) < 30)
    assert left.sum() > 40
    assert np.median(np.abs(photo_xy[left, 0] - 99.5)) < 0.25
    with pytest.raises(ValueError, match="detector"):
        photo_edges(img, Kp, np.array([100.0, 60.0, 180.0, 140.0]), detector="sobel")


def test_alignment_with_edpf_edges_stays_at_the_true_pose(part, make_pose):
    mesh, ren = part
    T = make_pose(mesh, 7, distance_factor=3.5, offset_px=40, K=K)
    img, box, _ = photo([ren], [T], 7)
    pe = photo_edges(img, K, box, detector="edpf")
    res = align(ren, pe, T, hull=mesh.hull_vertices, **ALIGN)
    assert rotation_angle_deg(res.T_cam_from_obj[:3, :3], T[:3, :3]) < 0.5
    assert abs(res.T_cam_from_obj[2, 3] - T[2, 3]) / T[2, 3] < 0.005
    assert res.fit.share > 0.6


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


@pytest.mark.parametrize("axes,n", [("camera", 2), ("object", 3), ("both", 5)])
def test_flip_twins_turn_half_a_turn_about_the_object_centre(part, make_pose, axes, n):
    mesh, _ = part
    T = make_pose(mesh, 5, K=K)
    c = transform_points(T, mesh.center[None])[0]
    twins = flip_twins(T, mesh.center, axes)
    assert len(twins) == n
    for F in twins:
        assert rotation_angle_deg(F[:3, :3], T[:3, :3]) == pytest.approx(180.0, abs=1e-6)
        np.testing.assert_allclose(transform_points(F, mesh.center[None])[0], c, atol=1e-9)
        axis_cam = Rotation.from_matrix(F[:3, :3] @ T[:3, :3].T).as_rotvec()
        axis_obj = T[:3, :3].T @ axis_cam / np.linalg.norm(axis_cam)  # the turn's axis in the object's frame
        on_camera_axis = np.isclose(np.abs(axis_cam / np.linalg.norm(axis_cam))[:2], 1.0, atol=1e-6).any()
        on_object_axis = np.isclose(np.abs(axis_obj), 1.0, atol=1e-6).any()
        assert on_camera_axis if axes == "camera" else (on_object_axis if axes == "object" else on_camera_axis or on_object_axis)
    with pytest.raises(ValueError, match="flip axes"):
        flip_twins(T, mesh.center, "image")


# ------------------------------------------------------------------------------------------ alignment


def test_alignment_from_the_true_pose_stays_and_fits(part, make_pose):
    mesh, ren = part
    T = make_pose(mesh, 7, distance_factor=3.5, offset_px=40, K=K)
    img, box, _ = photo([ren], [T], 7)
    pe = photo_edges(img, K, box, **PHOTO)
    res = align(ren, pe, T, hull=mesh.hull_vertices, **ALIGN)
    assert rotation_angle_deg(res.T_cam_from_obj[:3, :3], T[:3, :3]) < 0.5
    assert abs(res.T_cam_from_obj[2, 3] - T[2, 3]) / T[2, 3] < 0.005
    # the fit at the true pose is high and drops for a pose 8 % too far
    far = T.copy()
    far[:3, 3] *= 1.08
    assert res.fit.share > 0.6
    assert edge_fit(ren, pe, far).share < res.fit.share - 0.3


def test_silhouette_outset_is_half_a_render_pixel_less_the_inset_in_crop_px(part, make_pose):
    mesh, ren = part
    T = make_pose(mesh, 7, distance_factor=3.5, offset_px=40, K=K)
    img, box, _ = photo([ren], [T], 7)
    pe = photo_edges(img, K, box)
    assert pe.sil_inset == 0.0 and silhouette_outset(pe) == 0.5
    assert photo_edges(img, K, box, sil_inset=1.0).sil_inset == 1.0
    assert silhouette_outset(replace(pe, sil_inset=1.0)) == pytest.approx(0.5 - 1.0 / pe.scale)
    assert silhouette_outset(replace(pe, sil_inset=-0.5)) == pytest.approx(0.5 + 0.5 / pe.scale)
    assert photo_edges(img, K, box, **PHOTO).sil_inset == _A.silhouette_inset_px  # the estimator's edges carry it


def test_silhouette_inset_brings_the_aligned_pose_closer_by_the_inset(part, make_pose):
    """Silhouette points moved inwards by the photo's ``sil_inset`` (photo px) make the model appear smaller: aligned to
    the same outline it comes closer by about 2 * inset / the outline's width (the outline itself does not change)."""
    mesh, ren = part
    T = make_pose(mesh, 7, distance_factor=3.5, offset_px=40, K=K)
    img, box, _ = photo([ren], [T], 7)
    pe = photo_edges(img, K, box, **PHOTO)
    kw = ALIGN | {"box_taper": 0.0}
    z0 = align(ren, pe, T, hull=mesh.hull_vertices, **kw).T_cam_from_obj[2, 3]
    z1 = align(ren, replace(pe, sil_inset=1.0), T, hull=mesh.hull_vertices, **kw).T_cam_from_obj[2, 3]
    width = float(np.sqrt((box[2] - box[0]) * (box[3] - box[1])))  # photo px
    expected = 2.0 / width
    assert abs(z0 - T[2, 3]) / T[2, 3] < 0.005
    assert 0.4 * expected < (z0 - z1) / z0 < 2.0 * expected


def test_region_support_is_high_at_the_true_pose_and_drops_off_it(part, make_pose):
    """The colour region steps where the true pose's silhouette lies (most silhouette points within fit_px), not
    where a pose 8 % too far puts it; the support counts a point on an edge or on such a step, so it is at least
    the edge fit."""
    mesh, ren = part
    for seed in (7, 8, 9):
        T = make_pose(mesh, seed, distance_factor=3.5, offset_px=40, K=K)
        img, box, _ = photo([ren], [T], seed)
        pe = photo_edges(img, K, box, **PHOTO)
        far = T.copy()
        far[:3, 3] *= 1.08
        at, off = edge_fit(ren, pe, T, region=True), edge_fit(ren, pe, far, region=True)
        assert at.region_share > 0.7 and off.region_share < at.region_share - 0.4
        assert at.support_share >= at.share and off.support_share >= off.share
        assert np.isnan(edge_fit(ren, pe, T).region_share)  # not asked: not computed


@pytest.mark.parametrize("rerender", [1, 2])
def test_reported_fit_is_the_fit_of_the_final_pose_rendered_afresh(part, make_pose, rerender):
    """align() renders only when the pose has moved and hands its last render to the final fit: that fit must be
    the one of the returned pose rendered again (a stale render would give the start's or an earlier level's)."""
    mesh, ren = part
    T = make_pose(mesh, 11, distance_factor=3.5, offset_px=30, K=K)
    img, box, _ = photo([ren], [T], 11)
    pe = photo_edges(img, K, box, **PHOTO)
    T0 = turned(T, mesh.center, 6.0, 0.03, 2.0, np.random.default_rng(11))
    res = align(ren, pe, T0, hull=mesh.hull_vertices, **dict(ALIGN, rerender=rerender))
    assert rotation_angle_deg(res.T_cam_from_obj[:3, :3], T0[:3, :3]) > 1.0  # it moved
    fresh = edge_fit(ren, pe, res.T_cam_from_obj, fit_px=ALIGN["fit_px"], region=True)  # its colour model too
    assert res.fit == fresh and np.isfinite(res.fit.region_share)
    assert edge_fit(ren, pe, T0, fit_px=ALIGN["fit_px"]).share < res.fit.share


def test_alignment_with_every_part_dropped_returns_the_start(part, make_pose):
    """No model point left (every part dropped, as the part report's robust fit may do on a defective model): the
    start comes back unchanged with no cost recorded, not an exception (found on the defects benchmark, session 14)."""
    mesh, ren = part
    T = make_pose(mesh, 7, distance_factor=3.5, offset_px=40, K=K)
    img, box, _ = photo([ren], [T], 7)
    pe = photo_edges(img, K, box, **PHOTO)
    res = align(ren, pe, T, hull=mesh.hull_vertices, face_parts=np.zeros(len(mesh.faces), int), drop_parts={0},
                **ALIGN)
    np.testing.assert_array_equal(res.T_cam_from_obj, T)
    assert res.iterations == 0 and len(res.history) == len(ALIGN["schedule"]) and np.isnan(res.history).all()


def test_matcher_correspondences_pull_a_turned_start_to_the_pose(part, make_pose):
    """2D–3D correspondences as residuals (``matches``, ``w_matches``): 80 surface points seen at the true pose,
    1 px noise and 25 % wrong matches, bring a start 10° / 5 % off to the pose on a photo with clutter (without
    them, with session 7's alignment settings, this start stayed 10° off on seed 0); they are mapped from photo px into the crop (a wrong mapping would
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
        res = align(ren, photo_edges(img, K, box, **PHOTO), T0, hull=mesh.hull_vertices, matches=(uv, xyz),
                    **(ALIGN | {"w_matches": 3.0, "match_px": 30.0}))
        Ta = res.T_cam_from_obj
        assert rotation_angle_deg(Ta[:3, :3], T[:3, :3]) < 1.0, seed
        assert abs(Ta[2, 3] - T[2, 3]) / T[2, 3] < 0.01, seed


@pytest.mark.slow
def test_alignment_converges_from_10_degrees_and_5_percent(part):
    """Measured (these 12 seeds, procedural part, random colours, clutter, shipped align defaults): 11/12 end within
    1° and 1 % depth (issue 22 asks for 90 %) with the region search (session 23), 12/12 with the edge search along
    the normal (sessions 12-22). Session 7's defaults (the box at every scale, scales 8 -> 2 px) gave 5/12; the box at
    the coarsest scale only (box_taper 0) 10/12, and the first scale of 16 px 12/12."""
    errs = convergence(part)
    assert sum(r < 1.0 and dz < 0.01 for r, dz in errs) >= 10, errs
    assert sum(r < 5.0 and dz < 0.03 for r, dz in errs) >= 10, errs


@pytest.mark.slow
def test_alignment_with_half_the_part_covered(part):
    """Measured (12 seeds, a plate covering 25-75 % of the part): 11/12 within 1° / 1 % (issue 22 asks for 80 %), with
    the region search (session 23) and the edge search along the normal alike; session 7's defaults gave 4/12,
    box_taper 0 with scales 8 -> 2 px 8/12."""
    errs = convergence(part, plate_renderer())
    assert sum(r < 1.0 and dz < 0.01 for r, dz in errs) >= 9, errs
    assert sum(r < 5.0 and dz < 0.03 for r, dz in errs) >= 9, errs


@pytest.mark.slow
def test_alignment_with_its_first_scales_on_a_coarse_crop_converges(part):
    """align.coarse_px: the first two Tukey scales (16 and 8 px) run on a crop where the box spans 100 px instead of 200
    (a quarter of the render's pixels), then 4 and 2 px on the full crop, as the estimator runs them. An option (off):
    8 of the 12 seeds; measured (session 36) 7 / 8 within 1° / 1 % clean and 7 / 8 half covered (11 / 12 of 12)."""
    from pixie.cues.edge_align import coarse_kwargs

    ac = PixieConfig().align
    ac.coarse_px = 100.0
    kw = coarse_kwargs(ac, None)
    assert kw["coarse_schedule"] == (8.0, 4.0) and kw["schedule"] == (4.0, 2.0)
    for plate in (None, plate_renderer()):
        errs = align_trials(part[0], part[1], ALIGN, n=8, plate=plate, coarse_ac=ac, photo_kw=PHOTO)
        assert sum(r < 1.0 and dz < 0.01 for r, dz in errs) >= 6, errs


def test_region_steps_find_where_the_foreground_posterior_drops():
    """_region_steps on a hand-made posterior: object (0.9) left of x = 40.5, background (0.1) right of it; points
    looking outwards (+x) from x = 35 and 44 find the boundary 5.5 px out / 3.5 px in; a flat posterior has no step,
    nor a point looking the wrong way (background before foreground)."""
    from pixie.cues.edge_align import _region_steps

    fg = np.full((80, 80), 0.1, np.float32)
    fg[:, :41] = 0.9
    xy = np.array([[35.0, 40.0], [44.0, 40.0], [44.0, 40.0]])
    out = np.array([[1.0, 0.0], [1.0, 0.0], [-1.0, 0.0]])
    d, has = _region_steps(fg, xy, out, reach=8.0)
    assert has.tolist() == [True, True, False]
    np.testing.assert_allclose(d[:2], [5.5, -3.5])
    _, flat = _region_steps(np.full((80, 80), 0.5, np.float32), xy, out, reach=8.0)
    assert not flat.any()


@pytest.mark.parametrize("search", CHOICES["align.search"])
def test_alignment_on_a_crop_without_edges_returns_a_finite_pose(part, make_pose, search):
    """A blank crop (no photo edge, a flat colour posterior): every search returns a finite pose, no exception (the
    region search once failed on the empty edge list)."""
    mesh, ren = part
    T = make_pose(mesh, 3, distance_factor=3.5, offset_px=0, K=K)
    img = np.full((480, 640, 3), 128, np.uint8)
    box = projected_box(T, K, mesh.hull_vertices)
    res = align(ren, photo_edges(img, K, box, **PHOTO), T, hull=mesh.hull_vertices, **(ALIGN | {"search": search}))
    assert np.isfinite(res.T_cam_from_obj).all()


@pytest.mark.slow
def test_edge_search_along_the_normal_still_converges_on_rendered_photos(part):
    """search='normal' (every point on the nearest same-orientation edge along its normal; the default until session
    22): measured 12/12 within 1° / 1 % from 10° / 5 % clean, 11/12 with half the part covered; session 36: 11 / 12
    and 10 / 12, of which 7 / 8 and 7 / 8 on the 8 seeds run here (an option, off: the default's tests take 12)."""
    kw = ALIGN | {"search": "normal"}
    for plate in (None, plate_renderer()):
        errs = align_trials(part[0], part[1], kw, n=8, plate=plate, photo_kw=PHOTO)
        assert sum(r < 1.0 and dz < 0.01 for r, dz in errs) >= 6, errs


def test_alignment_on_real_lmo_crops_returns_finite_poses(lmo_dataset, lmo_meshes):
    ds = lmo_dataset
    t = next(t for t in ds.targets() if t.obj_id in lmo_meshes)
    g = next(g for g in ds.instances(t.scene_id, t.im_id) if g.obj_id == t.obj_id)
    img = ds.load_rgb(t.scene_id, t.im_id)
    Kc = ds.camera(t.scene_id, t.im_id).K
    box = check_bbox(g.box_visib, img.shape[:2])
    mesh = lmo_meshes[t.obj_id]
    ren = Renderer(mesh)
    res = align(ren, photo_edges(img, Kc, box, **PHOTO), g.T_cam_from_obj, hull=mesh.hull_vertices, **ALIGN)
    assert np.all(np.isfinite(res.T_cam_from_obj))
    assert 0.0 <= res.fit.share <= 1.0
    assert rotation_angle_deg(res.T_cam_from_obj[:3, :3], g.T_cam_from_obj[:3, :3]) < 20.0


def test_calibrated_confidence_is_the_logistic_of_the_named_terms():
    """logistic(c0 + c1 * x1 + ...) over config.align.confidence_terms, computed by hand; a term the pose lacks and
    coefficients that do not match the terms are refused naming the keys."""
    import math

    from pixie.config import PixieConfig
    from pixie.cues.edge_align import calibrated_confidence
    from pixie.errors import ConfigError

    ac = PixieConfig.from_dict({"align": {"confidence": [-1.0, 2.0, 0.5, -3.0],
                                          "confidence_terms": ["fit", "size", "margin"]}}).align
    x = {"fit": 0.4, "size": 1.2, "margin": 0.1, "edge": 9.0}
    z = -1.0 + 2.0 * 0.4 + 0.5 * 1.2 - 3.0 * 0.1
    assert calibrated_confidence(ac, x) == pytest.approx(1.0 / (1.0 + math.exp(-z)), abs=1e-12)
    with pytest.raises(ConfigError, match="uses size"):
        calibrated_confidence(ac, {"fit": 0.4, "margin": 0.1})
    ac.confidence = [1.0, 2.0]
    with pytest.raises(ConfigError, match="align.confidence has 2 coefficients but align.confidence_terms names 3"):
        calibrated_confidence(ac, x)
