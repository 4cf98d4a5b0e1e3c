"""Geometry foundations: render round trips, camera maths, normals, viewpoints, rolls, encodings, inputs.

Everything here is computed for real (Embree renders, trimesh files); nothing is mocked.
"""

from __future__ import annotations

import warnings

import cv2
import numpy as np
import pytest
import trimesh

from pixie.geometry import camera as cam
from pixie.references import views
from pixie.references.encode import ENCODINGS, check_encodings, edge_map, encode
from pixie.errors import CameraError, ConfigError, ImageError, MeshError
from pixie.geometry.rotations import check_image, check_mask, lookup, nearest_pixel, orthonormalize, rodrigues, rotation_between
from pixie.geometry.mesh import from_arrays, load_mesh
from pixie.pipeline.query import check_bbox, square_crop
from pixie.geometry.render import Renderer

H, W = 480, 640


def _roundtrip_errors(mesh, T, K):
    """(max XYZ error / diameter, max reprojection error px, number of object pixels) of one render."""
    r = Renderer(mesh).render(T, K, H, W)
    m = r.mask
    assert m.sum() > 500, "the object should be well in view"
    X_cam = cam.backproject_depth(K, r.depth.astype(np.float64))
    X_obj = cam.transform_points(cam.invert_T(T), X_cam)
    xyz_err = np.linalg.norm(X_obj[m] - r.xyz[m].astype(np.float64), axis=1).max()
    uv = cam.project(K, cam.transform_points(T, r.xyz[m].astype(np.float64)))
    v, u = np.nonzero(m)
    px_err = np.abs(uv - np.stack([u, v], axis=1)).max()
    return xyz_err / mesh.diameter, px_err, int(m.sum())


# ------------------------------------------------------------------------------ render round trip


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_roundtrip_procedural(proc_mesh, K640, make_pose, seed):
    T = make_pose(proc_mesh, seed, distance_factor=2.5 + seed, offset_px=80)
    xyz_rel, px, n = _roundtrip_errors(proc_mesh, T, K640)
    assert xyz_rel < 1e-3, f"back-projected depth misses the rendered XYZ by {xyz_rel:.2e} x diameter"
    assert px < 0.01, f"projected XYZ misses the pixel centres by {px:.4f} px"


def test_roundtrip_lmo(lmo_meshes, K640, make_pose):
    for obj_id, mesh in lmo_meshes.items():
        for seed in range(3):
            T = make_pose(mesh, 10 * obj_id + seed, distance_factor=3.0 + seed, offset_px=60)
            xyz_rel, px, n = _roundtrip_errors(mesh, T, K640)
            assert xyz_rel < 1e-3, f"obj {obj_id} seed {seed}: XYZ error {xyz_rel:.2e} x diameter"
            assert px < 0.01, f"obj {obj_id} seed {seed}: reprojection error {px:.4f} px"


@pytest.mark.parametrize("seed,distance_factor", [(7, 2.0), (8, 3.0), (9, 0.45)])
def test_render_roi_auto_equals_full(proc_mesh, K640, make_pose, seed, distance_factor):
    """The automatic ROI (projected hull box; the bounding sphere's when the camera is too close) only skips
    rays that would miss: the same image as casting every pixel, and a smaller box than the sphere's."""
    T = make_pose(proc_mesh, seed, distance_factor=distance_factor, offset_px=150)
    r = Renderer(proc_mesh)
    a, b = r.render(T, K640, H, W), r.render(T, K640, H, W, roi=None)
    assert a.mask.sum() > 100
    for f in ("tri_ids", "depth", "normals", "xyz"):
        assert np.array_equal(getattr(a, f), getattr(b, f)), f
    x0, y0, x1, y1 = r._hull_roi(T, K640, H, W) or (0, 0, W, H)  # None: too close, every pixel
    s0, t0, s1, t1 = r._sphere_roi(T, K640, H, W) or (0, 0, W, H)
    assert (x1 - x0) * (y1 - y0) <= (s1 - s0) * (t1 - t0)


def test_render_with_shifted_K_equals_crop(proc_mesh, K640, make_pose):
    """Rendering with crop_K of an integer, unscaled window equals cropping the full render."""
    T = make_pose(proc_mesh, 3, distance_factor=3.0)
    x0, y0, side = 200, 120, 240
    Kc = cam.crop_K(K640, x0, y0, side, side)
    r = Renderer(proc_mesh)
    full = r.render(T, K640, H, W)
    part = r.render(T, Kc, side, side)
    crop = (slice(y0, y0 + side), slice(x0, x0 + side))
    # the same rays up to float rounding: a ray grazing a triangle edge may pick its neighbour
    assert np.mean(part.tri_ids == full.tri_ids[crop]) > 0.999
    assert part.mask.sum() > 5000 and np.mean(part.mask == full.mask[crop]) > 0.999
    both = part.mask & full.mask[crop]
    np.testing.assert_allclose(part.xyz[both], full.xyz[crop][both], atol=1e-3)


# ------------------------------------------------------------------------------------ camera maths


def test_backproject_project_inverse():
    rng = np.random.default_rng(0)
    K = cam.make_K(512.3, 498.7, 300.2, 251.9)
    uv = rng.uniform([-50, -50], [700, 500], size=(1000, 2))
    z = rng.uniform(50, 5000, size=1000)
    X = cam.backproject(K, uv, z)
    np.testing.assert_allclose(X[:, 2], z)
    np.testing.assert_allclose(cam.project(K, X), uv, atol=1e-9)
    X2 = rng.uniform([-300, -300, 100], [300, 300, 2000], size=(1000, 3))
    np.testing.assert_allclose(cam.backproject(K, cam.project(K, X2), X2[:, 2]), X2, rtol=1e-12, atol=1e-9)


def test_invert_and_transform(make_pose, proc_mesh):
    T = make_pose(proc_mesh, 5)
    np.testing.assert_allclose(T @ cam.invert_T(T), np.eye(4), atol=1e-12)
    X = np.random.default_rng(1).normal(size=(20, 3)) * 50
    np.testing.assert_allclose(cam.transform_points(cam.invert_T(T), cam.transform_points(T, X)), X, atol=1e-9)


@pytest.mark.parametrize("x0,y0,side,size", [(100.0, 50.0, 200.0, 256), (-13.25, 7.5, 91.0, 512), (300.7, 200.2, 33.3, 64)])
def test_crop_K_maps_pixels_like_the_crop(x0, y0, side, size):
    """A point projected with K and mapped into the crop lands where K_crop projects it."""
    K = cam.make_K(600.0, 610.0, 320.5, 240.25)
    Kc = cam.crop_K(K, x0, y0, side, size)
    X = np.random.default_rng(2).uniform([-200, -200, 400], [200, 200, 1500], size=(200, 3))
    uv = cam.project(K, X)
    s = size / side
    uv_crop = (uv + 0.5 - [x0, y0]) * s - 0.5  # pixel-centre convention: edges at ±0.5
    np.testing.assert_allclose(cam.project(Kc, X), uv_crop, atol=1e-9)


def test_square_crop_K_centres_the_object(proc_mesh, K640, make_pose):
    T = make_pose(proc_mesh, 4, distance_factor=3.0, offset_px=100)
    size, pad = 256, 1.2
    Kc, box = views.square_crop_K(K640, T, proc_mesh.vertices, size, pad)
    uv = cam.project(Kc, cam.transform_points(T, proc_mesh.vertices))
    lo, hi = uv.min(0), uv.max(0)
    # the projected box's centre is exactly the crop's centre ((size-1)/2 in pixel-centre coordinates)
    np.testing.assert_allclose(0.5 * (lo + hi), [(size - 1) / 2] * 2, atol=1e-6)
    np.testing.assert_allclose((hi - lo).max(), size / pad, rtol=1e-9)
    # ... and the box it reports is the window crop_K was built from
    uv0 = cam.project(K640, cam.transform_points(T, proc_mesh.vertices))
    np.testing.assert_allclose(cam.crop_K(K640, box[0], box[1], box[2], size), Kc)
    assert box[3] == pytest.approx(size / box[2])
    np.testing.assert_allclose((uv0 + 0.5 - box[:2]) * box[3] - 0.5, uv, atol=1e-6)


def test_query_square_crop_agrees_with_crop_K():
    """The query crop's crop→original map is the inverse of the crop_K mapping used by the references."""
    K = cam.make_K(600.0, 600.0, 319.5, 239.5)
    box = np.array([210.0, 130.0, 330.0, 290.0])  # x0, y0, x1, y1 (pixel edges)
    size, pad = 256, 1.2
    img = np.zeros((H, W, 3), np.uint8)
    crop = square_crop(img, box, pad, size)
    side = pad * max(box[2] - box[0], box[3] - box[1])
    cx, cy = 0.5 * (box[0] + box[2]), 0.5 * (box[1] + box[3])
    Kc = cam.crop_K(K, cx - side / 2, cy - side / 2, side, size)
    X = np.random.default_rng(3).uniform([-60, -60, 500], [60, 60, 900], size=(100, 3))
    np.testing.assert_allclose(crop.to_original(cam.project(Kc, X)), cam.project(K, X), atol=1e-9)


def test_validate_K_rejects_bad_intrinsics():
    good = cam.make_K(600, 600, 320, 240)
    assert cam.validate_K(good, (480, 640)) is not None
    with pytest.raises(CameraError, match="focal"):
        cam.validate_K(cam.make_K(0.0, 600, 320, 240))
    with pytest.raises(CameraError, match="focal"):
        cam.validate_K(cam.make_K(600, -1.0, 320, 240))
    with pytest.raises(CameraError, match="principal point"):
        cam.validate_K(cam.make_K(600, 600, 900, 240), (480, 640))
    with pytest.raises(CameraError, match="principal point"):
        cam.check_image_K(cam.make_K(600, 600, 320, -5), (480, 640))
    with pytest.raises(CameraError, match="3x3"):
        cam.validate_K(np.eye(4))
    with pytest.raises(CameraError, match="non-finite"):
        cam.validate_K(cam.make_K(np.nan, 600, 320, 240))
    with pytest.raises(CameraError):
        cam.parse_K("600,600,320")
    np.testing.assert_allclose(cam.parse_K("600, 601, 320, 240"), cam.make_K(600, 601, 320, 240))


def test_renderer_rejects_bad_camera(proc_mesh, make_pose):
    r = Renderer(proc_mesh)
    T = make_pose(proc_mesh, 0)
    with pytest.raises(CameraError):
        r.render(T, cam.make_K(0.0, 600, 320, 240), H, W)
    with pytest.raises(CameraError):
        r.render(T, cam.make_K(600, 600, 320, 240), 0, W)
    bad = T.copy()
    bad[:3, :3] *= 2.0
    with pytest.raises(CameraError, match="rotation"):
        r.render(bad, cam.make_K(600, 600, 320, 240), H, W)


# ------------------------------------------------------------------------------------------ normals


def _fd_normals(r, T):
    """Normals (camera frame) from central differences of the rendered XYZ, and where they are defined."""
    P = cam.transform_points(T, r.xyz.astype(np.float64))
    dx = P[1:-1, 2:] - P[1:-1, :-2]
    dy = P[2:, 1:-1] - P[:-2, 1:-1]
    n = np.cross(dx, dy)
    n /= np.maximum(np.linalg.norm(n, axis=-1, keepdims=True), 1e-30)
    m = r.mask
    valid = m[1:-1, 1:-1] & m[1:-1, 2:] & m[1:-1, :-2] & m[2:, 1:-1] & m[:-2, 1:-1]
    return n, valid


def _angle_deg(a, b):
    return np.degrees(np.arccos(np.clip(np.abs(np.einsum("...k,...k->...", a, b)), 0.0, 1.0)))


def _cad_faces(mesh, max_angle_deg=1.0):
    """Label of the planar CAD face (coplanar connected triangles) of each triangle."""
    tm = trimesh.Trimesh(mesh.vertices, mesh.faces, process=False)
    edges = tm.face_adjacency[tm.face_adjacency_angles < np.radians(max_angle_deg)]
    return trimesh.graph.connected_component_labels(edges, node_count=len(mesh.faces))


def _planar_interior(r, labels, min_pixels=400):
    """Pixels whose 4 neighbours lie on the same large planar CAD face."""
    lab = np.where(r.mask, labels[np.maximum(r.tri_ids, 0)], -1)
    c = lab[1:-1, 1:-1]
    same = (c >= 0) & (c == lab[1:-1, 2:]) & (c == lab[1:-1, :-2]) & (c == lab[2:, 1:-1]) & (c == lab[:-2, 1:-1])
    counts = np.bincount(c[same], minlength=labels.max() + 1)
    return same & (counts[np.maximum(c, 0)] >= min_pixels)


@pytest.mark.parametrize("smooth", [True, False])
def test_normals_unit_and_facing(proc_mesh, K640, make_pose, smooth):
    for seed in range(3):
        T = make_pose(proc_mesh, seed, distance_factor=2.5)
        r = Renderer(proc_mesh, smooth_normals=smooth).render(T, K640, H, W)
        n = r.normals[r.mask].astype(np.float64)
        np.testing.assert_allclose(np.linalg.norm(n, axis=1), 1.0, atol=1e-5)
        rays = cam.pixel_rays(K640, H, W)[r.mask]
        dots = np.einsum("ij,ij->i", n, rays)
        assert np.all(dots <= 1e-9), "a normal points away from the camera"
        assert np.mean(dots < 0) > 0.999
        assert not np.any(r.normals[~r.mask]), "background normals must be 0"


def test_normals_match_finite_differences_on_sphere(sphere_mesh, K640, make_pose):
    T = make_pose(sphere_mesh, 0, distance_factor=2.5)
    r = Renderer(sphere_mesh, smooth_normals=True).render(T, K640, H, W)
    n_fd, valid = _fd_normals(r, T)
    ang = _angle_deg(n_fd, r.normals[1:-1, 1:-1].astype(np.float64))[valid]
    assert valid.sum() > 5000
    assert np.median(ang) < 5.0, f"median angle {np.median(ang):.2f} deg"
    # and the interpolated normals are close to the true sphere normals
    c = cam.transform_points(T, sphere_mesh.center[None])[0]
    P = cam.transform_points(T, r.xyz[r.mask].astype(np.float64))
    true_n = (P - c) / np.linalg.norm(P - c, axis=1, keepdims=True)
    assert np.median(_angle_deg(true_n, r.normals[r.mask].astype(np.float64))) < 2.0


def test_flat_normals_match_finite_differences_on_planar_faces(proc_mesh, K640, make_pose):
    labels = _cad_faces(proc_mesh)
    r_ = Renderer(proc_mesh, smooth_normals=False)
    for seed in range(3):
        T = make_pose(proc_mesh, seed, distance_factor=2.0)
        r = r_.render(T, K640, H, W)
        n_fd, _ = _fd_normals(r, T)
        sel = _planar_interior(r, labels)
        assert sel.sum() > 1000
        ang = _angle_deg(n_fd, r.normals[1:-1, 1:-1].astype(np.float64))[sel]
        assert np.median(ang) < 1.0 and np.percentile(ang, 99) < 5.0


def test_default_normals_match_finite_differences_on_planar_faces(proc_mesh, K640, make_pose):
    labels = _cad_faces(proc_mesh)
    r_ = Renderer(proc_mesh)  # default: smooth_normals=True, as references are built by default
    for seed in range(3):
        T = make_pose(proc_mesh, seed, distance_factor=2.0)
        r = r_.render(T, K640, H, W)
        n_fd, _ = _fd_normals(r, T)
        sel = _planar_interior(r, labels)
        ang = _angle_deg(n_fd, r.normals[1:-1, 1:-1].astype(np.float64))[sel]
        assert np.median(ang) < 5.0, f"median angle {np.median(ang):.1f} deg on planar faces"


def test_normals_do_not_depend_on_the_file_format(proc_trimesh, tmp_path, K640):
    rendered = {}
    for ext in ("ply", "stl"):
        proc_trimesh.export(tmp_path / f"part.{ext}")
        m = load_mesh(tmp_path / f"part.{ext}")
        T = cam.look_at(m.center + np.array([200.0, 150.0, 180.0]), m.center, np.array([0.0, 0.0, 1.0]))
        rendered[ext] = Renderer(m).render(T, K640, H, W)
    a, b = rendered["ply"], rendered["stl"]
    both = a.mask & b.mask
    assert both.sum() > 0.99 * a.mask.sum()
    ang = _angle_deg(a.normals[both].astype(np.float64), b.normals[both].astype(np.float64))
    assert np.percentile(ang, 99) < 1.0, f"PLY and STL normals differ by up to {ang.max():.1f} deg"


# ---------------------------------------------------------------------------------------- viewpoints


def test_fibonacci_directions_are_unit_and_cover_the_sphere():
    for n in (1, 10, 115, 500):
        d = views.fibonacci_sphere(n)
        assert d.shape == (n, 3)
        np.testing.assert_allclose(np.linalg.norm(d, axis=1), 1.0, atol=1e-12)
    assert views.fibonacci_sphere(0).shape == (0, 3)
    d121 = views.view_directions(115, canonical=True)
    assert len(d121) == 121
    gap121 = views.max_angular_gap_deg(d121)
    gap300 = views.max_angular_gap_deg(views.view_directions(294, canonical=True))
    gap40 = views.max_angular_gap_deg(views.view_directions(40, canonical=True))
    assert gap121 < 15.0, f"121 views leave a {gap121:.1f} deg gap"
    assert gap300 < gap121 < gap40
    # a lone direction leaves the antipode uncovered
    assert views.max_angular_gap_deg(np.array([[0.0, 0.0, 1.0]])) > 179.0


def test_canonical_views_look_along_the_axes(proc_mesh):
    dist = 500.0
    poses = views.view_poses(proc_mesh.center, dist, n_fibonacci=0, canonical=True)
    assert len(poses) == 6
    axes = np.array([cam.optical_axis_in_object(T) for T in poses])
    expected = -views.CANONICAL_DIRECTIONS  # the camera sits at centre + d and looks back at the centre
    np.testing.assert_allclose(axes, expected, atol=1e-12)
    assert {tuple(np.round(a).astype(int)) for a in axes} == {
        (1, 0, 0), (-1, 0, 0), (0, 1, 0), (0, -1, 0), (0, 0, 1), (0, 0, -1)
    }
    for T, d in zip(poses, views.CANONICAL_DIRECTIONS):
        cam.validate_pose(T)
        # camera centre in the object frame, and the object centre on the optical axis
        np.testing.assert_allclose(cam.invert_T(T)[:3, 3], proc_mesh.center + dist * d, atol=1e-9)
        np.testing.assert_allclose(cam.transform_points(T, proc_mesh.center[None])[0], [0, 0, dist], atol=1e-9)


def test_all_views_look_at_the_centre(proc_mesh):
    poses = views.view_poses(proc_mesh.center, 400.0, n_fibonacci=115)
    c = np.array([cam.transform_points(T, proc_mesh.center[None])[0] for T in poses])
    np.testing.assert_allclose(c[:, :2], 0.0, atol=1e-9)
    np.testing.assert_allclose(c[:, 2], 400.0)


def test_roll_rotates_image_content(proc_mesh):
    size = 320
    K = cam.make_K(800.0, 800.0, (size - 1) / 2, (size - 1) / 2)
    dist = views.camera_distance(proc_mesh.bounding_radius, 800.0, size, fill=0.85)
    T0 = views.view_poses(proc_mesh.center, dist, n_fibonacci=20)[9]
    r = Renderer(proc_mesh)
    m0 = r.render(T0, K, size, size).mask
    # the whole object fits inside the inscribed circle, so rotating the image loses nothing
    yy, xx = np.mgrid[0:size, 0:size]
    assert np.all(np.hypot(xx - K[0, 2], yy - K[1, 2])[m0] < size / 2 - 1)

    def rotated(mask, deg):
        M = cv2.getRotationMatrix2D((K[0, 2], K[1, 2]), deg, 1.0)
        return cv2.warpAffine(mask.astype(np.uint8), M, (size, size), flags=cv2.INTER_NEAREST) > 0

    def iou(a, b):
        return (a & b).sum() / (a | b).sum()

    for angle in (45.0, 135.0, -90.0):
        m1 = r.render(views.roll(T0, np.radians(angle)), K, size, size).mask
        # rolling the camera by +a turns the image content by Rz(a) in (x right, y down) pixels,
        # which is OpenCV's getRotationMatrix2D with -a (it counts counter-clockwise on screen)
        assert iou(m1, rotated(m0, -angle)) > 0.97, f"roll {angle}"
        assert iou(m1, rotated(m0, +angle)) < 0.9, f"roll {angle}: the other direction should not fit"
    np.testing.assert_allclose(views.roll(T0, 0.0), T0)
    np.testing.assert_allclose(views.roll_angles(8), np.radians(np.arange(8) * 45.0))


# ----------------------------------------------------------------------------------------- encodings


@pytest.fixture(scope="module")
def crop_render(proc_mesh):
    size = 256
    K0 = views.start_K(size, 4.0)
    dist = views.camera_distance(proc_mesh.bounding_radius, K0[0, 0], size, fill=1 / 1.2)
    T = views.view_poses(proc_mesh.center, dist, n_fibonacci=20)[12]
    K, _ = views.square_crop_K(K0, T, proc_mesh.vertices, size, 1.2)
    return Renderer(proc_mesh, smooth_normals=False).render(T, K, size, size)


@pytest.mark.parametrize("name", ENCODINGS)
def test_encodings_shape_dtype_background(crop_render, name):
    r = crop_render
    img = encode(name, r.depth, r.normals, r.mask)
    assert img.dtype == np.uint8
    assert img.shape in ((256, 256), (256, 256, 3))
    if name.startswith(("depth", "normal")):
        assert img.shape == (256, 256, 3)
    assert not img[~r.mask].any(), "background must be black"
    inside = img[r.mask]
    assert inside.reshape(len(inside), -1).max(axis=1).mean() > 30, "the object must be visible"


def test_depth_encoding_is_monotone(crop_render):
    r = crop_render
    img = encode("depth", r.depth, r.normals, r.mask)
    lut = cv2.applyColorMap(np.arange(256, dtype=np.uint8)[:, None], cv2.COLORMAP_TURBO)[:, 0, ::-1].astype(int)
    px = img[r.mask].astype(int)
    level = np.argmin(((px[:, None, :] - lut[None]) ** 2).sum(-1), axis=1)  # invert the colormap
    d = r.depth[r.mask]
    order = np.argsort(d)
    lv = level[order]
    # near is warm (high level): levels never rise with depth beyond one quantisation step
    assert np.all(np.maximum.accumulate(lv[::-1])[::-1] - lv <= 1)
    assert lv[0] >= 254 and lv[-1] <= 1
    assert np.corrcoef(d, level)[0, 1] < -0.99


@pytest.mark.parametrize("base", ["depth", "normal", "shade1", "shade3"])
def test_edge_encodings_draw_silhouettes(crop_render, base):
    r = crop_render
    cross = cv2.getStructuringElement(cv2.MORPH_CROSS, (3, 3))
    inner = r.mask & ~cv2.erode(r.mask.astype(np.uint8), cross).astype(bool)  # 4-neighbours of background
    plain = encode(base, r.depth, r.normals, r.mask)
    edged = encode(f"{base}_edges", r.depth, r.normals, r.mask)
    dark = (edged.reshape(*r.mask.shape, -1).max(-1) == 0)
    assert dark[inner].mean() > 0.95, "silhouette pixels should be drawn dark"
    assert (plain.reshape(*r.mask.shape, -1).max(-1) > 0)[inner].mean() > 0.9
    e = edge_map(r.depth, r.normals, r.mask)
    assert e[inner].all()
    # crease edges inside the object too, not only the outline
    assert (e & r.mask & ~inner).sum() > 100


def test_unknown_encoding_is_a_config_error(crop_render):
    r = crop_render
    with pytest.raises(ConfigError, match="unknown encoding 'sketch'"):
        encode("sketch", r.depth, r.normals, r.mask)
    with pytest.raises(ConfigError, match="unknown encoding"):
        check_encodings(["depth", "shade3_edge"])
    with pytest.raises(ConfigError):
        check_encodings([])
    assert check_encodings(["depth", "normal_edges"]) == ["depth", "normal_edges"]


# -------------------------------------------------------------------------------- meshes / bad inputs


@pytest.mark.parametrize("ext", ["ply", "obj", "stl", "glb"])
def test_load_mesh_formats(proc_trimesh, proc_mesh, tmp_path, ext):
    path = tmp_path / f"part.{ext}"
    proc_trimesh.export(path)
    m = load_mesh(path)
    assert m.diameter == pytest.approx(proc_mesh.diameter, rel=1e-6)
    np.testing.assert_allclose(m.bbox_min, proc_mesh.bbox_min, atol=1e-4)
    np.testing.assert_allclose(m.bbox_max, proc_mesh.bbox_max, atol=1e-4)
    assert m.name == "part" and len(m.source_hash) == 64
    np.testing.assert_allclose(np.linalg.norm(m.vertex_normals, axis=1), 1.0, atol=1e-9)
    # the same file twice has the same hash; a different file does not
    assert load_mesh(path).source_hash == m.source_hash


def test_mesh_errors_name_the_problem(tmp_path, proc_trimesh):
    with pytest.raises(MeshError, match="not found"):
        load_mesh(tmp_path / "missing.ply")
    (tmp_path / "empty.ply").write_bytes(b"")
    with pytest.raises(MeshError, match="empty"):
        load_mesh(tmp_path / "empty.ply")
    rng = np.random.default_rng(0)
    (tmp_path / "garbage.ply").write_bytes(rng.integers(0, 256, 4096, dtype=np.uint8).tobytes())
    with pytest.raises(MeshError, match="cannot read mesh"):
        load_mesh(tmp_path / "garbage.ply")
    # a valid PLY header followed by too few bytes
    good = proc_trimesh.export(file_type="ply")
    (tmp_path / "truncated.ply").write_bytes(good[: len(good) // 3])
    with pytest.raises(MeshError):
        load_mesh(tmp_path / "truncated.ply")
    (tmp_path / "flat.obj").write_text("v 0 0 0\nv 10 0 0\nv 20 0 0\nf 1 2 3\n")
    with pytest.raises(MeshError, match="zero surface area"):
        load_mesh(tmp_path / "flat.obj")
    (tmp_path / "nan.obj").write_text("v 0 0 0\nv 10 0 nan\nv 10 10 0\nf 1 2 3\n")
    with pytest.raises(MeshError, match="NaN"):
        load_mesh(tmp_path / "nan.obj")
    trimesh.PointCloud(rng.uniform(0, 100, (50, 3))).export(tmp_path / "cloud.ply")
    with pytest.raises(MeshError, match="no (vertices|triangles)"):
        load_mesh(tmp_path / "cloud.ply")
    (tmp_path / "lines.obj").write_text("v 0 0 0\nv 10 0 0\nv 10 10 0\nl 1 2 3\n")
    with pytest.raises(MeshError, match="no (vertices|triangles)"):
        load_mesh(tmp_path / "lines.obj")
    with pytest.raises(MeshError, match="units"):
        load_mesh(tmp_path / "flat.obj", units="furlong")


def test_point_cloud_ply_is_named_as_one(tmp_path):
    """A PLY with vertices but no faces is refused as a point cloud (not as 'no vertices'), naming the file."""
    path = tmp_path / "scan_points.ply"
    trimesh.PointCloud(np.random.default_rng(1).uniform(0, 100, (40, 3))).export(path)
    with pytest.raises(MeshError) as info:
        load_mesh(path)
    msg = str(info.value)
    assert "no triangles" in msg and "point cloud" in msg and "40 vertices" in msg
    assert str(path) in msg
    assert "no vertices" not in msg


@pytest.mark.parametrize("n", [1, 2, 7, 500, 2600])
def test_diameter_is_the_largest_pairwise_distance(n):
    """Hand check against every pair (the Gram-matrix shortcut then an exact re-measure must agree exactly)."""
    from pixie.geometry.mesh import _diameter

    p = np.random.default_rng(n).normal(size=(n, 3)) * [120.0, 30.0, 4.0] + 1e4  # far from the origin
    brute = max(float(np.linalg.norm(p[i:i + 256, None] - p[None], axis=-1).max()) for i in range(0, n, 256))
    assert _diameter(p) == brute


def test_from_arrays_validation():
    v = np.array([[0, 0, 0], [10, 0, 0], [10, 10, 0], [0, 10, 0]], float)
    quads = np.array([[0, 1, 2, 3]])
    with pytest.raises(MeshError, match="triangle"):
        from_arrays(v, quads)
    with pytest.raises(MeshError, match="no triangles"):
        from_arrays(v, np.zeros((0, 3), int))
    with pytest.raises(MeshError, match="outside"):
        from_arrays(v, np.array([[0, 1, 7]]))
    bad = v.copy()
    bad[2, 1] = np.nan
    with pytest.raises(MeshError, match="NaN"):
        from_arrays(bad, np.array([[0, 1, 2]]))
    with pytest.raises(MeshError, match="zero surface area"):
        from_arrays(v, np.array([[0, 1, 1]]))
    m = from_arrays(v, np.array([[0, 1, 2], [0, 2, 3]]))
    assert m.diameter == pytest.approx(np.hypot(10, 10))


def test_units(tmp_path, proc_trimesh, proc_mesh):
    metres = proc_trimesh.copy()
    metres.apply_scale(1e-3)
    path = tmp_path / "part_m.ply"
    metres.export(path)
    with pytest.warns(UserWarning, match="units"):
        m = load_mesh(path, units="mm")
    assert m.diameter == pytest.approx(proc_mesh.diameter * 1e-3, rel=1e-6)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # 'auto' converts silently
        auto = load_mesh(path, units="auto")
        explicit = load_mesh(path, units="m")
    assert auto.diameter == pytest.approx(proc_mesh.diameter, rel=1e-6)
    assert explicit.diameter == pytest.approx(proc_mesh.diameter, rel=1e-6)
    # a mesh already in mm is left alone by 'auto'
    proc_trimesh.export(tmp_path / "part_mm.ply")
    assert load_mesh(tmp_path / "part_mm.ply", units="auto").diameter == pytest.approx(proc_mesh.diameter)


def test_empty_crop_bbox_is_an_image_error():
    with pytest.raises(ImageError, match="empty crop"):
        check_bbox((10, 10, 0, 20), (480, 640))
    with pytest.raises(ImageError, match="empty crop"):
        check_bbox((700, 10, 50, 50), (480, 640))  # entirely right of the image
    with pytest.raises(ImageError, match="empty crop"):
        check_bbox((-100, -100, 50, 50), (480, 640))
    with pytest.raises(ImageError):
        check_bbox((1, 2, 3), (480, 640))
    with pytest.raises(ImageError):
        check_bbox((np.nan, 2, 3, 4), (480, 640))
    np.testing.assert_allclose(check_bbox((-10, 5, 100, 1000), (480, 640)), [0, 5, 90, 480])


# ------------------------------------------------------------------------ pixie.geometry.rotations helpers


def test_orthonormalize():
    rng = np.random.default_rng(0)
    T = np.eye(4)
    T[:3, :3] += rng.normal(0, 1e-3, (3, 3))
    T[:3, 3] = [1, 2, 3]
    U = orthonormalize(T)
    np.testing.assert_allclose(U[:3, :3] @ U[:3, :3].T, np.eye(3), atol=1e-12)
    assert np.linalg.det(U[:3, :3]) == pytest.approx(1.0)
    np.testing.assert_array_equal(U[:3, 3], [1, 2, 3])


def test_rodrigues_matches_opencv_and_rotation_between_maps_a_onto_b():
    rng = np.random.default_rng(1)
    for _ in range(5):
        axis, angle = rng.normal(size=3), rng.uniform(-np.pi, np.pi)
        np.testing.assert_allclose(rodrigues(3.0 * axis, angle),
                                   cv2.Rodrigues(angle * axis / np.linalg.norm(axis))[0], atol=1e-12)
        a, b = (v / np.linalg.norm(v) for v in rng.normal(size=(2, 3)))
        R = rotation_between(a, b)
        np.testing.assert_allclose(R @ a, b, atol=1e-12)
        np.testing.assert_allclose(R @ np.cross(a, b), np.cross(a, b), atol=1e-12)  # turns about a x b only
        assert np.linalg.det(R) == pytest.approx(1.0)
    np.testing.assert_allclose(rotation_between(a, a), np.eye(3), atol=1e-12)


def test_nearest_pixel_rounds_and_clips():
    kp = np.array([[0.49, 0.51], [-3.0, 9.7], [4.5, 2.0], [5.5, 1.49]])
    cols, rows = nearest_pixel(kp, (10, 5))
    np.testing.assert_array_equal(cols, [0, 0, 4, 4])  # 4.5 and 5.5 round to even, then clip to w - 1
    np.testing.assert_array_equal(rows, [1, 9, 2, 1])
    img = np.arange(50).reshape(10, 5)
    np.testing.assert_array_equal(lookup(img, kp), img[rows, cols])


def test_check_image_is_one_rule_for_every_input():
    grey = np.arange(64, dtype=np.uint8).reshape(8, 8)
    rgb = check_image(grey)
    assert rgb.shape == (8, 8, 3) and rgb.flags.c_contiguous and np.all(rgb[..., 2] == grey)
    rgba = np.dstack([rgb, np.full((8, 8), 9, np.uint8)])
    np.testing.assert_array_equal(check_image(rgba), rgb)  # alpha dropped
    np.testing.assert_array_equal(check_image(grey[..., None]), rgb)
    with pytest.raises(ImageError, match="query image is empty or too small"):
        check_image(rgb[:4], "query image", min_side=8)
    for bad, msg in ((rgb.astype(np.float32), "uint8"), (np.zeros((8, 8, 2), np.uint8), "shape"), ([[1]], "numpy")):
        with pytest.raises(ImageError, match=msg):
            check_image(bad)
    assert check_mask(None, (8, 8)) is None
    assert check_mask(np.ones((8, 8), np.uint8), (8, 8)).dtype == bool
    with pytest.raises(ImageError, match="does not match"):
        check_mask(np.ones((4, 8), bool), (8, 8))
