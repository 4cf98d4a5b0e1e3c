"""Ordering LINE-2D proposals by the part matches inside them, replayed from a bench/detect.py run.

Usage::

    python bench/detect_votes.py out/bench/detect_defects336_top20.json --dataset out/bench/defects300 \
        [--fit 48] [--out out/bench/detect_votes.json]

The run must list at least the 20 best boxes per target in LINE-2D's order (``bench/detect.py --top 20 --set
detect.vote_weight=0``). For each weight w and pool n of the grid, the first n boxes are re-ordered by similarity +
w x the number of other pool boxes lying inside them (at least 0.8 of their area; :func:`pixie.cues.detect.rank_scores`,
what :meth:`TemplateDetector.propose` calls), and the recall of the best 1 / 3 / 5 (IoU >= 0.5 with the GT amodal box)
is reported on the targets ``--max-targets FIT`` picks (the fitting set) and on the others (held out). Rule: most right
boxes among the best 5 on the fitting set, then among the best 1, then the smaller weight, then the smaller pool.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

import common as L  # noqa: E402  (bench/common.py: targets; puts src/ on the path)

from pixie.cues.detect import rank_scores, votes_inside  # noqa: E402

WEIGHTS = (0.0, 1.0, 2.0, 3.0, 5.0, 8.0)
POOLS = (10, 20)


def reorder(r: dict, w: float, n: int) -> list[float]:
    """The IoUs of row ``r``'s first ``n`` proposals in the voted order."""
    pr = r["proposals"]
    boxes = [np.asarray(b, np.float64) for b in pr["boxes"][:n]]
    votes = votes_inside(boxes) if w > 0 else np.zeros(len(boxes), int)
    _, order = rank_scores(np.asarray(pr["scores"][:n]), votes, w)
    return [pr["ious"][i] for i in order]


def recall(rows: list[dict], w: float, n: int, ks=(1, 3, 5)) -> list[float]:
    orders = [reorder(r, w, n) for r in rows]
    return [float(np.mean([max(o[:k], default=0.0) >= 0.5 for o in orders])) for k in ks]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("run", type=Path)
    ap.add_argument("--dataset", type=Path, default=L.DEFAULT_DATASET)
    ap.add_argument("--fit", type=int, default=48, help="the fitting set: the targets --max-targets FIT picks")
    ap.add_argument("--out", type=Path, default=L.REPO / "out/bench/detect_votes.json")
    args = ap.parse_args(argv)
    rows = json.loads(args.run.read_text())["rows"]
    fit_ids = {(t.scene_id, t.im_id, t.obj_id) for t in L.select_targets(L.BopDataset(args.dataset), args.fit)}
    fit = [r for r in rows if tuple(r["target"]) in fit_ids]
    held = [r for r in rows if tuple(r["target"]) not in fit_ids]
    table = []
    print(f"| weight | pool | fit ({len(fit)}): best 1 / 3 / 5 | held out ({len(held)}): best 1 / 3 / 5 |")
    print("|---|---|---|---|")
    for w in WEIGHTS:
        for n in POOLS:
            a, b = recall(fit, w, n), recall(held, w, n)
            table.append({"weight": w, "pool": n, "fit": a, "held_out": b})
            print(f"| {w:g} | {n} | {' / '.join(f'{v:.3f}' for v in a)} | {' / '.join(f'{v:.3f}' for v in b)} |")
    best = max(table, key=lambda e: (e["fit"][2], e["fit"][0], -e["weight"], -e["pool"]))
    print(f"rule's choice: weight {best['weight']:g}, pool {best['pool']}; held out best 1 / 3 / 5 "
          f"{' / '.join(f'{v:.3f}' for v in best['held_out'])}")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps({"run": str(args.run), "table": table, "choice": best}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
