"""Contour templates (pixie.references.templates) and the edge cue (pixie.cues.edges): geometry round trips, retrieval on
rendered photos of an asymmetric CAD-like part with random colours over clutter, and a real LM-O photo."""

from __future__ import annotations

import numpy as np
import pytest

from pixie.geometry.camera import make_K, project, transform_points
from pixie.references.templates import CREASE, SILHOUETTE, _edge_map_full, build_templates, edge_map
from pixie.cues.edges import prepare_query, quantised_orientations, search, template_bank
from pixie.pipeline.query import bbox_from_mask, check_bbox
from pixie.geometry.render import Renderer

K = make_K(600.0, 600.0, 319.5, 239.5)
H, W = 480, 640


@pytest.fixture(scope="module")
def proc_templates(proc_mesh):
    return build_templates(proc_mesh, n_views=240, size=96, renderer=Renderer(proc_mesh))


@pytest.mark.parametrize("seed,offset_px", [(1, 0.0), (2, 200.0)])
def test_edge_map_on_the_mask_box_equals_the_whole_image(proc_mesh, make_pose, seed, offset_px):
    """edge_map computes only the mask's box + margin: silhouettes, creases and strengths are those of the whole
    image, orientations agree to float rounding (OpenCV's vector / scalar filter paths), nothing outside the box."""
    T = make_pose(proc_mesh, seed, distance_factor=3.0, offset_px=offset_px, K=K)
    r = Renderer(proc_mesh).render(T, K, H, W)
    assert 500 < r.mask.sum() < 0.5 * H * W
    box = edge_map(r.depth, r.normals)
    full = _edge_map_full(r.depth, r.normals, 35.0, 0.03)
    for a, b in zip(box[:2], full[:2]):
        assert a.sum() > 50 and np.array_equal(a, b)
    on = box[0] | box[1]
    assert np.abs(box[2] - full[2])[on].max() < 1e-4
    assert np.array_equal(box[3], full[3])


def _centred_rotation(T, centre):
    """GT rotation seen by a camera turned to look at the object centre (the templates' convention)."""
    c = T[:3, :3] @ centre + T[:3, 3]
    a = c / np.linalg.norm(c)
    v, cos = np.cross(a, [0.0, 0.0, 1.0]), float(a[2])
    vx = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])
    return (np.eye(3) + vx + vx @ vx / (1.0 + cos)) @ T[:3, :3]


def test_rolled_points_are_the_projections_of_their_object_points(proc_templates):
    """Rolling a view's points in 2D equals projecting their 3D points with the rolled camera."""
    tpl = proc_templates
    angles = np.radians([0.0, 35.0, 190.0])
    xy, ori, boxes = tpl.rolled(angles)
    for v in (0, 77, 200):
        ok = tpl.valid[v]
        assert ok.sum() > 40 and (tpl.kind[v][ok] == SILHOUETTE).sum() > 30
        for j, a in enumerate(angles):
            uv = project(tpl.K, transform_points(tpl.pose(v, a), tpl.xyz[v][ok].astype(np.float64)))
            np.testing.assert_allclose(uv - tpl.K[:2, 2], xy[v, j][ok], atol=0.02)
            assert np.all((ori[v, j] >= 0) & (ori[v, j] < np.pi))
    # the part has creases: most views keep some crease points
    assert np.mean((tpl.kind == CREASE).sum(axis=1) > 5) > 0.8
    # the outline polygon is dense: rolled boxes contain every rolled point to a pixel
    assert np.all(xy[..., 0] >= boxes[..., None, 0] - 1.0) and np.all(xy[..., 0] <= boxes[..., None, 2] + 1.0)
    assert np.all(xy[..., 1] >= boxes[..., None, 1] - 1.0) and np.all(xy[..., 1] <= boxes[..., None, 3] + 1.0)


def test_orientation_bins_follow_the_edge_normal():
    """A vertical step edge gives horizontal gradients (bin 0), a horizontal one vertical gradients (bin 4)."""
    img = np.zeros((40, 40, 3), np.uint8)
    img[:, 20:] = (200, 30, 30)
    bins, _ = quantised_orientations(img)
    assert set(np.unique(bins[5:35, 18:22])) - {255} == {0}
    bins_t, _ = quantised_orientations(np.ascontiguousarray(img.transpose(1, 0, 2)))
    assert set(np.unique(bins_t[18:22, 5:35])) - {255} == {4}
    assert np.all(bins[:, :15] == 255)  # flat areas carry no orientation


def test_edge_search_ranks_a_view_near_the_truth_first(proc_mesh, proc_templates):
    """Photos of the part (random colour, lights, cluttered background): the best-scoring template is within 15°."""
    from pixie.synth.photo import Material, random_background, render_rgb

    from conftest import pose_facing

    ren = Renderer(proc_mesh)
    bank = template_bank(proc_templates, n_rolls=36)
    errs = []
    for seed in range(10):
        rng = np.random.default_rng(seed)
        T = pose_facing(proc_mesh, rng, distance_factor=5.0, offset_px=120, K=K)
        photo = render_rgb([ren], [T], K, H, W, [Material.random(rng)], rng,
                           background=random_background(H, W, rng, "clutter"))
        box = check_bbox(bbox_from_mask(photo.masks[0]), (H, W))
        scores, info = search(bank, prepare_query(photo.rgb, box))
        v, a = np.unravel_index(np.argmax(scores), scores.shape)
        R_t = proc_templates.pose(info["views"][v], info["angles"][a])[:3, :3]
        R_c = _centred_rotation(T, proc_mesh.center)
        errs.append(np.degrees(np.arccos(np.clip((np.trace(R_t.T @ R_c) - 1) / 2, -1, 1))))
    errs = np.array(errs)
    print("top-1 errors", errs.round(1))
    assert np.sum(errs < 15.0) >= 9, errs.round(1)


def test_edge_search_on_a_real_lmo_photo(lmo_dataset):
    """On LM-O every score is finite and in [0, 1], and placements are inside the crop."""
    from pixie.geometry.mesh import load_mesh

    t = next(t for t in lmo_dataset.targets() if t.obj_id == 5)
    g = max((g for g in lmo_dataset.instances(t.scene_id, t.im_id) if g.obj_id == 5), key=lambda g: g.visib_fract)
    img = lmo_dataset.load_rgb(t.scene_id, t.im_id)
    mesh = load_mesh(lmo_dataset.model_path(5))
    tpl = build_templates(mesh, n_views=60, size=96)
    q = prepare_query(img, check_bbox(g.box_visib, img.shape[:2]))
    scores, info = search(template_bank(tpl, n_rolls=12), q)
    assert scores.shape == (60, 12) and np.all(np.isfinite(scores))
    assert scores.min() >= 0 and scores.max() <= 1 and scores.max() > 0.5
    size = q.crop.image.shape[0]
    assert np.all((info["origin"] > 0) & (info["origin"] < size))


def test_templates_are_stored_with_the_reference_set(proc_mesh, tmp_path):
    """Templates kept in a reference set survive save/load exactly; a set without them loads None."""
    from pixie.config import RefsConfig
    from pixie.references.set import build_reference_set
    from pixie.references.store import load_reference_set, save_reference_set

    refs = build_reference_set(proc_mesh, RefsConfig(n_fibonacci=2, rotations=1, size=64, encodings=["depth"]))
    save_reference_set(refs, tmp_path / "plain.npz")
    assert load_reference_set(tmp_path / "plain.npz").templates is None
    from pixie.references.templates import ContourTemplates

    tpl = build_templates(proc_mesh, n_views=10, size=64, n_points=32)
    refs.templates = tpl.to_arrays()
    back = ContourTemplates.from_arrays(load_reference_set(save_reference_set(refs, tmp_path / "with.npz")).templates)
    for k, v in tpl.to_arrays().items():
        np.testing.assert_array_equal(np.asarray(getattr(back, k)), v)
    assert back.size == 64 and back.n_views == 10 and back.n_points == 32


def test_an_object_mask_leaves_the_clutters_edges_out_of_the_response_maps():
    """With a mask, only the photo's edges within ``mask_grow_px`` crop px of it answer a template; without one the
    clutter beside the object answers too."""
    img = np.full((H, W, 3), 40, np.uint8)
    img[200:280, 300:380] = 200  # the object: an 80 px square
    img[150:330, 283:286] = 230  # clutter: a bar 14 px left of it (~11 crop px), inside the crop around the box
    obj = np.zeros((H, W), bool)
    obj[200:280, 300:380] = True
    box = np.array([300.0, 200.0, 380.0, 280.0])
    plain = prepare_query(img, box)
    masked = prepare_query(img, box, mask=obj, mask_grow_px=5)

    def at(q, x, y):  # crop-pixel edges within 2 px of a photo point (inside the crop)
        c = np.linalg.solve(np.vstack([q.crop.A, [0, 0, 1]]), [x, y, 1.0])[:2]
        cx, cy = int(round(c[0])), int(round(c[1]))
        assert 2 <= cx < q.bins.shape[1] - 2 and 2 <= cy < q.bins.shape[0] - 2
        return q.bins[cy - 2:cy + 3, cx - 2:cx + 3] < 255

    assert at(plain, 283, 240).any() and not at(masked, 283, 240).any()  # the clutter's edge is gone
    assert at(plain, 300, 240).any() and at(masked, 300, 240).any()  # the object's own edge stays
    assert at(masked, 340, 200).any() and at(masked, 379, 260).any()
    assert masked.resp.max() > 0 and (masked.bins < 255).sum() < (plain.bins < 255).sum()
