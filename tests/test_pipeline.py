"""The whole pipeline: PoseEstimator on rendered queries with a known pose, and on real LM-O photos."""

from __future__ import annotations

import copy
import os

import numpy as np
import pytest

from pixie.geometry.camera import make_K, optical_axis_in_object
from pixie.config import PixieConfig, RefsConfig
from pixie.references.encode import encode
from pixie.errors import CameraError, ImageError
from pixie.pipeline.estimator import PoseEstimator
from pixie.geometry.render import Renderer
from pixie.app.runner import make_matcher
from pixie.references.views import max_angular_gap_deg

from conftest import TIMING_KEYS, check_result  # noqa: F401
from pixie.synth.e2e import E2E_POSES, H, K_Q, W, e2e_config, generic_pose, pose_errors, render_photo  # noqa: F401

pytestmark = pytest.mark.usefixtures("one_torch_thread")

QUERY_POSES = E2E_POSES[:4]  # test_estimator's poses (tests/test_estimator.py QUERY_POSES)


@pytest.fixture(scope="session")
def e2e(query_e2e):
    """The shipped default path (conftest ``query_e2e``): roll-0 reference features, the query crop rotated."""
    return query_e2e


# ------------------------------------------------------------------------------- rendered queries


@pytest.mark.slow
def test_encoded_render_at_a_reference_view_gives_its_pose(e2e, proc_mesh):
    """Geometry of crop → match → lift → PnP: a query that IS a reference encoding, seen from closer. The edge
    alignment is off here: an encoding is not a photo (its drawn edge lines give every contour a second, inner edge,
    which since session 12's alignment, the box at the coarsest scale only, pulled view 10's depth 3.8 % off)."""
    refs, cfg, matcher = e2e
    est = PoseEstimator(refs, copy.deepcopy(cfg).apply_overrides(["align.enabled=false"]), matcher=matcher)
    r_ = Renderer(proc_mesh, smooth_normals=refs.config.smooth_normals)
    for v in (10, 30):
        T = refs.poses[v, 0].copy()
        T[:3, 3] *= 3.0 * proc_mesh.diameter / np.linalg.norm(T[:3, 3])
        r = r_.render(T, K_Q, H, W)
        img = np.repeat(encode("shade3_edges", r.depth, r.normals, r.mask)[..., None], 3, axis=2)
        ys, xs = np.nonzero(r.mask)
        res = est.estimate(img, K_Q, bbox=(xs.min(), ys.min(), np.ptp(xs) + 1, np.ptp(ys) + 1))
        check_result(res)
        rot, trans = pose_errors(res.T_cam_from_obj, T, proc_mesh.diameter)
        assert rot < 2.0 and trans < 0.03, f"view {v}: {rot:.2f} deg, {100 * trans:.1f}% of the diameter"
        assert not res.failed



@pytest.fixture(scope="module")
def e2e_results(e2e, proc_mesh):
    """(rotation error deg, translation error / diameter, result) of the rendered photo at each pose."""
    refs, cfg, matcher = e2e
    est = PoseEstimator(refs, cfg, matcher=matcher)
    out = []
    for i, (az, el, rl) in enumerate(E2E_POSES):
        if i < len(QUERY_POSES):  # the first poses: test_estimator's (the same estimator and photos)
            continue
        T = generic_pose(proc_mesh, az, el, rl)
        img, bbox, _ = render_photo(proc_mesh, T, K_Q, seed=i)
        res = est.estimate(img, K_Q, bbox=bbox)
        check_result(res)
        out.append((*pose_errors(res.T_cam_from_obj, T, proc_mesh.diameter), res))
    print("end-to-end errors:", [f"{r:.1f} deg / {100 * t:.1f}%" for r, t, _ in out])
    return out


@pytest.mark.slow
def test_end_to_end_rendered_photo(e2e_results):
    """The issue's bar (< 5 deg and < 5 % of the diameter) on textured, shaded renders at generic poses.

    A 46-view set at 256 px is a modest reference set. On the shipped default path (roll-0 features, rotated
    query, edge alignment) all 14 poses were within the bar in session 9 (median 0.45 deg, worst 3.1 deg / 1.4 %),
    and all 10 of this test's in session 36 (median 0.2 deg, worst 0.8 deg / 1.3 %; the fixture had run the
    render-at-estimate refinement, which the default preset does not, until then);
    the matcher-only pipeline before the alignment had 25 of 28 (bench/e2e_margin.py). The first 4 poses are
    test_estimator's (the same estimator and photos); this test takes the other 10. The bar stays on the
    distribution, with margin for single poses that move between library versions and machines: at least 7 of
    the 10 within 5 deg / 5 % and a median rotation error under 3.5 deg.
    """
    within = [rot < 5.0 and tr < 0.05 for rot, tr, _ in e2e_results]
    errs = [(pose, f"{rot:.2f} deg", f"{100 * tr:.1f}%") for pose, (rot, tr, _) in zip(E2E_POSES[len(QUERY_POSES):],
                                                                                       e2e_results)]
    assert sum(within) >= 7, f"only {sum(within)} of {len(within)} poses within 5 deg / 5 %: {errs}"
    assert np.median([rot for rot, _, _ in e2e_results]) < 3.5, errs


@pytest.mark.slow
def test_end_to_end_finds_the_pose_basin(e2e, e2e_results):
    """Not the issue's bar: with modest references nearly every pose is at least as close as the nearest
    reference view can be (the set's covering radius), and not far off in distance. A 46-view set flipped
    about one photo in ten before the alignment (bench/e2e_margin.py: 2 of 28), so at least 8 of these 10."""
    refs, cfg, _ = e2e
    if cfg.match.matcher == "sift-nn":
        pytest.skip("SIFT does not bridge photo texture and shaded renders (measured 105-128 deg errors)")
    radius = max_angular_gap_deg(np.array([optical_axis_in_object(T) for T in refs.poses[:, 0]]))
    in_basin = [rot < radius and tr < 0.15 and not res.failed and res.n_inliers >= 20
                for rot, tr, res in e2e_results]
    assert sum(in_basin) >= 8, [(p, f"{r:.1f} deg", f"{100 * t:.1f}%")
                                for p, (r, t, _) in zip(E2E_POSES[len(QUERY_POSES):], e2e_results)]


@pytest.mark.slow
@pytest.mark.skipif(not os.environ.get("PIXIE_DENSE_E2E"), reason="about 3 CPU-minutes: set PIXIE_DENSE_E2E=1")
def test_end_to_end_dense_references(proc_mesh, matcher_name, build_refs):
    """The issue's bar with the default view density (6 + 115 views, 8 rolls) at size 256."""
    cfg = e2e_config(matcher_name)
    cfg.refs.n_fibonacci = 115
    matcher = make_matcher(cfg)
    est = PoseEstimator(build_refs(proc_mesh, cfg.refs, matcher=matcher), cfg, matcher=matcher)
    poses = E2E_POSES
    errs = []
    for i, (az, el, rl) in enumerate(poses):
        T = generic_pose(proc_mesh, az, el, rl)
        img, bbox, _ = render_photo(proc_mesh, T, K_Q, seed=i)
        res = est.estimate(img, K_Q, bbox=bbox)
        check_result(res)
        errs.append(pose_errors(res.T_cam_from_obj, T, proc_mesh.diameter))
    print("dense end-to-end errors:", [f"{r:.1f} deg / {100 * t:.1f}%" for r, t in errs])
    assert all(r < 5.0 and t < 0.05 for r, t in errs), errs


def test_estimator_input_errors(e2e, proc_mesh):
    refs, cfg, matcher = e2e
    est = PoseEstimator(refs, cfg, matcher=matcher)
    img = np.zeros((H, W, 3), np.uint8)
    with pytest.raises(ImageError, match="empty crop"):
        est.estimate(img, K_Q, bbox=(700, 10, 40, 40))
    with pytest.raises(ImageError, match="empty"):
        est.estimate(img, K_Q, mask=np.zeros((H, W), bool))
    with pytest.raises(ImageError, match="uint8"):
        est.estimate(img.astype(np.float32), K_Q, bbox=(10, 10, 40, 40))
    with pytest.raises(CameraError, match="focal"):
        est.estimate(img, make_K(0.0, 600.0, 320.0, 240.0), bbox=(10, 10, 40, 40))
    with pytest.raises(CameraError, match="principal point"):
        est.estimate(img, make_K(600.0, 600.0, 1000.0, 240.0), bbox=(10, 10, 40, 40))


# ------------------------------------------------------------------------------------- real LM-O

LMO_OBJECTS = (1, 5, 8)


@pytest.fixture(scope="session")
def lmo_setup(lmo_dataset, lmo_meshes, matcher_name, build_refs):
    """Small reference sets of LM-O objects 1, 5, 8 and one well-visible target image of each."""
    cfg = PixieConfig()
    cfg.refs = RefsConfig(n_fibonacci=10, rotations=4, size=128, encodings=["shade3_edges"])
    cfg.match.matcher = matcher_name
    matcher = make_matcher(cfg)
    targets = {}
    for t in lmo_dataset.targets():
        if t.obj_id in LMO_OBJECTS and t.obj_id not in targets:
            inst = [g for g in lmo_dataset.instances(t.scene_id, t.im_id) if g.obj_id == t.obj_id]
            if inst and inst[0].visib_fract is not None and inst[0].visib_fract > 0.8:
                targets[t.obj_id] = (t, inst[0])
    assert set(targets) == set(LMO_OBJECTS)
    ests = {o: PoseEstimator(build_refs(lmo_meshes[o], cfg.refs, matcher=matcher), cfg, matcher=matcher)
            for o in LMO_OBJECTS}
    return ests, targets


@pytest.mark.slow
@pytest.mark.parametrize("obj_id", LMO_OBJECTS)
def test_real_lmo_images(lmo_setup, lmo_dataset, obj_id):
    ests, targets = lmo_setup
    t, gt = targets[obj_id]
    img = lmo_dataset.load_rgb(t.scene_id, t.im_id)
    K = lmo_dataset.camera(t.scene_id, t.im_id).K
    res = ests[obj_id].estimate(img, K, bbox=gt.box_visib)
    check_result(res)
    assert res.n_inliers >= 0 and isinstance(res.failed, bool)
    # the pose puts the object in front of the camera, roughly where the box is
    c = res.T_cam_from_obj[:3, 3]
    assert c[2] > 0
    # (no accuracy bar with such small reference sets; the errors are reported for information)
    rot, trans = pose_errors(res.T_cam_from_obj, gt.T_cam_from_obj, ests[obj_id].refs.mesh.diameter)
    print(f"obj {obj_id} scene {t.scene_id} im {t.im_id}: {rot:.1f} deg, {100 * trans:.0f}% d, "
          f"timings { {k: round(v, 3) for k, v in res.timings.items()} }")


def test_a_box_alone_is_segmented_when_asked_and_the_mask_reaches_the_shape_and_alignment_stages(e2e, proc_mesh):
    """``query.segment=grabcut``: a box without a mask gets the object's pixels by colour; the query keeps them as
    it keeps a given mask (keypoints, the edge templates' response maps, the alignment's visible region)."""
    refs, cfg, matcher = e2e
    T = generic_pose(proc_mesh, 40.0, 30.0, 20.0)
    img, bbox, true_mask = render_photo(proc_mesh, T, K_Q, seed=5)
    c = copy.deepcopy(cfg)
    c.query.segment = "grabcut"
    c.shape.use_mask = True
    q = PoseEstimator(refs, c, matcher=matcher).prepare(img, K_Q, bbox=bbox)
    assert q.box_source == "bbox" and q.mask is not None
    iou = (q.mask & true_mask).sum() / (q.mask | true_mask).sum()
    x, y, w, h = bbox
    box_iou = true_mask.sum() / (w * h)
    assert iou > 0.85 and iou > box_iou + 0.1
    plain = PoseEstimator(refs, cfg, matcher=matcher).prepare(img, K_Q, bbox=bbox)
    assert plain.mask is None  # the default keeps the box alone
