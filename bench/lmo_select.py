"""Selection on the aligned fit, and a calibrated confidence, fitted on one half of an LM-O run and reported on the other.

Usage::

    python bench/lmo_select.py out/bench/lmo_pipeline/runs/<hash>/targets.jsonl [--out out/bench/lmo_select.json]

Reads a run made with ``align.enabled=true`` (every target records its aligned candidates, ``cands``: the starts and
their aligned poses with the terms ``fused`` (the shape stage's score) and ``fit`` (share of visible contour points on
a same-orientation edge), and the pose errors; bench/lmo_pipeline.py).

* **Selection.** For every ``w_fit`` on a fixed grid, pick per target the candidate with the highest
  ``fused + w_fit * fit``. Rule: on the fitting half (targets in even positions of the run's order) the ``w_fit``
  with the most ADD(-S)<0.1d hits wins; ties go to the smaller weight. Reported on the other half (odd positions).
* **Confidence.** A logistic model ``p = 1 / (1 + exp(-(a + b * fit + c * margin)))`` of the run's chosen pose
  (``fit`` its aligned fit, ``margin`` its score minus the best distinct alternative's, as the estimator computes
  them) fitted by Newton's method on the fitting half, predicting ADD(-S)<0.1d of the chosen pose; AUC and a reliability table (confidence bin -> share correct) on the
  other half. The coefficients are printed for ``config.align`` (``conf_a``, ``conf_b``, ``conf_c``).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

GRID = (0.0, 0.25, 0.5, 1.0, 2.0, 4.0, 8.0)


def load(path: Path) -> list[dict]:
    recs = [json.loads(line) for line in path.read_text().splitlines() if line.strip()]
    return [r for r in recs if r.get("cands")]


def choose(cands: list[dict], w_fit: float) -> tuple[int, float]:
    """Index of the best candidate by ``fused + w_fit * fit``, and its score."""
    s = np.array([(c["terms"].get("fused") or 0.0) + w_fit * (c["terms"].get("fit") or 0.0) for c in cands])
    i = int(np.argmax(s))
    return i, float(s[i])


def auc(score: np.ndarray, label: np.ndarray) -> float:
    pos, neg = score[label], score[~label]
    if len(pos) == 0 or len(neg) == 0:
        return float("nan")
    order = np.argsort(np.concatenate([pos, neg]), kind="stable")
    ranks = np.empty(len(order))
    ranks[order] = np.arange(1, len(order) + 1)
    return float((ranks[: len(pos)].sum() - len(pos) * (len(pos) + 1) / 2) / (len(pos) * len(neg)))


def logistic_fit(X: np.ndarray, y: np.ndarray, l2: float = 1e-3, iters: int = 50) -> np.ndarray:
    A = np.concatenate([np.ones((len(X), 1)), X], 1)
    w = np.zeros(A.shape[1])
    for _ in range(iters):
        p = 1 / (1 + np.exp(-A @ w))
        g = A.T @ (p - y) + l2 * w
        H = (A * (p * (1 - p))[:, None]).T @ A + l2 * np.eye(len(w))
        w -= np.linalg.solve(H, g)
    return w


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("targets", type=Path)
    ap.add_argument("--out", type=Path, default=Path("out/bench/lmo_select.json"))
    args = ap.parse_args(argv)
    recs = load(args.targets)
    fit_half, test_half = recs[0::2], recs[1::2]
    print(f"{len(recs)} targets with aligned candidates ({args.targets}); fitting half {len(fit_half)}, "
          f"report half {len(test_half)}")
    print("| w_fit | hits fitting half | hits report half |")
    print("|---|---|---|")
    table = {}
    for w in GRID:
        hf = sum(r["cands"][choose(r["cands"], w)[0]]["add_ok"] for r in fit_half)
        ht = sum(r["cands"][choose(r["cands"], w)[0]]["add_ok"] for r in test_half)
        table[w] = (hf, ht)
        print(f"| {w:g} | {hf} | {ht} |")
    best = max(GRID, key=lambda w: (table[w][0], -w))
    ceiling = sum(any(c["add_ok"] for c in r["cands"]) for r in test_half)
    shipped = sum(r["add_ok"] for r in test_half)
    print(f"chosen w_fit = {best:g} (rule: most hits on the fitting half, then the smaller weight); report half: "
          f"{table[best][1]}/{len(test_half)}; the run's own choice {shipped}/{len(test_half)}; any candidate {ceiling}")

    def feats(rs):
        """The run's chosen pose: its aligned fit and its margin over the best distinct alternative (as the
        estimator computes them), and whether it is right."""
        X, y = [], []
        for r in rs:
            h = r["hyps"]
            fit = (h[0]["terms"].get("fit") if h else None) or 0.0
            margin = (h[0]["score"] - (h[1]["score"] if len(h) > 1 else 0.0)) if h else 0.0
            X.append([fit, margin])
            y.append(bool(r["add_ok"]))
        return np.array(X), np.array(y)

    Xf, yf = feats(fit_half)
    Xt, yt = feats(test_half)
    w = logistic_fit(Xf, yf.astype(float))
    pt = 1 / (1 + np.exp(-(w[0] + Xt @ w[1:])))
    print(f"confidence = logistic({w[0]:.3f} + {w[1]:.3f} * fit + {w[2]:.3f} * margin); AUC on the report half "
          f"{auc(pt, yt):.3f} (fit alone {auc(Xt[:, 0], yt):.3f}, margin alone {auc(Xt[:, 1], yt):.3f})")
    print("| confidence | n | share correct |")
    print("|---|---|---|")
    rel = []
    for lo, hi in ((0, 0.2), (0.2, 0.4), (0.4, 0.6), (0.6, 0.8), (0.8, 1.01)):
        sel = (pt >= lo) & (pt < hi)
        rel.append({"bin": [lo, min(hi, 1.0)], "n": int(sel.sum()), "correct": float(yt[sel].mean()) if sel.any() else None})
        print(f"| {lo:.1f}-{min(hi, 1.0):.1f} | {int(sel.sum())} | {yt[sel].mean() if sel.any() else float('nan'):.2f} |")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps({"targets": str(args.targets), "grid": {str(k): v for k, v in table.items()},
                                    "w_fit": best, "confidence": {"a": w[0], "b": w[1], "c": w[2],
                                                                   "auc_report_half": auc(pt, yt)},
                                    "reliability": rel}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
