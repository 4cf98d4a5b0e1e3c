"""LINE-2D proposals (pixie.cues.detect) on a BOP set (LM-O dev, the defects benchmark): recall of the object's box.

Usage::

    PYTHONPATH=src .venv/bin/python bench/detect.py [--dataset DIR] [--max-targets 96] [--distance 340,1500] \
        [--top 5] [--grow 1.3] [--verify] [--gt-box] [--exclude 48] [--rerank 30] [--out out/bench/detect.json]

Per target: the reference set's contour templates (the preset's set, from the bench cache), rolled and scaled to
the distance range, searched over the whole photo; the best ``--top`` boxes after non-maximum suppression are
compared with the GT amodal box (``bbox_obj``) and the visible box (``bbox_visib``), IoU >= 0.5. Prints one table
(per object and all: recall of the best proposal and of the top 5, seconds per image for the search) and writes it
as JSON. With ``--verify`` the whole search of :func:`pixie.pipeline.find.find_objects` runs instead (its ``--top``
proposals each estimated, the most confident supported pose kept): the table adds the share of targets found, found
with the kept pose's projected box at IoU >= 0.5 with the amodal box, and with that pose ADD(-S) < 0.1 d, and the
seconds per image of the whole search; ``--gt-box`` adds the same code's ADD(-S) from the GT visible box. With
``--rerank N``: the best N proposals are each aligned from the pose their template stands for
(:meth:`TemplateDetector.pose`, :meth:`PoseEstimator.estimate_from_prior`) and re-ranked by the aligned fit; the table
adds the recall of that order (the aligned pose's projected box, IoU >= 0.5 with the amodal box) and the JSON every
proposal's terms.

The table also gives each object's **AP** (IoU >= 0.5 with the amodal box): the best ``--top`` proposals of every
target of that object pooled and ranked by the detector's rank score across photos, one GT box per target, the
first proposal on it a true positive, every other a false positive (all-point interpolated precision, as PASCAL VOC
2010+). Over all 716 LM-O targets the search takes hours on one core: ``--shard K/N`` runs ``targets[K::N]`` (one
process per core, each with its own ``--out``), ``--merge OUT...`` prints the table over their rows.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

import common as L  # noqa: E402  (bench/common.py: targets, object cache, presets)

from pixie.app.runner import make_matcher  # noqa: E402
from pixie.config import PixieConfig  # noqa: E402
from pixie.cues.detect import TemplateDetector  # noqa: E402
from pixie.errors import PixieError  # noqa: E402
from pixie.geometry.render import Renderer  # noqa: E402
from pixie.pipeline.estimator import PoseEstimator  # noqa: E402
from pixie.pipeline.find import detector_for, find_objects, propose_kwargs  # noqa: E402
from pixie.pose.solve import box_iou, projected_box  # noqa: E402
from pixie.references.templates import ContourTemplates  # noqa: E402


def xyxy(b) -> np.ndarray:
    b = np.asarray(b, np.float64)
    return np.r_[b[:2], b[:2] + b[2:]]


def average_precision(rows: list[dict], top: int) -> float:
    """AP (IoU >= 0.5 with the amodal box) of the best ``top`` proposals of ``rows`` (one object's targets, one GT box
    each), pooled and ranked by rank score; all-point interpolation. nan without targets."""
    if not rows:
        return float("nan")
    dets = []
    for i, r in enumerate(rows):
        p = r["proposals"]
        rank = p.get("rank_scores") or []
        if len(rank) != len(p["scores"]) or any(v is None for v in rank):  # rows written before rank scores were kept
            rank = p["scores"]
        dets += [(float(sc), i, float(iou)) for sc, iou in list(zip(rank, p["ious"]))[:top]]
    dets.sort(key=lambda d: -d[0])
    seen, tp = set(), []
    for _, i, iou in dets:
        hit = iou >= 0.5 and i not in seen
        if hit:
            seen.add(i)
        tp.append(hit)
    tp = np.asarray(tp, float)
    if not len(tp):
        return 0.0
    ctp, cfp = np.cumsum(tp), np.cumsum(1.0 - tp)
    recall = np.r_[0.0, ctp / len(rows), 1.0]
    precision = np.r_[1.0, ctp / np.maximum(ctp + cfp, 1e-12), 0.0]
    precision = np.maximum.accumulate(precision[::-1])[::-1]  # the envelope
    return float(np.sum((recall[1:] - recall[:-1]) * precision[1:]))


def table(rows: list[dict], top: int, verify: bool = False, gt_box: bool = False, rerank: int = 0) -> list[str]:
    """The printed table: per object and all, recall of the best / top proposals (amodal and visible box), AP,
    seconds per image, and the --verify / --gt-box / --rerank columns when the rows have them."""
    per: dict[int, list[dict]] = {}
    for r in rows:
        per.setdefault(int(r["target"][2]), []).append(r)

    def line(name, rs, ap_):
        m = lambda k: np.mean([r[k] for r in rs])  # noqa: E731
        s = (f"| {name} | {len(rs)} | {m('top1'):.2f} | {m('topk'):.2f} | {m('top1_visib'):.2f} | "
             f"{m('topk_visib'):.2f} | {ap_:.2f} | {np.mean([r['seconds'] for r in rs]):.2f} |")
        if verify:
            s += f" {m('found'):.2f} | {m('found_box'):.2f} | {m('found_add'):.2f} | {m('seconds_find'):.1f} |"
        if gt_box:
            s += f" {m('gt_box_add'):.2f} |"
        if rerank:
            s += f" {m('any_of_n'):.2f} | {m('rerank_top1'):.2f} | {m('rerank_topk'):.2f} | {m('seconds_rerank'):.2f} |"
        return s
    head = (f"| object | n | best proposal (amodal box) | top {top} | best (visible box) | top {top} | AP (top {top}) "
            f"| s/image |")
    if verify:
        head += " found | found, box IoU >= 0.5 | found, ADD(-S) < 0.1 d | s/image (whole search) |"
    if gt_box:
        head += " GT visible box: ADD(-S) < 0.1 d |"
    if rerank:
        head += (f" any of the {rerank} | re-ranked by aligned fit: best (aligned box) | top {top} | "
                 f"s/image (alignment) |")
    aps = {o: average_precision(per[o], top) for o in sorted(per)}
    out = [head, "|---" * (head.count("|") - 1) + "|"]
    out += [line(str(o), per[o], aps[o]) for o in sorted(per)]
    out.append(line("all", rows, float(np.mean(list(aps.values()))) if aps else float("nan")) + "  (AP: mean over objects)")
    return out


def merge(paths: list[Path], out: Path) -> int:
    """One table over the rows of several ``--shard`` runs (their ``--out`` JSONs), written to ``out``."""
    runs = [json.loads(Path(p).read_text()) for p in paths]
    a = runs[0]["args"]
    rows = [r for run in runs for r in run["rows"]]
    flags = dict(top=int(a["top"]), verify=a["verify"] == "True", gt_box=a["gt_box"] == "True", rerank=int(a["rerank"]))
    for ln in table(rows, **flags):
        print(ln)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps({"merged": [str(p) for p in paths], "args": a, "rows": rows}, indent=1))
    return 0


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--dataset", type=Path, default=L.DEFAULT_DATASET)
    ap.add_argument("--max-targets", type=int, default=96)
    ap.add_argument("--distance", default="340,1500", help="distance range searched, mm (LM-O: 346-1500)")
    ap.add_argument("--top", type=int, default=5)
    ap.add_argument("--preset", default="default")
    ap.add_argument("--set", action="append", default=[], metavar="SECTION.KEY=VALUE",
                    help="config override on top of --preset (e.g. detect.accept=[...])")
    ap.add_argument("--out", type=Path, default=L.REPO / "out/bench/detect.json")
    ap.add_argument("--rerank", type=int, default=0, metavar="N",
                    help="also align each of the best N proposals from its template's pose "
                         "(PoseEstimator.estimate_from_prior) and rank them by the aligned fit")
    ap.add_argument("--nms", type=float, help="non-maximum suppression IoU of the proposals (default: config detect)")
    ap.add_argument("--grow", type=float,
                    help="a suppressed box survives when its area is more than this times the better box's (0: never)")
    ap.add_argument("--stop-confidence", type=float,
                    help="--verify: estimate no more proposals once a pose is kept at this confidence (0: never stop)")
    ap.add_argument("--gt-box", action="store_true",
                    help="also estimate each target from its GT visible box (the same code's GT-box ADD(-S))")
    ap.add_argument("--exclude", type=int, default=0, metavar="N",
                    help="leave out the targets --max-targets N would pick (the set a parameter was chosen on)")
    ap.add_argument("--verify", action="store_true",
                    help="run find_objects (proposals, each estimated, the supported pose kept) and score its pose")
    ap.add_argument("--threshold", type=float, help="LINE-2D similarity threshold (0-100; default: config detect)")
    ap.add_argument("--shard", default="0/1", help="K/N: run targets[K::N] only (one process per core)")
    ap.add_argument("--merge", type=Path, nargs="+", default=None, metavar="OUT_JSON",
                    help="print the table over several --shard runs' --out files (written to --out) and exit")
    args = ap.parse_args(argv)
    if args.merge:
        return merge(args.merge, args.out)
    ds = L.BopDataset(args.dataset)
    objects = L.ObjectCache(ds)
    cfg = PixieConfig.from_preset(args.preset).apply_overrides(args.set)
    for key, value in (("nms_iou", args.nms), ("grow_ratio", args.grow), ("stop_confidence", args.stop_confidence),
                       ("threshold", args.threshold)):
        if value is not None:
            setattr(cfg.detect, key, value)
    dc = cfg.detect
    dist = tuple(float(v) for v in args.distance.split(","))
    targets = L.select_targets(ds, args.max_targets)
    if args.exclude:  # leave out the targets a parameter was chosen on
        chosen = {(t.scene_id, t.im_id, t.obj_id) for t in L.select_targets(ds, args.exclude)}
        targets = [t for t in targets if (t.scene_id, t.im_id, t.obj_id) not in chosen]
    k, n = (int(v) for v in args.shard.split("/"))
    targets = targets[k::n]
    matcher = None
    ests: dict[int, PoseEstimator] = {}
    rows = []
    dets: dict[int, TemplateDetector] = {}  # every object's, kept: targets come image by image
    det_kw = dict(distance_mm=dist, cache_dir=L.REPO / "out/bench/line2d")

    def estimator(oid: int) -> PoseEstimator:
        nonlocal matcher
        if oid not in ests:
            matcher = matcher or make_matcher(cfg)
            ests[oid] = PoseEstimator(objects.refs(cfg, oid, matcher), cfg, matcher)
        return ests[oid]

    for t in targets:
        K = ds.camera(t.scene_id, t.im_id).K
        if t.obj_id not in dets:
            t0 = time.perf_counter()
            if args.verify:  # the detector find_objects uses (cached on the estimator)
                dets[t.obj_id] = detector_for(estimator(t.obj_id), K, **det_kw)
            else:
                matcher = matcher or make_matcher(cfg)
                refs = objects.refs(cfg, t.obj_id, matcher)
                dets[t.obj_id] = TemplateDetector(ContourTemplates.from_arrays(refs.templates), K,
                                                  diameter=refs.mesh.diameter, renderer=Renderer(refs.mesh), **det_kw)
            print(f"obj {t.obj_id}: {dets[t.obj_id].n_templates} templates in {time.perf_counter() - t0:.1f} s",
                  flush=True)
        g = L.gt_instance(ds, t)
        img = ds.load_rgb(t.scene_id, t.im_id)
        verified = {}
        t0 = time.perf_counter()
        if args.verify:
            found = find_objects(estimator(t.obj_id), img, K, top_k=args.top, **det_kw)  # the rest: config detect
            props, dt = found.proposals, found.timings["propose"]
            best = found.poses[0] if found.poses else None
            T = None if best is None else best.T_cam_from_obj
            e = L.pose_errors(objects.eval_data(t.obj_id), T, g.T_cam_from_obj)
            iou_pose = 0.0 if T is None else box_iou(projected_box(T, K, estimator(t.obj_id).box_points),
                                                      xyxy(g.box_obj))
            per_prop = []  # every proposal's estimate: its named scores and whether it is right
            for pr, res, terms in zip(found.proposals, found.estimates, found.terms):
                rec = {"iou_gt": box_iou(pr.box_xyxy, xyxy(g.box_obj)), **terms}
                if res is not None and res.T_cam_from_obj is not None:
                    ep = L.pose_errors(objects.eval_data(t.obj_id), res.T_cam_from_obj, g.T_cam_from_obj)
                    rec.update(add_ok=bool(ep["add_ok"]), pose_iou_gt=box_iou(
                        projected_box(res.T_cam_from_obj, K, estimator(t.obj_id).box_points), xyxy(g.box_obj)))
                per_prop.append(rec)
            verified = {"found": found.found, "estimates": per_prop, "found_box": bool(iou_pose >= 0.5), "found_add": e["add_ok"],
                        "iou_pose": iou_pose, "confidence": None if best is None else best.confidence,
                        "seconds_find": found.timings["total"], "verdicts": found.verdicts}
        else:
            props = dets[t.obj_id].propose(img, top_k=max(args.top, args.rerank), **propose_kwargs(dc))
            dt = time.perf_counter() - t0
        box_obj = xyxy(g.box_obj)
        amodal = [box_iou(p.box_xyxy, box_obj) for p in props]  # every proposal's, the best --top ones reported below
        cands = []
        if args.rerank:
            est = estimator(t.obj_id)
            t1 = time.perf_counter()
            for p, iou in zip(props[: args.rerank], amodal):
                T0 = dets[t.obj_id].pose(p, K, est.refs.mesh.center, est.box_points)
                try:
                    res = est.estimate_from_prior(img, K, T0)
                except PixieError as e:  # e.g. a template pose partly behind the camera
                    cands.append({"score": p.score, "iou": iou, "error": str(e)})
                    continue
                pb = projected_box(res.T_cam_from_obj, K, est.box_points)
                terms = res.hypotheses[0].terms if res.hypotheses else {}
                cands.append({"score": p.score, "iou": iou, "iou_aligned": box_iou(pb, box_obj),
                              "box_aligned": pb.tolist(), **{k: float(v) for k, v in terms.items()}})
            dt_rerank = time.perf_counter() - t1
        ranked = {"ious": [round(float(v), 3) for v in amodal], "scores": [round(p.score, 2) for p in props],
                  "rank_scores": [None if not np.isfinite(p.rank_score) else round(float(p.rank_score), 3)
                                  for p in props],
                  "votes": [p.votes for p in props],
                  "regions": [None if not np.isfinite(p.region) else round(float(p.region), 4) for p in props],
                  "boxes": [[round(float(v), 1) for v in p.box_xyxy] for p in props]}  # every proposal, best first
        props, amodal = props[: args.top], amodal[: args.top]
        visib = [box_iou(p.box_xyxy, xyxy(g.box_visib)) for p in props]
        r = {"target": [t.scene_id, t.im_id, t.obj_id], "visib_fract": g.visib_fract, "seconds": dt,
             "top1": bool(amodal[:1] and amodal[0] >= 0.5), "topk": bool(max(amodal, default=0) >= 0.5),
             "top1_visib": bool(visib[:1] and visib[0] >= 0.5), "topk_visib": bool(max(visib, default=0) >= 0.5),
             **verified, "proposals": ranked}
        if args.rerank:
            r["candidates"] = cands
            r["seconds_rerank"] = dt_rerank
            order = sorted(range(len(cands)), key=lambda i: -cands[i].get("fit", -1.0))
            hit = [cands[i].get("iou_aligned", 0.0) >= 0.5 for i in order]
            r["rerank_top1"] = bool(hit[:1] and hit[0])
            r["rerank_topk"] = bool(any(hit[: args.top]))
            r["any_of_n"] = bool(any(c["iou"] >= 0.5 for c in cands))
        if args.gt_box:
            t1 = time.perf_counter()
            res = estimator(t.obj_id).estimate(img, K, bbox=g.box_visib)
            r["gt_box_add"] = L.pose_errors(objects.eval_data(t.obj_id), res.T_cam_from_obj, g.T_cam_from_obj)["add_ok"]
            r["seconds_gt_box"] = time.perf_counter() - t1
        rows.append(r)
        extra = ""
        if args.verify:
            extra = (f"; found {found.found} (box {verified['found_box']}, ADD {verified['found_add']}, "
                     f"{verified['seconds_find']:.1f} s)")
        if args.rerank:
            extra += (f"; re-ranked top-1 {r['rerank_top1']}, top-{args.top} {r['rerank_topk']}, "
                      f"in the {args.rerank}: {r['any_of_n']} ({dt_rerank:.1f} s)")
        print(f"  {len(rows)}/{len(targets)} {t.scene_id}/{t.im_id} obj {t.obj_id}: best IoU {max(amodal, default=0):.2f} "
              f"(visible {max(visib, default=0):.2f}), {dt:.1f} s{extra}", flush=True)
    for ln in table(rows, args.top, args.verify, args.gt_box, args.rerank):
        print(ln)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps({"args": {k: str(v) for k, v in vars(args).items()}, "rows": rows}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
