"""Which estimated proposal to keep: a calibrated acceptance of find_objects's estimates, fitted on one run of
bench/detect.py --verify and reported on another.

Usage::

    python bench/detect_accept.py FIT.json [REPORT.json] [--out out/bench/detect_accept.json]

Both files come from ``bench/detect.py --verify --stop-confidence 0`` (every proposal estimated; each row lists
its proposals' estimates with their named scores, :func:`pixie.pipeline.find.proposal_terms`, and whether the
estimate's pose is right: ADD(-S) < 0.1 d).

* **Model.** ``p = logistic(c0 + c1 * x1 + ...)`` over terms of an estimate, predicting that its pose is right.
  Rule for the terms: forward selection on FIT alone, each step adding the term that most raises the 5-fold
  cross-validated AUC (folds by target, so that one photo's proposals stay together; standardised terms, L2 1.0),
  stopping when no term adds 0.005; then fitted on all of FIT.
* **Decision** (as :func:`find_objects` makes it): the proposals in their order; an estimate is accepted when it is
  not failed and ``p >= 0.5`` (more likely right than wrong: the threshold is not fitted); the accepted estimate with
  the highest ``p`` is kept; with ``--stop`` the search stops once one is accepted at that ``p``.
  The shipped rule is replayed beside it: confidence >= 0.5 and the pose's box at IoU >= 0.5 with the proposal's,
  the most confident kept.
* **Reported** on REPORT: found, found with the right box (the kept pose's projected box at IoU >= 0.5 with the
  GT amodal box), found with ADD(-S) < 0.1 d, wrong finds (kept, pose wrong), estimates made.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from lmo_select import auc, cv_auc, fit_raw, predict  # noqa: E402  (bench/lmo_select.py; puts src/ on the path)

from pixie.config import ACCEPT_TERMS as TERMS  # noqa: E402  (what config.detect.accept_terms may name)


def finite(e: dict) -> dict:
    """An estimate's record with non-finite terms (e.g. ``fit_dist`` of a pose with no visible point) set to 0."""
    return {k: (0.0 if isinstance(v, float) and not np.isfinite(v) else v) for k, v in e.items()}


def estimates(rows: list[dict]) -> tuple[list[dict], np.ndarray, np.ndarray]:
    """Every made, not failed estimate: its terms, its label (pose right) and its target's index."""
    xs, ys, gs = [], [], []
    for i, r in enumerate(rows):
        for e in r.get("estimates", []):
            if "add_ok" not in e or e.get("failed", 1.0):
                continue
            xs.append(finite(e))
            ys.append(bool(e["add_ok"]))
            gs.append(i)
    return xs, np.array(ys, bool), np.array(gs, int)


def select_terms(xs, y, groups, min_gain: float = 0.005) -> tuple[list[str], list[tuple[str, float]]]:
    chosen, steps, best = [], [], 0.5
    while True:
        scores = {k: cv_auc(xs, y, chosen + [k], groups=groups) for k in TERMS if k not in chosen}
        if not scores:
            break
        k = max(scores, key=scores.get)
        if scores[k] < best + min_gain:
            break
        chosen.append(k)
        best = scores[k]
        steps.append((k, best))
    return chosen, steps


def decide(r: dict, accept, stop: float | None) -> tuple[dict | None, int]:
    """The estimate the rule keeps for row ``r`` (None: not found) and the estimates it made."""
    kept, made = None, 0
    for e in r.get("estimates", []):
        if kept is not None and stop is not None and kept["_p"] >= stop:
            break
        if "failed" not in e:  # not estimated in the run (it ran with an early stop)
            continue
        made += 1
        if e.get("failed", 1.0) or "add_ok" not in e:
            continue
        p = accept(finite(e))
        if p is None:
            continue
        if kept is None or p > kept["_p"]:
            kept = {**e, "_p": p}
    return kept, made


def score(rows: list[dict], accept, stop: float | None) -> dict:
    found = box = add = wrong = made = 0
    for r in rows:
        k, m = decide(r, accept, stop)
        made += m
        if k is None:
            continue
        found += 1
        box += k.get("pose_iou_gt", 0.0) >= 0.5
        add += bool(k["add_ok"])
        wrong += not k["add_ok"]
    n = max(len(rows), 1)
    return {"n": len(rows), "found": found / n, "found_box": box / n, "found_add": add / n, "wrong_kept": wrong,
            "estimates": made}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("fit", type=Path)
    ap.add_argument("report", type=Path, nargs="?", help="default: FIT itself (in-sample rows only)")
    ap.add_argument("--stop", type=float, default=0.9, help="stop once a pose is accepted at this p (0: never)")
    ap.add_argument("--out", type=Path, default=Path("out/bench/detect_accept.json"))
    args = ap.parse_args(argv)
    fit_rows = json.loads(args.fit.read_text())["rows"]
    rep_rows = json.loads((args.report or args.fit).read_text())["rows"]
    xs, y, g = estimates(fit_rows)
    print(f"fitting set: {len(fit_rows)} targets, {len(xs)} estimates, {int(y.sum())} right")
    terms, steps = select_terms(xs, y, g)
    coef = fit_raw(xs, y, terms)
    print("forward selection (CV AUC):", ", ".join(f"+{k} {a:.3f}" for k, a in steps))
    print("model:", dict(zip(["intercept"] + terms, np.round(coef, 3).tolist())))
    xr, yr, _ = estimates(rep_rows)
    a_new = auc(predict(xr, terms, coef), yr)
    a_old = auc(np.array([x["confidence"] for x in xr]), yr)
    print(f"report set: {len(rep_rows)} targets, {len(xr)} estimates; AUC right vs wrong: calibrated acceptance "
          f"{a_new:.3f}, the estimate's confidence {a_old:.3f}")
    stop = args.stop or None

    def shipped(e):
        return e["confidence"] if e["confidence"] >= 0.5 and e.get("box_iou", 0.0) >= 0.5 else None

    def calibrated(e):
        p = float(predict([e], terms, coef)[0])
        return p if p >= 0.5 else None

    table = {}
    print("| rule | set | n | found | found, box right | found, ADD(-S) < 0.1 d | wrong kept | estimates |")
    print("|---|---|---|---|---|---|---|---|")
    for name, rule in (("shipped (confidence >= 0.5, box IoU >= 0.5)", shipped), ("calibrated p >= 0.5", calibrated)):
        for set_name, rows in (("fit", fit_rows), ("report", rep_rows)):
            s = score(rows, rule, stop)
            table[f"{name} | {set_name}"] = s
            print(f"| {name} | {set_name} | {s['n']} | {s['found']:.2f} | {s['found_box']:.2f} | {s['found_add']:.2f} | "
                  f"{s['wrong_kept']} | {s['estimates']} |")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps({"terms": terms, "coef": coef, "steps": steps, "auc_report": a_new,
                                    "auc_report_confidence": a_old, "table": table}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
