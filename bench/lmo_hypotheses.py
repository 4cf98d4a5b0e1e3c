"""Hypothesis study on LM-O: where does the pipeline lose the targets it could get?

Usage::

    nice .venv/bin/python bench/lmo_hypotheses.py [--max-targets 96] [--set section.key=value ...]

Runs :meth:`pixie.pipeline.estimator.PoseEstimator.estimate` on each target (``bbox_visib`` as the crop, pixie's box
convention) keeping *every* hypothesis it produced, and counts, of all targets, how many have ADD(-S)<0.1d

* ``chosen``: the returned pose (what ``bench/lmo_pipeline.py`` scores);
* ``any``: any hypothesis (the ceiling of re-scoring alone; each hypothesis's score terms are saved);
* ``chosen, GT depth``: the returned pose moved along its centre ray to the true distance (the ceiling of a
  better distance estimate with the rotation and image position as they are);
* ``chosen, box depth``: the returned pose's distance re-derived from the box (``pose.depth_from_box``) —
  the same rule as the pipeline, a consistency check;
* ``GT rotation, box depth``: the true rotation with the distance from the box (the box rule's own error).

It also reports the chosen pose's rotation error classes (< 15°, 15–30°, farther). Prints a table and writes
``out/bench/lmo_hypotheses.json`` plus ``out/bench/lmo_hypotheses.csv``: one row per target with the chosen pose
(``T_cam_from_obj`` row-major, full float precision; empty when none), its score and every hypothesis's pose, so
that two code versions can be compared target by target (``diff`` of the two CSVs).
"""

from __future__ import annotations

import argparse
import copy
import csv
import json
import time
from pathlib import Path

import numpy as np

import common as L  # noqa: E402  (bench/common.py: targets, object cache, presets)

from pixie.pipeline.estimator import PoseEstimator  # noqa: E402
from pixie.eval import pose_errors  # noqa: E402
from pixie.pose.solve import depth_from_box  # noqa: E402
from pixie.pipeline.query import check_bbox  # noqa: E402
from pixie.app.runner import make_matcher  # noqa: E402


CSV_COLUMNS = ["obj_id", "scene_id", "im_id", "pose", "score", "n_hypotheses", "hypothesis_poses"]


def along_ray_to_depth(T: np.ndarray, z: float) -> np.ndarray:
    """``T`` with its translation scaled so that its depth is ``z`` (the object stays on its image ray)."""
    out = T.copy()
    out[:3, 3] *= z / T[2, 3]
    return out


def hypothesis_row(h, err: dict) -> dict:
    """What the estimator knew of one hypothesis (its score terms) and whether it was right."""
    return {"score": h.score, "n_inliers": h.n_inliers, "n_matches": h.n_matches, "rot_to_ref": h.rot_to_ref_deg,
            "box_iou": h.box_iou, "sim_sum": h.sim_sum, "sim_mean": h.sim_mean, "source": h.source,
            "view": h.view, "roll": h.roll, "add_ok": bool(err["add_ok"]), "rot_err": float(err["rot_err"])}


def pose_text(T: np.ndarray | None) -> str:
    """``T`` row-major as space-separated floats at full precision (``repr``); empty for no pose."""
    return "" if T is None else " ".join(repr(float(x)) for x in np.asarray(T, float).ravel())


def target_study(est: PoseEstimator, od, image, K, bbox, T_gt) -> dict:
    """ADD(-S)<0.1d of the chosen pose, of every hypothesis, and of the depth variants described above."""
    res = est.estimate(image, K, bbox=bbox)
    box = check_bbox(bbox, image.shape[:2])
    pts = est.box_points
    ok = lambda T: bool(pose_errors(od, T, T_gt)["add_ok"])  # noqa: E731
    T_rot_gt = T_gt.copy()
    T_rot_gt[:3, 3] *= 1.05  # start 5 % off: the box rule must find the distance itself
    row = {"gt_rotation_box_depth": ok(depth_from_box(T_rot_gt, K, pts, box)), "seconds": res.timings["total"],
           "pose": pose_text(res.T_cam_from_obj), "score": res.score,
           "hypothesis_poses": ";".join(pose_text(h.T_cam_from_obj) for h in res.hypotheses)}
    if res.T_cam_from_obj is None:
        return {**row, "chosen": False, "any": False, "chosen_gt_depth": False, "chosen_box_depth": False,
                "rot_err": None, "n_hypotheses": 0}
    e = pose_errors(od, res.T_cam_from_obj, T_gt)
    row.update(chosen=bool(e["add_ok"]), rot_err=float(e["rot_err"]), n_hypotheses=len(res.hypotheses),
               any=any(ok(h.T_cam_from_obj) for h in res.hypotheses),
               hypotheses=[hypothesis_row(h, pose_errors(od, h.T_cam_from_obj, T_gt)) for h in res.hypotheses],
               chosen_gt_depth=ok(along_ray_to_depth(res.T_cam_from_obj, T_gt[2, 3])),
               chosen_box_depth=ok(depth_from_box(res.T_cam_from_obj, K, pts, box)))
    return row


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--dataset", type=Path, default=L.DEFAULT_DATASET)
    ap.add_argument("--max-targets", type=int, default=96)
    ap.add_argument("--set", action="append", default=[], dest="overrides")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--out", type=Path, default=L.REPO / "out/bench/lmo_hypotheses.json")
    L.add_preset_arg(ap)
    args = ap.parse_args(argv)
    import torch

    torch.set_num_threads(args.threads)
    ds = L.BopDataset(args.dataset)
    cfg = L.make_config(args.overrides + ["refine.n_hypotheses=1000"], args.preset)  # keep every distinct hypothesis
    objects = L.ObjectCache(ds)
    matcher = make_matcher(cfg)
    targets = L.select_targets(ds, args.max_targets)
    rows, t0 = [], time.perf_counter()
    for oid in sorted({t.obj_id for t in targets}):
        est = PoseEstimator(objects.refs(cfg, oid, matcher), copy.deepcopy(cfg), matcher=matcher)
        od = objects.eval_data(oid)
        for t in (t for t in targets if t.obj_id == oid):
            g = L.gt_instance(ds, t)
            r = target_study(est, od, ds.load_rgb(t.scene_id, t.im_id), ds.camera(t.scene_id, t.im_id).K,
                             g.box_visib, g.T_cam_from_obj)
            rows.append({"obj_id": oid, "scene_id": t.scene_id, "im_id": t.im_id, "visib": g.visib_fract, **r})
            print(f"  {len(rows)}/{len(targets)} obj {oid} im {t.im_id}: chosen {r['chosen']} any {r['any']}",
                  flush=True)
    n = len(rows)
    keys = ["chosen", "any", "chosen_gt_depth", "chosen_box_depth", "gt_rotation_box_depth"]
    summary = {k: sum(r[k] for r in rows) for k in keys}
    rot = [r["rot_err"] for r in rows if r["rot_err"] is not None]
    summary["chosen_rot_lt15"] = sum(x < 15 for x in rot)
    summary["chosen_rot_15_30"] = sum(15 <= x < 30 for x in rot)
    summary["chosen_rot_ge30"] = sum(x >= 30 for x in rot) + (n - len(rot))
    print(f"\nADD(-S)<0.1d of {n} targets ({time.perf_counter() - t0:.0f} s)")
    for k, v in summary.items():
        print(f"  {k:<24}{v:>5}  ({100.0 * v / n:.1f} %)")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    csv_rows = [{k: r.get(k) for k in CSV_COLUMNS} for r in rows]
    for r in rows:
        del r["pose"], r["hypothesis_poses"]
    args.out.write_text(json.dumps({"config": cfg.to_dict(), "n_targets": n, "summary": summary, "targets": rows},
                                   indent=1))
    with open(args.out.with_suffix(".csv"), "w", newline="") as f:
        w = csv.DictWriter(f, CSV_COLUMNS)
        w.writeheader()
        w.writerows(csv_rows)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
