"""Retrieval study on LM-O: how high does each ranking put a reference (view, roll) near the true rotation?

Usage::

    nice .venv/bin/python bench/lmo_retrieval.py [--max-targets 48] [--set section.key=value ...] [--near 20]

For every target the query crop (``bbox_visib``) is matched against every (view, roll) pair of the object's
reference set exactly as :class:`pixie.pipeline.estimator.PoseEstimator` does before PnP. Each pair is then ranked by
several statistics of its matches (count, summed similarity, summed similarity above the query's background
level = ``pose.candidate_ranking=excess``, top-10 similarity, mean similarity), and the script reports how
often a pair whose rotation is within ``--near`` degrees of the ground truth is ranked 1st / in the top 5, 10,
24 (``pose.top_k_views``) and 50. Prints a table and writes ``out/bench/lmo_retrieval.json``.
"""

from __future__ import annotations

import argparse
import copy
import json
from pathlib import Path

import numpy as np

import common as L  # noqa: E402  (bench/common.py: targets, object cache, presets)

from pixie.geometry.camera import rotation_angle_deg  # noqa: E402
from pixie.pipeline.estimator import PoseEstimator  # noqa: E402
from pixie.app.runner import make_matcher  # noqa: E402

RANKS = (1, 5, 10, 24, 50)


def pair_statistics(sims: np.ndarray, background: float) -> dict[str, float]:
    """Ranking statistics of one (view, roll) pair's match similarities."""
    if len(sims) == 0:
        return {"count": 0.0, "sim_sum": 0.0, "excess": 0.0, "top10": 0.0, "mean": 0.0}
    return {"count": float(len(sims)), "sim_sum": float(sims.sum()),
            "excess": float(np.clip(sims - background, 0.0, None).sum()),
            "top10": float(np.sort(sims)[-10:].sum()), "mean": float(sims.mean())}


def target_ranks(est: PoseEstimator, image, K, bbox, T_gt, near_deg: float) -> dict:
    """Rank (0-based) of the best-placed pair within ``near_deg`` of the GT rotation, per statistic."""
    corr = est.match(est.prepare(image, K, bbox))
    means = [float(c[2].mean()) for c in corr.values() if len(c[2])]
    bg = float(np.median(means)) if means else 0.0
    keys = list(corr)
    err = np.array([rotation_angle_deg(est.refs.poses[v, r][:3, :3], T_gt[:3, :3]) for v, r in keys])
    stats = [pair_statistics(corr[k][2], bg) for k in keys]
    out = {"min_err_deg": float(err.min()) if len(err) else None}
    for name in stats[0] if stats else []:
        order = np.argsort([-s[name] for s in stats], kind="stable")
        good = np.nonzero(err[order] < near_deg)[0]
        out[name] = int(good[0]) if len(good) else None
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--dataset", type=Path, default=L.DEFAULT_DATASET)
    ap.add_argument("--max-targets", type=int, default=48)
    ap.add_argument("--set", action="append", default=[], dest="overrides")
    ap.add_argument("--near", type=float, default=20.0, help="degrees from the GT rotation that count as right")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--out", type=Path, default=L.REPO / "out/bench/lmo_retrieval.json")
    L.add_preset_arg(ap)
    args = ap.parse_args(argv)
    import torch

    torch.set_num_threads(args.threads)
    ds = L.BopDataset(args.dataset)
    cfg = L.make_config(args.overrides, args.preset)
    objects = L.ObjectCache(ds)
    matcher = make_matcher(cfg)
    targets = L.select_targets(ds, args.max_targets)
    rows = []
    for oid in sorted({t.obj_id for t in targets}):
        est = PoseEstimator(objects.refs(cfg, oid, matcher), copy.deepcopy(cfg), matcher=matcher)
        for t in (t for t in targets if t.obj_id == oid):
            g = L.gt_instance(ds, t)
            r = target_ranks(est, ds.load_rgb(t.scene_id, t.im_id), ds.camera(t.scene_id, t.im_id).K,
                             g.box_visib, g.T_cam_from_obj, args.near)
            rows.append({"obj_id": oid, "im_id": t.im_id, **r})
    names = [k for k in rows[0] if k not in ("obj_id", "im_id", "min_err_deg")]
    summary = {}
    print(f"pair within {args.near:.0f} deg of GT ranked in the top k, of {len(rows)} targets")
    print(f"{'ranking':<10}" + "".join(f"{'top' + str(k):>8}" for k in RANKS))
    for name in names:
        ranks = [r[name] for r in rows]
        counts = [sum(x is not None and x < k for x in ranks) for k in RANKS]
        summary[name] = dict(zip([f"top{k}" for k in RANKS], counts))
        print(f"{name:<10}" + "".join(f"{c:>8}" for c in counts))
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps({"config": cfg.to_dict(), "near_deg": args.near, "n_targets": len(rows),
                                    "summary": summary, "targets": rows}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
