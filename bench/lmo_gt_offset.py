"""How far LM-O's ground truth sits from the photo where pixie's poses are nearly right: a ceiling on RGB-only precision.

Usage::

    PYTHONPATH=src .venv/bin/python bench/lmo_gt_offset.py [--poses out/bench/rank/merged_regionfb.json] \
        [--variant NAME] [--max-deg 10] [--out out/bench/lmo_gt_offset.json]

Reads the chosen poses of one variant of a ``bench/lmo_align_study.py`` output (``--out`` or ``--merge`` JSON: rows
with ``poses``; by default the last row) and, for the targets whose rotation is within ``--max-deg`` of the GT, prints
per object and over all: the median image offset of the object's centre (pose − GT, photo px, u right and v down),
the median relative depth difference (pose − GT) / GT, and how many of them are ADD(-S)<0.1d hits. A pose aligned
to the photo's edges that is consistently offset from the GT in one direction across objects of every colour points
at the GT's registration to the RGB image (LM's GT comes from depth), not at the alignment; the convergence test on
rendered photos (exact GT) ends within 1° and 1 % depth.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

import common as L  # noqa: E402  (bench/common.py: targets, object cache; puts src/ on the path)

from pixie.geometry.camera import project, transform_points  # noqa: E402

REPO = L.REPO
NAMES = {1: "ape", 5: "can", 6: "cat", 8: "driller", 9: "duck", 10: "eggbox", 11: "glue", 12: "holepuncher"}


def centre_offset(K: np.ndarray, center: np.ndarray, T: np.ndarray, T_gt: np.ndarray) -> tuple[np.ndarray, float]:
    """Image offset (2,) in px of the object centre ``center`` (object frame) projected with ``T`` minus with
    ``T_gt``, and the relative depth difference of the centre, (z - z_gt) / z_gt."""
    X, Xg = transform_points(T, center), transform_points(T_gt, center)
    return project(K, X) - project(K, Xg), float((X[2] - Xg[2]) / Xg[2])


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--dataset", type=Path, default=L.DEFAULT_DATASET)
    ap.add_argument("--poses", type=Path, default=REPO / "out/bench/rank/merged_regionfb.json")
    ap.add_argument("--variant", default=None, help="row name (default: the last row)")
    ap.add_argument("--max-deg", type=float, default=10.0)
    ap.add_argument("--out", type=Path, default=REPO / "out/bench/lmo_gt_offset.json")
    args = ap.parse_args(argv)
    rows = json.loads(args.poses.read_text())["rows"]
    row = rows[-1] if args.variant is None else next(r for r in rows if r["variant"] == args.variant)
    ds = L.BopDataset(args.dataset)
    objects = L.ObjectCache(ds)
    bykey = {(t.scene_id, t.im_id, t.obj_id): t for t in ds.targets()}
    per: dict[int, list] = {}
    for tg, T in row["poses"]:
        t = bykey[tuple(tg)]
        T, T_gt = np.asarray(T, np.float64), L.gt_instance(ds, t).T_cam_from_obj
        e = L.pose_errors(objects.eval_data(t.obj_id), T, T_gt)
        if e["rot_err"] > args.max_deg:
            continue
        d, dz = centre_offset(ds.camera(t.scene_id, t.im_id).K, objects.mesh(t.obj_id).center, T, T_gt)
        per.setdefault(t.obj_id, []).append((d[0], d[1], dz, bool(e["add_ok"])))
    print(f"poses: {args.poses} row {row['variant']!r}; targets within {args.max_deg:g}° of the GT")
    print("| object | n | median du px | median dv px | median dz/z % | ADD(-S) hits |")
    print("|---|---|---|---|---|---|")
    out = {}
    for o, v in sorted(per.items()) + [(0, [x for vv in per.values() for x in vv])]:
        a = np.asarray(v, np.float64)
        name = NAMES.get(o, f"obj {o}") if o else "all"
        out[name] = {"n": len(a), "du": float(np.median(a[:, 0])), "dv": float(np.median(a[:, 1])),
                     "dz_rel": float(np.median(a[:, 2])), "hits": int(a[:, 3].sum())}
        r = out[name]
        print(f"| {name} | {r['n']} | {r['du']:+.2f} | {r['dv']:+.2f} | {100 * r['dz_rel']:+.2f} | {r['hits']} |")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps({"poses": str(args.poses), "variant": row["variant"], "max_deg": args.max_deg,
                                    "objects": out}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
