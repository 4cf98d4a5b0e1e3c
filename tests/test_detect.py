"""Finding the object without a box: LINE-2D proposals (pixie.cues.detect) verified by the pose (pixie.pipeline.find)."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest
import trimesh

from pixie.cues.detect import TemplateDetector, linemod_available, template_region
from pixie.cues.region import colour_index
from pixie.errors import PixieError
from pixie.geometry.camera import make_K, make_T, rotation_angle_deg
from pixie.geometry.mesh import from_arrays
from pixie.geometry.render import Renderer
from pixie.pipeline.estimator import PoseEstimator
from pixie.pipeline.find import find_objects
from pixie.pose.solve import box_iou, projected_box
from pixie.references.templates import ContourTemplates
from pixie.synth.photo import Material, random_background, render_rgb
from pixie.viz import save_png

from conftest import pose_facing, run_cli

pytestmark = [pytest.mark.usefixtures("one_torch_thread"),
              pytest.mark.skipif(not linemod_available(), reason="OpenCV without contrib (cv2.linemod)")]

K = make_K(600.0, 605.0, 321.5, 238.0)
K_ARG = "600,605,321.5,238"


@pytest.fixture(scope="module")
def scene_parts(proc_mesh):
    b = trimesh.creation.box(extents=[60.0, 45.0, 35.0])
    return Renderer(proc_mesh), Renderer(from_arrays(np.asarray(b.vertices), np.asarray(b.faces), name="box"))


def scene(proc_mesh, parts, seed: int, with_part: bool = True):
    """640 x 480: the part 3.5-5.5 diameters away, two box distractors beside it, a cluttered background."""
    ren, box = parts
    rng = np.random.default_rng(seed)
    T = pose_facing(proc_mesh, rng, 3.5 + rng.uniform(0, 2), 0.0, K)
    c = T[:3, 3]
    d1 = make_T(cv2.Rodrigues(rng.normal(size=3))[0], c + [-190.0, 40.0, 50.0])
    d2 = make_T(cv2.Rodrigues(rng.normal(size=3))[0], c + [180.0, -30.0, 30.0])
    rens, poses = ([ren] if with_part else []) + [box, box], ([T] if with_part else []) + [d1, d2]
    ph = render_rgb(rens, poses, K, 480, 640, [Material.random(rng) for _ in rens], rng,
                    background=random_background(480, 640, rng), shadows=False)
    return ph.rgb, T


@pytest.fixture(scope="module")
def line2d_cache(tmp_path_factory):
    """A user cache (``$XDG_CACHE_HOME``) shared by this module's API and CLI calls: templates written once."""
    return tmp_path_factory.mktemp("xdg")


@pytest.fixture(scope="module")
def query_est(query_e2e):
    refs, cfg, matcher = query_e2e
    return PoseEstimator(refs, cfg, matcher=matcher)


def distance(proc_mesh):
    return (3.3 * proc_mesh.diameter, 5.8 * proc_mesh.diameter)


def test_proposals_find_the_part_among_distractors_and_clutter(query_est, proc_mesh, scene_parts, line2d_cache):
    """Measured (these 4 seeds, session 9): the part's box is the best proposal in 3 of 4 scenes (IoU 0.78-0.93)
    and among the best 3 in 4 of 4; asserted with one scene of margin."""
    det = TemplateDetector(ContourTemplates.from_arrays(query_est.refs.templates), K, proc_mesh.diameter,
                           distance_mm=distance(proc_mesh), cache_dir=line2d_cache / "pixie" / "line2d")
    best, top3 = 0, 0
    for seed in range(4):
        img, T = scene(proc_mesh, scene_parts, seed)
        props = det.propose(img, top_k=3)
        gt = projected_box(T, K, proc_mesh.hull_vertices)
        ious = [box_iou(p.box_xyxy, gt) for p in props]
        best += bool(ious and ious[0] >= 0.7)
        top3 += max(ious, default=0.0) >= 0.7
    assert best >= 2 and top3 >= 3, (best, top3)


def test_template_region_tells_an_object_region_from_background():
    """template_region: a silhouette on a region whose colours differ from its surroundings separates (near 1); the
    same silhouette moved onto uniform texture does not (near 0.5); an empty one is 0.5 (no evidence)."""
    rng = np.random.default_rng(3)
    img = rng.integers(0, 256, (240, 320, 3), dtype=np.uint8)  # random-colour background: every colour everywhere
    yy, xx = np.mgrid[:240, :320]
    disc = (yy - 120) ** 2 + (xx - 100) ** 2 < 40 ** 2
    img[disc] = (200, 30, 30)
    idx = colour_index(img, 3)
    on = template_region(idx, disc)
    off = template_region(idx, np.roll(disc, 150, axis=1))  # the same shape on background only
    assert on > 0.9 and abs(off - 0.5) < 0.1, (on, off)
    assert template_region(idx, np.zeros_like(disc)) == 0.5


def test_region_weight_needs_the_renderer_and_orders_by_the_sum(query_est, proc_mesh, scene_parts, line2d_cache):
    """propose(region_weight > 0) without a renderer is a clear error; with one, the pooled proposals carry their
    region and the order is LINE-2D + vote + region terms (every returned rank_score is that sum, best first), and
    the part's box is found (the scenes of the test above; measured, session 22: the best proposal in 4 of 4, IoU
    0.79-0.93, its region 0.85-0.93; without the region term 3 of 4). Asserted with one scene of margin."""
    tpl = ContourTemplates.from_arrays(query_est.refs.templates)
    kw = dict(distance_mm=distance(proc_mesh), cache_dir=line2d_cache / "pixie" / "line2d")
    img, T = scene(proc_mesh, scene_parts, 0)
    with pytest.raises(PixieError, match="renderer"):
        TemplateDetector(tpl, K, proc_mesh.diameter, **kw).propose(img, region_weight=0.5)
    det = TemplateDetector(tpl, K, proc_mesh.diameter, renderer=scene_parts[0], **kw)
    best = top3 = 0
    for seed in range(4):
        img, T = scene(proc_mesh, scene_parts, seed)
        props = det.propose(img, top_k=3, region_weight=0.5, region_pool=20)
        assert all(0.0 <= p.region <= 1.0 for p in props)
        ranks = [p.score + 3.0 * p.votes + 0.5 * 100 * (p.region - 0.5) for p in props]
        assert np.allclose(ranks, [p.rank_score for p in props]) and ranks == sorted(ranks, reverse=True)
        gt = projected_box(T, K, proc_mesh.hull_vertices)
        ious = [box_iou(p.box_xyxy, gt) for p in props]
        best += ious[0] >= 0.7
        top3 += max(ious) >= 0.7
    assert best >= 3 and top3 >= 3, (best, top3)


def test_a_proposal_stands_for_its_pose(query_est, proc_mesh, scene_parts, line2d_cache):
    """TemplateDetector.pose: the pose a proposal's template stands for projects onto the proposal's own box, and for
    a proposal on the part it is a coarse start near the truth (views, rolls and scales are steps apart); aligned from
    it (estimate_from_prior), the part's pose is found. Measured (these 4 seeds, session 14): 4 proposals on the part,
    3 of them 6–11° / 4–17 % depth off, aligned to 0.35–0.59°; the fourth a silhouette twin 142° off. Asserted with
    one proposal of margin."""
    det = TemplateDetector(ContourTemplates.from_arrays(query_est.refs.templates), K, proc_mesh.diameter,
                           distance_mm=distance(proc_mesh), cache_dir=line2d_cache / "pixie" / "line2d")
    rot, dz, aligned = [], [], []
    for seed in range(4):
        img, T = scene(proc_mesh, scene_parts, seed)
        gt = projected_box(T, K, proc_mesh.hull_vertices)
        for p in det.propose(img, top_k=3):
            T0 = det.pose(p, K, proc_mesh.center, proc_mesh.hull_vertices)
            assert box_iou(projected_box(T0, K, proc_mesh.hull_vertices), p.box_xyxy) > 0.8
            if box_iou(p.box_xyxy, gt) >= 0.7:
                rot.append(rotation_angle_deg(T0[:3, :3], T[:3, :3]))
                dz.append(abs(T0[2, 3] / T[2, 3] - 1))
                res = query_est.estimate_from_prior(img, K, T0)
                aligned.append(rotation_angle_deg(res.T_cam_from_obj[:3, :3], T[:3, :3]))
    print(rot, dz, aligned)
    near = np.array(rot) < 15.0
    assert len(rot) >= 3 and near.sum() >= 2 and np.median(np.array(dz)[near]) < 0.1, (rot, dz)
    assert np.median(np.array(aligned)[near]) < 3.0, aligned


def test_find_gives_the_pose_or_not_found(query_est, proc_mesh, scene_parts, line2d_cache):
    img, T = scene(proc_mesh, scene_parts, 1)
    kw = dict(top_k=1, distance_mm=distance(proc_mesh), cache_dir=line2d_cache / "pixie" / "line2d")
    fr = find_objects(query_est, img, K, **kw)
    assert fr.found and len(fr.poses) == 1 and fr.verdicts == ["kept"]
    R = fr.poses[0].T_cam_from_obj
    assert rotation_angle_deg(R[:3, :3], T[:3, :3]) < 5.0 and abs(R[2, 3] / T[2, 3] - 1) < 0.05  # measured 1.3° / 3.2 %
    empty, _ = scene(proc_mesh, scene_parts, 9, with_part=False)
    none = find_objects(query_est, empty, K, **kw)
    assert not none.found and none.poses == [] and all(v.startswith("rejected") for v in none.verdicts)
    assert json.loads(json.dumps(none.to_dict()))["found"] is False


def test_find_stops_once_a_confident_pose_is_kept(query_est, proc_mesh, scene_parts, line2d_cache):
    """stop_confidence: the proposals after a pose kept at that confidence are listed but not estimated (seed 1: its
    best proposal is kept, see the test above)."""
    img, _ = scene(proc_mesh, scene_parts, 1)
    kw = dict(top_k=3, distance_mm=distance(proc_mesh), cache_dir=line2d_cache / "pixie" / "line2d")
    fr = find_objects(query_est, img, K, stop_confidence=0.5, **kw)
    assert fr.found and fr.verdicts[0] == "kept" and fr.poses[0].confidence >= 0.5
    assert len(fr.proposals) == 3 and all(v.startswith("not estimated") for v in fr.verdicts[1:]), fr.verdicts


def test_cli_detect_writes_found_false_and_exits_0(query_est, proc_mesh, scene_parts, line2d_cache, tmp_path,
                                                   monkeypatch):
    from pixie.references.store import save_reference_set

    refs = save_reference_set(query_est.refs, tmp_path / "part.npz")
    empty, _ = scene(proc_mesh, scene_parts, 9, with_part=False)
    save_png(tmp_path / "photo.png", empty)
    monkeypatch.setenv("XDG_CACHE_HOME", str(line2d_cache))
    lo, hi = distance(proc_mesh)
    code, out, err = run_cli("estimate", "--refs", str(refs), "--image", str(tmp_path / "photo.png"), "--K", K_ARG,
                             "--detect", "--distance", f"{lo:.0f},{hi:.0f}", "--proposals", "1", "-o",
                             str(tmp_path / "r.json"), "--overlay", str(tmp_path / "o.png"))
    assert code == 0, err
    rec = json.loads((tmp_path / "r.json").read_text())
    assert rec["found"] is False and rec["T_cam_from_obj"] is None and len(rec["detection"]["proposals"]) == 1
    assert "not found" in out and (tmp_path / "o.png").is_file()
    code, _, err = run_cli("estimate", "--refs", str(refs), "--image", str(tmp_path / "photo.png"), "--K", K_ARG,
                           "--detect", "--bbox", "1,1,5,5")
    assert code == 2 and "drop --bbox" in err


def two_copies(proc_mesh, parts, seed: int):
    """640 x 480: two copies of the part side by side (different rotations and distances), one box distractor
    between them, a cluttered background."""
    ren, box = parts
    rng = np.random.default_rng(100 + seed)
    Ts = []
    for side in (-1.0, 1.0):
        T = pose_facing(proc_mesh, rng, 3.8 + rng.uniform(0, 1.2), 0.0, K)
        T[0, 3] += side * 0.33 * T[2, 3]  # ~200 px left / right of the centre
        Ts.append(T)
    d = make_T(cv2.Rodrigues(rng.normal(size=3))[0], np.array([0.0, 0.3, 1.0]) * Ts[0][2, 3] * 1.1)
    rens, poses = [ren, ren, box], Ts + [d]
    ph = render_rgb(rens, poses, K, 480, 640, [Material.random(rng) for _ in rens], rng,
                    background=random_background(480, 640, rng), shadows=False)
    return ph.rgb, Ts


def test_two_instances_give_two_poses(query_est, proc_mesh, scene_parts, line2d_cache):
    """Several instances: each round fills in the instances found so far and searches the photo again. Measured on
    seeds 0-4 with the shipped default (session 36, no render-at-estimate refinement): both copies found in 5 of 5,
    10 of the 10 copies within 15° / 10 % (session 11, with the refinement: both in 3, 8 of 10). Three seeds are
    run, asserted with one scene's and one copy's margin."""
    kw = dict(top_k=2, max_instances=2, distance_mm=distance(proc_mesh), cache_dir=line2d_cache / "pixie" / "line2d")
    both, right = 0, 0
    for seed in range(3):
        img, Ts = two_copies(proc_mesh, scene_parts, seed)
        fr = find_objects(query_est, img, K, **kw)
        good = 0
        for T in Ts:
            good += any(rotation_angle_deg(r.T_cam_from_obj[:3, :3], T[:3, :3]) < 15.0
                        and abs(r.T_cam_from_obj[2, 3] / T[2, 3] - 1) < 0.1 for r in fr.poses)
        both += len(fr.poses) == 2
        right += good
    assert both >= 2 and right >= 5, (both, right)


def test_a_part_of_the_object_does_not_hide_the_whole():
    """Non-maximum suppression (TemplateDetector.propose): a box overlapping a better one is dropped, unless it is
    more than ``grow_ratio`` times larger (the whole object around a part whose scaled-down template fired first)."""
    from pixie.cues.detect import _suppresses

    part, whole = np.array([40.0, 40.0, 100.0, 100.0]), np.array([0.0, 0.0, 100.0, 100.0])
    assert box_iou(part, whole) == pytest.approx(0.36)  # 3600 / 10000, hand-computed
    assert not _suppresses(part, whole, 0.3, 1.3)  # area ratio 2.78: the whole survives its part
    assert _suppresses(part, whole, 0.3, None)  # plain suppression: it would not
    assert _suppresses(whole, part, 0.3, 1.3)  # a part inside a better whole is dropped as before
    near = np.array([0.0, 0.0, 100.0, 120.0])  # IoU 0.83, area ratio 1.2: the same place at about the same scale
    assert _suppresses(whole, near, 0.3, 1.3) and not _suppresses(whole, near, 0.3, 1.1)
    assert not _suppresses(whole, np.array([200.0, 0.0, 300.0, 100.0]), 0.3, 1.3)  # apart


def test_a_pose_is_judged_inside_its_own_box_not_the_proposal(query_est, proc_mesh, scene_parts):
    """proposal_terms: the pose's edge fit inside its *own* projected box (full_fit) is high at the true pose even when
    the proposal holds only a part of it, and falls when the pose is moved off the object; box_iou is hand-checkable."""
    from pixie.cues.detect import Proposal
    from pixie.pipeline.find import proposal_terms
    from pixie.pose.results import PoseResult

    img, T = scene(proc_mesh, scene_parts, 1)
    gt = projected_box(T, K, query_est.box_points)
    half = np.array([gt[0], gt[1], 0.5 * (gt[0] + gt[2]), gt[3]])  # the left half of the object's box
    p = Proposal(box_xyxy=half, score=80.0, view=0, angle=0.0, scale=1.0, centre=half[:2])
    x = proposal_terms(query_est, img, K, p, PoseResult(T, 1.0, 0, False, "ok", confidence=0.7))
    assert x["line2d"] == pytest.approx(0.8) and x["confidence"] == pytest.approx(0.7) and x["failed"] == 0.0
    assert x["box_iou"] == pytest.approx(0.5, abs=1e-9)  # half the box inside the whole
    assert x["full_visible"] > 0.95 and x["full_fit"] > 0.6, x
    off = T.copy()
    off[0, 3] += 0.25 * proc_mesh.diameter  # a quarter of the diameter aside
    y = proposal_terms(query_est, img, K, p, PoseResult(off, 1.0, 0, False, "ok", confidence=0.7))
    assert y["full_fit"] < 0.5 * x["full_fit"], (x["full_fit"], y["full_fit"])
    failed = proposal_terms(query_est, img, K, p, PoseResult(None, 0.0, 0, True, "no pose"))
    assert failed["failed"] == 1.0 and "full_fit" not in failed


def test_acceptance_is_the_configured_logistic_of_the_named_scores():
    from pixie.config import PixieConfig
    from pixie.pipeline.find import acceptance

    dc = PixieConfig().apply_overrides(["detect.accept_terms=[fit,full_fit]", "detect.accept=[-3,2,4]"]).detect
    x = {"failed": 0.0, "confidence": 0.9, "fit": 0.5, "full_fit": 0.5}
    assert acceptance(dc, x) == pytest.approx(1 / (1 + np.exp(-(-3 + 2 * 0.5 + 4 * 0.5))))  # z = 0: 0.5
    assert acceptance(dc, {**x, "failed": 1.0}) == 0.0
    assert acceptance(PixieConfig().apply_overrides(["detect.accept=[]"]).detect, x) == 0.9  # the confidence rule


def test_parts_inside_a_box_vote_for_it():
    """votes_inside (hand-computed boxes): a part's box counts for the box it lies in, not the other way round, and a
    box sticking out by more than a fifth of its area does not count."""
    from pixie.cues.detect import votes_inside

    whole = np.array([0.0, 0.0, 100.0, 100.0])
    part = np.array([10.0, 10.0, 40.0, 40.0])  # wholly inside
    edge = np.array([80.0, 0.0, 110.0, 30.0])  # 2/3 of its area inside: below 0.8
    apart = np.array([200.0, 0.0, 230.0, 30.0])
    assert votes_inside([whole, part, edge, apart]).tolist() == [1, 0, 0, 0]
    assert votes_inside([whole, part, edge, apart], inside=0.6).tolist() == [2, 0, 0, 0]


def test_rank_scores_add_votes_and_regions_and_keep_ties_in_line2d_order():
    """rank_scores on hand-computed cases: similarity + vote_weight x votes + region_weight x 100 x (region - 0.5), a
    region not computed (NaN) adds nothing, and equal sums keep the incoming (LINE-2D) order."""
    from pixie.cues.detect import rank_scores

    rank, order = rank_scores([90.0, 80.0, 80.0, 70.0], [0, 2, 0, 0], 5.0, [0.5, 0.6, np.nan, 0.9], 0.5)
    assert np.allclose(rank, [90.0, 80.0 + 10.0 + 5.0, 80.0, 70.0 + 20.0])
    assert order.tolist() == [1, 0, 3, 2]  # 95, 90 (first of the tie), 90, 80
    rank0, order0 = rank_scores([90.0, 80.0, 80.0], [0, 2, 0], 0.0, [0.9, 0.9, 0.9], 0.0)
    assert np.allclose(rank0, [90.0, 80.0, 80.0]) and order0.tolist() == [0, 1, 2]
