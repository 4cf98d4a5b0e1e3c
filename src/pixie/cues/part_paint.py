"""Paint spill: does a part's paint show where the CAD model says something else is?

A part of the wrong size (a 2x6 brick for a 1x3, a longer bracket) keeps the CAD part's contour supported: every
edge the CAD part predicts is there, so its edge support (:mod:`pixie.cues.parts`) says 'present'. What the photo
shows besides is the part's paint *around* it: over the neighbouring parts, or over the background, where the model
at the pose predicts another paint. This module measures that, per part, on the whole photo:

- the part's paint is the median chroma (CIELAB a*, b*) of its rendered region (eroded: no outline blur);
- a band around the region (from ``gap_px`` to ``band_frac`` x sqrt(region area) px beyond it) is looked at;
  band pixels where the model shows another part of a *like* paint (closer than ``2 colour_ab``) say nothing;
- a band pixel over another part counts when its chroma is within ``colour_ab`` of the part's paint and closer to
  it than to that part's paint by ``margin_ab``; over the background, when within ``colour_ab`` of the part's paint,
  less the share of such pixels in the background farther away (a ring from one to two band widths beyond the
  whole model): a table of the part's colour is not evidence;
- ``spill`` = those pixels / the band pixels that can say something: ~0 for a right part, the share of the band
  a larger part covers for a wrong one.

Parts whose paint has little chroma (grey, black, white: below ``min_chroma``) or whose region is smaller than
``min_px`` are not measured (NaN). An assembly's photos are combined by :func:`pixie.cues.part_views.combine_views`
(``config.parts.views_spill``): a part whose mean spill over the photos is high is 'wrong'.

>>> pid = part_id_map(renderer, mesh.face_parts, T, K, h, w)
>>> spill = paint_spill(image, pid, mesh.n_parts)          # (n_parts,) float, NaN where not measured
"""

from __future__ import annotations

import cv2
import numpy as np

from pixie.geometry.render import Renderer
from pixie.pose.solve import projected_box

__all__ = ["part_id_map", "paint_spill", "set_spill"]


def part_id_map(renderer: Renderer, face_parts: np.ndarray, T: np.ndarray, K: np.ndarray, h: int, w: int
                ) -> np.ndarray:
    """(h, w) int32: the part seen at each pixel of the model rendered at pose ``T`` with intrinsics ``K``, -1 off
    the model. ``face_parts``: each face's part (:attr:`pixie.geometry.mesh.Mesh.face_parts`)."""
    r = renderer.render(np.asarray(T, np.float64), np.asarray(K, np.float64), int(h), int(w))
    fp = np.asarray(face_parts, np.int32)
    return np.where(r.tri_ids >= 0, fp[np.clip(r.tri_ids, 0, None)], -1).astype(np.int32)


def _disc(radius: int) -> np.ndarray:
    return cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * radius + 1, 2 * radius + 1))


def paint_spill(image: np.ndarray, pid: np.ndarray, n_parts: int, *, colour_ab: float = 12.0,
                margin_ab: float = 6.0, band_frac: float = 0.35, gap_px: int = 2, min_px: int = 30,
                min_chroma: float = 8.0, min_band: int = 20) -> np.ndarray:
    """Each part's paint spill (see the module docstring) in RGB ``image`` with the model's part map ``pid``
    (:func:`part_id_map`, same size): (n_parts,) float, NaN where a part is not measured (too small, paint without
    chroma, or no band pixel that can tell)."""
    image = np.asarray(image)
    pid = np.asarray(pid)
    if image.shape[:2] != pid.shape:
        raise ValueError(f"paint_spill: image {image.shape[:2]} and part map {pid.shape} differ in size")
    ab = cv2.cvtColor(np.ascontiguousarray(image, np.uint8).astype(np.float32) / 255.0, cv2.COLOR_RGB2LAB)[..., 1:]
    out = np.full(n_parts, np.nan)
    erode = _disc(2)
    paints: dict[int, np.ndarray | None] = {}
    for k in range(n_parts):
        core = cv2.erode((pid == k).astype(np.uint8), erode) > 0
        paints[k] = np.median(ab[core], axis=0) if core.sum() >= min_px else None
    whole = (pid >= 0).astype(np.uint8)
    for k in range(n_parts):
        pk = paints[k]
        if pk is None or float(np.linalg.norm(pk)) < min_chroma:
            continue
        region = (pid == k).astype(np.uint8)
        r = max(4, int(round(band_frac * np.sqrt(region.sum()))))
        band = (cv2.dilate(region, _disc(r)) > 0) & (cv2.dilate(region, _disc(gap_px)) == 0)
        own, px = pid[band], ab[band]
        dk = np.linalg.norm(px - pk, axis=1)
        usable = np.ones(len(own), bool)
        match = np.zeros(len(own), bool)
        for j in np.unique(own):
            sel = own == j
            if j < 0:
                match[sel] = dk[sel] < colour_ab
                continue
            pj = paints.get(int(j))
            if pj is None or float(np.linalg.norm(pj - pk)) < 2 * colour_ab:  # a like paint (or unknown): no say
                usable[sel] = False
                continue
            dj = np.linalg.norm(px[sel] - pj, axis=1)
            match[sel] = (dk[sel] < colour_ab) & (dk[sel] + margin_ab < dj)
        n = int(usable.sum())
        if n < min_band:
            continue
        background = usable & (own < 0)
        far = (cv2.dilate(whole, _disc(2 * r)) > 0) & (cv2.dilate(whole, _disc(r)) == 0)
        base = float((np.linalg.norm(ab[far] - pk, axis=1) < colour_ab).mean()) if far.sum() > min_band else 1.0
        out[k] = (float(match[usable].sum()) - base * float(background.sum())) / n
    return out


def set_spill(parts: list, image: np.ndarray, K: np.ndarray, renderer: Renderer, face_parts: np.ndarray,
              T: np.ndarray, **kw) -> None:
    """Set each part record's ``spill`` (:class:`pixie.cues.parts.PartSupport`, indexed by ``index``) at pose ``T``
    in the whole photo ``image`` (intrinsics ``K``); ``kw``: :func:`paint_spill`'s keywords (``band_frac`` at most
    0.35: the photo is cut to the model's projected box grown by what the bands and the far ring reach, so a large
    photo costs what a small one does)."""
    image = np.asarray(image)
    h, w = image.shape[:2]
    x0, y0, x1, y1 = projected_box(np.asarray(T, np.float64), np.asarray(K, np.float64), renderer.mesh.hull_vertices)
    side = max(x1 - x0, y1 - y0)
    m = 2.0 * max(4.0, 0.35 * side) + 4.0  # the widest band (a part as large as the box) and its far ring
    c0, r0 = int(max(np.floor(x0 - m), 0)), int(max(np.floor(y0 - m), 0))
    c1, r1 = int(min(np.ceil(x1 + m), w)), int(min(np.ceil(y1 + m), h))
    spill = np.full(len(parts), np.nan)
    if c1 - c0 >= 2 and r1 - r0 >= 2:
        Kc = np.asarray(K, np.float64).copy()
        Kc[0, 2] -= c0
        Kc[1, 2] -= r0
        pid = part_id_map(renderer, face_parts, T, Kc, r1 - r0, c1 - c0)
        spill = paint_spill(image[r0:r1, c0:c1], pid, len(parts), **kw)
    for p in parts:
        p.spill = float(spill[p.index])
