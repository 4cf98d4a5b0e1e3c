"""Paint spill (pixie.cues.part_paint) on stored part-report rows, and the per-assembly verdicts with it (issue 26).

Rows of ``bench/defects_parts.py`` made before the spill was recorded keep the report's pose (``T_robust``); this
measures each photo's spill there with the estimator's function (:func:`pixie.cues.part_paint.set_spill`, cached in
``--cache``), then judges every seed's assemblies (:func:`defects_parts.assembly_table`'s rule: the configured
per-photo thresholds, the photos below ``parts.views_min_fit`` left out, ``combine_views``) for each
(``spill_cap``, ``views_spill``) of the grid, and prints recall per defect type per assembly, the mean and the false
alarms per correct assembly. ``--fit S,S`` names the seeds the choice is made on: the best mean recall over them with
no seed's false alarms above those without the spill; ties to the larger threshold, then the larger cap.

Usage::

    python bench/defects_spill.py --rows 1=out/bench/s37/mv_s1_0.json,out/bench/s37/mv_s1_1.json --data 1=out/bench/defects300s1 \
        ... --fit 0,1,2,3 --out out/bench/s39/spill.json
"""

from __future__ import annotations

import argparse
import dataclasses
import hashlib
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import defects_parts as DP  # noqa: E402
import defects_seeds as DS  # noqa: E402

from pixie.config import PixieConfig  # noqa: E402
from pixie.cues.part_paint import set_spill  # noqa: E402
from pixie.cues.parts import PartSupport  # noqa: E402
from pixie.eval.datasets import BopDataset  # noqa: E402
from pixie.geometry.mesh import load_mesh  # noqa: E402
from pixie.geometry.render import Renderer  # noqa: E402

INF = float("inf")
TYPES = ("missing", "shifted", "rotated", "wrong")


def spills(data: Path, rows: list[dict], colour_ab: float) -> dict[str, list]:
    """Each row's paint spill per part at its report's pose (:func:`set_spill`, as the estimator measures it), keyed
    'scene_image' (None: not measured)."""
    ds, meshes, out = BopDataset(data), {}, {}
    for r in rows:
        if r["obj_id"] not in meshes:
            m = load_mesh(data / "models_parts" / f"obj_{r['obj_id']:06d}.glb")
            meshes[r["obj_id"]] = (m, Renderer(m))
        m, ren = meshes[r["obj_id"]]
        img, K = ds.load_rgb(r["scene_id"], r["im_id"]), ds.camera(r["scene_id"], r["im_id"]).K
        parts = [PartSupport.from_dict(p) for p in r["parts"]]
        set_spill(parts, img, K, ren, m.face_parts, r["T_robust"], colour_ab=colour_ab)
        out[f"{r['scene_id']}_{r['im_id']}"] = [None if not np.isfinite(p.spill) else p.spill for p in parts]
    return out


def with_spill(rows: list[dict], sp: dict[str, list]) -> list[dict]:
    """The rows with each part record's ``paint_spill`` set from ``sp``."""
    out = []
    for r in rows:
        s = sp[f"{r['scene_id']}_{r['im_id']}"]
        out.append({**r, "parts": [{**p, "paint_spill": s[p["index"]]} for p in r["parts"]]})
    return out


def judge(rows: list[dict], cfg: PixieConfig, views_spill: float, spill_cap: float) -> dict:
    """Recall per defect type per assembly, their mean and false alarms per correct assembly, as a batch with
    assemblies judges them (``parts.evidence`` on: the mean 3D-move gains count, as ``defects_seeds.py``'s shipped
    row), with the spill's threshold and cap."""
    views = DP.views_kwargs(dataclasses.replace(cfg.parts, evidence=True))
    a = DP.assembly_table(rows, cfg, DS.configured(cfg), views={**views, "views_spill": views_spill,
                                                                 "spill_cap": spill_cap})
    rec = {d: a[d]["recall"] for d in TYPES if d in a}
    return dict(recall=rec, mean=float(np.mean(list(rec.values()))),
                fa=a.get("none (correct assembly)", {}).get("false_alarms_per_assembly", 0.0))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rows", action="append", required=True, metavar="SEED=ROWS.json[,ROWS.json]")
    ap.add_argument("--data", action="append", required=True, metavar="SEED=DATASET_DIR")
    ap.add_argument("--fit", default="", help="seeds the grid is chosen on (comma-separated); the others are judged")
    ap.add_argument("--thresholds", default="0.5,0.4,0.3,0.25,0.2,0.15")
    ap.add_argument("--caps", default="inf,0.5,0.4")
    ap.add_argument("--cache", type=Path, default=Path("out/bench/spill_cache"))
    ap.add_argument("--preset", default="default")
    ap.add_argument("--set", action="append", default=[], metavar="SECTION.KEY=VALUE")
    ap.add_argument("--out", type=Path, required=True)
    args = ap.parse_args(argv)
    cfg = PixieConfig.from_preset(args.preset).apply_overrides(args.set)
    data = dict(a.split("=", 1) for a in args.data)
    seeds = {}
    args.cache.mkdir(parents=True, exist_ok=True)
    for a in args.rows:
        s, files = a.split("=", 1)
        rows = [r for f in files.split(",") for r in json.loads(Path(f).read_text())["rows"] if "parts" in r]
        key = hashlib.sha1(json.dumps([files, cfg.parts.colour_ab]).encode()).hexdigest()[:12]
        cache = args.cache / f"seed{s}_{key}.json"
        sp = json.loads(cache.read_text()) if cache.is_file() else spills(Path(data[s]), rows, cfg.parts.colour_ab)
        cache.write_text(json.dumps(sp))
        seeds[s] = with_spill(rows, sp)
    grid = [(INF, INF)] + [(float(c), float(t)) for c in args.caps.split(",") for t in args.thresholds.split(",")]
    fit = [s for s in args.fit.split(",") if s]
    table, base = [], {s: judge(rows, cfg, INF, 0.5)["fa"] for s, rows in seeds.items()}
    best = None
    for cap, t in grid:
        res = {s: judge(rows, cfg, t, cap) for s, rows in seeds.items()}
        ok = all(res[s]["fa"] <= base[s] + 1e-9 for s in fit)
        fit_mean = float(np.mean([res[s]["mean"] for s in fit])) if fit else float("nan")
        table.append(dict(spill_cap=cap, views_spill=t, fit_mean=fit_mean, no_fa_added=ok, seeds=res))
        cells = []
        for s, r in res.items():
            rec = " ".join(f"{r['recall'][d]:.2f}" for d in TYPES)
            cells.append(f"s{s} {r['mean']:.3f} [{rec}] FA {r['fa']:.3f}")
        print(f"cap {cap:<4} views_spill {t:<4} fit mean {fit_mean:.3f} {'ok' if ok else '--'} | " + " | ".join(cells),
              flush=True)
        key = (round(fit_mean, 6), t, cap)
        if fit and ok and (best is None or key > best[0]):
            best = (key, dict(spill_cap=cap, views_spill=t))
    if best:
        print("chosen on seeds", ",".join(fit), ":", best[1])
    args.out.write_text(json.dumps(dict(grid=table, fit=fit, chosen=best[1] if best else None), indent=1, default=str))
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
