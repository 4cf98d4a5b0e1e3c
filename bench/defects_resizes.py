"""Which resizes an assembly's verdict reads (issue 26): the grid of ``parts.views_resize_factors`` x
``views_resize_same`` x ``views_resize_gain``, chosen on some benchmark seeds and judged on another.

Reads rows of ``bench/defects_parts.py`` computed with every resize's gain stored on every part in view
(``--set parts.resizes=true --set parts.resize_gain=1.0 --set parts.resize_factors=0.5,0.75,1.5,2,3 --set
parts.resize_below=100``, and the 3D moves as the shipped assembly verdict reads them: ``--set parts.moves=true
--set parts.move_gain=1.0``); ``--gt-only`` rows (the true poses, key ``parts_gt``) or rows at the estimated poses
(``parts``). Every other threshold is the shipped one; an assembly's photos are judged together
(:func:`defects_parts.assembly_table`).

The rule (session 40): the best mean recall of the wrong part per assembly over the ``--fit`` seeds, with no fitting
seed's false alarms per correct assembly above those of the report without these resizes on that seed; ties to the
larger gain, then fewer factors, then one resize over all photos. The other seeds are judged with the choice.

Usage::

    python bench/defects_resizes.py --key parts_gt --rows 0=gt_s0.json --rows 1=gt_s1.json ... --fit 0,1,2,3 \\
        --out resizes.json

Prints the grid (wrong-part recall per assembly, its number of assemblies and the false alarms per correct
assembly, per seed) and the choice; writes both as JSON.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import defects_parts as DP  # noqa: E402

from pixie.config import PixieConfig  # noqa: E402
from pixie.cues.part_views import views_kwargs  # noqa: E402

INF = float("inf")
FACTORS = ((0.5, 0.75), (0.75,), (0.5,), (0.5, 0.75, 1.5, 2.0, 3.0))
GAINS = (0.05, 0.1, 0.15, 0.2, 0.25, 0.3, 0.4)


def wrong_and_fa(rows: list[dict], cfg: PixieConfig, key: str, factors, gain: float, same: bool
                 ) -> tuple[float, int, float]:
    """(wrong-part recall per assembly, number of wrong assemblies, false alarms per correct assembly) with the
    assembly's verdict reading the resizes by ``factors`` at ``gain`` (``same``: one resize over all photos)."""
    cfg = dataclasses.replace(cfg, parts=dataclasses.replace(cfg.parts, views_resize_factors=list(factors)))
    views = views_kwargs(dataclasses.replace(cfg.parts, evidence=True))
    views.update(views_resize_gain=gain, views_resize_same=same, views_resize_factors=tuple(factors))
    a = DP.assembly_table(rows, cfg, DP.configured(cfg), key=key, views=views)
    w = a.get("wrong", {})
    return (float(w.get("recall", float("nan"))), int(w.get("n", 0)),
            float(a.get("none (correct assembly)", {}).get("false_alarms_per_assembly", 0.0)))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--rows", action="append", required=True, metavar="SEED=FILE[,FILE]")
    ap.add_argument("--key", default="parts_gt", choices=("parts_gt", "parts"), help="true (parts_gt) or estimated poses")
    ap.add_argument("--fit", default=None, metavar="S[,S]", help="the seeds the rule chooses on (default: all given)")
    ap.add_argument("--preset", default="default")
    ap.add_argument("--set", action="append", default=[], metavar="SECTION.KEY=VALUE")
    ap.add_argument("--out", type=Path, required=True)
    args = ap.parse_args(argv)
    cfg = PixieConfig.from_preset(args.preset).apply_overrides(args.set)
    seeds: dict[str, list[dict]] = {}
    for spec in args.rows:
        s, _, files = spec.partition("=")
        seeds[s] = [r for f in files.split(",") for r in json.loads(Path(f).read_text())["rows"]]
    fit = args.fit.split(",") if args.fit else list(seeds)
    grid = [((), INF, False)] + [(f, g, same) for f in FACTORS for same in (True, False) for g in GAINS]
    print(f"rows at the {'true' if args.key == 'parts_gt' else 'estimated'} poses; fit on seeds {', '.join(fit)}")
    print("| factors | gain | same | " + " | ".join(f"seed {s}: wrong (n), FA" for s in seeds) + " |")
    print("|---|---|---|" + "---|" * len(seeds))
    table = []
    for f, g, same in grid:
        res = {s: wrong_and_fa(r, cfg, args.key, f or (0.5,), g, same) for s, r in seeds.items()}
        table.append(dict(factors=list(f), gain=None if np.isinf(g) else g, same=same,
                          seeds={s: dict(wrong=w, n=n, fa=fa) for s, (w, n, fa) in res.items()}))
        print(f"| {','.join(f'{x:g}' for x in f) or 'none'} | {g:g} | {same} | "
              + " | ".join(f"{w:.2f} ({n}), {fa:.3f}" for w, n, fa in res.values()) + " |", flush=True)
    base = table[0]["seeds"]
    best, best_key = table[0], (float(np.mean([base[s]["wrong"] for s in fit])), INF, 0, False)
    for row in table[1:]:
        if any(row["seeds"][s]["fa"] > base[s]["fa"] + 1e-9 for s in fit):
            continue
        k = (round(float(np.mean([row["seeds"][s]["wrong"] for s in fit])), 9), row["gain"], -len(row["factors"]),
             row["same"])
        if k > best_key:
            best, best_key = row, k
    print(f"\nthe rule's choice on seeds {', '.join(fit)}: factors {best['factors'] or 'none'}, gain {best['gain']}, "
          f"same {best['same']}: mean wrong recall {best_key[0]:.3f} (without: "
          f"{np.mean([base[s]['wrong'] for s in fit]):.3f})")
    for s in seeds:
        if s not in fit:
            print(f"judged seed {s}: wrong {base[s]['wrong']:.2f} -> {best['seeds'][s]['wrong']:.2f}, false alarms "
                  f"{base[s]['fa']:.3f} -> {best['seeds'][s]['fa']:.3f} per correct assembly")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(dict(key=args.key, fit=fit, grid=table, choice=best), indent=1))
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
