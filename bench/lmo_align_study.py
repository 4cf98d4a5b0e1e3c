"""The alignment stage on cached pipeline hypotheses: compare ``config.align`` variants on the same LM-O starts.

Usage::

    PYTHONPATH=src .venv/bin/python bench/lmo_align_study.py [--max-targets 48] [--preset default] \
        [--variant NAME:align.key=value,align.key=value ...] [--out out/bench/lmo_align_study.json]

All 716 targets, stage 1 on both cores, then the rows with AR (the ablation table of bench/RESULTS.md, session 22)::

    PYTHONPATH=src .venv/bin/python bench/lmo_align_study.py --max-targets 716 --shard 0/2 &   # and --shard 1/2
    PYTHONPATH=src .venv/bin/python bench/lmo_align_study.py --max-targets 716 --ar --variant ...

Every candidate of the aligned stage, for offline selection studies (``bench/lmo_rank.py``), stage 2 on both cores::

    PYTHONPATH=src .venv/bin/python bench/lmo_align_study.py --max-targets 716 --ar --part 0/2 \
        --dump out/bench/rank/dump_0.pkl --out out/bench/rank/study_0.json &   # and --part 1/2 ... dump_1 / study_1

Stage 1 (cached in ``out/bench/lmo_align_study/<hash>/``, one pickle per target, keyed by the preset, the digest of
the config sections stage 1 reads (:func:`stage1_digest`: all but ``align`` and ``detect``), the targets and the
code tag; an older single ``<hash>.pkl`` is still read): the pipeline up to and including the shape stage (``PoseEstimator.estimate`` with ``align.enabled=false``) per target, keeping every
hypothesis. Stage 2, per variant: :meth:`PoseEstimator.align_stage` on copies of those hypotheses;
the chosen pose is scored (ADD(-S)<0.1d, rotation error) and every aligned candidate's correctness recorded. The
row ``no alignment`` is the cached pipeline's own choice. Prints one table (hits, share, any aligned candidate
right, median rotation error, seconds per target of the stage).
"""

from __future__ import annotations

import argparse
import copy
import hashlib
import json
import pickle
import time
from pathlib import Path

import numpy as np

import common as L  # noqa: E402  (bench/common.py: targets, object cache, presets)

REPO = L.REPO

from pixie.config import PixieConfig  # noqa: E402
from pixie.app.runner import make_matcher  # noqa: E402
from pixie.pipeline.estimator import PoseEstimator, Query  # noqa: E402
from pixie.pipeline.query import check_bbox  # noqa: E402
from pixie.eval import evaluate  # noqa: E402
from pixie.eval.datasets import PoseEstimate  # noqa: E402

TAG = "s9-1"  # s9: hypotheses keep their PnP inliers (support_uv, support_xyz)


def stage1_digest(cfg: PixieConfig) -> str:
    """What stage 1 depends on: the config without its ``align`` section (stage 1 runs with alignment off; every
    variant sets its own) and its ``detect`` section (the detector's, not read with a given box)."""
    d = {k: v for k, v in cfg.to_dict().items() if k not in ("align", "detect")}
    return hashlib.sha256(json.dumps(d, sort_keys=True).encode()).hexdigest()[:16]


def _stage1_record(ds, est, t) -> dict:
    g = L.gt_instance(ds, t)
    img = ds.load_rgb(t.scene_id, t.im_id)
    K = ds.camera(t.scene_id, t.im_id).K
    res = est.estimate(img, K, bbox=g.box_visib)
    return {"target": (t.scene_id, t.im_id, t.obj_id), "t": t, "hyps": res.candidates, "box": g.box_visib,
            "best_match": max([h.match_score for h in res.candidates], default=0.0),
            "seconds": sum(v for k, v in (res.timings or {}).items() if k != "total")}


def stage1(ds, objects, targets, cfg, cache: Path, shard: tuple[int, int] = (0, 1)) -> list[dict] | None:
    """Stage-1 records of ``targets``: from ``cache`` (one pickle, the older layout) or from the per-target pickles in
    the folder ``cache.with_suffix('')`` (computed for the shard's targets, ``targets[k::n]``, when missing). Returns
    None while another shard's targets are still missing."""
    if cache.is_file():
        return pickle.loads(cache.read_bytes())
    folder = cache.with_suffix("")
    folder.mkdir(parents=True, exist_ok=True)
    path = lambda t: folder / f"{t.scene_id:06d}_{t.im_id:06d}_{t.obj_id:06d}.pkl"  # noqa: E731
    k, n = shard
    todo = [t for t in targets[k::n] if not path(t).is_file()]
    matcher = make_matcher(cfg) if todo else None
    ests = {}
    for i, t in enumerate(todo):
        if t.obj_id not in ests:
            ests[t.obj_id] = PoseEstimator(objects.refs(cfg, t.obj_id, matcher), cfg, matcher=matcher)
        rec = _stage1_record(ds, ests[t.obj_id], t)
        tmp = path(t).with_suffix(".tmp")
        tmp.write_bytes(pickle.dumps(rec))
        tmp.replace(path(t))
        if (i + 1) % 12 == 0:
            print(f"  stage 1 (shard {k}/{n}): {i + 1}/{len(todo)}", flush=True)
    if not all(path(t).is_file() for t in targets):
        return None
    return [pickle.loads(path(t).read_bytes()) for t in targets]


def align_cached(ds, objects, rec: dict, cfg: PixieConfig, base: PixieConfig, ests: dict) -> tuple[list, float]:
    """:meth:`PoseEstimator.align_stage` with ``cfg`` on a stage-1 record's hypotheses (copies), and its seconds;
    ``ests`` caches one estimator per object (built from ``base``)."""
    sid, iid, oid = rec["target"]
    if oid not in ests:
        ests[oid] = PoseEstimator(objects.refs(base, oid, make_matcher(base)), base)
    est = ests[oid]
    est.cfg = copy.deepcopy(cfg)
    img = ds.load_rgb(sid, iid)
    K = ds.camera(sid, iid).K
    box = check_bbox(rec["box"], img.shape[:2])
    q = Query(img, K, box, None, [], [])
    q.edges = est._shape.query(img, box) if est._shape is not None else None
    q.best_match = rec["best_match"]
    hyps = copy.deepcopy(rec["hyps"])
    t0 = time.perf_counter()
    return est.align_stage(q, hyps), time.perf_counter() - t0


def candidate_records(rec: dict, hyps: list, od, g) -> dict:
    """One target's aligned-stage candidates (those with an aligned fit, in the stage's order) with their pose,
    source, scores and terms, and their errors against the ground truth (``pose_errors``)."""
    out = []
    for rank, h in enumerate(hyps):
        if "fit" not in h.terms:
            continue
        e = L.pose_errors(od, h.T_cam_from_obj, g.T_cam_from_obj)
        out.append({"rank": rank, "source": h.source, "T": np.asarray(h.T_cam_from_obj), "score": float(h.score),
                    "match_score": float(h.match_score), "n_inliers": int(h.n_inliers), "box_iou": float(h.box_iou),
                    "terms": {k: float(v) for k, v in h.terms.items() if v is not None}, **e})
    return {"target": rec["target"], "box": np.asarray(rec["box"]), "T_gt": np.asarray(g.T_cam_from_obj),
            "diameter": od.diameter, "symmetric": od.symmetric, "best_match": rec["best_match"], "cands": out}


def score_poses(ds, objects, targets: list, poses: dict, ar: bool) -> dict:
    """Scores of one variant's chosen poses ``poses`` ({(scene, image, object): T}) over ``targets`` (a target without a
    pose is a miss at 180°): per target its ADD(-S)<0.1d verdict, the hits, the median rotation error, the share right
    per object and, with ``ar``, AR (MSSD/MSPD, :func:`pixie.eval.evaluate`; None without)."""
    per, rots, per_obj = [], [], {}
    for t in targets:
        T = poses.get((t.scene_id, t.im_id, t.obj_id))
        ok, rot = False, 180.0
        if T is not None:
            e = L.pose_errors(objects.eval_data(t.obj_id), T, L.gt_instance(ds, t).T_cam_from_obj)
            ok, rot = bool(e["add_ok"]), e["rot_err"]
        per.append(ok)
        rots.append(rot)
        per_obj.setdefault(str(t.obj_id), []).append(ok)
    score = None
    if ar:
        ests = [PoseEstimate(k[0], k[1], k[2], 1.0, T, 0.0) for k, T in poses.items()]
        score = evaluate(ds, ests, metrics=["mssd", "mspd"], targets=targets, n_points=2000).overall.get("AR_noVSD")
    return {"per_target": per, "hits": int(sum(per)), "med_rot": float(np.median(rots)),
            "per_object": {o: float(np.mean(v)) for o, v in sorted(per_obj.items(), key=lambda kv: int(kv[0]))},
            "ar": score}


def merge(ds, objects, paths: list[Path], out: Path) -> int:
    """One table over the targets of several ``--part`` runs (their ``--out`` JSONs): each variant's poses pooled and
    scored again (:func:`score_poses`; rows written before they listed their targets count the targets they have a
    pose for)."""
    runs = [json.loads(Path(p).read_text()) for p in paths]
    names = [r["variant"] for r in runs[0]["rows"]]
    bykey = {(t.scene_id, t.im_id, t.obj_id): t for t in ds.targets()}
    rows = []
    print("| variant | ADD(-S)<0.1d | med rot° | AR (MSSD/MSPD) | per object ADD(-S) % |")
    print("|---|---|---|---|---|")
    for name in names:
        mine = [row for r in runs for row in r["rows"] if row["variant"] == name]
        poses = {tuple(tg): np.asarray(T) for row in mine for tg, T in row["poses"]}
        keys = [tuple(tg) for row in mine for tg in row.get("targets", [])] or list(poses)
        sc = score_poses(ds, objects, [bykey[k] for k in keys], poses, ar=True)
        n = len(keys)
        po = {o: round(100 * v, 1) for o, v in sc["per_object"].items()}
        rows.append({"variant": name, "hits": sc["hits"], "n": n, "med_rot": sc["med_rot"], "ar_mssd_mspd": sc["ar"],
                     "per_object": po, "poses": [[list(k), T.tolist()] for k, T in poses.items()]})
        print(f"| {name} | {sc['hits']}/{n} ({100 * sc['hits'] / n:.1f} %) | {sc['med_rot']:.1f} | {sc['ar']:.3f} | "
              + ", ".join(f"{o}: {v}" for o, v in po.items()) + " |", flush=True)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps({"merged": [str(p) for p in paths], "rows": rows}, indent=1))
    return 0


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--dataset", type=Path, default=L.DEFAULT_DATASET)
    ap.add_argument("--max-targets", type=int, default=48)
    ap.add_argument("--preset", default="default")
    ap.add_argument("--variant", action="append", default=[])
    ap.add_argument("--out", type=Path, default=REPO / "out/bench/lmo_align_study.json")
    ap.add_argument("--shard", default="0/1", help="K/N: compute stage 1 for targets[K::N] only (one process per core);"
                    " the variants run once every shard's targets are cached")
    ap.add_argument("--no-default", action="store_true", help="only the --variant rows (and 'no alignment')")
    ap.add_argument("--ar", action="store_true", help="also score each variant's poses with AR (MSSD/MSPD)")
    ap.add_argument("--part", default="0/1", help="K/N: run the variants on the cached targets[K::N] only (stage 2 on"
                    " both cores, each with its own --out / --dump; the rows then cover that part)")
    ap.add_argument("--merge", type=Path, nargs="+", default=None, metavar="STUDY_JSON",
                    help="score the rows of several --part runs' --out files together (all their targets) and exit")
    ap.add_argument("--dump", type=Path, default=None, help="write every aligned-stage candidate of each variant (pose,"
                    " terms, errors against the GT) to this pickle, for offline selection studies (bench/lmo_rank.py)")
    args = ap.parse_args(argv)
    ds = L.BopDataset(args.dataset)
    objects = L.ObjectCache(ds)
    if args.merge:
        return merge(ds, objects, args.merge, args.out)
    targets = L.select_targets(ds, args.max_targets)
    base = PixieConfig.from_preset(args.preset).apply_overrides(["align.enabled=false"])
    key = hashlib.sha256(json.dumps([TAG, args.preset, stage1_digest(base), [(t.scene_id, t.im_id, t.obj_id) for t in targets]],
                                    default=str).encode()).hexdigest()[:12]
    k, n = (int(v) for v in args.shard.split("/"))
    cached = stage1(ds, objects, targets, base, REPO / "out/bench/lmo_align_study" / f"{key}.pkl", (k, n))
    if cached is None:
        print(f"stage 1 (cache {key}): shard {k}/{n} done; other shards' targets still missing")
        return 0
    pk, pn = (int(v) for v in args.part.split("/"))
    cached = cached[pk::pn]
    variants = [("no alignment", None)] + ([] if args.no_default else [("default", [])]) + [(v.partition(":")[0], L.parse_config_arg(v)[1])
                                                           for v in args.variant]
    rows = []
    print(f"{len(cached)} targets (preset {args.preset}, stage-1 cache {key})")
    print("| variant | ADD(-S)<0.1d | any aligned right | med rot° | s/target |")
    print("|---|---|---|---|---|")
    ests: dict[int, PoseEstimator] = {}
    dumps: dict[str, list] = {}
    for name, overrides in variants:
        anyr, secs, poses, dumped = 0, 0.0, {}, []
        cfg = PixieConfig.from_preset(args.preset).apply_overrides(["align.enabled=true"] + (overrides or []))
        for rec in cached:
            if not rec["hyps"]:  # no hypothesis at all: a miss in every variant
                continue
            if overrides is None:
                poses[tuple(rec["target"])] = rec["hyps"][0].T_cam_from_obj
                continue
            od = objects.eval_data(rec["target"][2])
            g = L.gt_instance(ds, rec["t"])
            hyps, dt = align_cached(ds, objects, rec, cfg, base, ests)
            secs += dt
            poses[tuple(rec["target"])] = hyps[0].T_cam_from_obj
            anyr += any(L.pose_errors(od, h.T_cam_from_obj, g.T_cam_from_obj)["add_ok"]
                        for h in hyps if h.source in ("aligned", "flip"))
            if args.dump is not None:
                dumped.append(candidate_records(rec, hyps, od, g))
        n = len(cached)
        sc = score_poses(ds, objects, [r["t"] for r in cached], poses, args.ar)
        hits, ar = sc["hits"], sc["ar"]
        rows.append({"variant": name, "overrides": overrides, "hits": hits, "n": n, "any": anyr,
                     "targets": [list(r["target"]) for r in cached],
                     "med_rot": sc["med_rot"], "s_per_target": secs / n, "per_target": sc["per_target"],
                     "per_object": sc["per_object"], "ar_mssd_mspd": ar,
                     "poses": [[list(k), T.tolist()] for k, T in poses.items()]})
        if args.dump is not None:
            dumps[name] = dumped
        print(f"| {name} | {hits}/{n} ({100 * hits / n:.1f} %) | {anyr} | {sc['med_rot']:.1f} | {secs / n:.2f} |"
              + ("" if ar is None else f" AR {ar:.3f}"), flush=True)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    if args.dump is not None:
        args.dump.parent.mkdir(parents=True, exist_ok=True)
        tmp = args.dump.with_suffix(".tmp")
        tmp.write_bytes(pickle.dumps({"key": key, "preset": args.preset, "variants": dumps}))
        tmp.replace(args.dump)
    args.out.write_text(json.dumps({"args": vars(args) | {"dataset": str(args.dataset), "out": str(args.out)},
                                    "rows": rows}, indent=1, default=str))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
