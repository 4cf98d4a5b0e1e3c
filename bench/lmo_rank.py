"""Selection among the aligned candidates by a linear ranking over their named terms, fitted on one half of LM-O dev.

Usage::

    python bench/lmo_rank.py out/bench/rank/dump_0.pkl out/bench/rank/dump_1.pkl [--variant default] \
        [--out out/bench/lmo_rank.json]

Reads the candidate dumps of ``bench/lmo_align_study.py --dump`` (every aligned-stage candidate of every target:
pose, source, the shape stage's and the aligned fit's terms, its ADD(-S) verdict). The first file is the fitting
half, the others the report half (run the study with ``--part 0/2`` and ``--part 1/2``: even and odd positions).

Per candidate the features are the shipped ranking score (``fused + w_fit * fit``, always in the model), its terms,
and some that describe the pool rather than the candidate: ``consensus`` (how many other candidates of the target lie
within 5° and 2 % depth of it), the summed score of those, and the flags of its source. The model is a conditional
logit: the chosen candidate of a target is the one with the highest ``w · x``; ``w`` maximises the log-likelihood of
choosing a right candidate on the targets that have one (L2 on standardised features). Rule for the features: forward
selection on the fitting half alone from the shipped score, each step adding the feature that most raises the 5-fold
cross-validated hits there, stopping when no feature adds 2 hits; then fitted on the whole fitting half and reported
on the other half beside the shipped score, and the other way round (cross-fit).

``--auc``: only the AUC of the shipped calibrated confidence on each dump's chosen candidates (see
:func:`confidence_auc`).
"""

from __future__ import annotations

import argparse
import json
import pickle
from pathlib import Path

import numpy as np
from scipy.optimize import minimize

import common  # noqa: F401,E402  (bench/common.py: puts src/ on the path)

from pixie.geometry.camera import rotation_angle_deg  # noqa: E402

BASE = ("score", "fit", "fit_silhouette", "fit_dist", "fit_visible", "fused", "edge", "silhouette", "crease", "region",
        "match", "box_iou", "is_flip", "is_start", "iterations", "consensus", "consensus_score", "fit_region",
        "fit_support")


def features(t: dict) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(features [n, len(BASE)], right [n] bool, shipped score [n]) of one target's candidates."""
    cs = t["cands"]
    n = len(cs)
    X = np.zeros((n, len(BASE)))
    Ts = [c["T"] for c in cs]
    for i, c in enumerate(cs):
        tm = c["terms"]
        cons = [j for j in range(n) if j != i and rotation_angle_deg(Ts[i][:3, :3], Ts[j][:3, :3]) < 5.0
                and abs(Ts[i][2, 3] / Ts[j][2, 3] - 1) < 0.02]
        v = {"score": c["score"], "fit": tm.get("fit", 0.0), "fit_silhouette": tm.get("fit_silhouette", 0.0),
             "fit_dist": tm.get("fit_dist", 0.0), "fit_visible": tm.get("fit_visible", 0.0),
             "fused": tm.get("fused", 0.0), "edge": tm.get("edge", 0.0), "silhouette": tm.get("silhouette", 0.0),
             "crease": tm.get("crease", 0.0), "region": tm.get("region", 0.5),
             "match": c["match_score"] / max(t["best_match"], 1e-9), "box_iou": c["box_iou"],
             "is_flip": float(c["source"] == "flip"), "is_start": float(c["source"] not in ("flip", "aligned")),
             "iterations": tm.get("align_iterations", 0.0), "consensus": float(len(cons)),
             "consensus_score": float(sum(cs[j]["score"] for j in cons)),
             "fit_region": tm.get("fit_region", float("nan")), "fit_support": tm.get("fit_support", float("nan"))}
        X[i] = [0.0 if not np.isfinite(v[k]) else v[k] for k in BASE]
    y = np.array([bool(c["add_ok"]) for c in cs])
    s = np.array([c["score"] for c in cs])
    return X, y, s


def load(paths: list[Path], variant: str) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    out = []
    for p in paths:
        d = pickle.loads(Path(p).read_bytes())
        out += [features(t) for t in d["variants"][variant] if t["cands"]]
    return out


def fit_logit(data, cols: list[int], mu: np.ndarray, sd: np.ndarray, l2: float = 1.0) -> np.ndarray:
    """Conditional-logit weights over standardised features ``cols`` on the targets with a right candidate."""
    use = [((X[:, cols] - mu[cols]) / sd[cols], y) for X, y, _ in data if y.any() and not y.all()]

    def nll(w):
        f, g = l2 * 0.5 * w @ w, l2 * w
        for Z, y in use:
            a = Z @ w
            p = np.exp(a - a.max())
            p /= p.sum()
            pr = max(p[y].sum(), 1e-300)
            f -= np.log(pr)
            g -= Z.T @ (p * y / pr - p)  # the posterior over the right candidates minus the model's
        return f, g

    return minimize(nll, np.zeros(len(cols)), jac=True, method="L-BFGS-B").x


def hits(data, cols, w, mu, sd) -> int:
    return int(sum(y[int(np.argmax(((X[:, cols] - mu[cols]) / sd[cols]) @ w))] for X, y, _ in data))


def shipped_hits(data) -> int:
    return int(sum(y[int(np.argmax(s))] for _, y, s in data))


def cv_hits(data, cols, mu, sd, k: int = 5) -> int:
    tot = 0
    for f in range(k):
        tr = [d for i, d in enumerate(data) if i % k != f]
        te = [d for i, d in enumerate(data) if i % k == f]
        tot += hits(te, cols, fit_logit(tr, cols, mu, sd), mu, sd)
    return tot


def forward(data, mu, sd, min_gain: int = 2) -> list[int]:
    """Forward selection from the shipped score alone (column 0), by 5-fold cross-validated hits."""
    cols: list[int] = [0]
    best = cv_hits(data, cols, mu, sd)
    print(f"  forward: score alone -> {best} cross-validated hits", flush=True)
    while True:
        trials = [(cv_hits(data, cols + [j], mu, sd), j) for j in range(len(BASE)) if j not in cols]
        if not trials:
            return cols
        h, j = max(trials)
        print(f"  forward: + {BASE[j]} -> {h} cross-validated hits", flush=True)
        if h < best + min_gain:
            return cols
        cols, best = cols + [j], h


def confidence_auc(paths: list[Path], variant: str) -> None:
    """AUC (ADD(-S)-right against wrong) of the shipped calibrated confidence of each target's chosen candidate, per
    dump and over all: its ``fit``, ``size`` (projected diameter / 100 px, clipped) and ``margin`` (its score minus
    the best candidate's that is more than 10° away in rotation, as :meth:`PoseEstimator.distinct` would give
    among the aligned candidates)."""
    from common import DEFAULT_DATASET, BopDataset, ObjectCache
    from pixie.config import PixieConfig
    from pixie.cues.edge_align import calibrated_confidence, confidence_size
    from lmo_select import auc

    ac = PixieConfig.from_preset("default").align
    ds = BopDataset(DEFAULT_DATASET)
    objects = ObjectCache(ds)
    allc, ally = [], []
    for p in paths:
        conf, ok = [], []
        for t in pickle.loads(Path(p).read_bytes())["variants"][variant]:
            cs = t["cands"]
            if not cs:
                conf.append(0.0)
                ok.append(False)
                continue
            best = cs[0]
            other = [c["score"] for c in cs[1:] if rotation_angle_deg(c["T"][:3, :3], best["T"][:3, :3]) > 10.0]
            mesh = objects.mesh(t["target"][2])
            K = ds.camera(t["target"][0], t["target"][1]).K
            zc = (best["T"][:3, :3] @ mesh.center + best["T"][:3, 3])[2]
            x = {"fit": best["terms"]["fit"], "margin": best["score"] - (max(other) if other else 0.0),
                 "size": confidence_size(float(K[0, 0]) * mesh.diameter / max(float(zc), 1e-9))}
            conf.append(calibrated_confidence(ac, x))
            ok.append(bool(best["add_ok"]))
        print(f"{p}: {len(ok)} targets, {sum(ok)} right, AUC of the shipped confidence "
              f"{auc(np.array(conf), np.array(ok)):.3f}")
        allc += conf
        ally += ok
    print(f"all: {len(ally)} targets, AUC {auc(np.array(allc), np.array(ally)):.3f}")


def grid(paths: list[Path], variant: str, term: str, weights: list[float], out: Path) -> int:
    """Hits of simple rankings per dump (half): the shipped score, score + w * ``term`` for each weight, and the
    shipped score with ``term`` in place of the aligned fit (``fused + w_fit * term``, w_fit from the shipped score);
    prints one row per ranking, per dump and in all. A candidate without the term counts it as 0."""
    from pixie.config import PixieConfig

    w_fit = PixieConfig.from_preset("default").align.w_fit
    halves = []
    for p in paths:
        rows = []
        for t in pickle.loads(Path(p).read_bytes())["variants"][variant]:
            cs = t["cands"]
            if not cs:
                continue
            x = np.array([c["terms"].get(term, 0.0) for c in cs])
            rows.append((np.array([c["score"] for c in cs]), np.nan_to_num(x),
                         np.array([c["terms"].get("fused", 0.0) for c in cs]), np.array([bool(c["add_ok"]) for c in cs])))
        halves.append(rows)

    def count(rows, f) -> int:
        return int(sum(y[int(np.argmax(f(s, x, fu)))] for s, x, fu, y in rows))

    rankings = [("shipped", lambda s, x, fu: s)] + [(f"score + {w:g} {term}", lambda s, x, fu, w=w: s + w * x)
                                                   for w in weights]
    rankings.append((f"fused + {w_fit:g} {term} (in place of fit)", lambda s, x, fu: fu + w_fit * x))
    res = {}
    print(f"| ranking | {' | '.join(p.name for p in paths)} | all |\n|---|{'---|' * (len(paths) + 1)}")
    for name, f in rankings:
        hs = [count(r, f) for r in halves]
        res[name] = hs
        print(f"| {name} | {' | '.join(map(str, hs))} | {sum(hs)} |")
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps({"dumps": [str(p) for p in paths], "term": term, "hits": res}, indent=1))
    return 0


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("dumps", type=Path, nargs="+")
    ap.add_argument("--variant", default="default")
    ap.add_argument("--out", type=Path, default=Path("out/bench/lmo_rank.json"))
    ap.add_argument("--auc", action="store_true", help="only the AUC of the shipped confidence on the chosen poses")
    ap.add_argument("--grid", metavar="TERM", help="instead of the logit: hits per half of score + w * TERM (w on "
                    "--weights) and of fused + w_fit * TERM (TERM in place of the aligned fit)")
    ap.add_argument("--weights", default="-1,-0.5,-0.25,0.25,0.5,1,1.5,2,3")
    args = ap.parse_args(argv)
    if args.auc:
        confidence_auc(args.dumps, args.variant)
        return 0
    if args.grid:
        return grid(args.dumps, args.variant, args.grid, [float(w) for w in args.weights.split(",")], args.out)
    halves = [load([args.dumps[0]], args.variant), load(args.dumps[1:], args.variant)]
    rows = []
    for fi, ri in ((0, 1), (1, 0)):
        fit_d, rep_d = halves[fi], halves[ri]
        allX = np.concatenate([X for X, _, _ in fit_d])
        mu, sd = allX.mean(0), allX.std(0) + 1e-9
        print(f"fitting half {fi} ({len(fit_d)} targets), report half {ri} ({len(rep_d)})")
        cols = forward(fit_d, mu, sd)
        w = fit_logit(fit_d, cols, mu, sd)
        raw = w / sd[cols]
        row = {"fit_half": fi, "features": [BASE[c] for c in cols], "weights_std": w.tolist(),
               "weights_raw": raw.tolist(), "weights_per_score": (raw / raw[0]).tolist(),
               "fit": {"shipped": shipped_hits(fit_d), "model": hits(fit_d, cols, w, mu, sd), "n": len(fit_d),
                       "any_right": int(sum(y.any() for _, y, _ in fit_d))},
               "report": {"shipped": shipped_hits(rep_d), "model": hits(rep_d, cols, w, mu, sd), "n": len(rep_d),
                          "any_right": int(sum(y.any() for _, y, _ in rep_d))}}
        rows.append(row)
        print(f"| half {fi} fits | {', '.join(row['features'])} | fit: shipped {row['fit']['shipped']} / model "
              f"{row['fit']['model']} of {row['fit']['any_right']} | report: shipped {row['report']['shipped']} / "
              f"model {row['report']['model']} of {row['report']['any_right']} |", flush=True)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps({"dumps": [str(p) for p in args.dumps], "rows": rows}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
