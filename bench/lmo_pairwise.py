"""Selection by the photo evidence where two candidate poses disagree (a pairwise, differential fit), on the
candidates of ``bench/lmo_align_study.py --dump``.

Usage::

    PYTHONPATH=src .venv/bin/python bench/lmo_pairwise.py out/bench/rank/dump_0.pkl out/bench/rank/dump_1.pkl \
        [--variant default] [--top 3] [--out out/bench/lmo_pairwise.json]

The shipped ranking scores each aligned candidate by the share of *all* its visible contour points that lie on a
photo edge; two poses that share most of their outline (a pose and its 2 % deeper twin, two rotations about the
viewing ray's neighbourhood) then score alike and the choice follows small differences in the shared part. Here the
chosen candidate A is compared with each of the next ``--top`` candidates B on the contour points that only one of
them has: A's points with no B point of similar orientation within ``--excl-px`` crop px, and the other way round.
On those *exclusive* points the support is the share on a same-orientation photo edge within ``fit_px`` (the
alignment's fit criterion). B replaces A when its exclusive support beats A's by more than a margin and its shipped
score is within ``delta`` of A's; the margin and delta are chosen on the first file (the fitting half: most hits, then
the larger margin) and reported on the others (and the other way round).

Each target costs one photo-edge map and one render per candidate (denser contour sampling than the alignment's).
"""

from __future__ import annotations

import argparse
import json
import pickle
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

import common as L  # noqa: E402  (bench/common.py: puts src/ on the path)

from pixie.config import PixieConfig  # noqa: E402
from pixie.cues.edge_align import _project, edge_distances, model_points, photo_edges_kwargs  # noqa: E402
from pixie.cues.edge_photo import photo_edges  # noqa: E402
from pixie.geometry.camera import rotation_angle_deg  # noqa: E402
from pixie.pipeline.query import check_bbox  # noqa: E402

REPO = Path(__file__).resolve().parents[1]


def exclusive_support(pe, pa: np.ndarray, oa: np.ndarray, pb: np.ndarray, ob: np.ndarray, excl_px: float,
                      fit_px: float, max_deg: float = 30.0) -> tuple[float, int]:
    """Support share and count of A's points (crop px ``pa``, orientations ``oa``) that have no point of B within
    ``excl_px`` whose orientation is within ``max_deg``; (nan, 0) when A has no visible exclusive point."""
    if len(pa) == 0:
        return float("nan"), 0
    tree = cKDTree(pb) if len(pb) else None
    excl = np.ones(len(pa), bool)
    if tree is not None:
        for i, nb in enumerate(tree.query_ball_point(pa, excl_px)):
            if nb:
                d = np.abs(np.mod(ob[nb] - oa[i] + np.pi / 2, np.pi) - np.pi / 2)
                excl[i] = not np.any(d < np.deg2rad(max_deg))
    d, inside = edge_distances(pe, pa, oa, 1, fit_px)
    sel = excl & inside
    if not sel.any():
        return float("nan"), 0
    return float((d[sel] <= fit_px).mean()), int(sel.sum())


def target_pairs(ds, objects, t: dict, cfg: PixieConfig, top: int, n_points: int, excl_px: float) -> dict:
    """Per target: the chosen candidate, the next ``top`` distinct ones, and A's / B's exclusive supports."""
    sid, iid, oid = t["target"]
    img = ds.load_rgb(sid, iid)
    K = ds.camera(sid, iid).K
    ac = cfg.align
    pe = photo_edges(img, K, check_bbox(t["box"], img.shape[:2]), None, **photo_edges_kwargs(ac))
    ren = objects.renderer(oid, True)
    cands = sorted(t["cands"], key=lambda c: -c["score"])
    A = cands[0]
    pts = {}

    def points(c):
        key = id(c)
        if key not in pts:
            mp = model_points(ren, c["T"], pe.K, pe.size, n_points, 0.3)
            if mp is None:
                pts[key] = (np.zeros((0, 2)), np.zeros(0))
            else:
                T = c["T"]
                p = _project(pe.K, mp.xyz @ T[:3, :3].T + T[:3, 3]) + mp.offset
                pts[key] = (p, mp.ori)
        return pts[key]

    out = {"target": list(t["target"]), "A": {"score": A["score"], "ok": bool(A["add_ok"]), "rot": A["rot_err"]},
           "B": []}
    pa, oa = points(A)
    for B in cands[1:]:
        if len(out["B"]) >= top:
            break
        dr = rotation_angle_deg(A["T"][:3, :3], B["T"][:3, :3])
        dz = abs(B["T"][2, 3] / A["T"][2, 3] - 1)
        if dr < 2.0 and dz < 0.005:  # the same pose
            continue
        pb, ob = points(B)
        sa, na = exclusive_support(pe, pa, oa, pb, ob, excl_px, ac.fit_px)
        sb, nb = exclusive_support(pe, pb, ob, pa, oa, excl_px, ac.fit_px)
        out["B"].append({"score": B["score"], "ok": bool(B["add_ok"]), "rot": B["rot_err"], "dr": dr, "dz": dz,
                         "sa": sa, "na": na, "sb": sb, "nb": nb, "source": B["source"]})
    return out


def choose(rec: dict, margin: float, delta: float, min_n: int) -> bool:
    """Whether the rule's choice is right: the best challenger by (sb - sa) replaces A when it wins by ``margin``."""
    best, gain = None, margin
    for b in rec["B"]:
        if b["na"] < min_n or b["nb"] < min_n or not np.isfinite(b["sa"]) or not np.isfinite(b["sb"]):
            continue
        if rec["A"]["score"] - b["score"] > delta:
            continue
        g = b["sb"] - b["sa"]
        if g > gain:
            best, gain = b, g
    return best["ok"] if best is not None else rec["A"]["ok"]


def grid(recs: list[dict]) -> list[tuple[int, float, float, int]]:
    out = []
    for margin in (0.0, 0.05, 0.1, 0.15, 0.2, 0.3, 0.4, 0.5, 2.0):
        for delta in (0.02, 0.05, 0.1, 0.2, 0.5, 10.0):
            for min_n in (3, 6, 12):
                out.append((sum(choose(r, margin, delta, min_n) for r in recs), margin, delta, min_n))
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("dumps", type=Path, nargs="+")
    ap.add_argument("--dataset", type=Path, default=L.DEFAULT_DATASET)
    ap.add_argument("--variant", default="default")
    ap.add_argument("--preset", default="default")
    ap.add_argument("--top", type=int, default=3)
    ap.add_argument("--n-points", type=int, default=480)
    ap.add_argument("--excl-px", type=float, default=3.0)
    ap.add_argument("--max-targets", type=int, default=0)
    ap.add_argument("--cache", type=Path, default=None, help="pickle of the per-target records (written / reused)")
    ap.add_argument("--out", type=Path, default=REPO / "out/bench/lmo_pairwise.json")
    args = ap.parse_args(argv)
    ds = L.BopDataset(args.dataset)
    objects = L.ObjectCache(ds)
    cfg = PixieConfig.from_preset(args.preset)
    halves = []
    if args.cache is not None and args.cache.is_file():
        halves = pickle.loads(args.cache.read_bytes())
    else:
        for path in args.dumps:
            ts = pickle.loads(path.read_bytes())["variants"][args.variant]
            if args.max_targets:
                ts = ts[: args.max_targets]
            recs = []
            for i, t in enumerate(ts):
                if t["cands"]:
                    recs.append(target_pairs(ds, objects, t, cfg, args.top, args.n_points, args.excl_px))
                if (i + 1) % 50 == 0:
                    print(f"  {path.name}: {i + 1}/{len(ts)}", flush=True)
            halves.append(recs)
        if args.cache is not None:
            args.cache.parent.mkdir(parents=True, exist_ok=True)
            args.cache.write_bytes(pickle.dumps(halves))
    rows = []
    for fi, fit in enumerate(halves):
        g = sorted(grid(fit), key=lambda x: (-x[0], -x[1], x[2]))
        hits, margin, delta, min_n = g[0]
        base = [sum(r["A"]["ok"] for r in h) for h in halves]
        rep = [sum(choose(r, margin, delta, min_n) for r in h) for h in halves]
        oracle = [sum(r["A"]["ok"] or any(b["ok"] for b in r["B"]) for r in h) for h in halves]
        rows.append({"fit_half": fi, "margin": margin, "delta": delta, "min_n": min_n, "shipped": base, "rule": rep,
                     "oracle_top": oracle})
        print(f"fit on half {fi}: margin {margin}, delta {delta}, min_n {min_n}: shipped {base} -> rule {rep} "
              f"(a right one among A + top {args.top}: {oracle})")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps({"args": {k: str(v) for k, v in vars(args).items()}, "rows": rows}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
