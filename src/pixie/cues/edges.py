"""Texture-invariant edge cue: query gradient orientations scored against contour templates (LINE-2D style).

The query crop's colour gradients (the RGB channel of largest magnitude per pixel, as in LINEMOD,
Hinterstoisser et al.) are quantised to 8 unsigned orientations, spread over a small neighbourhood and turned
into 8 response maps: ``resp[o][y, x]`` is how well an edge of orientation ``o`` placed at (x, y) agrees with
the photo (|cos| of the smallest orientation difference present nearby). A template (a view's contour points,
rolled; :mod:`pixie.references.templates`) placed in the crop scores the weighted mean response over its points; each
point's score is bounded, so clutter and occlusion cost a template only the points they touch.

Placement: the template's rolled silhouette box is scaled and centred onto the query box (the larger of the
width and height ratios, like :func:`pixie.pose.solve.depth_from_box`), then a small grid of shifts and scales is
searched.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from pixie.references.templates import CREASE, ContourTemplates
from pixie.pipeline.query import QueryCrop, square_crop

N_BINS = 8


@dataclass
class EdgeQuery:
    """Response maps of one query crop."""

    resp: np.ndarray  # (8, H, W) float32
    crop: QueryCrop
    box_wh: np.ndarray  # (2,) query box width, height in crop px
    centre: np.ndarray  # (2,) query box centre in crop px
    mag: np.ndarray  # (H, W) gradient magnitude (kept for diagnostics / region cues)
    bins: np.ndarray  # (H, W) uint8 orientation bin, 255 where no edge
    valid: np.ndarray  # (H, W) bool, crop pixels inside the photo


def quantised_orientations(image: np.ndarray, sigma: float = 1.0, min_mag: float = 6.0,
                           valid: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Per-pixel orientation bin (0..7 over [0, pi), 255 = no edge) of the strongest RGB channel gradient.

    ``min_mag`` is in grey levels per pixel (Sobel / 8 of the blurred image); ``valid`` masks out pixels
    (e.g. outside the photo) and their neighbours.
    """
    img = cv2.GaussianBlur(image.astype(np.float32), (0, 0), sigma) if sigma > 0 else image.astype(np.float32)
    gx = cv2.Sobel(img, cv2.CV_32F, 1, 0, ksize=3) / 8.0
    gy = cv2.Sobel(img, cv2.CV_32F, 0, 1, ksize=3) / 8.0
    if img.ndim == 3:
        m2 = gx * gx + gy * gy
        ch = np.argmax(m2, axis=2)
        gx = np.take_along_axis(gx, ch[..., None], 2)[..., 0]
        gy = np.take_along_axis(gy, ch[..., None], 2)[..., 0]
    mag = np.sqrt(gx * gx + gy * gy)
    ang = np.mod(np.arctan2(gy, gx), np.pi)
    b = (np.floor(ang / (np.pi / N_BINS) + 0.5).astype(np.int32) % N_BINS).astype(np.uint8)
    ok = mag >= min_mag
    if valid is not None:
        ok &= cv2.erode(valid.astype(np.uint8), np.ones((5, 5), np.uint8)) > 0
    return np.where(ok, b, 255).astype(np.uint8), mag


def _response_lut(power: float = 1.0) -> np.ndarray:
    """(8, 256) best |cos| between orientation o and any orientation in an 8-bit set."""
    lut = np.zeros((N_BINS, 256), np.float32)
    for o in range(N_BINS):
        for m in range(1, 256):
            best = 0.0
            for b in range(N_BINS):
                if m >> b & 1:
                    d = min(abs(o - b), N_BINS - abs(o - b))
                    best = max(best, abs(np.cos(d * np.pi / N_BINS)))
            lut[o, m] = best ** power
    return lut


_LUT = {}


def response_maps(bins: np.ndarray, spread: int = 5, power: float = 2.0) -> np.ndarray:
    """(8, H, W) responses: best agreement of each orientation with the edges within a ``spread`` window."""
    bits = np.where(bins < N_BINS, np.left_shift(1, np.minimum(bins, 7).astype(np.int32)), 0).astype(np.uint8)
    if spread > 1:
        out = np.zeros_like(bits)
        for b in range(N_BINS):  # OR over the window = max over 0/1 planes, done per bit with dilate
            plane = ((bits >> b) & 1).astype(np.uint8)
            out |= (cv2.dilate(plane, np.ones((spread, spread), np.uint8)) << b).astype(np.uint8)
        bits = out
    key = round(power, 3)
    if key not in _LUT:
        _LUT[key] = _response_lut(power)
    return _LUT[key][:, bits]


def prepare_query(image: np.ndarray, box_xyxy: np.ndarray, box_px: float = 64.0, pad: float = 1.6,
                  sigma: float = 1.0, min_mag: float = 6.0, spread: int = 5, power: float = 2.0,
                  mask: np.ndarray | None = None, mask_grow_px: int = 5) -> EdgeQuery:
    """Crop the photo around ``box_xyxy`` so that its longer side spans ``box_px`` px and build response maps.

    With an object ``mask`` (H, W) only the edges within ``mask_grow_px`` crop px of it count: the clutter's edges
    around the object no longer answer a template."""
    w, h = box_xyxy[2] - box_xyxy[0], box_xyxy[3] - box_xyxy[1]
    L = max(w, h)
    size = int(round(box_px * pad))
    crop = square_crop(image, box_xyxy, pad, size, 0.0, mask)  # side pad*L -> size px (and the mask, if any)
    ones = np.full(image.shape[:2], 255, np.uint8)
    valid = cv2.warpAffine(ones, crop.A, (size, size), flags=cv2.WARP_INVERSE_MAP | cv2.INTER_NEAREST,
                           borderMode=cv2.BORDER_CONSTANT, borderValue=0) > 0
    edge_valid = valid
    if crop.mask is not None:
        k = 2 * int(mask_grow_px) + 1
        near = cv2.dilate(crop.mask.astype(np.uint8), cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (k, k))) > 0
        edge_valid = valid & near
    bins, mag = quantised_orientations(crop.image, sigma, min_mag, edge_valid)
    resp = response_maps(bins, spread, power)
    s = size / (pad * L)
    return EdgeQuery(resp, crop, np.array([w * s, h * s]), np.full(2, (size - 1) / 2.0), mag, bins, valid)


def orientation_bins(ori: np.ndarray) -> np.ndarray:
    return (np.floor(ori / (np.pi / N_BINS) + 0.5).astype(np.int32) % N_BINS).astype(np.int32)


def placement(box_t: np.ndarray, q: EdgeQuery) -> tuple[np.ndarray, np.ndarray]:
    """Scale (T,) and template-box centre (T, 2) that put template boxes (T, 4) onto the query box."""
    wt = np.maximum(box_t[..., 2] - box_t[..., 0], 1e-3)
    ht = np.maximum(box_t[..., 3] - box_t[..., 1], 1e-3)
    s = np.maximum(q.box_wh[0] / wt, q.box_wh[1] / ht)
    c = 0.5 * (box_t[..., :2] + box_t[..., 2:])
    return s, c


@dataclass
class TemplateBank:
    """Contour templates rolled to every in-plane angle, ready for scoring (query independent: build once).

    Attributes
    ----------
    views : (V,) template view indices;  angles : (A,) roll angles, radians
    xy : (V*A, N, 2) float32 offsets from the rolled outline's box centre, template px
    bins : (V*A, N) int64 orientation bin x (H*W) is added per query; kept as plain bins here
    weights : (V*A, N) float32 (silhouette 1, crease ``crease_weight``, padding 0)
    wh : (V*A, 2) rolled outline box width, height (template px)
    origin : (V*A, 2) principal point relative to the rolled box centre (template px)
    """

    views: np.ndarray
    angles: np.ndarray
    xy: np.ndarray
    bins: np.ndarray
    weights: np.ndarray
    wh: np.ndarray
    origin: np.ndarray

    @property
    def shape(self) -> tuple[int, int]:
        return len(self.views), len(self.angles)


def template_bank(tpl: ContourTemplates, n_rolls: int = 36, crease_weight: float = 0.5,
                  views: np.ndarray | None = None, angles: np.ndarray | None = None) -> TemplateBank:
    """Roll every template view to ``n_rolls`` angles (or ``angles``) and precompute what scoring needs."""
    views = np.arange(tpl.n_views) if views is None else np.asarray(views)
    angles = np.arange(n_rolls) * (2 * np.pi / n_rolls) if angles is None else np.asarray(angles, np.float64)
    sub = ContourTemplates(tpl.poses[views], tpl.K, tpl.xy[views], tpl.ori[views], tpl.kind[views], tpl.xyz[views],
                           tpl.outline[views], tpl.size)
    xy, ori, boxes = sub.rolled(angles)
    V, A, N = ori.shape
    c = 0.5 * (boxes[..., :2] + boxes[..., 2:])
    w = np.where(sub.kind == CREASE, crease_weight, 1.0) * (sub.kind >= 0)
    return TemplateBank(
        views=views, angles=angles,
        xy=(xy - c[:, :, None, :]).reshape(V * A, N, 2).astype(np.float32),
        bins=orientation_bins(ori).reshape(V * A, N),
        weights=np.broadcast_to(w[:, None, :], (V, A, N)).reshape(V * A, N).astype(np.float32),
        wh=np.maximum((boxes[..., 2:] - boxes[..., :2]).reshape(V * A, 2), 1e-3).astype(np.float32),
        origin=(-c).reshape(V * A, 2).astype(np.float32),
    )


def score_bank(q: EdgeQuery, xy: np.ndarray, bins: np.ndarray, weights: np.ndarray, shifts: np.ndarray) -> np.ndarray:
    """Scores (T, S) of T placed point sets (T, N, 2 crop px, float) under S integer pixel shifts (S, 2)."""
    nb, H, W = q.resp.shape
    pad = int(np.abs(shifts).max()) + 1 if len(shifts) else 1
    Hp, Wp = H + 2 * pad, W + 2 * pad
    flat = np.zeros((nb, Hp, Wp), np.float32)
    flat[:, pad:pad + H, pad:pad + W] = q.resp
    flat = flat.reshape(-1)
    x = np.clip(np.rint(xy[..., 0]).astype(np.int64), -1, W) + pad  # off the crop: the zero border
    y = np.clip(np.rint(xy[..., 1]).astype(np.int64), -1, H) + pad
    base = bins.astype(np.int64) * (Hp * Wp) + y * Wp + x
    wn = weights / np.maximum(weights.sum(axis=1, keepdims=True), 1e-9)
    out = np.empty((xy.shape[0], len(shifts)), np.float32)
    for k, (dx, dy) in enumerate(np.asarray(shifts, np.int64)):
        out[:, k] = np.einsum("tn,tn->t", flat[base + (dy * Wp + dx)], wn)
    return out


@dataclass
class EdgeMatch:
    """Best placements of templates: view, roll angle, score, scale and shift (crop px)."""

    view: np.ndarray  # (M,)
    angle: np.ndarray  # (M,) radians
    score: np.ndarray  # (M,)
    scale: np.ndarray  # (M,) template px -> crop px
    offset: np.ndarray  # (M, 2) crop px of the template's principal point (the object centre's image)


def search(tpl: ContourTemplates | TemplateBank, q: EdgeQuery, n_rolls: int = 36, crease_weight: float = 0.5,
           shift_px: float = 4.0, shift_steps: int = 1, scales: tuple[float, ...] = (1.0,),
           views: np.ndarray | None = None, angles: np.ndarray | None = None) -> tuple[np.ndarray, dict]:
    """Score every (view, roll) template against the query; returns scores (V, A) and the best placement per pair.

    Parameters
    ----------
    tpl : templates, or a prebuilt :class:`TemplateBank` (then ``n_rolls``, ``crease_weight``, ``views`` and
        ``angles`` are those of the bank)
    shift_px, shift_steps : shift grid (2*steps+1)^2 with this step, crop px
    scales : multipliers of the box-implied scale

    Returns
    -------
    scores : (V, A)
    info : views, angles, and per pair the best 'scale' (template px -> crop px) and 'origin' (crop px where the
        template's principal point, i.e. the object centre, lands)
    """
    bank = tpl if isinstance(tpl, TemplateBank) else template_bank(tpl, n_rolls, crease_weight, views, angles)
    V, A = bank.shape
    s0 = np.maximum(q.box_wh[0] / bank.wh[:, 0], q.box_wh[1] / bank.wh[:, 1]).astype(np.float32)
    g = np.rint(np.arange(-shift_steps, shift_steps + 1) * shift_px).astype(np.int64)
    shifts = np.stack(np.meshgrid(g, g), -1).reshape(-1, 2)
    best = np.full(V * A, -1.0, np.float32)
    best_s = np.ones(V * A, np.float32)
    best_o = np.zeros((V * A, 2), np.float32)
    for sc in scales:
        s = (s0 * sc)[:, None]
        P = q.centre.astype(np.float32) + s[:, :, None] * bank.xy
        sco = score_bank(q, P, bank.bins, bank.weights, shifts)
        k = np.argmax(sco, axis=1)
        val = sco[np.arange(V * A), k]
        upd = val > best
        best = np.where(upd, val, best)
        best_s = np.where(upd, s[:, 0], best_s)
        origin = q.centre + s * bank.origin  # where the principal point lands
        best_o = np.where(upd[:, None], origin + shifts[k], best_o)
    return best.reshape(V, A), {"views": bank.views, "angles": bank.angles, "scale": best_s.reshape(V, A),
                                "origin": best_o.reshape(V, A, 2)}
