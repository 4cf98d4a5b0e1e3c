"""Fusion-weight study: re-rank the verified hypotheses of an LM-O pipeline run by weighted score terms.

Usage::

    python bench/lmo_fusion.py out/bench/lmo_pipeline/runs/<hash>/targets.jsonl [--out out/bench/lmo_fusion.json]

Reads a run made with ``shape.enabled=true`` and a large ``refine.n_hypotheses`` (every target records its
distinct hypotheses with their matcher score, edge / silhouette / crease / region agreement and pose errors,
see bench/lmo_pipeline.py) and, for every weight triple on a fixed grid, picks per target the hypothesis with the
highest ``w_match * match / best_match + w_edge * edge + w_region * (region - 0.5)``. Rule: the triple with the
most ADD(-S)<0.1d hits wins (ties: more rotations within 15°, then the smaller total weight). Prints the grid's best rows,
the matcher-only choice (today's default) and the ceiling (any hypothesis right).
"""

from __future__ import annotations

import argparse
import itertools
import json
from pathlib import Path

import numpy as np

GRID_MATCH = (0.0, 0.25, 0.5, 1.0, 2.0)
GRID_EDGE = (0.0, 0.5, 1.0, 2.0, 4.0)
GRID_REGION = (0.0, 0.5, 1.0, 2.0, 4.0)


def load(path: Path) -> list[dict]:
    recs = [json.loads(line) for line in path.read_text().splitlines() if line.strip()]
    return [r for r in recs if r.get("hyps")]


def choose(hyps: list[dict], w_m: float, w_e: float, w_r: float, w_c: float = 0.0) -> dict:
    best_m = max([h["match_score"] or 0.0 for h in hyps], default=0.0)

    def f(h):
        m = (h["match_score"] or 0.0) / best_m if best_m > 0 else 0.0
        e = h["edge"] if h["edge"] is not None else 0.0
        r = h["region"] if h["region"] is not None else 0.5
        c = (h.get("terms") or {}).get("crease")
        c = e if c is None else c
        return w_m * m + w_e * e + w_r * (r - 0.5) + w_c * (c - e)

    return max(hyps, key=f)


def evaluate(recs: list[dict], w: tuple) -> dict:
    ch = [choose(r["hyps"], *w) for r in recs]
    rot = np.array([c["rot_err"] for c in ch], float)
    return {"w_match": w[0], "w_edge": w[1], "w_region": w[2], "hits": int(sum(c["add_ok"] for c in ch)),
            "rot15": int(np.sum(rot < 15)), "median_rot": float(np.median(rot)),
            "per_object": {str(o): int(sum(c["add_ok"] for c, r in zip(ch, recs) if r["obj_id"] == o))
                           for o in sorted({r["obj_id"] for r in recs})}}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("targets", type=Path)
    ap.add_argument("--out", type=Path, default=Path("out/bench/lmo_fusion.json"))
    ap.add_argument("--max-matcher", type=int, default=0, help="keep the N best matcher hypotheses only (0: all)")
    ap.add_argument("--max-edges", type=int, default=0,
                    help="keep the N best edge hypotheses (by verified edge + region - 0.5) only (0: all)")
    args = ap.parse_args(argv)
    recs = load(args.targets)
    for r in recs:
        m = sorted([h for h in r["hyps"] if h["source"] != "edges"], key=lambda h: -(h["match_score"] or 0.0))
        e = sorted([h for h in r["hyps"] if h["source"] == "edges"],
                   key=lambda h: -((h["edge"] or 0.0) + (h["region"] or 0.5) - 0.5))
        r["hyps"] = (m[: args.max_matcher] if args.max_matcher else m) + (e[: args.max_edges] if args.max_edges else e)
    n = len(recs)
    matcher_only = []
    for r in recs:
        flagged = [h for h in r["hyps"] if h.get("matcher_best")]
        m = [h for h in r["hyps"] if h["source"] not in ("edges", "region")]
        matcher_only.append(flagged[0] if flagged else max(m, key=lambda h: h["match_score"] or 0.0) if m else r["hyps"][0])
    base = {"hits": int(sum(h["add_ok"] for h in matcher_only)),
            "rot15": int(sum((h["rot_err"] or 1e9) < 15 for h in matcher_only))}
    ceiling = int(sum(any(h["add_ok"] for h in r["hyps"]) for r in recs))
    rows = [evaluate(recs, w) for w in itertools.product(GRID_MATCH, GRID_EDGE, GRID_REGION) if any(w)]
    rows.sort(key=lambda d: (-d["hits"], -d["rot15"], d["w_match"] + d["w_edge"] + d["w_region"]))
    print(f"{n} targets; matcher only: {base['hits']} hits, {base['rot15']} within 15°; ceiling (any hypothesis): {ceiling}")
    print("| w_match | w_edge | w_region | ADD<0.1d hits | rot < 15° | median rot° |")
    print("|---|---|---|---|---|---|")
    for d in rows[:12]:
        print(f"| {d['w_match']} | {d['w_edge']} | {d['w_region']} | {d['hits']} | {d['rot15']} | {d['median_rot']:.1f} |")
    best = rows[0]
    for wc in (0.25, 0.5, 1.0):
        d = evaluate(recs, (best["w_match"], best["w_edge"], best["w_region"], wc))
        print(f"best + crease term {wc} * (crease - edge): {d['hits']} hits, {d['rot15']} within 15°")
    for name, w in (("edge only", (0, 1, 0)), ("region only", (0, 0, 1)), ("edge + region", (0, 1, 1))):
        d = evaluate(recs, w)
        print(f"{name}: {d['hits']} hits, {d['rot15']} within 15°")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps({"n": n, "matcher_only": base, "ceiling": ceiling, "grid": rows}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
