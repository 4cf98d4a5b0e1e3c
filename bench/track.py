"""Pose tracking (``pixie track``) against estimating every frame from scratch, on rendered sequences.

Usage::

    OMP_NUM_THREADS=1 PYTHONPATH=src .venv/bin/python bench/track.py [--frames 60] [--seeds 0,1] [--threads 1] \
        [--out out/bench/track.json]

Per seed, two 640x480 sequences of the procedural part (:func:`pixie.synth.sequence.smooth_sequence`: 2°/frame
about a random axis, 2 px/frame drift, ±10 % depth, a cluttered background): ``clean`` and ``clutter`` (three
static distractor boxes in front, occluding the part at times). Each is run three ways with the ``default``
preset (reference set: 36 views): **scratch** (``estimate`` on every frame in its visible box), **track**
(frame 0 from the GT pose, then each result is the next prior; the full search in the last good pose's box
when the fit says lost) and **track+loss** (as track, but at frame n/2 the prior is replaced by the GT pose
turned 90°: a forced loss; the frames after it show whether tracking recovers). Reports per run: frames with
rotation < 5° and depth < 5 %, median rotation / depth error, seconds per frame, frames searched; writes JSON.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import cv2
import numpy as np

import common as L  # noqa: E402

from pixie.app.runner import make_matcher  # noqa: E402
from pixie.app.track import Frame, Tracker  # noqa: E402
from pixie.config import PixieConfig  # noqa: E402
from pixie.geometry.camera import make_K, make_T, rotation_angle_deg  # noqa: E402
from pixie.geometry.mesh import from_arrays  # noqa: E402
from pixie.pipeline.estimator import PoseEstimator  # noqa: E402
from pixie.references.set import build_reference_set  # noqa: E402
from pixie.synth.e2e import procedural_part  # noqa: E402
from pixie.synth.sequence import smooth_sequence  # noqa: E402
from pixie.threads import set_threads  # noqa: E402

K = make_K(600.0, 600.0, 320.0, 240.0)


def errors(T: np.ndarray | None, Tg: np.ndarray) -> tuple[float, float]:
    if T is None:
        return 180.0, 1.0
    return rotation_angle_deg(T[:3, :3], Tg[:3, :3]), abs(T[2, 3] - Tg[2, 3]) / Tg[2, 3]


def turned(T: np.ndarray, centre: np.ndarray, deg: float) -> np.ndarray:
    R = cv2.Rodrigues(np.array([1.0, 1.0, 0.0]) / np.sqrt(2) * np.radians(deg))[0] @ T[:3, :3]
    c = T[:3, :3] @ centre + T[:3, 3]
    return make_T(R, c - R @ centre)


def summary(name: str, errs: list, secs: list, modes: list) -> dict:
    e = np.array(errs)
    ok = (e[:, 0] < 5) & (e[:, 1] < 0.05)
    return {"run": name, "frames": len(e), "ok": int(ok.sum()), "med_rot": float(np.median(e[:, 0])),
            "med_dz": float(np.median(e[:, 1])), "s_per_frame": float(np.mean(secs)),
            "searched": int(sum(m == "search" for m in modes)), "ok_flags": ok.tolist()}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--frames", type=int, default=60)
    ap.add_argument("--seeds", default="0,1")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--out", type=Path, default=L.REPO / "out/bench/track.json")
    args = ap.parse_args(argv)
    set_threads(args.threads)
    tm = procedural_part()
    mesh = from_arrays(np.asarray(tm.vertices), np.asarray(tm.faces), name="proc")
    cfg = PixieConfig.from_preset("default")
    cfg.refs.n_fibonacci = 30
    matcher = make_matcher(cfg)
    t0 = time.perf_counter()
    est = PoseEstimator(build_reference_set(mesh, cfg.refs, matcher=matcher, shape=cfg.shape), cfg, matcher=matcher)
    print(f"reference set: 36 views x 8 rolls in {time.perf_counter() - t0:.0f} s")
    rows = []
    for seed in [int(s) for s in args.seeds.split(",")]:
        for kind, n_dis in (("clean", 0), ("clutter", 3)):
            seq = smooth_sequence(mesh, K, 480, 640, n_frames=args.frames, seed=seed, distractors=n_dis)
            frames = [Frame(image=im, K=K, bbox=None, name=str(i)) for i, im in enumerate(seq.images)]
            # scratch: the full pipeline on every frame, in its visible box
            errs, secs = [], []
            for fr, Tg, box in zip(frames, seq.poses, seq.boxes):
                t = time.perf_counter()
                r = est.estimate(fr.image, K, bbox=box)
                secs.append(time.perf_counter() - t)
                errs.append(errors(r.T_cam_from_obj, Tg))
            rows.append({"seed": seed, "scene": kind, **summary("scratch", errs, secs, ["search"] * len(errs))})
            for name in ("track", "track+loss"):
                errs, secs, modes, fits = [], [], [], []
                loss_at = args.frames // 2 if name == "track+loss" else -1
                tr = Tracker(est, init_pose=seq.poses[0])
                for i, (fr, Tg) in enumerate(zip(frames, seq.poses)):
                    if i == loss_at:  # this frame's prior is wrong by 90° (a forced loss)
                        tr.prior = turned(Tg, mesh.center, 90.0)
                    step = tr.step(fr)
                    errs.append(errors(step.result.T_cam_from_obj, Tg))
                    secs.append(step.seconds)
                    modes.append(step.mode)
                    fits.append(float(step.result.confidence) if step.mode == "prior" else None)
                rows.append({"seed": seed, "scene": kind, **summary(name, errs, secs, modes),
                             "loss_at": loss_at, "modes": modes, "fits": fits})
            for r in rows[-3:]:
                print(f"seed {seed} {kind:8s} {r['run']:10s} ok {r['ok']}/{r['frames']}  med rot {r['med_rot']:.2f}°  "
                      f"med dz {100 * r['med_dz']:.2f} %  {r['s_per_frame']:.2f} s/frame  searched {r['searched']}",
                      flush=True)
    print("\n| seed | scene | run | frames < 5° / 5 % | median rot° | median |dz| % | s/frame | frames searched |")
    print("|---|---|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['seed']} | {r['scene']} | {r['run']} | {r['ok']}/{r['frames']} | {r['med_rot']:.2f} | "
              f"{100 * r['med_dz']:.2f} | {r['s_per_frame']:.2f} | {r['searched']} |")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps({"frames": args.frames, "rows": rows}, indent=1))
    print(f"-> {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
