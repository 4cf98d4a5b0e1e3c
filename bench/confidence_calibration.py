"""How well does ``PoseResult.confidence`` predict a correct pose? A reliability table from a lmo_pipeline run.

Usage::

    nice .venv/bin/python bench/lmo_pipeline.py $BASE --max-targets 96 --no-ar --tag calib --out out/bench/calib
    .venv/bin/python bench/confidence_calibration.py out/bench/calib/runs/<hash>/targets.jsonl \
        [--out out/bench/calib/calibration.json]

Reads the per-target records (``confidence``, ``failed``, ``add_ok`` = ADD(-S) < 0.1 d) and prints, per
confidence bin, the number of targets and the fraction whose pose is correct, for all results and for the
results not flagged failed; plus the rank correlation (AUC) of confidence with correctness.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from common import write_json  # noqa: E402  (the bench folder is on sys.path)

BINS = [0.5, 0.55, 0.6, 0.7, 0.8, 0.9, 1.0001]


def auc(scores: np.ndarray, positive: np.ndarray) -> float | None:
    """Probability that a random correct result has a higher confidence than a random wrong one (ties 1/2)."""
    pos, neg = scores[positive], scores[~positive]
    if len(pos) == 0 or len(neg) == 0:
        return None
    greater = (pos[:, None] > neg[None, :]).sum() + 0.5 * (pos[:, None] == neg[None, :]).sum()
    return float(greater / (len(pos) * len(neg)))


def table(recs: list[dict]) -> dict:
    conf = np.array([r["confidence"] for r in recs], np.float64)
    ok = np.array([bool(r["add_ok"]) for r in recs])
    failed = np.array([bool(r["failed"]) for r in recs])
    rows = []
    for lo, hi in zip(BINS[:-1], BINS[1:]):
        sel = (conf >= lo) & (conf < hi)
        rows.append({"bin": [lo, min(hi, 1.0)], "n": int(sel.sum()), "correct": int(ok[sel].sum()),
                     "fraction_correct": float(ok[sel].mean()) if sel.any() else None})
    return {"n": len(recs), "correct": int(ok.sum()), "n_failed": int(failed.sum()),
            "correct_among_failed": int(ok[failed].sum()), "auc_confidence": auc(conf, ok),
            "auc_confidence_not_failed": auc(conf[~failed], ok[~failed]), "bins": rows}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("jsonl", type=Path)
    ap.add_argument("--out", type=Path)
    args = ap.parse_args(argv)
    recs = []
    for line in args.jsonl.read_text().splitlines():
        try:
            r = json.loads(line)
        except ValueError:
            continue
        if "confidence" in r:
            recs.append(r)
    if not recs:
        print(f"{args.jsonl}: no records with a confidence", file=sys.stderr)
        return 2
    res = table(recs)
    print(f"{res['n']} targets, {res['correct']} correct (ADD(-S)<0.1d), {res['n_failed']} flagged failed "
          f"({res['correct_among_failed']} of them correct); AUC(confidence -> correct) = {res['auc_confidence']}")
    print("confidence bin | targets | correct | fraction correct")
    for b in res["bins"]:
        frac = "-" if b["fraction_correct"] is None else f"{b['fraction_correct']:.2f}"
        print(f"[{b['bin'][0]:.2f}, {b['bin'][1]:.2f}) | {b['n']:7d} | {b['correct']:7d} | {frac}")
    write_json(args.out, res)
    return 0


if __name__ == "__main__":
    sys.exit(main())
