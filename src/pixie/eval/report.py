"""Self-contained HTML report of an evaluation: summary, per-object table, error histograms
(matplotlib, Agg) and contour overlays of the best and worst targets (OpenCV).

Every image is embedded as base64 PNG, so ``report.html`` can be moved or mailed alone.
"""

from __future__ import annotations

import base64
import html
import io
import math
from pathlib import Path

import cv2
import numpy as np

from pixie.eval.datasets import BopDataset
from pixie.eval.objects import ObjectData, load_object_data
from pixie.eval.scores import Scores, TargetResult
from pixie.eval.writers import format_table
from pixie.geometry.rotations import orthonormalize
from pixie.paths import write_atomic
from pixie.viz import EST_COLOR, GT_COLOR, draw_contours


def png_base64(rgb: np.ndarray) -> str:
    """Encode an RGB uint8 image as a base64 PNG string."""
    ok, buf = cv2.imencode(".png", cv2.cvtColor(np.ascontiguousarray(rgb), cv2.COLOR_RGB2BGR))
    if not ok:
        raise ValueError("PNG encoding failed")
    return base64.b64encode(buf.tobytes()).decode("ascii")


def _fig_base64(fig) -> str:
    import matplotlib.pyplot as plt

    bio = io.BytesIO()
    fig.savefig(bio, format="png", dpi=90, bbox_inches="tight")
    plt.close(fig)
    return base64.b64encode(bio.getvalue()).decode("ascii")


def error_histograms(scores: Scores, diameters: dict[int, float]) -> list[tuple[str, str]]:
    """Histograms of the per-target errors: list of (title, base64 PNG).

    MSSD and ADD family are shown relative to the diameter, MSPD in px, VSD as the mean over taus.
    Targets without an estimate are counted in the title, not drawn.
    """
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    specs = [
        ("mssd", "MSSD / diameter", True, np.linspace(0, 0.6, 31)),
        ("mspd", "MSPD (px)", False, np.linspace(0, 60, 31)),
        ("vsd", "VSD (mean over taus)", False, np.linspace(0, 1, 21)),
        ("ad", "ADD(-S) / diameter", True, np.linspace(0, 0.3, 31)),
        ("add", "ADD (mm)", False, np.linspace(0, 60, 31)),
        ("aps", "APS", False, np.linspace(0, 1, 21)),
    ]
    out = []
    for key, title, rel, bins in specs:
        vals = [
            t.errors[key] / (diameters[t.obj_id] if rel else 1.0)
            for t in scores.targets
            if key in t.errors and t.has_estimate and math.isfinite(t.errors[key])
        ]
        if not vals:
            continue
        n_missing = sum(1 for t in scores.targets if key in t.errors and not t.has_estimate)
        v = np.clip(np.asarray(vals), bins[0], bins[-1])
        fig, ax = plt.subplots(figsize=(4.2, 2.8))
        ax.hist(v, bins=bins, color="#4477aa")
        ax.set_xlabel(title + (" (clipped)" if np.any(np.asarray(vals) > bins[-1]) else ""))
        ax.set_ylabel("targets")
        ax.set_title(f"{title}: n={len(vals)}" + (f", {n_missing} without estimate" if n_missing else ""), fontsize=9)
        out.append((title, _fig_base64(fig)))
    return out


def overlay_target(dataset: BopDataset, target: TargetResult, renderer, pad: int = 40) -> np.ndarray:
    """RGB crop with the model contour at the GT (green) and at the estimate (red)."""
    rgb = dataset.load_rgb(target.scene_id, target.im_id)
    h, w = rgb.shape[:2]
    K = dataset.camera(target.scene_id, target.im_id).K
    m_gt = renderer.render(orthonormalize(target.T_gt), K, h, w).mask
    img = draw_contours(rgb, m_gt, GT_COLOR)
    box_mask = m_gt.copy()
    if target.T_est is not None:
        m_est = renderer.render(orthonormalize(target.T_est), K, h, w).mask
        img = draw_contours(img, m_est, EST_COLOR)
        box_mask |= m_est
    ys, xs = np.nonzero(box_mask)
    if len(ys):
        y0, y1 = max(ys.min() - pad, 0), min(ys.max() + pad + 1, h)
        x0, x1 = max(xs.min() - pad, 0), min(xs.max() + pad + 1, w)
        img = img[y0:y1, x0:x1]
    if img.shape[0] < 160:  # small objects: enlarge the crop so the contours stay readable
        f = int(math.ceil(160 / max(img.shape[0], 1)))
        img = cv2.resize(img, (img.shape[1] * f, img.shape[0] * f), interpolation=cv2.INTER_NEAREST)
    return img


def _rank_key(t: TargetResult, diameters: dict[int, float]) -> float:
    for key, rel in (("mssd", True), ("ad", True), ("mspd", False), ("vsd", False), ("add", True)):
        if key in t.errors:
            v = t.errors[key]
            return v / diameters[t.obj_id] if rel else v
    return 0.0


def _table_html(scores: Scores) -> str:
    keys = [k for k in scores.overall if k not in ("n_missing",)]
    head = "".join(f"<th>{html.escape(k)}</th>" for k in ["object", *keys])
    rows = []
    for name, row in [*((str(o), s) for o, s in scores.per_object.items()), ("all", scores.overall)]:
        cells = []
        for k in keys:
            v = row.get(k)
            if v is None:
                s = "n/a"
            elif isinstance(v, float):
                s = f"{v:.1f}" if k.startswith(("mean_A", "median_")) and "APS" not in k else f"{v:.3f}"
            else:
                s = str(v)
            cells.append(f"<td>{s}</td>")
        cls = ' class="all"' if name == "all" else ""
        rows.append(f"<tr{cls}><td>{name}</td>{''.join(cells)}</tr>")
    return f"<table><tr>{head}</tr>{''.join(rows)}</table>"


def write_report(
    scores: Scores,
    dataset: BopDataset,
    out_dir: str | Path,
    n_overlays: int = 4,
    objects: dict[int, ObjectData] | None = None,
    title: str | None = None,
) -> Path:
    """Write ``out_dir/report.html`` and return its path.

    Parameters
    ----------
    scores : result of :func:`pixie.eval.evaluate`
    dataset : the evaluated dataset (for images and models)
    n_overlays : number of best and of worst targets drawn (ranked by MSSD/diameter, or the
        first available error); 0 disables overlays
    objects : ObjectData cache from the evaluation, reused for its renderers
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    objects = {} if objects is None else objects
    diameters = {o: float(dataset.model_info(o, eval=True)["diameter"]) for o in {t.obj_id for t in scores.targets}}
    parts = [
        "<!doctype html><html><head><meta charset='utf-8'>",
        f"<title>{html.escape(title or 'pixie eval: ' + scores.dataset)}</title>",
        "<style>body{font-family:sans-serif;margin:1.5em;max-width:1300px}"
        "table{border-collapse:collapse;font-size:12px}td,th{border:1px solid #ccc;padding:2px 6px;text-align:right}"
        "tr.all{font-weight:bold;background:#eef}figure{display:inline-block;margin:4px;vertical-align:top}"
        "figcaption{font-size:11px;max-width:320px}img.ov{max-height:260px}pre{background:#f6f6f6;padding:8px}</style>",
        "</head><body>",
        f"<h1>{html.escape(title or 'Evaluation: ' + scores.dataset)}</h1>",
        f"<pre>{html.escape(format_table(scores))}</pre>",
    ]
    if not scores.vsd_available and "vsd" in scores.metrics:
        parts.append(f"<p><b>{html.escape(scores.vsd_note)}</b>; the overall score is AR (no VSD).</p>")
    parts.append("<h2>Per object</h2>" + _table_html(scores))
    hists = error_histograms(scores, diameters)
    if hists:
        parts.append("<h2>Error histograms</h2>")
        for t, b64 in hists:
            parts.append(f"<figure><img src='data:image/png;base64,{b64}' alt='{html.escape(t)}'></figure>")
    if n_overlays > 0 and scores.targets:
        ranked = sorted(scores.targets, key=lambda t: _rank_key(t, diameters))
        best = ranked[:n_overlays]
        worst = ranked[::-1][:n_overlays]
        for label, sel in (("Best targets", best), ("Worst targets", worst)):
            parts.append(f"<h2>{label}</h2><p>green: model at GT, red: model at the estimate</p>")
            for t in sel:
                if t.obj_id not in objects:
                    objects[t.obj_id] = load_object_data(dataset, t.obj_id)
                try:
                    img = overlay_target(dataset, t, objects[t.obj_id].renderer)
                except Exception as exc:  # a missing image must not kill the report
                    parts.append(f"<p>scene {t.scene_id} im {t.im_id} obj {t.obj_id}: {html.escape(str(exc))}</p>")
                    continue
                errs = ", ".join(f"{k}={v:.3g}" for k, v in t.errors.items())
                cap = f"scene {t.scene_id} im {t.im_id} obj {t.obj_id} gt {t.gt_id}: {errs}"
                parts.append(
                    f"<figure><img class='ov' src='data:image/png;base64,{png_base64(img)}'>"
                    f"<figcaption>{html.escape(cap)}</figcaption></figure>"
                )
    parts.append("</body></html>")
    path = out / "report.html"
    return write_atomic(path, "\n".join(parts))
