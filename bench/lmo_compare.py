"""Two LM-O runs of ``bench/lmo_pipeline.py`` compared target by target (the same targets, one journal each).

Prints ADD(-S)<0.1d hits overall, on the two halves (even / odd positions of ``select_targets``' list, the halves
of ``bench/lmo_align_study.py``), on a subset's targets and on the rest (a choice made on a subset is reported on
the targets it did not see), the targets only one of them gets right, AR (MSSD/MSPD) and the median rotation
error; writes the table as JSON.

    PYTHONPATH=src .venv/bin/python bench/lmo_compare.py RUN_A RUN_B --max-targets 716 --subset 96 --out OUT.json

RUN_A / RUN_B: run directories (``out/bench/lmo_pipeline/runs/<hash>``) or their ``targets.jsonl``.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import DEFAULT_DATASET, select_targets, write_json  # noqa: E402

from pixie.app.runner import Journal  # noqa: E402
from pixie.eval import evaluate  # noqa: E402
from pixie.eval.datasets import BopDataset, PoseEstimate  # noqa: E402



def load(run: Path) -> Journal:
    path = run / "targets.jsonl" if run.is_dir() else run
    if not path.is_file():
        raise SystemExit(f"{path}: no journal")
    return Journal(path, key=lambda d: (d["scene_id"], d["im_id"], d["obj_id"]))


def row(ds: BopDataset, targets, recs: list[dict | None], subset: set, ar: bool) -> dict:
    keys = [(t.scene_id, t.im_id, t.obj_id) for t in targets]
    ok = np.array([bool(r and r["add_ok"]) for r in recs])
    rot = [r["rot_err"] if r and r.get("rot_err") is not None else 180.0 for r in recs]
    ins = np.array([k in subset for k in keys])
    out = {"n": len(recs), "missing": sum(r is None for r in recs), "add_s_hits": int(ok.sum()),
           "add_s": float(ok.mean()), "half_even": int(ok[0::2].sum()), "half_odd": int(ok[1::2].sum()),
           "subset_hits": int(ok[ins].sum()), "subset_n": int(ins.sum()), "rest_hits": int(ok[~ins].sum()),
           "rest_n": int((~ins).sum()), "median_rot_deg": float(np.median(rot)),
           "seconds_per_target": float(np.mean([r["seconds"] for r in recs if r]))}
    per = {}
    for t, o in zip(targets, ok):
        per.setdefault(t.obj_id, []).append(o)
    out["per_object"] = {str(k): round(float(np.mean(v)), 3) for k, v in sorted(per.items())}
    if ar:
        ests = [PoseEstimate(r["scene_id"], r["im_id"], r["obj_id"], float(r["score"]), np.array(r["T"]), r["seconds"])
                for r in recs if r and r["T"] is not None]
        sc = evaluate(ds, ests, metrics=["mssd", "mspd"], targets=targets, n_points=2000)
        out["ar_mssd_mspd"] = sc.overall.get("AR_noVSD")
        for h, sl in (("even", slice(0, None, 2)), ("odd", slice(1, None, 2))):
            hs = evaluate(ds, [e for e in ests if (e.scene_id, e.im_id, e.obj_id) in set(keys[sl])], metrics=["mssd", "mspd"],
                          targets=targets[sl], n_points=2000)
            out[f"ar_{h}"] = hs.overall.get("AR_noVSD")
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("runs", nargs=2, type=Path)
    ap.add_argument("--names", default="A,B")
    ap.add_argument("--dataset", type=Path, default=DEFAULT_DATASET)
    ap.add_argument("--max-targets", type=int, default=716)
    ap.add_argument("--subset", type=int, default=96, help="the targets of select_targets(SUBSET): where it was chosen")
    ap.add_argument("--no-ar", action="store_true")
    ap.add_argument("--out", type=Path, default=None)
    a = ap.parse_args(argv)
    ds = BopDataset(a.dataset)
    targets = select_targets(ds, a.max_targets, None)
    subset = {(t.scene_id, t.im_id, t.obj_id) for t in select_targets(ds, a.subset, None)}
    names = a.names.split(",")
    res, oks = {}, []
    for name, run in zip(names, a.runs):
        j = load(run)
        recs = [j.get((t.scene_id, t.im_id, t.obj_id)) for t in targets]
        res[name] = row(ds, targets, recs, subset, not a.no_ar)
        oks.append(np.array([bool(r and r["add_ok"]) for r in recs]))
    res["only_" + names[0]] = int((oks[0] & ~oks[1]).sum())
    res["only_" + names[1]] = int((oks[1] & ~oks[0]).sum())
    cols = ["add_s_hits", "add_s", "half_even", "half_odd", "subset_hits", "rest_hits", "ar_mssd_mspd", "ar_even",
            "ar_odd", "median_rot_deg", "seconds_per_target", "missing"]
    print("| run | " + " | ".join(cols) + " |")
    print("|---" * (len(cols) + 1) + "|")
    for name in names:
        r = res[name]
        print(f"| {name} | " + " | ".join(f"{r[c]:.3f}" if isinstance(r.get(c), float) else str(r.get(c, "-"))
                                          for c in cols) + " |")
    for name in names:
        print(f"{name} per object: {res[name]['per_object']}")
    print(f"right only in {names[0]}: {res['only_' + names[0]]}, only in {names[1]}: {res['only_' + names[1]]}")
    write_json(a.out, res)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
