"""End-to-end pixie benchmark on the LM-O dev subset (real photos, bbox_visib crops), plus an oracle mode.

Usage::

    nice .venv/bin/python bench/lmo_pipeline.py [--max-targets 48] [--set section.key=value ...] \
        [--config NAME:section.key=value,section.key=value ...] [--oracle] [--out out/bench/lmo_pipeline]

Every ``--config`` is run in turn, starting from ``--preset`` (default ``default``) with the global ``--set``
overrides applied first; without any ``--config`` the preset (+ ``--set``) runs under the preset's name. Per configuration it

* builds (or loads from ``out/bench/refs/``) one reference set per object with
  :func:`pixie.app.runner.cached_reference_set` (its key covers the mesh, ``cfg.refs`` and the matcher's
  extraction settings, so configurations that only differ in matching/pose settings share references);
* runs ``PoseEstimator.estimate(image, K, bbox=bbox_visib)`` per target and appends one JSON line per
  target to ``<out>/runs/<run hash>/targets.jsonl`` (a :class:`pixie.app.runner.Journal`: finished targets are skipped);
* writes ``<out>/runs/<run hash>/results.csv`` (BOP'19 format) and ``<out>/<NAME>.json``, and prints a table.

Metrics: ADD(-S)<0.1d (ADD-S for the symmetric objects 10 and 11, BOP evaluation models), median
rotation / translation error, AR (no VSD) = mean(AR_MSSD, AR_MSPD) from :func:`pixie.eval.evaluate`,
seconds per target with the estimator's stage breakdown, and the reference build time.

Oracle mode (``--oracle``): for each target one reference is rendered at the ground-truth view (same
object-centred square-crop convention as the reference sets, the GT rotation turned so that the object
centre lies on the optical axis, like a query crop) and the query is matched against it alone. It measures
the matcher/encoding across the real-photo/render gap independent of retrieval: raw matches, *correct*
matches (reference XYZ projected with the GT pose within 5 crop pixels of the query keypoint), PnP
inliers and ADD(-S)<0.1d of the estimator run on that single reference. Reuse it from other code with
:func:`oracle_target` / :func:`run_oracle`.
"""

from __future__ import annotations

import argparse
import copy
import json
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from common import (DEFAULT_DATASET, DEFAULT_OUT, REFS_CACHE, REPO, ObjectCache, add_preset_arg,  # noqa: E402,F401
                    config_for_hash, gt_instance, make_config, parse_config_arg, refs_key, select_targets, short_hash)

from pixie.geometry.camera import make_T, project, transform_points  # noqa: E402
from pixie.config import PixieConfig  # noqa: E402
from pixie.references.encode import encode  # noqa: E402
from pixie.pipeline.estimator import PoseEstimator  # noqa: E402
from pixie.eval import evaluate, pose_errors  # noqa: E402
from pixie.eval.datasets import BopDataset, PoseEstimate, Target, write_results_csv  # noqa: E402
from pixie.geometry.rotations import rotation_between  # noqa: E402
from pixie.pose.solve import lift  # noqa: E402
from pixie.pipeline.query import check_bbox, square_crop  # noqa: E402
from pixie.references.set import ReferenceSet, keypoint_xyz_from_depth  # noqa: E402
from pixie.geometry.render import Renderer  # noqa: E402
from pixie.app.runner import Journal, make_matcher  # noqa: E402
from pixie.threads import set_threads  # noqa: E402
from pixie.references.views import camera_distance, square_crop_K, start_K  # noqa: E402

CORRECT_PX = 5.0  # crop pixels: a match is correct when the GT projection of its 3D point is this close


# ------------------------------------------------------------------------------------------ helpers


# ------------------------------------------------------------------------------------------ oracle


def oracle_reference(mesh, cfg: PixieConfig, T_gt: np.ndarray, matcher, renderer=None):
    """A one-view :class:`ReferenceSet` rendered at the GT view, with ``matcher`` features.

    The GT rotation is turned (about the camera centre) so that the object centre lies on the optical axis,
    then rendered like a reference view: K_start focal, object-centred square crop of ``cfg.refs.size`` px.
    """
    rc = cfg.refs
    S = int(rc.size)
    K0 = start_K(S, rc.focal_factor)
    dist = camera_distance(mesh.bounding_radius, K0[0, 0], S, fill=1.0 / rc.crop_pad)
    c = T_gt[:3, :3] @ mesh.center + T_gt[:3, 3]
    R = rotation_between(c / np.linalg.norm(c), np.array([0.0, 0.0, 1.0])) @ T_gt[:3, :3]
    T = make_T(R, np.array([0.0, 0.0, dist]) - R @ mesh.center)
    K, _ = square_crop_K(K0, T, mesh.vertices, S, rc.crop_pad)
    renderer = renderer or Renderer(mesh, smooth_normals=rc.smooth_normals)
    r = renderer.render(T, K, S, S)
    feats, encs = {}, {}
    for e in rc.encodings:
        img = encode(e, r.depth, r.normals, r.mask)
        encs[e] = img[None]
        feats[e] = matcher.extract(img, mask=r.mask)
    rc1 = copy.deepcopy(rc)
    rc1.rotations, rc1.n_fibonacci, rc1.canonical = 1, 1, False
    refs = ReferenceSet(mesh=mesh, config=rc1, poses=T[None, None], Ks=K[None, None], K_start=K0,
                        canonical=np.zeros(1, bool), depth=r.depth[None].astype(np.float32),
                        normals=r.normals[None].astype(np.float32), encodings=encs)
    for e, f in feats.items():
        refs.set_features(matcher.name, e, [f], [keypoint_xyz_from_depth(r.depth, K, T, f.keypoints)])
    return refs


@dataclass
class OracleResult:
    n_matches: int = 0
    n_correct: int = 0
    n_inliers: int = 0
    T_est: np.ndarray | None = None
    per_encoding: dict = field(default_factory=dict)  # encoding -> (matches, correct)


def oracle_target(image: np.ndarray, K: np.ndarray, bbox, T_gt: np.ndarray, mesh, cfg: PixieConfig, matcher,
                  renderer=None) -> OracleResult:
    """Match a query crop against one reference rendered at the GT view; count correct matches; run PnP.

    ``bbox`` is (x, y, w, h) as given to :meth:`PoseEstimator.estimate`. Any matcher built by
    :func:`pixie.matching.get_matcher` (or with the same interface) can be passed.
    """
    cfg = copy.deepcopy(cfg)
    cfg.match.in_plane = "reference"
    refs = oracle_reference(mesh, cfg, T_gt, matcher, renderer)
    est = PoseEstimator(refs, cfg, matcher=matcher)
    res = est.estimate(image, K, bbox=bbox)
    out = OracleResult(n_inliers=res.n_inliers, T_est=res.T_cam_from_obj)
    box = check_bbox(bbox, image.shape[:2])
    crop = square_crop(image, box, cfg.query.crop_pad, refs.size)
    qf = matcher.extract(crop.image)
    A = np.vstack([crop.A, [0, 0, 1]])
    Ainv = np.linalg.inv(A)[:2]
    for e in est.encodings:
        (rf,), (rxyz,) = refs.features_for(matcher.name, e)
        p2, p3, _ = lift(qf.keypoints, rxyz, matcher.match(qf, rf))
        if len(p2):
            uv = project(K, transform_points(T_gt, p3))
            uvc = uv @ Ainv[:, :2].T + Ainv[:, 2]
            nc = int(np.sum(np.linalg.norm(uvc - p2, axis=1) < CORRECT_PX))
        else:
            nc = 0
        out.per_encoding[e] = (len(p2), nc)
        out.n_matches += len(p2)
        out.n_correct += nc
    return out


def run_oracle(ds: BopDataset, targets: list[Target], cfg: PixieConfig, matcher=None, crop: str = "visib",
               objects: ObjectCache | None = None, progress=print) -> dict:
    """Oracle mode over ``targets``; returns a summary dict (and per-target rows under 'targets')."""
    objects = objects or ObjectCache(ds)
    matcher = matcher or make_matcher(cfg)
    rows = []
    t0 = time.perf_counter()
    for i, t in enumerate(targets):
        g = gt_instance(ds, t)
        img = ds.load_rgb(t.scene_id, t.im_id)
        K = ds.camera(t.scene_id, t.im_id).K
        bbox = g.box_visib if crop == "visib" else g.box_obj
        r = oracle_target(img, K, bbox, g.T_cam_from_obj, objects.mesh(t.obj_id), cfg, matcher,
                          objects.renderer(t.obj_id, cfg.refs.smooth_normals))
        err = pose_errors(objects.eval_data(t.obj_id), r.T_est, g.T_cam_from_obj)
        rows.append({"im_id": t.im_id, "obj_id": t.obj_id, "visib": g.visib_fract, "matches": r.n_matches,
                     "correct": r.n_correct, "inliers": r.n_inliers, "per_encoding": r.per_encoding, **err})
        if progress and (i + 1) % 10 == 0:
            progress(f"  oracle {i + 1}/{len(targets)}  {time.perf_counter() - t0:.0f} s")
    n = max(len(rows), 1)
    return {
        "n_targets": len(rows),
        "mean_matches": float(np.mean([r["matches"] for r in rows])) if rows else 0.0,
        "mean_correct": float(np.mean([r["correct"] for r in rows])) if rows else 0.0,
        "median_correct": float(np.median([r["correct"] for r in rows])) if rows else 0.0,
        "mean_inliers": float(np.mean([r["inliers"] for r in rows])) if rows else 0.0,
        "add_0.1d": sum(r["add_ok"] for r in rows) / n,
        "median_rot_err": _median([r["rot_err"] for r in rows]),
        "median_trans_err": _median([r["trans_err"] for r in rows]),
        "seconds_per_target": (time.perf_counter() - t0) / n,
        "targets": rows,
    }


def _median(vals):
    v = [x if x is not None else float("inf") for x in vals]
    return float(np.median(v)) if v else None


# ------------------------------------------------------------------------------------------ pipeline


def query_mask(mode: str, ds: BopDataset, t: Target, img: np.ndarray, K: np.ndarray, bbox, objects: ObjectCache):
    """The object mask given with the box: none, ``render`` (the target's visible pixels among the image's annotated
    GT instances, rendered at their GT poses: an upper bound for a segmenter) or ``grabcut``
    (:func:`pixie.pipeline.query.grabcut_mask` from the box alone)."""
    if mode == "none":
        return None
    if mode == "grabcut":
        from pixie.pipeline.query import grabcut_mask
        return grabcut_mask(img, bbox)
    h, w = img.shape[:2]
    deps = {}
    for g in ds.instances(t.scene_id, t.im_id):
        r = objects.renderer(g.obj_id).render(g.T_cam_from_obj, K, h, w, roi=None)
        deps.setdefault(g.obj_id, []).append(np.where(r.tri_ids >= 0, r.depth, np.inf))
    mine = min(deps[t.obj_id], key=lambda d: np.isfinite(d).sum() * -1)
    others = [d for oid, ds_ in deps.items() for d in ds_ if d is not mine]
    front = np.minimum.reduce(others) if others else np.full((h, w), np.inf)
    m = np.isfinite(mine) & (mine <= front)
    return m if m.any() else None


def run_pipeline(ds: BopDataset, targets: list[Target], cfg: PixieConfig, name: str, out_dir: Path,
                 crop: str = "visib", tag: str = "", objects: ObjectCache | None = None, ar: bool = True,
                 progress=print, reverse: bool = False, mask: str = "none", shard: tuple[int, int] | None = None
                 ) -> dict | None:
    """Run the estimator on ``targets``; resumable through ``<out>/runs/<hash>/targets.jsonl``.

    ``shard`` (k, n): only every n-th target from the k-th, into the same journal (processes side by side), and no
    summary (None); a run without it afterwards finds them all and summarises."""
    objects = objects or ObjectCache(ds)
    run_hash = short_hash({"cfg": config_for_hash(cfg), "crop": crop, "tag": tag,
                           **({"mask": mask} if mask != "none" else {})})
    run_dir = out_dir / "runs" / run_hash
    run_dir.mkdir(parents=True, exist_ok=True)
    (run_dir / "config.json").write_text(json.dumps({"name": name, "preset": cfg.preset, "cfg": cfg.to_dict(), "crop": crop,
                                                     "tag": tag, "mask": mask}, indent=1))
    done = Journal(run_dir / "targets.jsonl", key=lambda d: (d["scene_id"], d["im_id"], d["obj_id"]))
    todo = [t for i, t in enumerate(targets) if (t.scene_id, t.im_id, t.obj_id) not in done
            and (shard is None or i % shard[1] == shard[0])]
    progress(f"[{name}] {len(targets)} targets, {len(done)} cached, {len(todo)} to run"
             f"{f' (shard {shard[0]}/{shard[1]})' if shard else ''}, run {run_hash}")
    matcher = None
    by_obj: dict[int, list[Target]] = {}
    for t in todo:
        by_obj.setdefault(t.obj_id, []).append(t)
    t_start = time.perf_counter()
    n_run = 0
    for oid in sorted(by_obj, reverse=reverse):
        cfg_o = copy.deepcopy(cfg)
        if matcher is None:
            matcher = make_matcher(cfg_o)
        refs = objects.refs(cfg_o, oid, matcher, log=progress)
        est = PoseEstimator(refs, cfg_o, matcher=matcher)
        od = objects.eval_data(oid)
        for t in by_obj[oid]:
            g = gt_instance(ds, t)
            img = ds.load_rgb(t.scene_id, t.im_id)
            K = ds.camera(t.scene_id, t.im_id).K
            bbox = g.box_visib if crop == "visib" else g.box_obj
            t0 = time.perf_counter()
            m = query_mask(mask, ds, t, img, K, bbox, objects)
            res = est.estimate(img, K, bbox=bbox, mask=m)
            dt = time.perf_counter() - t0
            err = pose_errors(od, res.T_cam_from_obj, g.T_cam_from_obj)
            # the distinct hypotheses (multi-hypothesis output): is any of them right?
            hyp_err = [pose_errors(od, h.T_cam_from_obj, g.T_cam_from_obj) for h in res.hypotheses]
            hyp_ok = [bool(e["add_ok"]) for e in hyp_err]
            # score terms of each output hypothesis (offline re-ranking / fusion-weight studies)
            hyp_terms = [{"source": h.source, "score": h.score, "match_score": h.match_score,
                          "edge": None if not np.isfinite(h.edge) else h.edge,
                          "region": None if not np.isfinite(h.region) else h.region,
                          "terms": {k: (None if not np.isfinite(v) else v) for k, v in h.terms.items()},
                          "n_inliers": h.n_inliers, "matcher_best": h.matcher_best,
                          "add_ok": bool(e["add_ok"]), "rot_err": e["rot_err"], "add": e["add"]}
                         for h, e in zip(res.hypotheses, hyp_err)]
            # every aligned candidate (config.align) with its terms: selection-weight studies (bench/lmo_select.py)
            cands = [h for h in res.candidates if "fused" in h.terms]
            cand_terms = []
            for h in cands:
                e = pose_errors(od, h.T_cam_from_obj, g.T_cam_from_obj)
                cand_terms.append({"source": h.source, "match_score": h.match_score, "T": h.T_cam_from_obj.tolist(),
                                   "terms": {k: (None if not np.isfinite(v) else v) for k, v in h.terms.items()},
                                   "add_ok": bool(e["add_ok"]), "rot_err": e["rot_err"], "add": e["add"]})
            rec = {"hyp_add_ok": hyp_ok, "hyps": hyp_terms, "cands": cand_terms, "scene_id": t.scene_id, "im_id": t.im_id, "obj_id": t.obj_id, "visib": g.visib_fract,
                   "T": None if res.T_cam_from_obj is None else res.T_cam_from_obj.tolist(), "score": res.score,
                   "n_inliers": res.n_inliers, "failed": res.failed, "view": res.view, "roll": res.roll,
                   "confidence": res.confidence, "message": res.message,
                   "seconds": dt, "timings": res.timings, **err}
            done.append(rec)
            n_run += 1
            if n_run % 10 == 0:
                ok = sum(r["add_ok"] for r in done.records.values())
                progress(f"  [{name}] {n_run}/{len(todo)}  {(time.perf_counter() - t_start) / n_run:.2f} s/target  "
                         f"ADD<0.1d so far {ok}/{len(done)}")
    if shard is not None:
        progress(f"[{name}] shard {shard[0]}/{shard[1]} done: {n_run} targets")
        return None
    recs = [done.get((t.scene_id, t.im_id, t.obj_id)) for t in targets]
    return summarise(ds, targets, recs, cfg, name, run_dir, objects, ar)


def summarise(ds, targets, recs, cfg, name, run_dir, objects, ar=True) -> dict:
    ests = [PoseEstimate(r["scene_id"], r["im_id"], r["obj_id"], float(r["score"]), np.array(r["T"]), r["seconds"])
            for r in recs if r["T"] is not None]
    write_results_csv(run_dir / "results.csv", ests)
    n = max(len(recs), 1)
    stages = {}
    for r in recs:
        for k, v in (r.get("timings") or {}).items():
            stages.setdefault(k, []).append(v)
    per_obj = {}
    for r in recs:
        per_obj.setdefault(r["obj_id"], []).append(r["add_ok"])
    out = {
        "name": name, "run": run_dir.name, "n_targets": len(recs),
        "add_0.1d": sum(r["add_ok"] for r in recs) / n,
        "add_0.1d_any_hypothesis": sum(any(r.get("hyp_add_ok") or [r["add_ok"]]) for r in recs) / n,
        "add_0.1d_per_object": {str(k): float(np.mean(v)) for k, v in sorted(per_obj.items())},
        "median_rot_err": _median([r["rot_err"] for r in recs]),
        "median_trans_err": _median([r["trans_err"] for r in recs]),
        "failed": sum(bool(r["failed"]) for r in recs),
        "mean_inliers": float(np.mean([r["n_inliers"] for r in recs])) if recs else 0.0,
        "seconds_per_target": float(np.mean([r["seconds"] for r in recs])) if recs else 0.0,
        "stage_seconds": {k: float(np.mean(v)) for k, v in stages.items()},
        "refs_key": refs_key(cfg),
        "refs_build_seconds_per_object": _mean_or_none([v for (k, o), v in objects.build_seconds.items() if k == refs_key(cfg)]),
        "refs_mb_per_object": _mean_or_none([v / 1e6 for (k, o), v in objects.refs_bytes.items() if k == refs_key(cfg)]),
        "config": cfg.to_dict(),
    }
    if ar:  # over every target: one without a pose is a miss (BOP), also when none has one (AR 0, not absent)
        t0 = time.perf_counter()
        sc = evaluate(ds, ests, metrics=["mssd", "mspd"], targets=targets, n_points=2000)
        out["ar_no_vsd"] = sc.overall.get("AR_noVSD")
        out["eval_seconds"] = time.perf_counter() - t0
    return out


def _mean_or_none(v):
    return float(np.mean(v)) if v else None


def format_table(rows: list[dict], oracle: bool = False) -> str:
    if oracle:
        head = f"{'config':<28}{'n':>5}{'matches':>9}{'correct':>9}{'inliers':>9}{'ADD<.1d':>9}{'rot°':>8}{'t mm':>8}{'s/tg':>7}"
        lines = [head]
        for r in rows:
            lines.append(f"{r['name']:<28}{r['n_targets']:>5}{r['mean_matches']:>9.1f}{r['mean_correct']:>9.1f}"
                         f"{r['mean_inliers']:>9.1f}{100 * r['add_0.1d']:>8.1f}%{r['median_rot_err']:>8.1f}"
                         f"{r['median_trans_err']:>8.1f}{r['seconds_per_target']:>7.2f}")
        return "\n".join(lines)
    head = (f"{'config':<28}{'n':>5}{'ADD<.1d':>9}{'any hyp':>8}{'AR(noVSD)':>10}{'rot°':>8}{'t mm':>8}{'s/tg':>7}  stages (extract/match/pnp/vs/rr/edges/verify/region)"
            f"   refs s/obj, MB/obj")
    lines = [head]
    for r in rows:
        st = r["stage_seconds"]
        stages = "/".join(f"{st.get(k, 0):.2f}" for k in ("extract", "match", "pnp", "view_selection", "render_refine",
                                                           "edge_retrieval", "verify", "region_refine"))
        ar = r.get("ar_no_vsd")
        b = r.get("refs_build_seconds_per_object")
        mb = r.get("refs_mb_per_object")
        lines.append(f"{r['name']:<28}{r['n_targets']:>5}{100 * r['add_0.1d']:>8.1f}%"
                     f"{100 * r.get('add_0.1d_any_hypothesis', float('nan')):>7.1f}%"
                     f"{(f'{ar:.3f}' if isinstance(ar, (int, float)) else '-'):>10}{r['median_rot_err']:>8.1f}"
                     f"{r['median_trans_err']:>8.1f}{r['seconds_per_target']:>7.2f}  {stages:<29}"
                     f"   {(f'{b:.0f}' if b else '-')}, {(f'{mb:.1f}' if mb else '-')}")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--dataset", type=Path, default=DEFAULT_DATASET)
    ap.add_argument("--out", type=Path, default=DEFAULT_OUT)
    ap.add_argument("--max-targets", type=int, default=None, help="spread evenly over the objects")
    ap.add_argument("--objects", type=str, default=None, help="comma-separated object ids (measuring only)")
    ap.add_argument("--set", action="append", default=[], dest="overrides", help="section.key=value, for every config")
    ap.add_argument("--config", action="append", default=[], help="NAME:section.key=value,section.key=value")
    ap.add_argument("--oracle", action="store_true", help="match each target only against a GT-view reference")
    ap.add_argument("--crop", choices=("visib", "obj"), default="visib", help="query box: bbox_visib (default) or bbox_obj")
    ap.add_argument("--mask", choices=("none", "render", "grabcut"), default="none",
                    help="an object mask with the box: rendered from the GT (upper bound) or GrabCut from the box")
    ap.add_argument("--shard", default=None, help="K/N: run only every N-th target from the K-th (no summary; "
                    "run again without --shard to summarise)")
    ap.add_argument("--tag", default="", help="part of the run hash (bump it after changing the estimator code)")
    ap.add_argument("--no-ar", action="store_true", help="skip AR (no VSD)")
    ap.add_argument("--reverse-objects", action="store_true", help="process objects in decreasing id order "
                    "(a second process then builds other objects' references first)")
    ap.add_argument("--threads", type=int, default=None, help="torch/OpenCV threads (default: pixie.threads' policy)")
    add_preset_arg(ap)
    args = ap.parse_args(argv)
    set_threads(args.threads)
    ds = BopDataset(args.dataset)
    objs = [int(x) for x in args.objects.split(",")] if args.objects else None
    targets = select_targets(ds, args.max_targets, objs)
    configs = [parse_config_arg(c) for c in args.config] or [(args.preset, [])]  # named after the preset it runs
    objects = ObjectCache(ds)
    args.out.mkdir(parents=True, exist_ok=True)
    rows = []
    for name, ov in configs:
        cfg = make_config(args.overrides + ov, args.preset)
        if args.oracle:
            t0 = time.perf_counter()
            r = run_oracle(ds, targets, cfg, crop=args.crop, objects=objects)
            r["name"] = name
            r["config"], r["preset"] = cfg.to_dict(), cfg.preset
            print(f"[{name}] oracle done in {time.perf_counter() - t0:.0f} s")
            (args.out / f"oracle_{name}.json").write_text(json.dumps(r, indent=1, default=float))
        else:
            r = run_pipeline(ds, targets, cfg, name, args.out, crop=args.crop, tag=args.tag, objects=objects,
                             ar=not args.no_ar, reverse=args.reverse_objects, mask=args.mask,
                             shard=tuple(int(x) for x in args.shard.split("/")) if args.shard else None)
            if r is None:
                continue
            (args.out / f"{name}.json").write_text(json.dumps(r, indent=1, default=float))
        rows.append(r)
        print(format_table([r], oracle=args.oracle).splitlines()[1])
    print()
    print(format_table(rows, oracle=args.oracle))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
