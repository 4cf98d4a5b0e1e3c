"""Writing an evaluation: ``scores.json``, ``per_target.csv`` and the plain-text table."""

from __future__ import annotations

import csv
import json
import math
from pathlib import Path

from pixie.eval.scores import Scores

def write_scores_json(scores: Scores, path: str | Path, with_targets: bool = True) -> Path:
    """Write ``scores.json`` (non-finite numbers become null). Returns the path."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(scores.to_dict(with_targets), indent=1), encoding="utf-8")
    return path


def write_per_target_csv(scores: Scores, path: str | Path) -> Path:
    """One row per valid GT instance with its errors."""
    path = Path(path)
    keys = sorted({k for t in scores.targets for k in t.errors})
    with open(path, "w", newline="", encoding="utf-8") as f:
        w = csv.writer(f)
        w.writerow(["scene_id", "im_id", "obj_id", "gt_id", "visib_fract", "has_estimate", "score", *keys])
        for t in scores.targets:
            w.writerow(
                [t.scene_id, t.im_id, t.obj_id, t.gt_id, t.visib_fract, int(t.has_estimate), t.score]
                + [f"{t.errors.get(k, float('nan')):.6g}" for k in keys]
            )
    return path


def _fmt(v, digits: int = 3) -> str:
    if v is None:
        return "n/a"
    if isinstance(v, float):
        return f"{v:.{digits}f}" if math.isfinite(v) else "inf"
    return str(v)


def format_table(scores: Scores) -> str:
    """A short plain-text table: one row per object and an overall row."""
    cols: list[tuple[str, str, int]] = [("n", "n_targets", 0)]
    o = scores.overall
    ar_cols = (("AR_MSSD", "AR_MSSD"), ("AR_MSPD", "AR_MSPD"), ("AR_VSD", "AR_VSD"), ("AR_noVSD", "AR(noVSD)"), ("AR", "AR"))
    for key, label in ar_cols:
        if key in o:
            cols.append((label, key, 3))
    other_cols = (("ADD(-S)<0.1d", "ADD(-S)<.1d"), ("ADD<1cm", "ADD<1cm"), ("median_ADD", "medADD mm"), ("mean_APS", "APS"))
    for key, label in other_cols:
        if key in o:
            cols.append((label, key, 1 if key.startswith("median") else 3))
    widths = [max(len(c[0]), 7) for c in cols]
    lines = [f"{'obj':>5} " + " ".join(f"{c[0]:>{wd}}" for c, wd in zip(cols, widths))]
    rows = [(str(k), v) for k, v in scores.per_object.items()] + [("all", o)]
    for name, row in rows:
        cells = []
        for (label, key, digits), wd in zip(cols, widths):
            v = row.get(key)
            cells.append(f"{(_fmt(v, digits) if digits else _fmt(v)):>{wd}}")
        lines.append(f"{name:>5} " + " ".join(cells))
    head = (
        f"{scores.dataset}: {scores.n_targets} targets, {scores.n_estimates} estimates evaluated "
        f"({scores.n_ignored_estimates} ignored), {scores.time_s:.1f} s"
    )
    tail = []
    if o.get("AR") is not None:
        tail.append(f"AR = {o['AR']:.4f}  (mean of AR_VSD, AR_MSSD, AR_MSPD)")
    elif "AR_noVSD" in o:
        why = scores.vsd_note or "VSD not evaluated"
        tail.append(f"AR (no VSD) = {o['AR_noVSD']:.4f}  (mean of AR_MSSD, AR_MSPD; {why})")
    return "\n".join([head, *lines, *tail])
