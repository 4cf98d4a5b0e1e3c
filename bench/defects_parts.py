"""Part verdicts on the synthetic defects benchmark: which part is wrong, at the estimated and at the true pose.

Reads the target-model estimates that ``bench/defects.py`` cached (``--estimates``, the journal of its run with
the same ``--preset``) and, for every image, computes the part report of :mod:`pixie.cues.parts` with the target
model's parts (``models_parts/obj_*.glb``):

* at the estimated pose, with the re-alignment that leaves flagged parts out (:func:`robust_part_fit`, what
  ``pixie inspect`` does) -- also reporting the ADD of that re-aligned pose;
* at the ground-truth pose (the report's own quality, free of pose errors).

With ``--mask`` the report runs inside the GT visible mask (the estimates stay those made from the box).

Thresholds (``config.parts.flag_below``, ``colour_weight``): chosen on the *fitting half* (even image ids, i.e.
viewpoints 0 and 2 of every scene) on a grid, as the pair with the best mean recall of the defective part over the
missing / shifted / rotated / wrong scenes among those with <= ``--max-fa`` (0.1) false alarms per correct assembly, at the
estimated poses; reported on the other half (odd image ids). The verdicts in the per-image records use the
configured thresholds. The cross-fit applies the same rule on each half and judges every image with the other
half's choice: a two-fold estimate over all images (48 correct assemblies, not 24), also restricted to the images
whose estimated pose is right (ADD < 1 cm), which separates the report's own errors from the pose's.

Usage::

    OMP_NUM_THREADS=1 .venv/bin/python bench/defects_parts.py --data out/bench/defects300 \\
        --estimates out/bench/defects300_run/estimates.jsonl --preset default --out out/bench/defects300_parts.json

Two processes side by side: ``--shard 0/2 --out a.json`` and ``--shard 1/2 --out b.json``, then ``--merge a.json
b.json --out all.json`` (the same rows as one process).

Prints the tables (per defect type: recall of the defective part, false alarms per correct assembly) and writes
the JSON (per image: verdicts and supports of every part, ADD before / after the re-alignment).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "src"))
sys.path.insert(0, str(REPO / "bench"))

from pixie.config import PixieConfig  # noqa: E402
from pixie.cues.edge_align import align_kwargs, edge_fit, photo_edges, photo_edges_kwargs  # noqa: E402
from pixie.cues.part_paint import set_spill  # noqa: E402
from pixie.cues.part_views import combine_views, trusted_views, views_kwargs  # noqa: E402
from pixie.cues.parts import (PartSupport, complement_renderers, hidden_from_runner_up, is_flip_runner_up,  # noqa: E402
                              judge_parts, only_resizes, part_renderers, part_support, report_kwargs,
                              robust_part_fit)
from pixie.eval import pose_error as M  # noqa: E402
from pixie.eval.datasets import BopDataset  # noqa: E402
from pixie.geometry.collide import part_solids  # noqa: E402
from pixie.geometry.mesh import load_mesh  # noqa: E402
from pixie.geometry.render import Renderer  # noqa: E402

GRID = [round(x, 2) for x in np.arange(-0.5, 0.951, 0.05)]  # flag_below (a score below 0: colour_weight > 0)
COLOUR_GRID = [0.0, 0.5, 1.0, 1.5, 2.0, 3.0]
REVEALED_GRID = [0.0, 0.5, 1.0, 1.5, 2.0]  # 0: the session-10 score (no contrast with the model without the part)
SHIFT_GRID = [0.0, 0.5, 1.0]  # weight of the shift search's gain in the score
MOVE_GRID = [0.1, 0.15, 0.2, 0.25, 0.3, 0.35, 0.4, 0.5, 0.6, float("inf")]  # parts.move_gain (inf: no 3D moves)
ALT_GRID = [0.0, 0.05, 0.1, 0.15, 0.2, 0.25, 0.3, 0.4, 0.5]  # parts.alt_gap (0: no runner-up)
RESIZE_GRID = [0.1, 0.15, 0.2, 0.25, 0.3, 0.35, 0.4, 0.5, 0.6, float("inf")]  # parts.resize_gain (inf: no resizes)
FLAG = ("missing", "displaced", "wrong")  # the verdicts that flag a part (pixie.pose.results.SUSPECT_VERDICTS)
PART_DEFECTS = ("missing", "shifted", "rotated", "wrong")


def _kw(cfg: PixieConfig, flag_below: float | None = None, colour_weight: float | None = None,
        revealed_weight: float | None = None, shift_weight: float | None = None,
        move_gain: float | None = None, resize_gain: float | None = None) -> tuple[dict, dict, dict]:
    pc, ac = cfg.parts, cfg.align
    support, judge = report_kwargs(pc)
    for k, v in (("flag_below", flag_below), ("colour_weight", colour_weight), ("revealed_weight", revealed_weight),
                 ("shift_weight", shift_weight), ("move_gain", move_gain), ("resize_gain", resize_gain)):
        if v is not None:
            judge[k] = v
    align = align_kwargs(ac)
    return support, judge, align


def target_estimates(journal: Path, data: Path, cfg: PixieConfig, by_target: bool = False
                     ) -> dict[tuple[int, int], dict]:
    """The cached target-model estimates of ``bench/defects.py`` (same keys: config, model, target, threshold).
    ``by_target``: any record of the target model for the target (scene, image, object), whatever config made it
    (estimates from an earlier commit whose config keys differ but whose poses are the current default's)."""
    import defects as D  # bench/defects.py
    from pixie.app.runner import make_matcher

    ds = BopDataset(data)
    thr = make_matcher(cfg).extractor.threshold
    recs = {}
    for line in journal.read_text().splitlines():
        try:
            r = json.loads(line)
        except ValueError:
            continue
        recs[r["key"]] = r
        if by_target:
            t = (r["scene_id"], r["im_id"], r["obj_id"])
            if t in recs and recs[t]["key"] != r["key"]:
                raise SystemExit(f"{journal}: two estimates of target {t} (target and defective model?); "
                                 "--by-target needs one per target")
            recs[t] = r
    out = {}
    for tg in ds.targets():
        if by_target and (tg.scene_id, tg.im_id, tg.obj_id) in recs:
            out[(tg.scene_id, tg.im_id)] = recs[(tg.scene_id, tg.im_id, tg.obj_id)]
            continue
        key = D.run_key(cfg, data / "models" / f"obj_{tg.obj_id:06d}.ply", data, tg, thr)
        if key in recs:
            out[(tg.scene_id, tg.im_id)] = recs[key]
    return out


def analyse(data: Path, ests: dict, cfg: PixieConfig, echo=print, use_mask: bool = False,
            parts_dir: str = "models_parts") -> list[dict]:
    ds = BopDataset(data)
    variants = {v["scene_id"]: v for v in json.loads((data / "variants.json").read_text())}
    support_kw, judge_kw, align_kw = _kw(cfg)
    models: dict[int, tuple] = {}
    phys_pts: dict[str, np.ndarray] = {}
    rows = []
    t0 = time.perf_counter()
    for n, ((sid, im), est) in enumerate(sorted(ests.items())):
        v = variants[sid]
        oid = v["obj_id"]
        if oid not in models:
            m = load_mesh(data / parts_dir / f"obj_{oid:06d}.glb")
            models[oid] = (m, Renderer(m, smooth_normals=True), part_renderers(m),
                           complement_renderers(m, smooth_normals=True),
                           part_solids(m) if (cfg.parts.moves or cfg.parts.resizes) and cfg.parts.move_collide
                           else None)
        mesh, ren, prs, comps, solids = models[oid]
        phys = data / v["model_dir"] / f"obj_{v['model_obj_id']:06d}.ply"
        if str(phys) not in phys_pts:
            phys_pts[str(phys)] = load_mesh(phys).sample_points(2000, seed=1)
        (inst,) = ds.instances(sid, im)
        img, K = ds.load_rgb(sid, im), ds.camera(sid, im).K
        x, y, w, h = inst.box_visib
        ac = cfg.align
        mask = ds.load_mask_visib(sid, im, 0) if use_mask else None
        pe = photo_edges(img, K, np.array([x, y, x + w, y + h], np.float64), mask=mask, **photo_edges_kwargs(ac))
        defect = v.get("defect") or {}
        rec = dict(scene_id=sid, im_id=im, obj_id=oid, defect=defect.get("type"), defect_part=defect.get("part"),
                   colour=v["colour_variant"], family="mechanical" if "standoff" in " ".join(mesh.part_names) else "lego",
                   failed=bool(est.get("failed")) or est.get("T") is None)
        t = time.perf_counter()
        if not rec["failed"]:
            T = np.asarray(est["T"], np.float64)
            Tr, ps, dropped = robust_part_fit(ren, mesh.face_parts, mesh.part_names, pe, T, renderers=prs, complements=comps,
                                              solids=solids,
                                              align_kw=dict(hull=mesh.hull_vertices, **align_kw),
                                              support_kw=support_kw, judge_kw=judge_kw)
            if cfg.parts.spill:  # the paint spill at the report's pose, as the estimator records it
                set_spill(ps, img, K, ren, mesh.face_parts, Tr, colour_ab=cfg.parts.colour_ab)
            rec.update(add_mm=float(M.add(T, inst.T_cam_from_obj, phys_pts[str(phys)])),
                       add_robust_mm=float(M.add(Tr, inst.T_cam_from_obj, phys_pts[str(phys)])),
                       rot_deg=float(M.rotation_error_deg(T, inst.T_cam_from_obj)),
                       dropped=dropped, parts=[p.as_dict() for p in ps], T=T.tolist(), T_robust=Tr.tolist(),
                       score=float(est.get("score", 0.0)),
                       pose_fit=edge_fit(ren, pe, T, fit_px=ac.fit_px).as_dict())
            if est.get("runner_up_T") is not None:  # the runner-up (parts.alt_gap): judged when it is a flip
                Ta = np.asarray(est["runner_up_T"], np.float64)
                rec.update(alt_gap=float(est["score"]) - float(est["runner_up_score"]), T_alt=Ta.tolist(),
                           alt_deg=float(M.rotation_error_deg(Ta, T)),
                           alt_add_mm=float(M.add(Ta, inst.T_cam_from_obj, phys_pts[str(phys)])))
                if rec["alt_deg"] >= cfg.parts.alt_min_deg:
                    _, pa, _ = robust_part_fit(ren, mesh.face_parts, mesh.part_names, pe, Ta, renderers=prs,
                                               complements=comps, solids=solids,
                                               align_kw=dict(hull=mesh.hull_vertices, **align_kw),
                                               support_kw=support_kw, judge_kw=judge_kw)
                    rec["parts_alt"] = [p.as_dict() for p in pa]
        rec["seconds"] = time.perf_counter() - t
        gt = judge_parts(part_support(ren, mesh.face_parts, mesh.part_names, pe, inst.T_cam_from_obj, renderers=prs,
                                      complements=comps, solids=solids,
                                      **support_kw), **judge_kw)
        if cfg.parts.spill:
            set_spill(gt, img, K, ren, mesh.face_parts, inst.T_cam_from_obj, colour_ab=cfg.parts.colour_ab)
        rec["parts_gt"] = [p.as_dict() for p in gt]
        rows.append(rec)
        if (n + 1) % 24 == 0:
            echo(f"  {n + 1}/{len(ests)} images ({time.perf_counter() - t0:.0f} s)")
    return rows


def _judged(parts: list[dict], cfg: PixieConfig, params: tuple) -> list[PartSupport]:
    """Stored part records judged under other (flag_below, colour_weight, revealed_weight, shift_weight[, move_gain[,
    alt_gap[, resize_gain]]]) (:func:`judge_parts` on the records; a missing resize_gain: none, as without resizes),
    their resizes restricted to those the config tries (:func:`only_resizes`: ``cfg.parts.resize_factors`` for one
    photo's verdict, ``views_resize_factors`` for an assembly's)."""
    _, judge, _ = _kw(cfg, *params[:5], resize_gain=params[6] if len(params) > 6 else float("inf"))
    factors = sorted(set(cfg.parts.resize_factors) | set(cfg.parts.views_resize_factors))
    return judge_parts([only_resizes(PartSupport.from_dict(p), factors) for p in parts], **judge)


def row_verdicts(r: dict, cfg: PixieConfig, params: tuple, key: str = "parts") -> list[str]:
    """The verdicts of row ``r``'s parts (``key``) under ``params`` (:func:`_judged`). A sixth entry of ``params`` is
    ``parts.alt_gap``: at the estimated pose, parts not visible take the runner-up's verdict (its report is stored as
    ``parts_alt`` when it is turned >= ``parts.alt_min_deg``) when :func:`pixie.cues.parts.is_flip_runner_up` says it
    is a near-equal flip within that gap (:func:`pixie.cues.parts.hidden_from_runner_up`: the estimator's rule)."""
    ps = _judged(r[key], cfg, params)
    gap = params[5] if len(params) > 5 else 0.0
    if key == "parts" and "parts_alt" in r and is_flip_runner_up(
            np.asarray(r["T"]), r["score"], np.asarray(r["T_alt"]), r["score"] - r["alt_gap"], alt_gap=gap,
            alt_min_deg=cfg.parts.alt_min_deg):  # the estimator's rule (PoseEstimator.runner_up)
        hidden_from_runner_up(ps, _judged(r["parts_alt"], cfg, params))
    return [p.verdict for p in ps]


def _summary(by: dict[str, list[tuple[dict, list[str]]]], unit: str, units: str) -> dict:
    """Per defect type, from each judged unit's (its row, its parts' verdicts) -- a photo (``unit`` 'image') or an
    assembly's photos together ('assembly'): recall of the defective part (flagged missing, displaced or wrong), the
    share flagged with the right kind (missing for 'missing', displaced for shifted / rotated), the share where it is
    not visible, the other parts flagged per unit; on correct assemblies the false alarms (flagged parts) per unit;
    for 'extra' (no defective part of the CAD model) the share of units with any flagged part."""
    out: dict[str, dict] = {}
    for d, items in sorted(by.items()):
        vs = [v for _, v in items]
        if d == "none (correct assembly)":
            fa = [sum(x in FLAG for x in v) for v in vs]
            out[d] = {"n": len(items), f"false_alarms_per_{unit}": float(np.mean(fa)),
                      f"{units}_with_a_false_alarm": float(np.mean([f > 0 for f in fa]))}
        elif d == "extra":
            out[d] = {"n": len(items), f"{units}_flagged": float(np.mean([any(x in FLAG for x in v) for v in vs]))}
        else:
            ver = [v[r["defect_part"]] if r["defect_part"] < len(v) else "not visible" for r, v in items]
            right = {"missing": ("missing",), "shifted": ("displaced",), "rotated": ("displaced",),
                     "wrong": ("missing", "displaced", "wrong")}[d]
            other = [sum(x in FLAG for j, x in enumerate(v) if j != r["defect_part"]) for r, v in items]
            out[d] = {"n": len(items), "recall": float(np.mean([x in FLAG for x in ver])),
                      "recall_visible": float(np.mean([x in FLAG for x in ver if x != "not visible"]))
                      if any(x != "not visible" for x in ver) else None,
                      "right_kind": float(np.mean([x in right for x in ver])),
                      "not_visible": float(np.mean([x == "not visible" for x in ver])),
                      f"other_parts_flagged_per_{unit}": float(np.mean(other))}
    return out


def table(rows: list[dict], cfg: PixieConfig, params, key: str = "parts") -> dict:
    """Per defect type, per photo (:func:`_summary`): recall of the defective part, the right kind, and on correct
    assemblies the false alarms per image. ``params``: one tuple for every row, or a function of the row giving its
    tuple (the cross-fit: each half judged with what the other half chose)."""
    of = params if callable(params) else (lambda r: params)
    by: dict[str, list[tuple[dict, list[str]]]] = {}
    for r in rows:
        if key in r:
            by.setdefault(r["defect"] or "none (correct assembly)", []).append((r, row_verdicts(r, cfg, of(r), key)))
    return _summary(by, "image", "images")


def assembly_table(rows: list[dict], cfg: PixieConfig, params, key: str = "parts", views: dict | None = None) -> dict:
    """:func:`table` per assembly instead of per photo: the photos of one scene (one assembly in one colour, seen
    from several viewpoints) judged together (:func:`pixie.cues.part_views.combine_views` over their part records
    judged with ``params``); false alarms per correct assembly. ``views``: ``combine_views``' thresholds on the mean
    3D-move / resize gains (``views_kwargs(cfg.parts)`` when None). Photos whose pose's aligned fit (``pose_fit``) is
    below ``cfg.parts.views_min_fit`` are left out at the estimated poses (:func:`pixie.cues.part_views.trusted_views`),
    as a batch does."""
    of = params if callable(params) else (lambda r: params)
    views = views_kwargs(cfg.parts) if views is None else views
    scenes: dict[int, list[dict]] = {}
    for r in rows:
        if key in r:
            scenes.setdefault(r["scene_id"], []).append(r)
    by: dict[str, list[tuple[dict, list[str]]]] = {}
    for _, rs in sorted(scenes.items()):
        if key == "parts":  # the estimated poses' fits (at the true poses every photo counts)
            rs = [rs[i] for i in trusted_views([(r.get("pose_fit") or {}).get("fit") for r in rs],
                                               cfg.parts.views_min_fit)]
        prm = of(rs[0])
        _, judge, _ = _kw(cfg, *prm[:5], resize_gain=prm[6] if len(prm) > 6 else float("inf"))
        combined = combine_views([_judged(r[key], cfg, prm) for r in rs], **views, **judge)
        by.setdefault(rs[0]["defect"] or "none (correct assembly)", []).append((rs[0], [p.verdict for p in combined]))
    return _summary(by, "assembly", "assemblies")


def _markdown(t: dict, header: list[str], keys: list[str]) -> str:
    """A table of ``t`` (defect -> its record): one row per defect, then ``n`` and ``keys`` ('-' where absent)."""
    f = lambda x: "-" if x is None else f"{x:.2f}"  # noqa: E731
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += [f"| {d} | {r['n']} | " + " | ".join(f(r.get(k)) for k in keys) + " |" for d, r in t.items()]
    return "\n".join(lines)


def fmt_assembly(t: dict) -> str:
    """Markdown of an :func:`assembly_table`."""
    return _markdown(t, ["defect", "assemblies", "recall of the defective part", "not visible in any photo",
                         "false alarms / correct assembly", "assemblies flagged"],
                     ["recall", "not_visible", "false_alarms_per_assembly", "assemblies_flagged"])


def choose_moves(rows: list[dict], cfg: PixieConfig, params: tuple, grid=MOVE_GRID, max_fa: float = 0.1) -> tuple:
    """``params`` (flag_below, colour_weight, revealed_weight, shift_weight) with the ``move_gain`` of ``grid`` that
    gives the best mean recall over the part defects with <= ``max_fa`` false alarms per correct assembly (ties to the
    fewer alarms, then to the larger threshold)."""
    best, key = tuple(params) + (float("inf"),), (-1.0, 0.0)
    for mg in sorted(grid, reverse=True):
        t = table(rows, cfg, tuple(params) + (mg,))
        fa = t.get("none (correct assembly)", {}).get("false_alarms_per_image", 0.0)
        if fa > max_fa + 1e-9:
            continue
        rec = float(np.mean([t[d]["recall"] for d in PART_DEFECTS if d in t]))
        if (rec, -fa) > key:
            best, key = tuple(params) + (mg,), (rec, -fa)
    return best


def choose_alt(rows: list[dict], cfg: PixieConfig, params: tuple, grid=ALT_GRID, max_fa: float = 0.1) -> tuple:
    """``params`` (five entries, :func:`choose_moves`) with the ``parts.alt_gap`` of ``grid`` that gives the best mean
    recall over the part defects with <= ``max_fa`` false alarms per correct assembly, ties to the fewer alarms; of
    the gaps tied on both, the middle one (the middle of the plateau, not its edge)."""
    scored = []
    for g in grid:
        t = table(rows, cfg, tuple(params[:5]) + (g,))
        fa = t.get("none (correct assembly)", {}).get("false_alarms_per_image", 0.0)
        if fa <= max_fa + 1e-9:
            scored.append(((round(mean_recall(t), 9), -round(fa, 9)), g))
    if not scored:
        return tuple(params[:5]) + (0.0,)
    top = max(k for k, _ in scored)
    tied = sorted(g for k, g in scored if k == top)
    return tuple(params[:5]) + (tied[(len(tied) - 1) // 2],)


def choose_resize(rows: list[dict], cfg: PixieConfig, params: tuple, grid=RESIZE_GRID, max_fa: float = 0.1) -> tuple:
    """``params`` (six entries, :func:`choose_alt`) with the ``parts.resize_gain`` of ``grid`` that gives the best mean
    recall over the part defects with <= ``max_fa`` false alarms per correct assembly (ties to the fewer alarms, then
    to the larger threshold)."""
    best, key = tuple(params[:6]) + (float("inf"),), (-1.0, 0.0)
    for rg in sorted(grid, reverse=True):
        t = table(rows, cfg, tuple(params[:6]) + (rg,))
        fa = t.get("none (correct assembly)", {}).get("false_alarms_per_image", 0.0)
        if fa > max_fa + 1e-9:
            continue
        rec = mean_recall(t)
        if (rec, -fa) > key:
            best, key = tuple(params[:6]) + (rg,), (rec, -fa)
    return best


def choose(rows: list[dict], cfg: PixieConfig, colours=COLOUR_GRID, revealed=REVEALED_GRID,
           shifts=SHIFT_GRID, max_fa: float = 0.1) -> tuple:
    """(flag_below, colour_weight, revealed_weight, shift_weight) with the best mean recall over the part defects among those with
    <= ``max_fa`` false alarms per correct assembly at the estimated poses (the fitting half); ties to the fewer
    alarms, then to the first on the grids (smaller weights)."""
    best, key = (GRID[0], 0.0, 0.0, 0.0), (-1.0, 0.0)
    for sw in shifts:
        for rw in revealed:
            for cb in colours:
                for fb in GRID:
                    t = table(rows, cfg, (fb, cb, rw, sw, float("inf")))
                    fa = t.get("none (correct assembly)", {}).get("false_alarms_per_image", 0.0)
                    if fa > max_fa + 1e-9:
                        continue
                    rec = float(np.mean([t[d]["recall"] for d in PART_DEFECTS if d in t]))
                    if (rec, -fa) > key:
                        best, key = (fb, cb, rw, sw), (rec, -fa)
    return best


def half_of(r: dict) -> int:
    """The half an image belongs to: 0 (fitting: even image ids, viewpoints 0 and 2 of every scene) or 1 (report)."""
    return int(r["im_id"]) % 2


def cross_fit(rows: list[dict], cfg: PixieConfig, max_fa: float = 0.1) -> dict[int, tuple]:
    """The rule (:func:`choose`, then :func:`choose_moves`, :func:`choose_alt` and :func:`choose_resize`) applied on
    each half: {half: its parameters}. Judging
    every image with the other half's choice gives a two-fold estimate over all images, twice the report half's
    (48 correct assemblies instead of 24), and shows how much the choice depends on which half it saw."""
    return {h: rule([r for r in rows if half_of(r) == h], cfg, max_fa) for h in (0, 1)}


def rule(rows: list[dict], cfg: PixieConfig, max_fa: float = 0.1) -> tuple:
    """The bench's whole rule on ``rows``: :func:`choose`, then :func:`choose_moves`, :func:`choose_alt` and
    :func:`choose_resize`, each at <= ``max_fa`` false alarms per correct assembly."""
    return choose_resize(rows, cfg, choose_alt(rows, cfg, choose_moves(rows, cfg, choose(rows, cfg, max_fa=max_fa),
                                                                       max_fa=max_fa), max_fa=max_fa), max_fa=max_fa)


def mean_recall(t: dict) -> float:
    """Mean recall of the defective part over the part defects of a :func:`table`."""
    return float(np.mean([t[d]["recall"] for d in PART_DEFECTS if d in t]))


def fmt(t: dict) -> str:
    """Markdown of a :func:`table`."""
    return _markdown(t, ["defect", "n", "recall of the defective part", "(visible)", "right kind", "not visible",
                         "other parts flagged / img", "false alarms / correct assembly", "images flagged"],
                     ["recall", "recall_visible", "right_kind", "not_visible", "other_parts_flagged_per_image",
                      "false_alarms_per_image", "images_flagged"])


def configured(cfg: PixieConfig) -> tuple:
    """The configured thresholds as :func:`row_verdicts`' ``params`` (flag_below, colour_weight, revealed_weight,
    shift_weight, move_gain, alt_gap, resize_gain; a move / resize gain of inf: not judged on)."""
    pc, inf = cfg.parts, float("inf")
    return (pc.flag_below, pc.colour_weight, pc.revealed_weight, pc.shift_weight,
            pc.move_gain if pc.moves else inf, pc.alt_gap, pc.resize_gain if pc.resizes else inf)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", type=Path, required=True)
    ap.add_argument("--estimates", type=Path, action="append", default=[], help="bench/defects.py journal(s)")
    ap.add_argument("--gt-only", action="store_true", help="no estimates: the part report at the true poses only, "
                    "every photo (the evidence's own quality, before any pose is estimated); the rows are written "
                    "to --out and scored at the true poses")
    ap.add_argument("--preset", default="default")
    ap.add_argument("--set", action="append", default=[], metavar="SECTION.KEY=VALUE")
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--reuse", action="store_true", help="re-score the rows of an existing --out (no computation)")
    ap.add_argument("--shard", default=None, metavar="K/N", help="compute the rows of every N-th photo from the K-th "
                    "(sorted by scene and image id) into --out and stop: N processes side by side, then --merge")
    ap.add_argument("--merge", type=Path, nargs="+", default=None, help="re-score the rows of these --shard outputs "
                    "together (written to --out)")
    ap.add_argument("--mask", action="store_true", help="the part report inside the GT visible mask (as with "
                    "`pixie inspect --mask`): occluders in front of the assembly are then known")
    ap.add_argument("--parts-dir", default=None, help="the part models under --data: models_parts_solid (every part "
                    "a closed solid, as a multi-body CAD export holds them: moves are checked for collisions; the "
                    "default when the directory exists) or models_parts (the union's triangles by part)")
    ap.add_argument("--fit-on", type=Path, default=None, metavar="JSON", help="also choose the thresholds by the rule on "
                    "every row of this earlier --out (another benchmark seed: other assemblies) and judge this run's "
                    "rows with them: a held-out estimate with no assembly shared")
    ap.add_argument("--by-target", action="store_true", help="take the journal's target-model estimate of each target "
                    "whatever config key it was cached under (estimates of an earlier commit with the same poses)")
    ap.add_argument("--max-fa", type=float, default=0.1, help="the rule's false alarms per correct assembly on the "
                    "half it chooses on (0.1: the bar itself; 0.05: a margin for the 24 correct assemblies of a half)")
    ap.add_argument("--types", default=None, metavar="T[,T]", help="compute the rows of these defect types' photos only "
                    "(missing, shifted, rotated, wrong, extra; none: the correct assemblies)")
    args = ap.parse_args(argv)
    cfg = PixieConfig.from_preset(args.preset).apply_overrides(args.set)
    if args.parts_dir is None:
        args.parts_dir = "models_parts_solid" if (args.data / "models_parts_solid").is_dir() else "models_parts"
    if args.merge:
        rows = [r for f in args.merge for r in json.loads(f.read_text())["rows"]]
    elif args.reuse and args.out.is_file():
        rows = json.loads(args.out.read_text())["rows"]
    else:
        ests: dict = {}
        if args.gt_only:  # every photo, no estimated pose (analyse then reports at the true pose only)
            ests = {(tg.scene_id, tg.im_id): {"failed": True} for tg in BopDataset(args.data).targets()}
        elif not args.estimates:
            raise SystemExit("--estimates JOURNAL is needed (or --gt-only, --merge, --reuse)")
        for j in args.estimates:
            ests.update(target_estimates(j, args.data, cfg, by_target=args.by_target))
        print(f"{len(ests)} target-model estimates" + (" (none: true poses only)" if args.gt_only else ""))
        if args.types:  # only the photos of these defect types ('none': the correct assemblies)
            want = set(args.types.split(","))
            kind = {v["scene_id"]: (v.get("defect") or {}).get("type") or "none"
                    for v in json.loads((args.data / "variants.json").read_text())}
            ests = {key: e for key, e in ests.items() if kind[key[0]] in want}
            print(f"{len(ests)} of them of the types {sorted(want)}")
        if args.shard:
            k, n = (int(x) for x in args.shard.split("/"))
            ests = {key: ests[key] for key in sorted(ests)[k::n]}
        rows = analyse(args.data, ests, cfg, use_mask=args.mask, parts_dir=args.parts_dir)
        if args.shard or args.gt_only:
            args.out.write_text(json.dumps({"shard": args.shard, "rows": rows}, default=float))
            if args.gt_only and not args.shard:
                print(fmt_assembly(assembly_table(rows, cfg, configured(cfg), key="parts_gt")))
            print(f"wrote {len(rows)} rows to {args.out} (shard {args.shard}; --merge the shards to score them)")
            return 0
    fit = [r for r in rows if half_of(r) == 0]
    rep = [r for r in rows if half_of(r) == 1]
    mf = args.max_fa
    chosen4 = choose(fit, cfg, max_fa=mf)  # the session-11 rule, without 3D moves
    chosen5 = choose_moves(fit, cfg, chosen4, max_fa=mf)  # then the 3D moves' threshold with those fixed
    chosen6 = choose_alt(fit, cfg, chosen5, max_fa=mf)  # then the runner-up's gap
    chosen = choose_resize(fit, cfg, chosen6, max_fa=mf)  # then the resizes' threshold
    conf = configured(cfg)
    inf = float("inf")
    ablations = {"session-10 score (support + colour)": choose(fit, cfg, revealed=[0.0], shifts=[0.0], max_fa=mf) + (inf, 0.0, inf),
                 "no colour": choose(fit, cfg, colours=[0.0], max_fa=mf) + (inf, 0.0, inf),
                 "no contrast with the model without the part": choose(fit, cfg, revealed=[0.0], max_fa=mf) + (inf, 0.0, inf),
                 "no shift term": choose(fit, cfg, shifts=[0.0], max_fa=mf) + (inf, 0.0, inf),
                 "no 3D moves (session 11's report)": chosen4 + (inf, 0.0, inf),
                 "no runner-up (session 31's report)": chosen5 + (0.0, inf),
                 "no resizes (session 33's report)": chosen6 + (inf,),
                 "configured": conf,
                 "configured without 3D moves": conf[:4] + (inf,) + conf[5:],
                 "configured without the runner-up": conf[:5] + (0.0,) + conf[6:],
                 "configured without resizes": conf[:6] + (inf,),
                 "configured, the 3D moves' threshold by the rule": choose_moves(fit, cfg, conf[:4], max_fa=mf) + conf[5:],
                 "configured, the runner-up's gap by the rule": choose_alt(fit, cfg, conf[:5], max_fa=mf) + conf[6:],
                 "configured, the resizes' threshold by the rule": choose_resize(fit, cfg, conf[:6], max_fa=mf)}
    names = ("flag_below", "colour_weight", "revealed_weight", "shift_weight", "move_gain", "alt_gap", "resize_gain")
    def named(params: tuple) -> dict:  # JSON: an infinite move_gain / resize_gain (none tried) as null
        return {k: (None if np.isinf(v) else float(v)) for k, v in zip(names, params)}

    folds = cross_fit(rows, cfg, max_fa=mf)
    other = lambda r: folds[1 - half_of(r)]  # noqa: E731
    posed = [r for r in rows if r.get("add_mm", 1e9) < 10.0]  # the pose right (ADD < 1 cm)
    res = {"max_fa": mf, "chosen": named(chosen), "configured": named(conf), "n_images": len(rows), "parts_dir": args.parts_dir,
           "cross_fit": {"chosen": {str(h): named(v) for h, v in folds.items()},
                         "estimated": table(rows, cfg, other), "gt_pose": table(rows, cfg, other, key="parts_gt"),
                         "estimated_add_below_1cm": table(posed, cfg, other), "n_add_below_1cm": len(posed)},
           "estimated_fit_half": table(fit, cfg, chosen), "estimated_report_half": table(rep, cfg, chosen),
           "gt_pose_report_half": table(rep, cfg, chosen, key="parts_gt"),
           "estimated_all_configured": table(rows, cfg, conf),
           "gt_pose_all_configured": table(rows, cfg, conf, key="parts_gt"),
           "ablations_report_half": {k: {"params": named(v), "table": table(rep, cfg, v)} for k, v in ablations.items()}}
    res["by_assembly"] = {"configured": assembly_table(rows, cfg, conf),
                          "configured_gt_pose": assembly_table(rows, cfg, conf, key="parts_gt")}
    if args.fit_on is not None:
        other_rows = json.loads(args.fit_on.read_text())["rows"]
        held = rule(other_rows, cfg, max_fa=mf)
        res["held_out"] = {"fit_on": str(args.fit_on), "n_fit_images": len(other_rows), "chosen": named(held),
                           "estimated": table(rows, cfg, held), "gt_pose": table(rows, cfg, held, key="parts_gt"),
                           "by_assembly": assembly_table(rows, cfg, held)}
        print(f"\nheld out: chosen on every row of {args.fit_on} ({len(other_rows)} images): {held}; this run's rows "
              f"judged with it (mean recall {mean_recall(res['held_out']['estimated']):.3f})\n"
              f"{fmt(res['held_out']['estimated'])}")
    ok = [r for r in rows if "add_mm" in r]
    res["add"] = {"n": len(rows), "add_1cm_before": float(np.mean([r.get("add_mm", 1e9) < 10 for r in rows])),
                  "add_1cm_after_part_realignment": float(np.mean([r.get("add_robust_mm", 1e9) < 10 for r in rows])),
                  "realigned": int(sum(1 for r in ok if r["dropped"])),
                  "median_s_per_image": float(np.median([r["seconds"] for r in ok])) if ok else None}
    print(f"chosen on the fitting half: flag_below, colour_weight, revealed_weight, shift_weight, move_gain, alt_gap,"
          f" resize_gain"
          f" = {chosen}")
    print(f"cross-fit: chosen on the even ids {folds[0]}, on the odd ids {folds[1]}; every image judged with the other"
          f" half's choice:")
    for k in ("estimated", "gt_pose", "estimated_add_below_1cm"):
        print(f"\ncross_fit, {k} (mean recall {mean_recall(res['cross_fit'][k]):.3f})\n{fmt(res['cross_fit'][k])}")
    for k in ("estimated_report_half", "gt_pose_report_half", "estimated_all_configured", "gt_pose_all_configured"):
        print(f"\n{k}\n{fmt(res[k])}")
    for k, v in res["ablations_report_half"].items():
        print(f"\nablation, report half: {k}, chosen on the fitting half by the same rule: {v['params']}\n{fmt(v['table'])}")
    for k, v in res["by_assembly"].items():
        print(f"\nper assembly (its photos judged together, pixie.cues.part_views.combine_views), {k}\n{fmt_assembly(v)}")
    print("\n", json.dumps(res["add"]))
    args.out.write_text(json.dumps({**res, "rows": rows}, indent=1, default=float))
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
