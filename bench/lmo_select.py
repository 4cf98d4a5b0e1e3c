"""Selection on the aligned fit, and a calibrated confidence, fitted on one half of an LM-O run and reported on the other.

Usage::

    python bench/lmo_select.py out/bench/lmo_pipeline/runs/<hash>/targets.jsonl [--out out/bench/lmo_select.json]
    python bench/lmo_select.py out/bench/rank/dump_0.pkl out/bench/rank/dump_1.pkl --variant NAME [--out ...]

The second form reads the aligned candidates that ``bench/lmo_align_study.py --dump`` wrote for one variant (both
parts, in the order given: part 0's targets then part 1's); the chosen pose is each target's first candidate, the
runner-up for ``margin`` the first one more than 10° away in rotation (as ``PoseEstimator.distinct``).

Reads a run made with ``align.enabled=true`` (every target records its aligned candidates, ``cands``: the starts and
their aligned poses with the terms ``fused`` (the shape stage's score) and ``fit`` (share of visible contour points on
a same-orientation edge), and the pose errors; bench/lmo_pipeline.py).

* **Selection.** For every ``w_fit`` on a fixed grid, pick per target the candidate with the highest
  ``fused + w_fit * fit``. Rule: on the fitting half (targets in even positions of the run's order) the ``w_fit``
  with the most ADD(-S)<0.1d hits wins; ties go to the smaller weight. Reported on the other half (odd positions).
* **Confidence.** A logistic model ``p = 1 / (1 + exp(-(c0 + c1 * x1 + ...)))`` of the run's chosen pose over
  terms the estimator has for it (``pixie.config.CONFIDENCE_TERMS``: ``fit`` its aligned fit, ``margin`` its score
  minus the best distinct alternative's, ``size`` its projected diameter in photo px / 100, the fit's and the shape
  stage's other terms; not ``fit_visible``, which measures how tight the given box is as much as the pose, unless
  ``--with-visible``), predicting ADD(-S)<0.1d of the chosen pose. Rule for the terms: forward selection on the
  fitting half alone, each step adding the term that most raises the 5-fold cross-validated AUC there (standardised
  terms, L2 1.0), stopping when no term adds 0.005; the model is then fitted on the whole fitting half (Newton) and
  its AUC and a reliability table (confidence bin -> share correct) reported on the other half, beside the
  ``[fit, margin]`` model refitted the same way. The coefficients are printed in the terms' own units for
  ``config.align.confidence`` / ``confidence_terms``.
"""

from __future__ import annotations

import argparse
import json
import pickle
from pathlib import Path

import numpy as np

from common import DEFAULT_DATASET  # noqa: E402  (bench/common.py: puts src/ on the path)

from pixie.config import CONFIDENCE_TERMS, AlignConfig  # noqa: E402
from pixie.cues.edge_align import confidence_size  # noqa: E402
from pixie.geometry.camera import rotation_angle_deg  # noqa: E402

GRID = (0.0, 0.25, 0.5, 1.0, 2.0, 4.0, 8.0)


def load(path: Path) -> list[dict]:
    recs = [json.loads(line) for line in path.read_text().splitlines() if line.strip()]
    return [r for r in recs if r.get("cands")]


def load_dumps(paths: list[Path], variant: str) -> list[dict]:
    """Targets of ``lmo_align_study.py --dump`` files for ``variant`` in the record layout :func:`load` returns:
    ``cands`` in the stage's order (the first is the chosen pose), ``hyps`` the chosen pose and the first candidate
    more than 10° from it, ``add_ok`` / ``T`` / ``obj_id`` of the chosen pose."""
    out = []
    for path in paths:
        for r in pickle.loads(path.read_bytes())["variants"][variant]:
            c = r["cands"]
            if not c:
                continue
            hyps = [c[0]] + [h for h in c[1:] if rotation_angle_deg(h["T"][:3, :3], c[0]["T"][:3, :3]) > 10.0][:1]
            out.append({"target": r["target"], "obj_id": int(r["target"][2]), "cands": c, "hyps": hyps,
                        "add_ok": bool(c[0]["add_ok"]), "T": np.asarray(c[0]["T"])})
    return out


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


def auc_interval(score: np.ndarray, label: np.ndarray, n: int = 1000, seed: int = 0) -> tuple[float, float]:
    """95 % bootstrap interval of :func:`auc` (targets resampled with replacement, ``n`` times, seeded)."""
    rng = np.random.default_rng(seed)
    vals = [auc(score[i], label[i]) for i in (rng.integers(0, len(score), len(score)) for _ in range(n))]
    lo, hi = np.nanpercentile(vals, [2.5, 97.5])
    return float(lo), float(hi)


def logistic_fit(X: np.ndarray, y: np.ndarray, l2: float = 1e-3, iters: int = 50) -> np.ndarray:
    A = np.concatenate([np.ones((len(X), 1)), X], 1)
    w = np.zeros(A.shape[1])
    for _ in range(iters):
        p = 1 / (1 + np.exp(-A @ w))
        g = A.T @ (p - y) + l2 * w
        H = (A * (p * (1 - p))[:, None]).T @ A + l2 * np.eye(len(w))
        w -= np.linalg.solve(H, g)
    return w


def object_sizes(dataset: Path) -> tuple[dict[int, float], float]:
    """Each object's diameter (mm, the BOP models' models_info.json) and the dataset's focal length (px)."""
    info = json.loads((dataset / "models" / "models_info.json").read_text())
    cam = json.loads((dataset / "camera.json").read_text())
    return {int(k): float(v["diameter"]) for k, v in info.items()}, float(cam["fx"])


def conf_inputs(r: dict, diam: dict[int, float], focal: float) -> dict[str, float]:
    """The terms of the run's chosen pose the calibrated confidence may use (``CONFIDENCE_TERMS``), as the estimator
    computes them: its recorded terms, ``margin`` (its score minus the best distinct alternative's) and ``size``
    (projected diameter / 100 px, clipped as the estimator clips it; from the pose, the object's diameter and the focal length when not recorded)."""
    h = r["hyps"]
    x = {k: float(v) for k, v in (h[0]["terms"] if h else {}).items() if v is not None}
    x["margin"] = (h[0]["score"] - (h[1]["score"] if len(h) > 1 else 0.0)) if h else 0.0
    if "size" not in x:
        T = np.asarray(r["T"], np.float64)
        x["size"] = confidence_size(focal * diam[int(r["obj_id"])] / max(T[2, 3], 1e-9))
    return x


def _matrix(xs: list[dict], ks: list[str]) -> np.ndarray:
    return np.array([[x.get(k, 0.0) for k in ks] for x in xs], np.float64).reshape(len(xs), len(ks))


def cv_auc(xs: list[dict], y: np.ndarray, ks: list[str], folds: int = 5, groups: np.ndarray | None = None) -> float:
    """Cross-validated AUC of a logistic model on terms ``ks`` (standardised; folds by position, or by ``groups``:
    records of one group stay in one fold)."""
    X = _matrix(xs, ks)
    X = (X - X.mean(0)) / (X.std(0) + 1e-9)
    fold = (np.arange(len(y)) if groups is None else np.asarray(groups)) % folds
    pred = np.zeros(len(y))
    for k in range(folds):
        te = fold == k
        w = logistic_fit(X[~te], y[~te].astype(float), l2=1.0)
        pred[te] = w[0] + X[te] @ w[1:]
    return auc(pred, y)


def fit_raw(xs: list[dict], y: np.ndarray, ks: list[str]) -> list[float]:
    """Logistic coefficients (intercept first) in the terms' own units, fitted on standardised terms (L2 1.0)."""
    X = _matrix(xs, ks)
    mu, sd = X.mean(0), X.std(0) + 1e-9
    w = logistic_fit((X - mu) / sd, y.astype(float), l2=1.0)
    b = w[1:] / sd
    return [float(w[0] - (b * mu).sum())] + [float(v) for v in b]


def predict(xs: list[dict], ks: list[str], coef: list[float]) -> np.ndarray:
    return 1.0 / (1.0 + np.exp(-(coef[0] + _matrix(xs, ks) @ np.asarray(coef[1:]))))


def reliability(p: np.ndarray, y: np.ndarray) -> list[dict]:
    """Confidence bins (0.2 wide) -> how many poses and the share correct; printed as a table."""
    print("| confidence | n | share correct |")
    print("|---|---|---|")
    rel = []
    for lo, hi in ((0, 0.2), (0.2, 0.4), (0.4, 0.6), (0.6, 0.8), (0.8, 1.01)):
        sel = (p >= lo) & (p < hi)
        rel.append({"bin": [lo, min(hi, 1.0)], "n": int(sel.sum()), "correct": float(y[sel].mean()) if sel.any() else None})
        print(f"| {lo:.1f}-{min(hi, 1.0):.1f} | {int(sel.sum())} | {y[sel].mean() if sel.any() else float('nan'):.2f} |")
    return rel


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("targets", type=Path, nargs="+", help="a run's targets.jsonl, or lmo_align_study.py dumps")
    ap.add_argument("--variant", default=None, help="with dumps: the variant whose candidates are read")
    ap.add_argument("--current", action="store_true", help="also report config.align.confidence as shipped")
    ap.add_argument("--out", type=Path, default=Path("out/bench/lmo_select.json"))
    ap.add_argument("--with-visible", action="store_true", help="let the confidence use fit_visible too")
    ap.add_argument("--dataset", type=Path, default=DEFAULT_DATASET, help="for the objects' diameters and the cameras")
    args = ap.parse_args(argv)
    recs = load_dumps(args.targets, args.variant) if args.variant else load(args.targets[0])
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

    diam, focal = object_sizes(args.dataset)
    xf, yf = [conf_inputs(r, diam, focal) for r in fit_half], np.array([bool(r["add_ok"]) for r in fit_half])
    xt, yt = [conf_inputs(r, diam, focal) for r in test_half], np.array([bool(r["add_ok"]) for r in test_half])
    # fit_visible (the share of the pose's contour inside the given box) is left out: it measures how tight the box is
    # as much as the pose, and LM-O's boxes are cut from its GT masks (--with-visible puts it back)
    names = [k for k in CONFIDENCE_TERMS if all(k in x for x in xf + xt) and (args.with_visible or k != "fit_visible")]
    chosen, best_cv = [], 0.0
    while True:
        trial = [(cv_auc(xf, yf, chosen + [k]), k) for k in names if k not in chosen]
        if not trial:
            break
        a, k = max(trial)
        if a < best_cv + 0.005:
            break
        chosen, best_cv = chosen + [k], a
        print(f"  + {k}: fitting-half 5-fold AUC {a:.3f}")
    print("| terms | AUC report half | 95 % interval | coefficients (intercept first) |")
    print("|---|---|---|---|")
    models = {}
    shipped_terms = list(AlignConfig().confidence_terms)
    for ks in (["fit", "margin"], shipped_terms, chosen):
        coef = fit_raw(xf, yf, ks)
        pt = predict(xt, ks, coef)
        ci = auc_interval(pt, yt)
        models[",".join(ks)] = {"terms": ks, "coef": coef, "auc_report_half": auc(pt, yt), "auc_interval": ci}
        print(f"| {', '.join(ks)} | {auc(pt, yt):.3f} | {ci[0]:.2f}-{ci[1]:.2f} | {[round(c, 3) for c in coef]} |")
    for k in names:
        print(f"  {k} alone: AUC report half {auc(np.array([x[k] for x in xt]), yt):.3f}")
    if args.current:
        ac = AlignConfig()
        pc = predict(xt, list(ac.confidence_terms), list(ac.confidence))
        models["current"] = {"terms": list(ac.confidence_terms), "coef": list(ac.confidence), "auc_report_half": auc(pc, yt)}
        print(f"  shipped config.align.confidence {ac.confidence_terms}: AUC report half {auc(pc, yt):.3f}")
    pt = predict(xt, chosen, models[",".join(chosen)]["coef"])
    print(f"chosen: confidence_terms {chosen}, confidence {[round(c, 3) for c in models[','.join(chosen)]['coef']]}")
    rel = reliability(pt, yt)
    print(f"refitted on the fitting half, the shipped terms {shipped_terms}:")
    models[",".join(shipped_terms)]["reliability"] = reliability(predict(xt, shipped_terms, models[",".join(shipped_terms)]["coef"]), yt)
    if args.current:
        print("shipped confidence:")
        rel_current = reliability(pc, yt)
        models["current"]["reliability"] = rel_current
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps({"targets": [str(p) for p in args.targets], "variant": args.variant, "grid": {str(k): v for k, v in table.items()},
                                    "w_fit": best, "confidence": models, "chosen_terms": chosen,
                                    "reliability": rel}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
