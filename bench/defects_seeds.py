"""The part report judged on assemblies it was not fitted on: the rule of ``bench/defects_parts.py`` fitted on each
benchmark seed's rows and applied to every other seed's (issue 26).

Each seed of ``bench/defects.py`` builds its own assemblies and defects, so a seed's rows share nothing with another
seed's. For each fitting seed and each variant of the rule, the thresholds are chosen on that seed
(:func:`defects_parts.choose`, then the 3D-move, runner-up and resize thresholds) at <= ``--max-fa`` false alarms per
correct assembly; every other seed is judged with them. Variants: ``none`` (no 3D moves, no resizes: their grids
restricted to off), ``moves``, ``resizes``, ``both`` (the bench's whole rule), ``views`` (the shipped thresholds per
photo, and per assembly the thresholds on the mean 3D-move / resize gains over its photos, :func:`choose_views`). The moves / resizes variants need rows
computed with ``--set parts.moves=true --set parts.move_gain=1.0 --set parts.resizes=true --set parts.resize_gain=1.0``
(the evidence stored, no verdict from it in the re-alignment, so the poses are the shipped default's).

Usage::

    python bench/defects_seeds.py --rows 0=a0.json,a1.json --rows 1=b0.json,b1.json --rows 2=c.json --out seeds.json

Prints one line per (fit seed, judged seed, variant): recall of the defective part per defect type, their mean and
the false alarms per correct assembly, per photo and per assembly (its photos judged together); first the shipped
thresholds on every seed; then per variant the means over the held-out pairs. Writes all of it as JSON.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import defects_parts as DP  # noqa: E402

from pixie.config import PixieConfig  # noqa: E402
from pixie.cues.part_views import views_kwargs  # noqa: E402

INF = float("inf")
VARIANTS = ("none", "moves", "resizes", "both", "views")


def fit_variants(rows: list[dict], cfg: PixieConfig, max_fa: float, variants=VARIANTS) -> dict[str, tuple]:
    """The rule's parameters on ``rows`` per variant (:data:`VARIANTS`); the score's thresholds are chosen once."""
    variants = [v for v in variants if v != "views"]  # fitted per assembly: choose_views
    if not variants:
        return {}
    base = tuple(DP.choose(rows, cfg, max_fa=max_fa))
    no_moves = base + (INF,)
    with_moves = DP.choose_moves(rows, cfg, base, max_fa=max_fa) if {"moves", "both"} & set(variants) else no_moves
    out = {}
    for v in variants:
        p = with_moves if v in ("moves", "both") else no_moves
        p = DP.choose_alt(rows, cfg, p, max_fa=max_fa)
        out[v] = DP.choose_resize(rows, cfg, p, grid=DP.RESIZE_GRID if v in ("resizes", "both") else [INF],
                                  max_fa=max_fa)
    return out


def judge(rows: list[dict], cfg: PixieConfig, params: tuple, key: str = "parts", views: dict | None = None) -> dict:
    """Recall per part defect type, their mean, and false alarms per correct assembly, per photo
    (:func:`defects_parts.table`) and per assembly, its photos judged together (``by_assembly``:
    :func:`defects_parts.assembly_table`). ``key``: 'parts' (the estimated poses) or 'parts_gt' (the true poses)."""
    t = DP.table(rows, cfg, params, key=key)
    rec = {d: t[d]["recall"] for d in DP.PART_DEFECTS if d in t}
    a = DP.assembly_table(rows, cfg, params, key=key, views=views)
    arec = {d: a[d]["recall"] for d in DP.PART_DEFECTS if d in a}
    return dict(recall=rec, mean=float(np.mean(list(rec.values()))),
                fa=t.get("none (correct assembly)", {}).get("false_alarms_per_image", 0.0),
                by_assembly=dict(recall=arec, mean=float(np.mean(list(arec.values()))),
                                 fa=a.get("none (correct assembly)", {}).get("false_alarms_per_assembly", 0.0),
                                 n={d: a[d]["n"] for d in a}))


VIEWS_GRID = [0.1, 0.15, 0.2, 0.25, 0.3, 0.4, 0.5, INF]  # the mean move / resize gain over an assembly's photos


def choose_views(rows: list[dict], cfg: PixieConfig, params: tuple, max_fa: float) -> dict:
    """(views_move_gain, views_resize_gain) of :data:`VIEWS_GRID` with the best mean recall per assembly
    (:func:`defects_parts.assembly_table`, photos judged with ``params``) at <= ``max_fa`` false alarms per correct
    assembly, or at no more than the report without them has when that is more (they may add no false alarm);
    ties to the fewer alarms, then to the larger thresholds."""
    off = DP.assembly_table(rows, cfg, params, views=dict(views_move_gain=INF, views_resize_gain=INF))
    max_fa = max(max_fa, off.get("none (correct assembly)", {}).get("false_alarms_per_assembly", 0.0))
    best, key = dict(views_move_gain=INF, views_resize_gain=INF), (-1.0, 0.0)
    for mg in sorted(VIEWS_GRID, reverse=True):
        for rg in sorted(VIEWS_GRID, reverse=True):
            v = dict(views_move_gain=mg, views_resize_gain=rg)
            a = DP.assembly_table(rows, cfg, params, views=v)
            fa = a.get("none (correct assembly)", {}).get("false_alarms_per_assembly", 0.0)
            if fa > max_fa + 1e-9:
                continue
            rec = float(np.mean([a[d]["recall"] for d in DP.PART_DEFECTS if d in a]))
            if (rec, -fa) > key:
                best, key = v, (rec, -fa)
    return best


def configured(cfg: PixieConfig) -> tuple:
    """The shipped thresholds as the rule's parameter tuple (defects_parts' order)."""
    pc = cfg.parts
    return (pc.flag_below, pc.colour_weight, pc.revealed_weight, pc.shift_weight, pc.move_gain if pc.moves else INF,
            pc.alt_gap, pc.resize_gain if pc.resizes else INF)


def _json(x):
    """Parameters for JSON: infinite thresholds (off) as null."""
    if isinstance(x, dict):
        return {k: _json(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_json(v) for v in x]
    return None if isinstance(x, float) and np.isinf(x) else x


def _line(j: dict) -> str:
    return (" / ".join(f"{d} {x:.2f}" for d, x in j["recall"].items()) + f" | mean {j['mean']:.3f} FA {j['fa']:.3f}")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--rows", action="append", required=True, metavar="SEED=FILE[,FILE]",
                    help="a seed's rows: bench/defects_parts.py --out or --shard outputs (their 'rows')")
    ap.add_argument("--preset", default="default")
    ap.add_argument("--set", action="append", default=[], metavar="SECTION.KEY=VALUE",
                    help="config overrides (e.g. parts.views_resize_gain=0.2, parts.resize_factors=0.5,0.75,1.5,2,3)")
    ap.add_argument("--max-fa", type=float, default=0.05, help="the rule's false alarms per correct assembly")
    ap.add_argument("--variants", default=",".join(VARIANTS))
    ap.add_argument("--configured-only", action="store_true", help="only the shipped thresholds on every seed (no "
                    "fitting: seconds)")
    ap.add_argument("--out", type=Path, required=True)
    args = ap.parse_args(argv)
    cfg = PixieConfig.from_preset(args.preset).apply_overrides(args.set)
    variants = tuple(v for v in args.variants.split(",") if v)
    if not set(variants) <= set(VARIANTS):
        ap.error(f"--variants: choose from {', '.join(VARIANTS)}")
    rows: dict[str, list[dict]] = {}
    for spec in args.rows:
        seed, _, files = spec.partition("=")
        rows[seed] = [r for f in files.split(",") for r in json.loads(Path(f).read_text())["rows"]]
    if len(rows) < 2 and not args.configured_only:
        ap.error("give the rows of at least two seeds")
    res: dict = {"max_fa": args.max_fa, "preset": args.preset, "set": args.set,
                 "n_rows": {s: len(r) for s, r in rows.items()}, "configured": {"params": _json(configured(cfg))}, "fits": {}, "pairs": []}
    # the shipped thresholds, no fitting; per assembly as a batch with assemblies judges them (parts.evidence on:
    # the mean 3D-move / resize gains count where the rows hold that evidence)
    shipped_views = views_kwargs(dataclasses.replace(cfg.parts, evidence=True))
    res["configured"]["views"] = _json(shipped_views)
    for s, r in rows.items():
        for key, at in (("parts", ""), ("parts_gt", ", at the true poses")):
            j = judge(r, cfg, configured(cfg), key=key, views=shipped_views)
            res["configured"][s + at] = j
            print(f"configured thresholds, seed {s}{at}: per photo {_line(j)}\n{'':33s}per assembly "
                  f"{_line(j['by_assembly'])} ({j['by_assembly']['n']})", flush=True)
    for fs, fr in rows.items() if not args.configured_only else ():
        t0 = time.perf_counter()
        fits = {v: (p, None) for v, p in fit_variants(fr, cfg, args.max_fa, variants).items()}
        if "views" in variants:  # the shipped per-photo thresholds; the mean move / resize gains' fitted per assembly
            fits["views"] = (configured(cfg), choose_views(fr, cfg, configured(cfg), args.max_fa))
        res["fits"][fs] = {v: [_json(p), _json(vw)] for v, (p, vw) in fits.items()}
        for v, (p, vw) in fits.items():
            for js, jr in rows.items():
                j = judge(jr, cfg, p, views=vw)
                res["pairs"].append(dict(fit=fs, judged=js, variant=v, params=_json(p), views=_json(vw), **j))
                tag = "fit itself" if js == fs else "held out"
                print(f"fit {fs} judged {js} ({tag}) {v:8s} {_line(j)} | params {tuple(p)}{'' if vw is None else vw}\n"
                      f"{'':39s}per assembly {_line(j['by_assembly'])}", flush=True)
        print(f"  (seed {fs} fitted in {time.perf_counter() - t0:.0f} s)", flush=True)
    if not args.configured_only:
        print("\n| variant | judged | held-out pairs | " + " | ".join(DP.PART_DEFECTS) + " | mean recall | FA per "
              "correct assembly |")
        print("|---|---|---|" + "---|" * len(DP.PART_DEFECTS) + "---|---|")
    res["held_out_means"] = {}
    for v in variants if not args.configured_only else ():
        ps = [p for p in res["pairs"] if p["variant"] == v and p["fit"] != p["judged"]]
        for unit, get in (("per photo", lambda p: p), ("per assembly", lambda p: p["by_assembly"])):
            m = {d: float(np.mean([get(p)["recall"][d] for p in ps])) for d in DP.PART_DEFECTS}
            mean, fa = float(np.mean([get(p)["mean"] for p in ps])), float(np.mean([get(p)["fa"] for p in ps]))
            res["held_out_means"][f"{v}, {unit}"] = dict(recall=m, mean=mean, fa=fa, n_pairs=len(ps))
            print(f"| {v} | {unit} | {len(ps)} | " + " | ".join(f"{m[d]:.2f}" for d in DP.PART_DEFECTS)
                  + f" | {mean:.3f} | {fa:.3f} |")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(res, indent=1, default=float))
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
