"""The estimator's stages: public, free of per-query state, and the ``match.in_plane=query`` path end to end."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import check_result

from pixie.synth.e2e import E2E_POSES, K_Q, generic_pose, pose_errors, render_photo

from pixie.errors import ConfigError
from pixie.pipeline.estimator import PoseEstimator
from pixie.pose.solve import background_similarity
from pixie.app.runner import make_matcher

pytestmark = pytest.mark.usefixtures("one_torch_thread")


@pytest.fixture(scope="module")
def query_est(query_e2e):
    """The demo's and the README's LM-O path (conftest ``query_e2e``): roll-0 reference features, rotated query."""
    refs, cfg, matcher = query_e2e
    return PoseEstimator(refs, cfg, matcher=matcher)


# The first four generic poses of test_pipeline (rolled -10 to 30 degrees), fixed before looking at results.
QUERY_POSES = E2E_POSES[:4]


@pytest.fixture(scope="module")
def query_results(query_est, proc_mesh):
    out = []
    for i, (az, el, rl) in enumerate(QUERY_POSES):
        T = generic_pose(proc_mesh, az, el, rl)
        img, bbox, _ = render_photo(proc_mesh, T, K_Q, seed=i)
        res = query_est.estimate(img, K_Q, bbox=bbox)
        check_result(res)
        out.append((*pose_errors(res.T_cam_from_obj, T, proc_mesh.diameter), res, img, bbox))
    print("in_plane=query errors:", [f"{r:.1f} deg / {100 * t:.1f}%" for r, t, *_ in out])
    return out


@pytest.mark.slow
def test_in_plane_query_end_to_end(query_est, query_results, matcher_name):
    """Rotated query crops against roll-0 references find the rolled poses (rolls -10..30 deg): a roll bug
    (a crop turned the wrong way, or the roll index mirrored) puts them tens of degrees off.

    Measured (ALIKED, 2 cores): 0.9-2.5 deg / 0.5-3.4 % for the four poses; 0.25-0.48 deg / 0.4-1.1 % in session
    36, on the default preset's path (no render-at-estimate refinement). As in test_pipeline, the bar is on
    the set, with margin for single poses moving between versions: 3 of 4 within 5 deg / 5 %, median < 3.5 deg.
    """
    if matcher_name == "sift-nn":
        pytest.skip("SIFT does not bridge photo texture and shaded renders")
    assert query_est.pairs == [(v, 0) for v in range(query_est.refs.n_views)]  # roll-0 references only
    errs = [(pose, f"{rot:.2f} deg", f"{100 * tr:.1f}%") for pose, (rot, tr, *_) in zip(QUERY_POSES, query_results)]
    within = [rot < 5.0 and tr < 0.05 and not res.failed for rot, tr, res, *_ in query_results]
    assert sum(within) >= 3, f"only {sum(within)} of 4 poses within 5 deg / 5 %: {errs}"
    assert np.median([rot for rot, *_ in query_results]) < 3.5, errs


@pytest.mark.slow
def test_stages_reproduce_estimate_and_leave_no_state(query_est, query_results):
    """Calling the public stages by hand gives estimate()'s pose, and estimate() changes nothing on the estimator."""
    _, _, res, img, bbox = query_results[0]
    before = {k: id(v) for k, v in vars(query_est).items()}
    q = query_est.prepare(img, K_Q, bbox)
    assert len(q.crops) == query_est.refs.n_rolls == len(q.features)
    corr = query_est.match(q)
    assert corr and all(len(p2) == len(p3) == len(s) for p2, p3, s in corr.values())
    q.background = background_similarity([c[2] for c in corr.values()])
    hyps = query_est.select_views(q, query_est.solve(q, corr))
    if query_est.cfg.refine.render_iters > 0:
        hyps = query_est.render_refine(q, hyps)
    if query_est.cfg.shape.enabled:  # shape cues (default): edge candidates + verification after refinement
        hyps = query_est.shape_stage(q, hyps, {})
    if query_est.cfg.align.enabled:  # edge alignment (default): aligned candidates, selection on the fit
        hyps = query_est.align_stage(q, hyps)
    out = query_est.result(hyps, q=q)
    np.testing.assert_array_equal(out.T_cam_from_obj, res.T_cam_from_obj)
    assert out.score == res.score
    again = query_est.estimate(img, K_Q, bbox=bbox)
    np.testing.assert_array_equal(again.T_cam_from_obj, res.T_cam_from_obj)
    assert {k: id(v) for k, v in vars(query_est).items()} == before


def test_config_values_are_checked(proc_mesh, build_refs):
    from pixie.config import PixieConfig, RefsConfig

    cfg = PixieConfig()
    cfg.refs = RefsConfig(n_fibonacci=2, rotations=2, size=64, encodings=["shade3_edges"])
    cfg.match.matcher = "sift-nn"
    refs = build_refs(proc_mesh, cfg.refs, matcher=make_matcher(cfg))
    for key, value, message in (("match.in_plane", "photo", "in_plane"), ("pose.threshold_space", "px", "threshold")):
        bad = PixieConfig.from_dict(cfg.to_dict())
        with pytest.raises(ConfigError, match=message):  # refused when set, before any estimator exists
            bad.set(key, value)
    PoseEstimator(refs, cfg)  # the valid config builds
    # no config: the preset every command runs, not the bare dataclass defaults (which refine by re-rendering)
    plain = PoseEstimator(refs).cfg
    assert plain.to_dict() == PixieConfig.from_preset("default").to_dict()
    assert plain.refine.render_iters == 0 and PixieConfig().refine.render_iters > 0


@pytest.mark.slow
def test_alignment_on_two_threads_gives_the_serial_candidates(query_est, query_results):
    """The alignment stage aligns its starts on the process's threads (``pixie.threads.map_threads``): with torch at
    two threads the ranked candidates (poses, scores, sources, terms) are those of one thread, bit for bit (the
    stages before it run once, on one thread: torch's thread count may change the matcher's float sums)."""
    import copy

    from conftest import torch_threads

    _, _, res, img, bbox = query_results[1]
    q = query_est.prepare(img, K_Q, bbox)
    corr = query_est.match(q)
    q.background = background_similarity([c[2] for c in corr.values()])
    hyps = query_est.shape_stage(q, query_est.select_views(q, query_est.solve(q, corr)), {})
    out = {}
    for n in (1, 2):
        with torch_threads(n):
            out[n] = query_est.align_stage(copy.copy(q), copy.deepcopy(hyps))
    assert len(out[1]) == len(out[2]) and sum(h.source in ("aligned", "flip") for h in out[2]) >= 4
    for a, b in zip(out[1], out[2]):
        np.testing.assert_array_equal(a.T_cam_from_obj, b.T_cam_from_obj)
        assert (a.score, a.source) == (b.score, b.source)
        np.testing.assert_equal(a.terms, b.terms)  # NaN terms (no crease points) count as equal


@pytest.mark.slow
def test_extra_search_aligns_every_start_twice_and_keeps_both(query_est, query_results):
    """``align.extra_search``: each alignment job also runs with the second correspondence search; both poses join
    the ranked pool (term ``extra_search`` 0 / 1) with their aligned fit and support (support >= edge fit)."""
    import copy

    _, _, res, img, bbox = query_results[0]
    est = copy.copy(query_est)
    est.cfg = copy.deepcopy(query_est.cfg)
    est.cfg.align.extra_search = "normal"
    q = est.prepare(img, K_Q, bbox)
    corr = est.match(q)
    q.background = background_similarity([c[2] for c in corr.values()])
    hyps = est.shape_stage(q, est.select_views(q, est.solve(q, corr)), {})
    out = est.align_stage(q, hyps)
    aligned = [h for h in out if h.source in ("aligned", "flip")]
    extra = [h for h in aligned if h.terms["extra_search"] == 1.0]
    assert len(extra) == len(aligned) - len(extra) > 0
    assert all(np.isfinite(h.terms["fit_support"]) and h.terms["fit_support"] >= h.terms["fit"] for h in aligned)


@pytest.mark.slow
def test_object_axis_twins_and_the_silhouette_term_in_the_ranking(query_est, query_results):
    """``align.flip_axes=object``: the best start's twins turn about the model's own three axes (three 'flip'
    candidates, each 180° from that start's pose before alignment); ``align.w_silhouette``: every aligned
    candidate's score is fused + w_fit x fit + w_silhouette x the silhouette points' fit, and the pool is ranked
    by it."""
    import copy

    _, _, res, img, bbox = query_results[0]
    est = copy.copy(query_est)
    est.cfg = copy.deepcopy(query_est.cfg)
    est.cfg.align.flip_axes, est.cfg.align.w_silhouette = "object", 0.5
    q = est.prepare(img, K_Q, bbox)
    corr = est.match(q)
    q.background = background_similarity([c[2] for c in corr.values()])
    hyps = est.shape_stage(q, est.select_views(q, est.solve(q, corr)), {})
    out = est.align_stage(q, hyps)
    assert sum(h.source == "flip" for h in out) == 3 * est.cfg.align.flips
    ac = est.cfg.align
    ranked = [h for h in out if "fit_silhouette" in h.terms]
    for h in ranked:
        want = h.terms["fused"] + ac.w_fit * h.terms["fit"] + ac.w_silhouette * h.terms["fit_silhouette"]
        assert h.score == pytest.approx(want, abs=1e-12)
    assert [h.score for h in ranked] == sorted((h.score for h in ranked), reverse=True)


@pytest.mark.slow
def test_coarse_crop_option_runs_the_first_scales_on_a_half_size_crop(query_est, query_results):
    """``align.coarse_px``: the estimator makes the coarse crop's edges once per query (the box at ``coarse_px``),
    passes them to every alignment with the first scales converted to their px, and the pose stays at the photo's
    pose (within 2° / 2 % of the default's, which is within a few degrees of the truth here)."""
    import copy

    from pixie.geometry.camera import rotation_angle_deg

    _, _, res, img, bbox = query_results[0]
    est = copy.copy(query_est)
    est.cfg = copy.deepcopy(query_est.cfg)
    est.cfg.align.coarse_px = 100.0
    q = est.prepare(img, K_Q, bbox)
    _, pe, kw = est._align_setup(q)
    pc = q.photo_edges_coarse
    assert kw["coarse"] is pc and pc.size * 2 == pytest.approx(pe.size, abs=2)
    assert kw["coarse_schedule"] == (8.0, 4.0) and kw["schedule"] == (4.0, 2.0)
    out = est.estimate(img, K_Q, bbox=bbox)
    T, T0 = out.T_cam_from_obj, res.T_cam_from_obj
    assert rotation_angle_deg(T[:3, :3], T0[:3, :3]) < 2.0 and abs(T[2, 3] / T0[2, 3] - 1) < 0.02
