"""Part support: does every part of the CAD model agree with the photo at the estimated pose?

For a mesh with parts (:attr:`pixie.geometry.mesh.Mesh.face_parts`: a GLB's sub-meshes or connected
components), the model is rendered at the pose in the alignment crop's camera (:class:`PhotoEdges`). Each part's
visible contour pixels are its silhouette, its creases, the depth steps where it is in front, and its seams with
other parts. A pixel counts as *supported* when a photo edge of the same orientation (±1 bin) lies within
``fit_px`` crop px: the aligned fit of :mod:`pixie.cues.edge_align`, per part.

Per part (:class:`PartSupport`):

- ``support``: the share of its visible contour pixels that are supported;
- ``relative``: support / the median support of the assembly's visible parts (the photo's edge quality and the
  pose's overall precision cancel out);
- ``shifted`` / ``shift_px``: the best support when the part's contour is slid in the image by up to
  ``shift_frac`` of the box (a displaced part's edges are nearby, a missing part's are nowhere);
- ``visible``: its visible pixels / its pixels when rendered alone (hidden by other parts or outside the box / mask);
- ``exclusive`` / ``revealed``: the model is also rendered *without* the part. ``exclusive`` is the support of the
  part's contour pixels that this render lacks (what only the part explains: not the lower brick's outline it sits
  on), ``revealed`` the support of the contour pixels this render has and the whole model's lacks (the edges of what
  the part hides). A missing part has the second and not the first; a part hidden by an occluder, or painted like
  its surroundings, has neither (its low support is no evidence of absence);
- ``colour``: the share of its visible inner pixels whose chroma (CIELAB a*, b*) is within ``colour_ab`` of their
  median: one paint gives ~1 whatever the shading, a moved part and what it uncovered less (``colour_weight`` 0: off);
- ``move`` / ``move_gain`` (with ``moves``, off by default): the 3D move of a less supported part (along / about the
  model's axes, :mod:`pixie.cues.part_moves`) the photo supports best, and its gain: ``displaced`` from ``move_gain``.
- ``size`` / ``size_gain`` (with ``resizes``, off): the same for the part longer or shorter along a model axis, one
  end kept: ``wrong`` from ``resize_gain``. ``move_gains`` / ``size_gains``: every move's. ``spill``: see part_paint.

:func:`judge_parts` turns these into verdicts: ``not visible`` (too little of it to judge), ``missing`` (its contour
is unsupported and no shift finds it), ``displaced`` (unsupported where it should be, fully supported nearby),
``wrong`` (better supported as another size), ``present``. Thresholds: ``config.parts`` (``bench/defects_parts.py``).

>>> parts = part_support(renderer, mesh.face_parts, mesh.part_names, pe, T)
>>> parts = judge_parts(parts, **report_kwargs(config.parts)[1])
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import cv2
import numpy as np

from pixie.config import PART_KINDS, PartsConfig
from pixie.cues.edge_align import align, edge_distances
from pixie.cues.edge_photo import PhotoEdges
from pixie.geometry.camera import rotation_angle_deg
from pixie.geometry.collide import PartSolids, collides, part_solids
from pixie.geometry.mesh import Mesh, from_arrays
from pixie.cues.part_moves import (MoveFit, coarse_pixels, explain_away, explained, move_evidence, near_maps,
                                   of_factors, part_contours, part_moves, part_resizes, RESIZE_FACTORS)
from pixie.geometry.render import Renderer
from pixie.pose.results import SUSPECT_VERDICTS

__all__ = ["VERDICTS", "PartSupport", "only_resizes", "tried_resizes", "report_kwargs", "part_renderers",
           "complement_renderers", "part_support", "part_score", "photo_medians", "judge_parts", "robust_part_fit",
           "hidden_from_runner_up", "is_flip_runner_up"]

VERDICTS = ("present", "missing", "displaced", "wrong", "not visible")


@dataclass(kw_only=True)
class PartSupport:
    """One part's agreement with the photo at a pose (see the module docstring); ``verdict`` is set by
    :func:`judge_parts` ('' before)."""

    index: int
    name: str
    support: float
    relative: float
    shifted: float
    shift_px: float
    visible: float
    n_points: int
    colour: float = 1.0
    exclusive: float = 0.0  # support of its contour pixels that the model without it does not have
    n_exclusive: int = 0
    revealed: float = 0.0  # support of the contour pixels the model without it has and the whole model does not
    n_revealed: int = 0
    exclusive_shifted: float = 0.0  # the exclusive contour's best support when slid (the shift search)
    move_gain: float = 0.0  # the best 3D move's support gain where the moved part's contour differs (move_evidence)
    move: str = ""  # that move, in words ('+x 8.0 mm', 'turned 90 deg about z'); '' when none was tried
    move_support: float = 0.0  # the support of the moved part's own contour pixels (where it differs) at that move
    move_explained_by: int = -1  # another part whose move explains the same pixels better (explain_away), or -1
    size_gain: float = 0.0  # the best resize's support gain (part_resizes, move_evidence): a part of the wrong size
    size: str = ""  # that resize, in words ('1.5x as long along z, low end kept'); '' when none was tried
    size_support: float = 0.0  # the support of the resized part's own contour pixels at that resize
    move_gains: dict[str, float] = field(default_factory=dict)  # every judged move's gain by name (combine_views)
    size_gains: dict[str, float] = field(default_factory=dict)  # every judged resize's gain by name
    spill: float = float("nan")  # its paint around it where the model shows another (part_paint); NaN: not measured
    verdict: str = ""
    judged_at: str = ""  # 'runner-up': hidden at the chosen pose, judged at the runner-up pose (config.parts.alt_gap)
    uv: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)), repr=False)  # its contour points, photo px
    hit: np.ndarray = field(default_factory=lambda: np.zeros(0, bool), repr=False)  # ... and which are supported

    def as_dict(self) -> dict:
        """JSON-able record (without the points)."""
        return {"index": self.index, "name": self.name, "verdict": self.verdict,
                "support": round(self.support, 4), "relative": round(self.relative, 4),
                "shifted_support": round(self.shifted, 4), "shift_px": round(self.shift_px, 2),
                "visible": round(self.visible, 4), "n_points": self.n_points, "colour": round(self.colour, 4),
                "exclusive_support": round(self.exclusive, 4), "n_exclusive": self.n_exclusive,
                "revealed_support": round(self.revealed, 4), "n_revealed": self.n_revealed,
                "exclusive_shifted_support": round(self.exclusive_shifted, 4),
                "move_gain": round(self.move_gain, 4), "move": self.move, "move_support": round(self.move_support, 4),
                "move_explained_by": self.move_explained_by, "size_gain": round(self.size_gain, 4), "size": self.size,
                "size_support": round(self.size_support, 4), "judged_at": self.judged_at,
                "move_gains": {k: round(v, 4) for k, v in self.move_gains.items()},
                "size_gains": {k: round(v, 4) for k, v in self.size_gains.items()},
                "paint_spill": round(float(self.spill), 4) if np.isfinite(self.spill) else None}

    @classmethod
    def from_dict(cls, d: dict) -> "PartSupport":
        """Inverse of :meth:`as_dict` (records without the later fields get their defaults; no contour points)."""
        return cls(index=d["index"], name=d["name"], verdict=d.get("verdict", ""), support=d["support"],
                   relative=d["relative"], shifted=d["shifted_support"], shift_px=d["shift_px"], visible=d["visible"],
                   n_points=d["n_points"], colour=d.get("colour", 1.0), exclusive=d.get("exclusive_support", 0.0),
                   n_exclusive=d.get("n_exclusive", 0), revealed=d.get("revealed_support", 0.0),
                   n_revealed=d.get("n_revealed", 0), exclusive_shifted=d.get("exclusive_shifted_support", 0.0),
                   move_gain=d.get("move_gain", 0.0), move=d.get("move", ""), move_support=d.get("move_support", 0.0),
                   move_explained_by=d.get("move_explained_by", -1), size_gain=d.get("size_gain", 0.0),
                   size=d.get("size", ""), size_support=d.get("size_support", 0.0), judged_at=d.get("judged_at", ""),
                   move_gains=dict(d.get("move_gains", {})), size_gains=dict(d.get("size_gains", {})),
                   spill=float("nan") if d.get("paint_spill") is None else float(d["paint_spill"]))


def only_resizes(p: PartSupport, factors) -> PartSupport:
    """A copy of ``p`` as if only the resizes by ``factors`` (:func:`of_factors`) had been tried: its best one among
    them, or none ('', gain 0). Records without per-resize gains are returned as they are."""
    if not p.size_gains:
        return p
    keep = of_factors(p.size_gains, factors)
    best = max(keep, key=keep.get) if keep else ""
    support = p.size_support if best == p.size else 0.0  # the support of another resize's own pixels is not kept
    return replace(p, size_gains=keep, size=best, size_gain=keep.get(best, 0.0), size_support=support)


def tried_resizes(pc: PartsConfig) -> tuple[tuple[float, ...], float]:
    """The resize factors :func:`part_support` tries and its support gate: ``resize_factors`` / ``resize_below`` for one
    photo's verdict (``pc.resizes``), with an assembly's evidence (``pc.evidence``, ``views_resize_gain`` <= 1) also
    ``views_resize_factors`` / ``views_resize_below``; each verdict reads its own (:func:`only_resizes`). ((), 0): none."""
    photo, views = pc.resizes, pc.evidence and pc.views_resize_gain <= 1
    factors = sorted(set(pc.resize_factors if photo else []) | set(pc.views_resize_factors if views else []))
    below = max([pc.resize_below] * photo + [pc.views_resize_below] * views, default=0.0)
    return tuple(factors), below


def report_kwargs(pc: PartsConfig) -> tuple[dict, dict]:
    """The keywords of :func:`part_support` and of :func:`judge_parts` that ``config.parts`` sets (``pc.evidence``:
    the 3D moves / resizes an assembly's verdict uses, ``pc.views_move_gain`` / ``views_resize_gain`` <= 1, are
    tried, but a photo is judged on them only with ``pc.moves`` / ``pc.resizes`` (its ``resize_factors``))."""
    factors, below = tried_resizes(pc)
    support = dict(fit_px=pc.fit_px, shift_frac=pc.shift_frac, min_points=pc.min_points, colour_ab=pc.colour_ab,
                   step_frac=pc.step_frac, detail_px=pc.detail_px, contrast_px=pc.contrast_px,
                   kinds=tuple(PART_KINDS.index(k) for k in pc.kinds),
                   moves=pc.moves or (pc.evidence and pc.views_move_gain <= 1), min_visible=pc.min_visible,
                   move_below=pc.move_below, move_changed=pc.move_changed, move_px=pc.move_px,
                   move_collide=pc.move_collide, resizes=bool(factors), resize_factors=factors or RESIZE_FACTORS,
                   resize_below=below)
    judge = dict(flag_below=pc.flag_below, colour_weight=pc.colour_weight, revealed_weight=pc.revealed_weight,
                 shift_weight=pc.shift_weight, supported_above=pc.supported_above, shift_gain=pc.shift_gain,
                 found_shifted=pc.found_shifted, min_points=pc.min_points, min_visible=pc.min_visible,
                 move_gain=pc.move_gain if pc.moves else float("inf"),
                 resize_gain=pc.resize_gain if pc.resizes else float("inf"), resize_factors=tuple(pc.resize_factors))
    return support, judge


def part_renderers(mesh: Mesh) -> list[Renderer]:
    """One renderer per part of ``mesh`` (its own triangles, in the mesh's order, and only its own vertices, so that
    a render casts rays over the part's projection, not the whole model's; for the visible fractions and the moves)."""
    if mesh.face_parts is None:
        return []
    out = []
    for k in range(mesh.n_parts):
        sel = mesh.face_parts == k
        f = mesh.faces[sel] if sel.any() else mesh.faces[:1]
        used, inv = np.unique(f, return_inverse=True)
        sub = from_arrays(mesh.vertices[used], inv.reshape(f.shape), name=f"{mesh.name}:{k}")
        out.append(Renderer(sub, smooth_normals=False))
    return out


def complement_renderers(mesh: Mesh, smooth_normals: bool = True) -> list[tuple[Renderer, np.ndarray]]:
    """Per part of ``mesh``: a renderer of the mesh *without* that part and the remaining faces' part indices (what
    the photo would show if the part were absent; for :func:`part_support`'s exclusive and revealed contours)."""
    if mesh.face_parts is None:
        return []
    out = []
    for k in range(mesh.n_parts):
        sel = mesh.face_parts != k
        if not sel.any():
            sel = np.zeros(len(mesh.faces), bool)
            sel[0] = True
        sub = from_arrays(mesh.vertices, mesh.faces[sel], name=f"{mesh.name}:without{k}")
        out.append((Renderer(sub, smooth_normals=smooth_normals), np.asarray(mesh.face_parts)[sel]))
    return out


def _shift_grid(reach: float, step: float) -> np.ndarray:
    """2D shifts (crop px) with 2 px <= |s| <= reach on a ``step`` grid."""
    g = np.arange(-reach, reach + 1e-9, step)
    s = np.stack(np.meshgrid(g, g), -1).reshape(-1, 2)
    n = np.linalg.norm(s, axis=1)
    return s[(n >= 2.0) & (n <= reach)]


def _slide(pe: PhotoEdges, xy: np.ndarray, ori: np.ndarray, sel: np.ndarray, shifts: np.ndarray, max_points: int,
           max_bin_gap: int, fit_px: float) -> tuple[float, int]:
    """The best support of the contour pixels ``sel`` slid by one of ``shifts`` (at most ``max_points`` of them,
    evenly spaced), and that shift's index."""
    idx = np.flatnonzero(sel)
    idx = idx[np.linspace(0, len(idx) - 1, min(len(idx), max_points)).astype(int)]
    q = (xy[idx][None, :, :] + shifts[:, None, :]).reshape(-1, 2)
    dq, _ = edge_distances(pe, q, np.tile(ori[idx], len(shifts)), max_bin_gap, fit_px)
    sup = (dq.reshape(len(shifts), len(idx)) <= fit_px).mean(axis=1)
    j = int(np.argmax(sup))
    return float(sup[j]), j


def part_support(renderer: Renderer, face_parts: np.ndarray, part_names, pe: PhotoEdges, T: np.ndarray, *,
                 fit_px: float = 1.5, max_bin_gap: int = 1, shift_frac: float = 0.12, shift_step: float = 2.0,
                 renderers: list[Renderer] | None = None, min_points: int = 12, kinds=(0, 1, 2),
                 max_points: int = 240, step_frac: float = 0.0, colour_ab: float = 12.0,
                 complements: list[tuple[Renderer, np.ndarray]] | None = None,
                 moves: bool = False, min_visible: float = 0.2, move_below: float = 0.9, move_changed: float = 0.3,
                 move_px: float = 4.0, move_collide: bool = True, solids: PartSolids | None = None,
                 detail_px: float = 0.0, contrast_px: int = 3, resizes: bool = False, resize_factors=RESIZE_FACTORS,
                 resize_below: float | None = None) -> list[PartSupport]:
    """Every part's support at pose ``T`` (verdicts not yet set: :func:`judge_parts`).

    Parameters
    ----------
    renderer : the whole mesh's renderer; face_parts, part_names : its parts (:class:`Mesh`)
    pe : the photo's edges (the alignment crop)
    T : (4, 4) pose, mm
    fit_px : a contour pixel is supported by a same-orientation edge this close, crop px
    shift_frac, shift_step : the displaced-part search slides each contour up to this share of the box's side, step px
    renderers : :func:`part_renderers` of the mesh (made here when None)
    min_points : parts with fewer visible contour pixels get no shift search (and are judged 'not visible')
    kinds : the contour pixel kinds that count (:func:`part_contours`)
    max_points : at most this many of a part's pixels (evenly spaced in raster order) enter the shift search
    step_frac : a depth step counts when it is deeper than this share of the mesh's diameter (:func:`part_contours`)
    colour_ab : chroma distance (CIELAB a*, b* units) within which a pixel has the part's paint
    complements : :func:`complement_renderers` of the mesh (made here when None): the model without each part, for
        the exclusive contour (what only the part explains) and the revealed one (what its absence would show)
    moves, min_visible, move_below : test 3D moves (:func:`part_moves`, :func:`move_evidence`: ``move_gain`` and
        ``move``) of every part with ``min_points`` visible contour pixels, at least ``min_visible`` of it in view and
        a support below ``move_below`` of the median part's
    move_changed, move_px : a move is judged when it changes at least ``move_changed`` x the part's visible contour
        pixels and shifts some vertex of it by ``move_px`` crop px (:func:`pixie.cues.part_moves.move_evidence`)
    move_collide, solids : with ``move_collide``, moves that pass the part into another are not tried
        (:func:`collides` on the parts' ``solids``, :func:`pixie.geometry.collide.part_solids`; made when None)
    detail_px : the exclusive and revealed contours leave out pieces smaller than this (crop px,
        :func:`coarse_pixels`): the studs a missing brick uncovers, which the photo does not resolve
    contrast_px : a contour pixel of the model with the part (without it) belongs to the exclusive (revealed)
        contour only when the other model has no contour pixel of a like orientation within this many crop px
    resizes, resize_factors : also test the part as long x each factor along a model axis (:func:`part_resizes`:
        ``size_gain``, ``size``) where the moves would (their conditions apply): a part of the wrong size
    resize_below : the resizes' own relative-support gate (None: ``move_below``); high: every visible part is tried
    """
    face_parts = np.asarray(face_parts)
    n_parts = len(part_names)
    step_mm = step_frac * renderer.mesh.diameter
    r = renderer.render(T, pe.K, pe.size, pe.size)
    xy, ori, part, part_map, kind = part_contours(r, face_parts, step_mm=step_mm)
    keep = np.isin(kind, np.asarray(kinds))
    xy, ori, part = xy[keep], ori[keep], part[keep]
    d, inside = edge_distances(pe, xy, ori, max_bin_gap, fit_px) if len(xy) else (np.zeros(0), np.zeros(0, bool))
    hit = d <= fit_px
    whole = replace(renderer.mesh, face_parts=face_parts, part_names=tuple(part_names))
    renderers = renderers if renderers is not None else part_renderers(whole)
    complements = complements if complements is not None else complement_renderers(
        whole, smooth_normals=renderer.smooth_normals)
    near_all = near_maps(xy, ori, part_map.shape, radius=contrast_px)
    lab = cv2.cvtColor(np.ascontiguousarray(pe.crop.image), cv2.COLOR_RGB2LAB).astype(np.float32)
    box_side = float(max(pe.box[2] - pe.box[0], pe.box[3] - pe.box[1]))
    shifts = _shift_grid(max(shift_frac * box_side, 2.0), shift_step)
    allowed = pe.allowed
    out = []
    for k in range(n_parts):
        own = (part == k) & inside
        n = int(own.sum())
        visible_px = int(((part_map == k) & allowed).sum())
        alone = int(renderers[k].render(T, pe.K, pe.size, pe.size).mask.sum()) if k < len(renderers) else 0
        visible = float(visible_px / alone) if alone else 0.0
        support = float(hit[own].mean()) if n else 0.0
        best, best_shift = support, 0.0
        if n >= min_points and len(shifts):
            sup, j = _slide(pe, xy, ori, own, shifts, max_points, max_bin_gap, fit_px)
            if sup > best:
                best, best_shift = sup, float(np.linalg.norm(shifts[j]) * pe.scale)
        inner = (cv2.erode((part_map == k).astype(np.uint8), np.ones((3, 3), np.uint8)) > 0) & allowed
        colour = 1.0
        if inner.sum() >= 20:
            ab = lab[inner][:, 1:]
            colour = float(np.mean(np.linalg.norm(ab - np.median(ab, axis=0), axis=1) < colour_ab))
        excl, n_excl, rev, n_rev, excl_shifted = 0.0, 0, 0.0, 0, 0.0
        if k < len(complements) and visible_px:
            cr, cparts = complements[k]
            rw = cr.render(T, pe.K, pe.size, pe.size)
            wxy, wori, _, _, wkind = part_contours(rw, cparts, step_mm=step_mm)
            wk = np.isin(wkind, np.asarray(kinds))
            wxy, wori = wxy[wk], wori[wk]
            mine = coarse_pixels(xy, inside & ~explained(xy, ori, near_maps(wxy, wori, part_map.shape,
                                                                             radius=contrast_px)),
                                 part_map.shape, detail_px)
            n_excl = int(mine.sum())
            excl = float(hit[mine].mean()) if n_excl else 0.0
            excl_shifted = excl
            if n_excl >= min_points and len(shifts):
                excl_shifted = max(excl, _slide(pe, xy, ori, mine, shifts, max_points, max_bin_gap, fit_px)[0])
            new_px = coarse_pixels(wxy, ~explained(wxy, wori, near_all), part_map.shape, detail_px)
            if new_px.any():
                dw, win = edge_distances(pe, wxy[new_px], wori[new_px], max_bin_gap, fit_px)
                n_rev = int(win.sum())
                rev = float((dw[win] <= fit_px).mean()) if n_rev else 0.0
        out.append(PartSupport(index=k, name=str(part_names[k]), support=support, relative=0.0, shifted=best,
                               shift_px=best_shift, visible=visible, n_points=n, colour=colour,
                               exclusive=excl, n_exclusive=n_excl, revealed=rev, n_revealed=n_rev,
                               exclusive_shifted=excl_shifted,
                               uv=pe.to_photo(xy[own]) if n else np.zeros((0, 2)), hit=hit[own]))
    judged = [p.support for p in out if p.n_points >= min_points]
    med = float(np.median(judged)) if judged else 0.0
    for p in out:
        p.relative = float(p.support / med) if med > 0 else 0.0
    if moves or resizes:  # 3D moves / resizes of the parts the photo supports less than the median part
        fits: dict[int, MoveFit] = {}
        resize_below = move_below if resize_below is None else resize_below
        for p in out:
            k = p.index
            if not (p.n_points >= min_points and p.visible >= min_visible and k < len(complements)
                    and k < len(renderers)):
                continue
            families = ((part_moves,) * (moves and p.relative < move_below)
                        + (part_resizes,) * (resizes and p.relative < resize_below))
            for family in families:
                tried = family(whole, k) if family is part_moves else family(whole, k, factors=resize_factors)
                if move_collide:
                    solids = solids if solids is not None else part_solids(whole)
                    tried = [(name, M) for name, M in tried if not collides(solids, k, M)]
                f = move_evidence(pe, T, k, complements[k], renderers[k], tried, fit_px=fit_px,
                                  max_bin_gap=max_bin_gap, kinds=kinds, step_mm=step_mm, min_points=min_points,
                                  min_changed=max(min_points, int(np.ceil(move_changed * p.n_points))),
                                  min_px=move_px)
                if f is None:
                    continue
                if family is part_resizes:
                    p.size_gain, p.size, p.size_support, p.size_gains = f.gain, f.name, f.support, f.gains
                else:
                    p.move_gain, p.move, p.move_support, p.move_gains = f.gain, f.name, f.support, f.gains
                    if f.gain > 0:
                        fits[k] = f
        for loser, winner in explain_away(fits, min_points).items():
            out[loser].move_explained_by = winner
    return out


def part_score(p: PartSupport, colour_weight: float = 0.0, colour_median: float = 1.0, revealed_weight: float = 0.0,
               median: float | None = None, min_points: int = 12, shift_weight: float = 0.0) -> float:
    """The evidence that a part is where the model has it; about 1 for a present part, lower the less the photo agrees.

    Without ``revealed_weight``: its relative edge support + ``colour_weight`` x (min(colour consistency / the median
    part's, 1) - 1). With it, the edge term is a likelihood-ratio-like contrast of the model with and without the
    part: the relative support of its *exclusive* contour (pixels the model without it lacks; its whole contour when
    fewer than ``min_points``) minus ``revealed_weight`` x the relative support of the contour its absence would
    reveal (what is behind it). A part hidden by an occluder or painted like its surroundings has neither and is not
    flagged on edges; a missing one has the second. Relative (to ``median``, the median judged part's support;
    ``p.relative``'s when None), so a photo's edge quality cancels, and a photo where no part looks uniformly
    painted flags none on colour. ``shift_weight`` x the relative support a slide of its contour gains (the shift
    search: a displaced part's edges lie nearby; of the exclusive contour when ``revealed_weight`` is set) is
    subtracted too."""
    rel_colour = min(p.colour / colour_median, 1.0) if colour_median > 0 else 1.0
    med = median if median is not None else (p.support / p.relative if p.relative > 0 else 0.0)
    if med <= 0:
        edge = 0.0
    elif revealed_weight <= 0:
        edge = p.relative if median is None else p.support / med
    else:
        own = p.exclusive if p.n_exclusive >= min_points else p.support
        edge = own / med - revealed_weight * (p.revealed / med if p.n_revealed >= min_points else 0.0)
    if shift_weight > 0 and med > 0:
        gain = (p.exclusive_shifted - p.exclusive if revealed_weight > 0 and p.n_exclusive >= min_points
                else p.shifted - p.support)
        edge -= shift_weight * max(gain, 0.0) / med
    return edge + colour_weight * (rel_colour - 1.0)


def judge_parts(parts: list[PartSupport], *, flag_below: float = 0.6, colour_weight: float = 0.0,
                revealed_weight: float = 0.0, shift_weight: float = 0.0, supported_above: float = 1.0,
                shift_gain: float = 0.4, found_shifted: float = 0.97, min_points: int = 12,
                min_visible: float = 0.2, move_gain: float = float("inf"),
                resize_gain: float = float("inf"), resize_factors=None) -> list[PartSupport]:
    """Set each part's verdict (in place; returns ``parts``); supports are relative to the median judged part.

    ``not visible``: fewer than ``min_points`` visible contour pixels or less than ``min_visible`` of it in view.
    Otherwise a part is flagged when its :func:`part_score` (relative edge support, or with ``revealed_weight`` its
    exclusive contour's against what its absence would reveal, lowered by ``colour_weight`` x its paint
    inconsistency relative to the median part's) is below ``flag_below`` and its relative edge support below
    ``supported_above`` (colour alone never flags a well-supported contour): ``displaced`` when a shift finds it
    (shifted support >= ``found_shifted`` of the median and >= ``shift_gain`` above its own), else ``missing``. The
    others are ``present``. On repetitive assemblies (LEGO studs) a shift also finds a neighbour's edges, hence the
    strict ``found_shifted``. A part whose best 3D move (:func:`move_evidence`) gains at least ``move_gain`` of
    support is ``displaced`` whatever the rest says (its ``move`` says how), unless another part's move that also
    passes explains the same pixels better (``move_explained_by``, :func:`explain_away`). A part whose best resize
    (:func:`part_resizes`) gains at least ``resize_gain`` (and more than a passing move) is ``wrong``: a part of
    another size is mounted there (its ``size`` says how); only the resizes by ``resize_factors`` count (None: all).
    """
    med, med_colour = photo_medians(parts, min_points, min_visible)
    for p in parts:
        read = only_resizes(p, resize_factors) if resize_factors is not None else p
        size_gain = read.size_gain if read.size else -np.inf
        if p.n_points < min_points or p.visible < min_visible or med <= 0:
            p.verdict = "not visible"
        elif size_gain >= resize_gain and not (p.move and p.move_gain >= max(move_gain, size_gain)):
            p.verdict = "wrong"
        elif p.move and p.move_gain >= move_gain and not (
                0 <= p.move_explained_by < len(parts) and parts[p.move_explained_by].move_gain >= move_gain):
            p.verdict = "displaced"
        elif (part_score(p, colour_weight, med_colour, revealed_weight, med, min_points, shift_weight) >= flag_below
              or p.support / med >= supported_above):
            p.verdict = "present"
        elif p.shifted / med >= found_shifted and (p.shifted - p.support) / med >= shift_gain:
            p.verdict = "displaced"
        else:
            p.verdict = "missing"
    return parts


def photo_medians(parts: list[PartSupport], min_points: int, min_visible: float) -> tuple[float, float]:
    """The median support and median colour consistency of the parts judged in one photo (the references of
    :func:`part_score`); (0, 1) when none is judged."""
    judged = [p for p in parts if p.n_points >= min_points and p.visible >= min_visible]
    if not judged:
        return 0.0, 1.0
    return float(np.median([p.support for p in judged])), float(np.median([p.colour for p in judged]))


def robust_part_fit(renderer: Renderer, face_parts: np.ndarray, part_names, pe: PhotoEdges, T: np.ndarray, *,
                    align_kw: dict, support_kw: dict | None = None, judge_kw: dict | None = None,
                    renderers: list[Renderer] | None = None,
                    complements: list[tuple[Renderer, np.ndarray]] | None = None,
                    solids: PartSolids | None = None) -> tuple[np.ndarray, list[PartSupport], list[int]]:
    """The pose re-aligned without the parts the photo does not support, and the part report at it.

    The parts judged missing or displaced at ``T`` (:func:`part_support`, :func:`judge_parts`) are left out of a
    second alignment from ``T`` (:func:`pixie.cues.edge_align.align` with ``drop_parts``): a missing or moved part
    no longer pulls the pose. The new pose is kept when the other parts' median support does not drop; the
    report is then redone at the kept pose.

    Returns
    -------
    (pose, parts, dropped part indices); the pose is ``T`` when nothing was flagged or the re-alignment was not kept.
    """
    support_kw, judge_kw = dict(support_kw or {}), dict(judge_kw or {})
    whole = replace(renderer.mesh, face_parts=np.asarray(face_parts), part_names=tuple(part_names))
    renderers = renderers if renderers is not None else part_renderers(whole)
    complements = complements if complements is not None else complement_renderers(
        whole, smooth_normals=renderer.smooth_normals)
    if ((support_kw.get("moves") or support_kw.get("resizes")) and support_kw.get("move_collide", True)
            and solids is None):
        solids = part_solids(whole)  # once for both reports
    ps = judge_parts(part_support(renderer, face_parts, part_names, pe, T, renderers=renderers,
                                  complements=complements, solids=solids, **support_kw),
                     **judge_kw)
    drop = [p.index for p in ps if p.verdict in SUSPECT_VERDICTS]
    if not drop or len(drop) >= sum(p.verdict != "not visible" for p in ps):
        return np.asarray(T, np.float64), ps, []
    res = align(renderer, pe, T, face_parts=face_parts, drop_parts=drop, **align_kw)
    ps2 = judge_parts(part_support(renderer, face_parts, part_names, pe, res.T_cam_from_obj, renderers=renderers,
                                   complements=complements, solids=solids, **support_kw), **judge_kw)

    def kept_median(parts: list[PartSupport]) -> float:
        vals = [p.support for p in parts if p.index not in drop and p.verdict != "not visible"]
        return float(np.median(vals)) if vals else 0.0

    if kept_median(ps2) >= kept_median(ps):
        return res.T_cam_from_obj, ps2, drop
    return np.asarray(T, np.float64), ps, []


def is_flip_runner_up(T: np.ndarray, score: float, T_alt: np.ndarray, score_alt: float, *, alt_gap: float,
                      alt_min_deg: float = 150.0) -> bool:
    """Whether the runner-up pose ``T_alt`` (score ``score_alt``) is a near-equal flip of the chosen pose ``T``
    (``score``): turned at least ``alt_min_deg`` from it and scoring within ``alt_gap`` of it
    (``config.parts.alt_gap`` / ``alt_min_deg``; ``alt_gap`` <= 0: never). Then the parts hidden at ``T`` are judged
    at ``T_alt`` (:func:`hidden_from_runner_up`)."""
    if alt_gap <= 0 or score - score_alt > alt_gap:
        return False
    return rotation_angle_deg(np.asarray(T_alt)[:3, :3], np.asarray(T)[:3, :3]) >= alt_min_deg


def hidden_from_runner_up(parts: list[PartSupport], runner_up: list[PartSupport]) -> list[PartSupport]:
    """Each part judged ``not visible`` in ``parts`` (the report at the chosen pose) that the report at the runner-up
    pose (``runner_up``, same parts) flags missing or displaced takes that verdict, marked ``judged_at='runner-up'``
    (in place; returns ``parts``). The caller decides when the runner-up is a near-equal alternative (a flip of a
    near-symmetric assembly, whose hidden side is where the defect may be)."""
    for p, a in zip(parts, runner_up):
        if p.verdict == "not visible" and a.verdict in SUSPECT_VERDICTS:
            p.verdict, p.judged_at = a.verdict, "runner-up"
    return parts
