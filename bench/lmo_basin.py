"""Convergence basin of the edge alignment (pixie.cues.edge_align) on real LM-O photos.

Usage::

    PYTHONPATH=src .venv/bin/python bench/lmo_basin.py [--max-targets 96] [--degs 5,10,15,20] [--dzs 0,0.03,0.06] \
        [--shift-px 3] [--set key=value ...] [--out out/bench/lmo_basin.json]

Per target (``--max-targets`` spread evenly over the 8 objects) and per perturbation (rotation ``deg`` about a
random axis through the object centre, depth scaled by ``1 ± dz``, the image of the centre shifted by
``shift-px`` in a random direction; all seeded per target) the start pose is aligned to the photo's edges in the
GT ``bbox_visib`` box. Reports ADD(-S)<0.1d, median rotation error and median |dz| of the start, of the start with
the box depth (:func:`pixie.pose.depth_from_box`, as the pipeline sets it) and of the aligned pose; seconds per
alignment. The alignment runs with the preset's settings (``--preset``, default ``default``: what the pipeline
runs, through :func:`pixie.cues.edge_align.align_kwargs`); ``--set`` overrides keywords of
`pixie.cues.edge_align.align` / `pixie.cues.edge_align.photo_edges` on top (e.g. ``object_px=250``,
``schedule=16,8,4,2``). Before session 13 the bench started from ``align()``'s own keyword defaults (no box,
scales 8 → 2) unless ``--set`` said otherwise.
"""

from __future__ import annotations

import argparse
import inspect
import json
import time
from pathlib import Path

import numpy as np

import common as L  # noqa: E402  (bench/common.py: targets, object cache, presets)

REPO = L.REPO

from pixie.config import PixieConfig  # noqa: E402
from pixie.cues.edge_align import align, align_kwargs, photo_edges, photo_edges_kwargs  # noqa: E402
from pixie.pose.solve import depth_from_box, depth_from_visible_sides  # noqa: E402
from pixie.pipeline.query import check_bbox  # noqa: E402
from pixie.synth.e2e import turned_pose  # noqa: E402

NAMES = {1: "ape", 5: "can", 6: "cat", 8: "driller", 9: "duck", 10: "eggbox", 11: "glue", 12: "holepuncher"}


def preset_kwargs(preset: str) -> tuple[dict, dict]:
    """The photo-edge and alignment keywords the pipeline uses under ``preset`` (the estimator's ``_align_setup``)."""
    ac = PixieConfig.from_preset(preset).align
    return photo_edges_kwargs(ac), align_kwargs(ac)


def parse_sets(items: list[str], preset: str = "default") -> tuple[dict, dict]:
    pe_keys = set(inspect.signature(photo_edges).parameters)
    al_keys = set(inspect.signature(align).parameters)
    pe_kw, al_kw = preset_kwargs(preset)
    for it in items:
        k, _, v = it.partition("=")
        val = tuple(float(x) for x in v.split(",")) if "," in v else (float(v) if v.replace(".", "", 1).lstrip("-").isdigit() else v)
        if isinstance(val, float) and val.is_integer() and k in ("iters", "n_points", "n_bins", "max_bin_gap", "rerender"):
            val = int(val)
        if k in pe_keys:
            pe_kw[k] = val
        elif k in al_keys:
            al_kw[k] = val
        else:
            raise SystemExit(f"unknown key {k!r}")
    return pe_kw, al_kw


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--dataset", type=Path, default=L.DEFAULT_DATASET)
    ap.add_argument("--max-targets", type=int, default=96)
    ap.add_argument("--degs", default="5,10,15,20")
    ap.add_argument("--dzs", default="0,0.03,0.06")
    ap.add_argument("--shift-px", type=float, default=3.0)
    ap.add_argument("--box-noise", type=float, default=0.0,
                    help="move each side of the GT box by up to this many photo px (uniform, seeded per target): a detector's box")
    ap.add_argument("--set", action="append", default=[], dest="sets")
    ap.add_argument("--preset", default="default", help="alignment settings to start from (then --set)")
    ap.add_argument("--out", type=Path, default=REPO / "out/bench/lmo_basin.json")
    args = ap.parse_args(argv)
    pe_kw, al_kw = parse_sets(args.sets, args.preset)
    degs = [float(x) for x in args.degs.split(",")]
    dzs = [float(x) for x in args.dzs.split(",")]
    ds = L.BopDataset(args.dataset)
    objects = L.ObjectCache(ds)
    rows = []
    t_all = time.perf_counter()
    for i, t in enumerate(L.select_targets(ds, args.max_targets)):
        mesh = objects.mesh(t.obj_id)
        renderer = objects.renderer(t.obj_id)
        od = objects.eval_data(t.obj_id)
        g = L.gt_instance(ds, t)
        img = ds.load_rgb(t.scene_id, t.im_id)
        K = ds.camera(t.scene_id, t.im_id).K
        box = np.asarray(g.box_visib, np.float64).copy()
        if args.box_noise > 0:  # x, y, w, h -> each side moved independently
            d = np.random.default_rng([t.im_id, t.obj_id, 7]).uniform(-args.box_noise, args.box_noise, 4)
            box = np.array([box[0] + d[0], box[1] + d[1], box[2] - d[0] + d[2], box[3] - d[1] + d[3]])
            box[2:] = np.maximum(box[2:], 4.0)
        box = check_bbox(box, img.shape[:2])
        t0 = time.perf_counter()
        pe = photo_edges(img, K, box, **pe_kw)
        t_edges = time.perf_counter() - t0
        z = g.T_cam_from_obj[2, 3]
        for deg in degs:
            for dz in dzs:
                rng = np.random.default_rng([t.im_id, t.obj_id, int(deg * 10), int(dz * 1000)])
                T0 = turned_pose(g.T_cam_from_obj, K, mesh.center, deg, dz, args.shift_px, rng, signed_dz=True)
                Tb = depth_from_box(T0, K, mesh.hull_vertices, box)
                t1 = time.perf_counter()
                res = align(renderer, pe, T0, hull=mesh.hull_vertices, **al_kw)
                dt = time.perf_counter() - t1
                row = {"obj_id": t.obj_id, "im_id": t.im_id, "visib": g.visib_fract, "deg": deg, "dz": dz,
                       "seconds": dt, "edges_seconds": t_edges, "fit": res.fit.share, "iterations": res.iterations}
                Ta = res.T_cam_from_obj
                Tab = depth_from_box(Ta, K, mesh.hull_vertices, box)
                Tas = depth_from_visible_sides(Ta, K, mesh.hull_vertices, box)
                for name, T in (("start", T0), ("box", Tb), ("aligned", Ta), ("aligned_box", Tab), ("aligned_sides", Tas)):
                    e = L.pose_errors(od, T, g.T_cam_from_obj)
                    row[f"add_{name}"] = bool(e["add_ok"])
                    row[f"rot_{name}"] = float(e["rot_err"])
                    row[f"dz_{name}"] = float((T[2, 3] - z) / z)
                rows.append(row)
        if (i + 1) % 12 == 0:
            r10 = [r for r in rows if r["deg"] == 10.0 and abs(r["dz"] - 0.03) < 1e-9]
            print(f"  {i + 1} targets, {time.perf_counter() - t_all:.0f} s; 10°/3 %: ADD aligned "
                  f"{np.mean([r['add_aligned'] for r in r10]) if r10 else float('nan'):.2f}", flush=True)
    print(f"edge alignment basin, {len(rows) // (len(degs) * len(dzs))} targets, shift {args.shift_px} px, "
          f"box noise {args.box_noise} px, preset {args.preset}, sets {args.sets}")
    print("| start | n | ADD start | ADD box depth | ADD aligned | + box depth | + visible sides | med rot° start | aligned | "
          "med |dz| box | aligned | s |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|")
    for deg in degs:
        for dz in dzs:
            rs = [r for r in rows if r["deg"] == deg and r["dz"] == dz]
            print(f"| {deg:g}° / {100 * dz:g} % | {len(rs)} | {np.mean([r['add_start'] for r in rs]):.2f} | "
                  f"{np.mean([r['add_box'] for r in rs]):.2f} | **{np.mean([r['add_aligned'] for r in rs]):.2f}** | "
                  f"{np.mean([r['add_aligned_box'] for r in rs]):.2f} | {np.mean([r['add_aligned_sides'] for r in rs]):.2f} | "
                  f"{np.median([r['rot_start'] for r in rs]):.1f} | {np.median([r['rot_aligned'] for r in rs]):.1f} | "
                  f"{np.median(np.abs([r['dz_box'] for r in rs])):.3f} | {np.median(np.abs([r['dz_aligned'] for r in rs])):.3f} | "
                  f"{np.mean([r['seconds'] for r in rs]):.2f} |")
    print("per object at 10° / 3 %: " + ", ".join(
        f"{NAMES[o]} {np.mean([r['add_aligned'] for r in rows if r['obj_id'] == o and r['deg'] == 10 and r['dz'] == 0.03]):.2f}"
        for o in sorted({r["obj_id"] for r in rows}) if any(r["deg"] == 10 and r["dz"] == 0.03 for r in rows)))
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps({"args": {k: str(v) for k, v in vars(args).items()}, "targets": rows}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
