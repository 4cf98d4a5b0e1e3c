"""Where the shipped pipeline loses its LM-O targets, by cause and by how much of the object is visible.

Usage::

    OMP_NUM_THREADS=1 PYTHONPATH=src .venv/bin/python bench/lmo_losses.py [--max-targets 192] [--set align.key=value ...] \
        [--template-boxes] [--out out/bench/lmo_losses.json]

Builds on ``bench/lmo_align_study.py``: its stage-1 cache (the pipeline up to the shape stage, every hypothesis
kept), then the alignment stage of the preset (with the ``--set`` overrides) on each target. Per target the chosen
pose and every candidate (the aligned ones and their starts) are scored against the ground truth. Prints:

* the causes: chosen right (ADD(-S)<0.1d); *retrieval* (no candidate within 15° of the GT rotation); *depth*
  (the chosen pose within 15°, wrong: another candidate right, or none); *only a start right* (an unaligned start
  is right, no aligned pose is: the alignment moved it off); *selection* (a pose > 15° off chosen while another
  is right);
* the same by the GT visible fraction (``visib_fract``) and by how much occlusion shrinks the box;
* recall of the distinct pool (10° apart, in the ranking the alignment stage sees) within 15° at k = 1 ... all;
* with ``--template-boxes``: the edge-template retrieval (``ShapeCues.retrieve``, 24 candidates) from the GT
  *visible* box and from the GT *full* box (``bbox_obj``): what template placement under occlusion costs.

Writes the JSON (per target: causes, errors, visibility).
"""

from __future__ import annotations

import argparse
import hashlib
import json
from pathlib import Path

import numpy as np

import common as L  # noqa: E402  (bench/common.py)
import lmo_align_study as S  # noqa: E402  (its stage-1 cache and align_cached)

from pixie.app.runner import make_matcher  # noqa: E402
from pixie.config import PixieConfig  # noqa: E402
from pixie.cues.shape import shape_cues  # noqa: E402
from pixie.pipeline.estimator import PoseEstimator  # noqa: E402
from pixie.pipeline.query import check_bbox  # noqa: E402

KS = (1, 2, 4, 8, 16, 1000)


def cause(cands: list[dict]) -> str:
    """The loss category of one target from its scored candidates (chosen first)."""
    c0 = cands[0]
    if c0["ok"]:
        return "right"
    if not any(c["rot"] < 15 for c in cands):
        return "retrieval"
    aligned_ok = any(c["ok"] for c in cands if c["aligned"])
    start_ok = any(c["ok"] for c in cands if not c["aligned"])
    if start_ok and not aligned_ok:
        return "only a start right"
    if c0["rot"] < 15:
        return "depth (another right)" if aligned_ok else "depth (none right)"
    return "selection" if aligned_ok else "other"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--dataset", type=Path, default=L.DEFAULT_DATASET)
    ap.add_argument("--max-targets", type=int, default=192)
    ap.add_argument("--preset", default="default")
    ap.add_argument("--set", action="append", default=[], dest="sets")
    ap.add_argument("--template-boxes", action="store_true")
    ap.add_argument("--out", type=Path, default=L.REPO / "out/bench/lmo_losses.json")
    args = ap.parse_args(argv)
    ds = L.BopDataset(args.dataset)
    objects = L.ObjectCache(ds)
    targets = L.select_targets(ds, args.max_targets)
    base = PixieConfig.from_preset(args.preset).apply_overrides(["align.enabled=false"])
    key = hashlib.sha256(json.dumps([S.TAG, args.preset, base.digest(), [(t.scene_id, t.im_id, t.obj_id) for t in targets]],
                                    default=str).encode()).hexdigest()[:12]
    cached = S.stage1(ds, objects, targets, base, L.REPO / "out/bench/lmo_align_study" / f"{key}.pkl")
    cfg = PixieConfig.from_preset(args.preset).apply_overrides(["align.enabled=true"] + args.sets)
    ests: dict = {}
    rows = []
    recall = {k: 0 for k in KS}
    cues: dict = {}
    tpl = {"visib": {k: 0 for k in (1, 4, 24)}, "obj": {k: 0 for k in (1, 4, 24)}}
    matcher = make_matcher(base) if args.template_boxes else None
    for rec in cached:
        sid, iid, oid = rec["target"]
        od = objects.eval_data(oid)
        g = L.gt_instance(ds, rec["t"])
        hyps, _ = S.align_cached(ds, objects, rec, cfg, base, ests)
        cands = []
        for h in hyps:
            if not h.terms or "fit" not in h.terms:
                continue
            e = L.pose_errors(od, h.T_cam_from_obj, g.T_cam_from_obj)
            cands.append({"ok": bool(e["add_ok"]), "rot": float(e["rot_err"]), "aligned": h.source in ("aligned", "flip"),
                          "dz": float(h.T_cam_from_obj[2, 3] / g.T_cam_from_obj[2, 3] - 1), "source": h.source})
        pool = [L.pose_errors(od, h.T_cam_from_obj, g.T_cam_from_obj)["rot_err"] for h in PoseEstimator.distinct(rec["hyps"], len(rec["hyps"]))]
        for k in KS:
            recall[k] += any(r < 15 for r in pool[:k])
        bv, bo = np.asarray(g.bbox_visib, float), np.asarray(g.bbox_obj, float)
        row = {"target": [sid, iid, oid], "cause": cause(cands), "chosen": cands[0], "visib_fract": g.visib_fract,
               "box_side_ratio": float(max(bv[2], bv[3]) / max(bo[2], bo[3], 1.0))}
        if args.template_boxes:
            if oid not in cues:
                cues[oid] = shape_cues(objects.refs(base, oid, matcher), base.shape)
            img = ds.load_rgb(sid, iid)
            K = ds.camera(sid, iid).K
            for name, b in (("visib", g.box_visib), ("obj", g.box_obj)):
                cs = cues[oid].retrieve(cues[oid].query(img, check_bbox(b, img.shape[:2])), K, 24)
                errs = [L.pose_errors(od, c.T_cam_from_obj, g.T_cam_from_obj)["rot_err"] for c in cs]
                for k in tpl[name]:
                    tpl[name][k] += any(e < 15 for e in errs[:k])
        rows.append(row)
    n = len(rows)
    causes = sorted({r["cause"] for r in rows}, key=lambda c: -sum(r["cause"] == c for r in rows))
    print(f"{n} targets (preset {args.preset}{', ' + ', '.join(args.sets) if args.sets else ''}; stage-1 cache {key})")
    print("\n| cause | targets | share |\n|---|---|---|")
    for c in causes:
        m = sum(r["cause"] == c for r in rows)
        print(f"| {c} | {m} | {100 * m / n:.1f} % |")
    print("\n| visible fraction | targets | chosen right | some candidate within 15° |\n|---|---|---|---|")
    bins = {}
    for lo, hi in ((0.0, 0.5), (0.5, 0.7), (0.7, 0.9), (0.9, 1.01)):
        sel = [r for r in rows if r["visib_fract"] is not None and lo <= r["visib_fract"] < hi]
        right = sum(r["cause"] == "right" for r in sel)
        near = sum(r["cause"] != "retrieval" for r in sel)
        bins[f"{lo}-{min(hi, 1.0)}"] = {"n": len(sel), "right": right, "within_15": near}
        print(f"| {lo:.1f}–{min(hi, 1.0):.1f} | {len(sel)} | {right} | {near} |")
    print("\n| visible box / full box (longer side) | targets | chosen right | some candidate within 15° |\n|---|---|---|---|")
    for lo, hi in ((0.0, 0.95), (0.95, 1.01)):
        sel = [r for r in rows if lo <= r["box_side_ratio"] < hi]
        print(f"| {lo:.2f}–{min(hi, 1.0):.2f} | {len(sel)} | {sum(r['cause'] == 'right' for r in sel)} | "
              f"{sum(r['cause'] != 'retrieval' for r in sel)} |")
    print("\nrecall of the distinct pool within 15° at k: " + ", ".join(f"{k}: {recall[k]}" for k in KS))
    if args.template_boxes:
        print("edge templates within 15° (top 1 / 4 / 24): visible box "
              + " / ".join(str(tpl["visib"][k]) for k in (1, 4, 24)) + ", full box "
              + " / ".join(str(tpl["obj"][k]) for k in (1, 4, 24)))
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps({"args": {**vars(args), "dataset": str(args.dataset), "out": str(args.out)},
                                    "causes": {c: sum(r["cause"] == c for r in rows) for c in causes},
                                    "visibility": bins, "pool_recall_15deg": recall,
                                    "templates_15deg": tpl if args.template_boxes else None, "rows": rows},
                                   indent=1, default=str))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
