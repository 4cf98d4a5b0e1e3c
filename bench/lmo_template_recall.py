"""Contour-template retrieval on LM-O: how often does the shape stage's template search put a right rotation among
its candidates, per ``config.shape`` variant?

Usage::

    OMP_NUM_THREADS=1 PYTHONPATH=src .venv/bin/python bench/lmo_template_recall.py --max-targets 716 \
        --variant "base:" --variant "rw2:shape.region_weight=2" [--part K/N] [--out out/bench/tpl_recall.json]

(Session 25 measured side-anchored placements, ``shape.anchors``, with it at commit 89a80fb; that option was not kept.)

For every target (GT ``bbox_visib`` box) the query crop's response maps are built once and each variant's
:meth:`pixie.cues.shape.ShapeCues.retrieve` returns its ``shape.candidates`` template poses (depth from the box, as the
shape stage does). A candidate is right when its rotation is within ``--near`` degrees of the GT (the smallest over the
object's symmetries). Prints recall at 1 / 4 / all candidates, overall and for targets more or less than
``--occluded`` visible, the median centre error (px) of the first right candidate, and seconds per target; writes
the per-target ranks as JSON (``--merge`` pools the JSON of ``--part`` runs).
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

import common as L  # noqa: E402  (bench/common.py: targets, object cache, presets)

from pixie.app.runner import make_matcher  # noqa: E402
from pixie.cues.shape import shape_cues  # noqa: E402
from pixie.geometry.camera import project, transform_points  # noqa: E402
from pixie.pipeline.query import check_bbox  # noqa: E402
from pixie.pose.solve import depth_from_box  # noqa: E402

def table(rows: dict[str, list[dict]], near: float, occluded: float) -> str:
    out = [f"| variant | targets | right@1 | right@4 | right@all | occluded (<{occluded:g}) @4 / @all | "
           f"visible @4 / @all | centre err px (median) | s/target |", "|---|---|---|---|---|---|---|---|---|"]
    for name, rs in rows.items():
        n = len(rs)
        rk = np.array([r["rank"] if r["rank"] is not None else 999 for r in rs])
        occ = np.array([r["visib"] < occluded for r in rs])
        c = [r["centre_px"] for r in rs if r["centre_px"] is not None]
        out.append(f"| {name} | {n} | {np.mean(rk < 1):.3f} | {np.mean(rk < 4):.3f} | {np.mean(rk < 999):.3f} | "
                   f"{np.mean(rk[occ] < 4):.3f} / {np.mean(rk[occ] < 999):.3f} ({occ.sum()}) | "
                   f"{np.mean(rk[~occ] < 4):.3f} / {np.mean(rk[~occ] < 999):.3f} | "
                   f"{np.median(c) if c else float('nan'):.1f} | {np.mean([r['seconds'] for r in rs]):.3f} |")
    return "\n".join(out)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--dataset", type=Path, default=L.DEFAULT_DATASET)
    ap.add_argument("--max-targets", type=int, default=96)
    L.add_preset_arg(ap)
    ap.add_argument("--variant", action="append", default=[], help="NAME:section.key=value,... (repeatable)")
    ap.add_argument("--near", type=float, default=15.0)
    ap.add_argument("--occluded", type=float, default=0.7, help="visible fraction below which a target is occluded")
    ap.add_argument("--part", default="0/1", help="K/N: only targets[K::N]")
    ap.add_argument("--merge", nargs="+", type=Path, help="pool these JSON outputs and print the table")
    ap.add_argument("--out", type=Path, default=L.REPO / "out/bench/tpl_recall.json")
    a = ap.parse_args(argv)
    if a.merge:
        rows: dict[str, list[dict]] = {}
        for p in a.merge:
            for k, v in json.loads(p.read_text())["rows"].items():
                rows.setdefault(k, []).extend(v)
        print(table(rows, a.near, a.occluded))
        return 0
    variants = [L.parse_config_arg(v) for v in (a.variant or ["base:"])]
    ds = L.BopDataset(a.dataset)
    objects = L.ObjectCache(ds)
    targets = L.select_targets(ds, a.max_targets)
    k, n = (int(x) for x in a.part.split("/"))
    targets = targets[k::n]
    base = L.make_config([], a.preset)
    matcher = None
    cues: dict[tuple[str, int], object] = {}
    rows = {name: [] for name, _ in variants}
    for i, t in enumerate(targets):
        g = L.gt_instance(ds, t)
        od = objects.eval_data(t.obj_id)
        img = ds.load_rgb(t.scene_id, t.im_id)
        K = ds.camera(t.scene_id, t.im_id).K
        box = check_bbox(g.box_visib, img.shape[:2])
        mesh = objects.mesh(t.obj_id)
        centre_px = lambda T: project(K, transform_points(T, mesh.center[None]))[0]  # noqa: E731
        c_gt = centre_px(g.T_cam_from_obj)
        q = None
        for name, ov in variants:
            cfg = L.make_config(ov, a.preset)
            if (name, t.obj_id) not in cues:
                matcher = matcher or make_matcher(base)
                cues[(name, t.obj_id)] = shape_cues(objects.refs(base, t.obj_id, matcher), cfg.shape)
            sc = cues[(name, t.obj_id)]
            t0 = time.perf_counter()
            q = q or sc.query(img, box)
            cands = sc.retrieve(q, K, cfg.shape.candidates)
            sec = time.perf_counter() - t0
            Ts = [depth_from_box(c.T_cam_from_obj, K, mesh.hull_vertices, box) for c in cands]
            errs = [L.pose_errors(od, T, g.T_cam_from_obj)["rot_err"] for T in Ts]  # the smallest over symmetries
            good = [j for j, e in enumerate(errs) if e < a.near]
            cpx = None
            if good:
                cpx = float(np.linalg.norm(centre_px(Ts[good[0]]) - c_gt))
            rows[name].append({"target": [t.scene_id, t.im_id, t.obj_id], "rank": good[0] if good else None,
                               "best_err": float(min(errs)) if errs else None, "visib": float(g.visib_fract or 0.0),
                               "centre_px": cpx, "seconds": sec})
        if (i + 1) % 50 == 0:
            print(f"  {i + 1}/{len(targets)}", flush=True)
    print(table(rows, a.near, a.occluded))
    a.out.parent.mkdir(parents=True, exist_ok=True)
    a.out.write_text(json.dumps({"variants": dict(variants), "near": a.near, "rows": rows}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
