"""Edge-template retrieval study on LM-O: is a contour template near the true rotation ranked first / top 24?

Usage::

    PYTHONPATH=src .venv/bin/python bench/lmo_edges.py [--max-targets 96] [--views 300] [--rolls 36] \
        [--set key=value ...] [--out out/bench/lmo_edges.json]

Per object, contour templates (:func:`pixie.references.templates.build_templates`: silhouette + crease points of
``--views`` Fibonacci views rendered at low resolution) are built once. Per target the query crop (GT
``bbox_visib``, pixie convention) gets orientation response maps (:func:`pixie.cues.edges.prepare_query`) and every
(view, roll) template is scored (:func:`pixie.cues.edges.search`). Views are ranked by their best roll. A template
counts as right when its rotation is within ``--near`` degrees of the ground truth *as seen by a camera looking
at the object centre* (the GT rotation turned by the smallest rotation taking the optical axis onto the ray to
the object centre: templates look at the object centre too), minimised over the object's symmetries.

Reports per object and overall: top-1 / top-5 / top-24 (distinct views, best roll each) within ``--near``,
the coverage ceiling (best template of all), and seconds per target (query prep + search). Writes JSON.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
import common as L  # noqa: E402  (bench/common.py: targets, object cache, presets)

from pixie.references.templates import build_templates, distinct_by_rotation  # noqa: E402
from pixie.cues.edges import prepare_query, search, template_bank  # noqa: E402
from pixie.pipeline.query import check_bbox  # noqa: E402

NAMES = {1: "ape", 5: "can", 6: "cat", 8: "driller", 9: "duck", 10: "eggbox", 11: "glue", 12: "holepuncher"}
RANKS = (1, 5, 24)
TEMPLATE_VERSION = "t6"  # bump when pixie.references.templates changes what it stores


def centred_rotation(T: np.ndarray, centre: np.ndarray) -> np.ndarray:
    """Rotation of pose ``T`` seen by a camera turned (about its centre) to look at the object centre."""
    c = T[:3, :3] @ centre + T[:3, 3]
    a = c / np.linalg.norm(c)
    z = np.array([0.0, 0.0, 1.0])
    v, cos = np.cross(a, z), float(a @ z)
    vx = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])
    Rc = np.eye(3) + vx + vx @ vx / (1.0 + cos)  # rotates a onto z
    return Rc @ T[:3, :3]


def template_errors(tpl, angles: np.ndarray, R_c: np.ndarray, syms) -> np.ndarray:
    """(V, A) rotation error (deg) of every rolled template against ``R_c``, min over symmetries."""
    c, s = np.cos(angles), np.sin(angles)
    Rz = np.zeros((len(angles), 3, 3))
    Rz[:, 0, 0], Rz[:, 0, 1], Rz[:, 1, 0], Rz[:, 1, 1], Rz[:, 2, 2] = c, -s, s, c, 1
    R = np.einsum("aij,vjk->vaik", Rz, tpl.poses[:, :3, :3])  # (V, A, 3, 3)
    best = np.full(R.shape[:2], np.inf)
    for S in ([np.eye(4)] if syms is None or len(syms) == 0 else syms):
        G = R_c @ np.asarray(S)[:3, :3]
        tr = np.einsum("vaij,ij->va", R, G)
        best = np.minimum(best, np.degrees(np.arccos(np.clip((tr - 1) / 2, -1, 1))))
    return best


def cached_templates(objects, oid: int, views: int, size: int, points: int):
    """Templates of one object, built once and kept in out/bench/templates/ (build time kept from the build)."""
    from pixie.references.templates import ContourTemplates

    path = REPO / f"out/bench/templates/{TEMPLATE_VERSION}_v{views}_s{size}_p{points}/obj_{oid:06d}.npz"
    if path.is_file():
        with np.load(path) as z:
            return ContourTemplates.from_arrays({k: z[k] for k in z.files})
    tpl = build_templates(objects.mesh(oid), views, size, points, renderer=objects.renderer(oid))
    path.parent.mkdir(parents=True, exist_ok=True)
    np.savez(path, **tpl.to_arrays())
    return tpl


def region_scores(tpl, q, v_i, a_i, info, band: float) -> np.ndarray:
    """Region agreement of the placed outlines of pairs (v_i, a_i) on the query crop."""
    from pixie.cues.region import polygon_scores

    ang = info["angles"][a_i]
    c, s = np.cos(ang), np.sin(ang)
    R = np.stack([np.stack([c, -s], -1), np.stack([s, c], -1)], -2)
    out = np.einsum("kij,kmj->kmi", R, tpl.outline[info["views"][v_i]])
    polys = info["origin"][v_i, a_i][:, None, :] + info["scale"][v_i, a_i][:, None, None] * out
    return polygon_scores(q.crop.image, polys, max(int(round(band * q.box_wh.max())), 2), q.valid)


def parse_sets(items: list[str]) -> dict:
    out = {}
    for it in items:
        k, v = it.split("=", 1)
        try:
            out[k] = json.loads(v)
        except ValueError:
            out[k] = v
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--dataset", type=Path, default=L.DEFAULT_DATASET)
    ap.add_argument("--max-targets", type=int, default=96)
    ap.add_argument("--views", type=int, default=300)
    ap.add_argument("--size", type=int, default=128)
    ap.add_argument("--points", type=int, default=96)
    ap.add_argument("--rolls", type=int, default=36)
    ap.add_argument("--near", type=float, default=20.0)
    ap.add_argument("--region-k", type=int, default=0, help="region-score the K best pairs by edges (saved for offline fusion)")
    ap.add_argument("--region-w", type=float, default=1.0, help="weight of (region - 0.5) added to the edge score")
    ap.add_argument("--nms", type=float, default=0.0,
                    help="top-N lists keep pairs more than this many degrees apart (0: distinct views, best roll each)")
    ap.add_argument("--band", type=float, default=0.15, help="region band width, fraction of the box's longer side")
    ap.add_argument("--set", action="append", default=[], dest="sets",
                    help="prepare_query / search keyword, e.g. box_px=64, spread=5, crease_weight=0.5")
    ap.add_argument("--out", type=Path, default=REPO / "out/bench/lmo_edges.json")
    args = ap.parse_args(argv)
    kw = parse_sets(args.sets)
    qkw = {k: v for k, v in kw.items() if k in ("box_px", "pad", "sigma", "min_mag", "spread", "power")}
    bkw = {k: v for k, v in kw.items() if k in ("crease_weight",)}
    skw = {k: (tuple(v) if isinstance(v, list) else v) for k, v in kw.items() if k not in qkw and k not in bkw}
    ds = L.BopDataset(args.dataset)
    objects = L.ObjectCache(ds)
    targets = L.select_targets(ds, args.max_targets)
    tpls, build, banks, rots = {}, {}, {}, {}
    rows = []
    t_all = time.perf_counter()
    for i, t in enumerate(targets):
        if t.obj_id not in tpls:
            tpls[t.obj_id] = cached_templates(objects, t.obj_id, args.views, args.size, args.points)
            build[t.obj_id] = tpls[t.obj_id].build_seconds
            banks[t.obj_id] = template_bank(tpls[t.obj_id], args.rolls, **bkw)
            rots[t.obj_id] = tpls[t.obj_id].rotations(banks[t.obj_id].angles)
        tpl, bank = tpls[t.obj_id], banks[t.obj_id]
        g = L.gt_instance(ds, t)
        img = ds.load_rgb(t.scene_id, t.im_id)
        box = check_bbox(g.box_visib, img.shape[:2])
        t0 = time.perf_counter()
        q = prepare_query(img, box, **qkw)
        scores, info = search(bank, q, **skw)
        od = objects.eval_data(t.obj_id)
        err = template_errors(tpl, info["angles"], centred_rotation(g.T_cam_from_obj, objects.mesh(t.obj_id).center),
                              od.syms if od.symmetric else None)
        extra = {}
        if args.region_k > 0:
            top = np.argsort(-scores.ravel(), kind="stable")[: args.region_k]
            v_i, a_i = np.unravel_index(top, scores.shape)
            reg = region_scores(tpl, q, v_i, a_i, info, args.band)
            edge_top = scores.ravel()[top].copy()
            fused = edge_top + args.region_w * (reg - 0.5)
            scores = np.full_like(scores, -np.inf)
            scores[v_i, a_i] = fused
            extra = {"cand_edge": edge_top.tolist(), "cand_region": reg.tolist(),
                     "cand_err": err[v_i, a_i].tolist(), "cand_view": v_i.tolist()}
        dt = time.perf_counter() - t0
        if args.nms > 0:
            flat_order = np.argsort(-scores.ravel(), kind="stable")[:2000]
            keep = distinct_by_rotation(rots[t.obj_id].reshape(-1, 3, 3), flat_order, max(RANKS), args.nms)
            verr_sel = err.ravel()[keep]
            good = np.nonzero(verr_sel < args.near)[0]
            verr, order = verr_sel, np.arange(len(keep))
            vscore = scores.ravel()[keep]
        else:
            best_roll = np.argmax(scores, axis=1)
            vscore = scores[np.arange(len(scores)), best_roll]
            verr = err[np.arange(len(scores)), best_roll]
            order = np.argsort(-vscore, kind="stable")
            good = np.nonzero(verr[order] < args.near)[0]
        pair_order = np.argsort(-scores.ravel(), kind="stable")
        rows.append({"scene_id": t.scene_id, "im_id": t.im_id, "obj_id": t.obj_id, "visib": g.visib_fract,
                     "rank": int(good[0]) if len(good) else None, "top1_err": float(verr[order[0]]),
                     "min_err": float(err.min()), "pair_rank": int(np.nonzero(err.ravel()[pair_order] < args.near)[0][0])
                     if (err < args.near).any() else None, "seconds": dt,
                     "top1_score": float(vscore[order[0]]), **extra})
        if (i + 1) % 24 == 0:
            print(f"  {i + 1}/{len(targets)}  {time.perf_counter() - t_all:.0f} s", flush=True)

    def summary(rs):
        n = max(len(rs), 1)
        d = {f"top{k}": sum(r["rank"] is not None and r["rank"] < k for r in rs) / n for k in RANKS}
        d.update(n=len(rs), ceiling=sum(r["min_err"] < args.near for r in rs) / n,
                 median_top1_err=float(np.median([r["top1_err"] for r in rs])) if rs else None,
                 seconds=float(np.mean([r["seconds"] for r in rs])) if rs else None)
        return d

    per_obj = {NAMES.get(o, str(o)): summary([r for r in rows if r["obj_id"] == o]) for o in sorted({r["obj_id"] for r in rows})}
    allsum = summary(rows)
    print(f"\nedge retrieval, {len(rows)} targets, {args.views} views x {args.rolls} rolls, near {args.near} deg, {kw}")
    print("| obj | n | top1 | top5 | top24 | ceiling | med top1 err | s/target |")
    print("|---|---|---|---|---|---|---|---|")
    for name, d in list(per_obj.items()) + [("all", allsum)]:
        print(f"| {name} | {d['n']} | {d['top1']:.2f} | {d['top5']:.2f} | {d['top24']:.2f} | {d['ceiling']:.2f} | "
              f"{d['median_top1_err']:.1f} | {d['seconds']:.3f} |")
    print("template build s per object:", {NAMES.get(k, k): round(v, 1) for k, v in build.items()},
          f"size {next(iter(tpls.values())).nbytes() / 1e6:.2f} MB")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps({"args": {k: str(v) for k, v in vars(args).items()}, "summary": allsum,
                                    "per_object": per_obj, "build_seconds": build, "targets": rows}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
