"""Region-refinement study on LM-O: from poses as retrieval delivers them, does region refinement reach ADD<0.1d?

Usage::

    PYTHONPATH=src .venv/bin/python bench/lmo_region.py [--max-targets 96] [--deg 8] [--out out/bench/lmo_region.json]

Per target the start pose is the GT rotation turned by ``--deg`` degrees about a random axis (seeded per
target) through the object centre, with the distance from the visible box (:func:`pixie.pose.solve.depth_from_box`
on GT ``bbox_visib``, as the pipeline sets it). It is refined with :meth:`pixie.cues.shape.ShapeCues.refine`
(region-based, along correspondence lines). Reports ADD(-S)<0.1d, median rotation error and relative depth
error before and after, per object, and seconds per refinement.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import cv2
import numpy as np

REPO = Path(__file__).resolve().parents[1]
import common as L  # noqa: E402  (bench/common.py: targets, object cache, presets)

from pixie.geometry.camera import make_T  # noqa: E402
from pixie.references.templates import build_templates  # noqa: E402
from pixie.pose.solve import depth_from_box  # noqa: E402
from pixie.pipeline.query import check_bbox  # noqa: E402
from pixie.cues.shape import ShapeCues  # noqa: E402

NAMES = {1: "ape", 5: "can", 6: "cat", 8: "driller", 9: "duck", 10: "eggbox", 11: "glue", 12: "holepuncher"}


def turned(T: np.ndarray, centre: np.ndarray, deg: float, rng: np.random.Generator) -> np.ndarray:
    axis = rng.normal(size=3)
    R = cv2.Rodrigues(axis / np.linalg.norm(axis) * np.radians(deg))[0]
    c = T[:3, :3] @ centre + T[:3, 3]
    R0 = R @ T[:3, :3]
    return make_T(R0, c - R0 @ centre)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--dataset", type=Path, default=L.DEFAULT_DATASET)
    ap.add_argument("--max-targets", type=int, default=96)
    ap.add_argument("--deg", type=float, default=8.0)
    ap.add_argument("--box-px", type=float, default=96.0)
    ap.add_argument("--iterations", type=int, default=4)
    ap.add_argument("--rebox", action="store_true", help="re-derive the refined pose's distance from the box")
    ap.add_argument("--out", type=Path, default=REPO / "out/bench/lmo_region.json")
    args = ap.parse_args(argv)
    ds = L.BopDataset(args.dataset)
    objects = L.ObjectCache(ds)
    rows, cues = [], {}
    for i, t in enumerate(L.select_targets(ds, args.max_targets)):
        mesh = objects.mesh(t.obj_id)
        if t.obj_id not in cues:
            cues[t.obj_id] = ShapeCues(mesh, build_templates(mesh, n_views=4, size=32))  # templates unused here
        g = L.gt_instance(ds, t)
        img = ds.load_rgb(t.scene_id, t.im_id)
        K = ds.camera(t.scene_id, t.im_id).K
        box = check_bbox(g.box_visib, img.shape[:2])
        rng = np.random.default_rng(1000 * t.im_id + t.obj_id)
        T0 = depth_from_box(turned(g.T_cam_from_obj, mesh.center, args.deg, rng), K, mesh.hull_vertices, box)
        t0 = time.perf_counter()
        res = cues[t.obj_id].refine(img, K, T0, box, args.box_px, iterations=args.iterations)
        if args.rebox:
            res.T_cam_from_obj = depth_from_box(res.T_cam_from_obj, K, mesh.hull_vertices, box)
        dt = time.perf_counter() - t0
        od = objects.eval_data(t.obj_id)
        z = g.T_cam_from_obj[2, 3]
        e0, e1 = L.pose_errors(od, T0, g.T_cam_from_obj), L.pose_errors(od, res.T_cam_from_obj, g.T_cam_from_obj)
        rows.append({"obj_id": t.obj_id, "visib": g.visib_fract, "add0": e0["add_ok"], "add1": e1["add_ok"],
                     "rot0": e0["rot_err"], "rot1": e1["rot_err"], "dz0": (T0[2, 3] - z) / z,
                     "dz1": (res.T_cam_from_obj[2, 3] - z) / z, "seconds": dt, "iterations": res.iterations})
    print(f"region refinement from GT turned {args.deg}° + box depth, {len(rows)} targets")
    print("| obj | n | ADD<0.1d start | refined | med rot° start | refined | med |dz| start | refined | s |")
    print("|---|---|---|---|---|---|---|---|---|")
    groups = [(NAMES[o], [r for r in rows if r["obj_id"] == o]) for o in sorted({r["obj_id"] for r in rows})]
    for name, rs in groups + [("all", rows)]:
        print(f"| {name} | {len(rs)} | {np.mean([r['add0'] for r in rs]):.2f} | {np.mean([r['add1'] for r in rs]):.2f} | "
              f"{np.median([r['rot0'] for r in rs]):.1f} | {np.median([r['rot1'] for r in rs]):.1f} | "
              f"{np.median(np.abs([r['dz0'] for r in rs])):.3f} | {np.median(np.abs([r['dz1'] for r in rs])):.3f} | "
              f"{np.mean([r['seconds'] for r in rs]):.2f} |")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps({"args": {k: str(v) for k, v in vars(args).items()}, "targets": rows}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
