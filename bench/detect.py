"""LINE-2D proposals (pixie.cues.detect) on LM-O dev: recall of the object's box among the best proposals.

Usage::

    PYTHONPATH=src .venv/bin/python bench/detect.py [--max-targets 96] [--distance 340,1500] [--top 5] \
        [--out out/bench/detect.json]

Per target: the reference set's contour templates (the preset's set, from the bench cache), rolled and scaled to
the distance range, searched over the whole photo; the best ``--top`` boxes after non-maximum suppression are
compared with the GT amodal box (``bbox_obj``) and the visible box (``bbox_visib``), IoU >= 0.5. Prints one table
(per object and all: recall of the best proposal and of the top 5, seconds per image for the search) and writes it
as JSON. No pose is estimated (the verification of :func:`pixie.pipeline.find.find_objects` is not measured here).
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
from pixie.pose.solve import box_iou  # noqa: E402
from pixie.references.templates import ContourTemplates  # noqa: E402


def xyxy(b) -> np.ndarray:
    b = np.asarray(b, np.float64)
    return np.r_[b[:2], b[:2] + b[2:]]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--dataset", type=Path, default=L.DEFAULT_DATASET)
    ap.add_argument("--max-targets", type=int, default=96)
    ap.add_argument("--distance", default="340,1500", help="distance range searched, mm (LM-O: 346-1500)")
    ap.add_argument("--top", type=int, default=5)
    ap.add_argument("--preset", default="default")
    ap.add_argument("--out", type=Path, default=L.REPO / "out/bench/detect.json")
    args = ap.parse_args(argv)
    ds = L.BopDataset(args.dataset)
    objects = L.ObjectCache(ds)
    cfg = PixieConfig.from_preset(args.preset)
    dist = tuple(float(v) for v in args.distance.split(","))
    targets = L.select_targets(ds, args.max_targets)
    matcher = None
    rows, per = [], {}
    dets: dict[int, TemplateDetector] = {}  # every object's, kept: targets come image by image
    for t in targets:
        if t.obj_id not in dets:
            matcher = matcher or make_matcher(cfg)
            refs = objects.refs(cfg, t.obj_id, matcher)
            K0 = ds.camera(t.scene_id, t.im_id).K
            t0 = time.perf_counter()
            dets[t.obj_id] = (TemplateDetector(ContourTemplates.from_arrays(refs.templates), K0,
                                               diameter=refs.mesh.diameter, distance_mm=dist,
                                               cache_dir=L.REPO / "out/bench/line2d"))
            print(f"obj {t.obj_id}: {dets[t.obj_id].n_templates} templates in {time.perf_counter() - t0:.1f} s",
                  flush=True)
        g = L.gt_instance(ds, t)
        img = ds.load_rgb(t.scene_id, t.im_id)
        t0 = time.perf_counter()
        props = dets[t.obj_id].propose(img, top_k=args.top)
        dt = time.perf_counter() - t0
        amodal = [box_iou(p.box_xyxy, xyxy(g.box_obj)) for p in props]
        visib = [box_iou(p.box_xyxy, xyxy(g.box_visib)) for p in props]
        r = {"target": [t.scene_id, t.im_id, t.obj_id], "visib_fract": g.visib_fract, "seconds": dt,
             "top1": bool(amodal[:1] and amodal[0] >= 0.5), "topk": bool(max(amodal, default=0) >= 0.5),
             "top1_visib": bool(visib[:1] and visib[0] >= 0.5), "topk_visib": bool(max(visib, default=0) >= 0.5)}
        rows.append(r)
        per.setdefault(t.obj_id, []).append(r)
        print(f"  {len(rows)}/{len(targets)} {t.scene_id}/{t.im_id} obj {t.obj_id}: best IoU {max(amodal, default=0):.2f} "
              f"(visible {max(visib, default=0):.2f}), {dt:.1f} s", flush=True)
    def line(name, rs):
        m = lambda k: np.mean([r[k] for r in rs])  # noqa: E731
        return (f"| {name} | {len(rs)} | {m('top1'):.2f} | {m('topk'):.2f} | {m('top1_visib'):.2f} | "
                f"{m('topk_visib'):.2f} | {np.mean([r['seconds'] for r in rs]):.2f} |")
    print(f"| object | n | best proposal (amodal box) | top {args.top} | best (visible box) | top {args.top} | s/image |")
    print("|---|---|---|---|---|---|---|")
    for o in sorted(per):
        print(line(str(o), per[o]))
    print(line("all", rows))
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps({"args": {k: str(v) for k, v in vars(args).items()}, "rows": rows}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
