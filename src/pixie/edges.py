"""Texture-invariant edge cue: query gradient orientations scored against contour templates (LINE-2D style).

The query crop's colour gradients (the RGB channel of largest magnitude per pixel, as in LINEMOD,
Hinterstoisser et al.) are quantised to 8 unsigned orientations, spread over a small neighbourhood and turned
into 8 response maps: ``resp[o][y, x]`` is how well an edge of orientation ``o`` placed at (x, y) agrees with
the photo (|cos| of the smallest orientation difference present nearby). A template (a view's contour points,
rolled; :mod:`pixie.contours`) placed in the crop scores the weighted mean response over its points; each
point's score is bounded, so clutter and occlusion cost a template only the points they touch.

Placement: the template's rolled silhouette box is scaled and centred onto the query box (the larger of the
width and height ratios, like :func:`pixie.pose.depth_from_box`), then a small grid of shifts and scales is
searched.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from pixie.contours import CREASE, ContourTemplates
from pixie.query import QueryCrop, square_crop

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


def quantised_orientations(image: np.ndarray, sigma: float = 1.0, min_mag: float = 12.0,
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
                  sigma: float = 1.0, min_mag: float = 12.0, spread: int = 5, power: float = 2.0) -> EdgeQuery:
    """Crop the photo around ``box_xyxy`` so that its longer side spans ``box_px`` px and build response maps."""
    w, h = box_xyxy[2] - box_xyxy[0], box_xyxy[3] - box_xyxy[1]
    L = max(w, h)
    size = int(round(box_px * pad))
    crop = square_crop(image, box_xyxy, pad, size)  # side pad*L -> size px
    ones = np.full(image.shape[:2], 255, np.uint8)
    valid = cv2.warpAffine(ones, crop.A, (size, size), flags=cv2.WARP_INVERSE_MAP | cv2.INTER_NEAREST,
                           borderMode=cv2.BORDER_CONSTANT, borderValue=0) > 0
    bins, mag = quantised_orientations(crop.image, sigma, min_mag, valid)
    resp = response_maps(bins, spread, power)
    s = size / (pad * L)
    return EdgeQuery(resp, crop, np.array([w * s, h * s]), np.full(2, (size - 1) / 2.0), mag, bins)


def orientation_bins(ori: np.ndarray) -> np.ndarray:
    return (np.floor(ori / (np.pi / N_BINS) + 0.5).astype(np.int32) % N_BINS).astype(np.int32)


def placement(box_t: np.ndarray, q: EdgeQuery) -> tuple[np.ndarray, np.ndarray]:
    """Scale (T,) and template-box centre (T, 2) that put template boxes (T, 4) onto the query box."""
    wt = np.maximum(box_t[..., 2] - box_t[..., 0], 1e-3)
    ht = np.maximum(box_t[..., 3] - box_t[..., 1], 1e-3)
    s = np.maximum(q.box_wh[0] / wt, q.box_wh[1] / ht)
    c = 0.5 * (box_t[..., :2] + box_t[..., 2:])
    return s, c


def score_points(q: EdgeQuery, xy: np.ndarray, bins: np.ndarray, weights: np.ndarray,
                 shifts: np.ndarray) -> np.ndarray:
    """Scores (T, S) of T placed point sets (T, N, 2 crop px) under S pixel shifts (S, 2)."""
    nb, H, W = q.resp.shape
    flat = q.resp.reshape(-1)
    wsum = np.maximum(weights.sum(axis=1), 1e-9)
    base = bins.astype(np.int64) * (H * W)
    out = np.zeros((xy.shape[0], len(shifts)), np.float32)
    for k, (dx, dy) in enumerate(shifts):
        x = np.clip(np.rint(xy[..., 0] + dx).astype(np.int64), 0, W - 1)
        y = np.clip(np.rint(xy[..., 1] + dy).astype(np.int64), 0, H - 1)
        r = flat[base + y * W + x]
        out[:, k] = (r * weights).sum(axis=1) / wsum
    return out


@dataclass
class EdgeMatch:
    """Best placements of templates: view, roll angle, score, scale and shift (crop px)."""

    view: np.ndarray  # (M,)
    angle: np.ndarray  # (M,) radians
    score: np.ndarray  # (M,)
    scale: np.ndarray  # (M,) template px -> crop px
    offset: np.ndarray  # (M, 2) crop px of the template's principal point (the object centre's image)


def search(tpl: ContourTemplates, q: EdgeQuery, n_rolls: int = 36, crease_weight: float = 0.5,
           shift_px: float = 4.0, shift_steps: int = 1, scales: tuple[float, ...] = (1.0,),
           views: np.ndarray | None = None, angles: np.ndarray | None = None) -> tuple[np.ndarray, dict]:
    """Score every (view, roll) template against the query; returns scores (V, A) and the best placement per pair.

    Parameters
    ----------
    n_rolls : in-plane angles 0, 360/n_rolls, ... (ignored when ``angles`` is given)
    shift_px, shift_steps : shift grid (2*steps+1)^2 with this step, crop px
    scales : multipliers of the box-implied scale
    """
    views = np.arange(tpl.n_views) if views is None else np.asarray(views)
    angles = np.arange(n_rolls) * (2 * np.pi / n_rolls) if angles is None else np.asarray(angles, np.float64)
    sub = ContourTemplates(tpl.poses[views], tpl.K, tpl.xy[views], tpl.ori[views], tpl.kind[views], tpl.xyz[views],
                           tpl.outline[views], tpl.size)
    xy, ori, boxes = sub.rolled(angles)  # (V, A, N, 2), (V, A, N), (V, A, 4)
    V, A, N = ori.shape
    s0, c0 = placement(boxes, q)
    w = np.where(sub.kind == CREASE, crease_weight, 1.0) * (sub.kind >= 0)
    w = np.broadcast_to(w[:, None, :], (V, A, N)).reshape(V * A, N).astype(np.float32)
    b = orientation_bins(ori).reshape(V * A, N)
    g = np.arange(-shift_steps, shift_steps + 1) * shift_px
    shifts = np.stack(np.meshgrid(g, g), -1).reshape(-1, 2)
    best = np.full(V * A, -1.0, np.float32)
    best_s = np.ones(V * A, np.float32)
    best_o = np.zeros((V * A, 2), np.float32)
    for sc in scales:
        s = (s0 * sc).reshape(V * A, 1, 1)
        P = q.centre + s * (xy.reshape(V * A, N, 2) - c0.reshape(V * A, 1, 2))
        sco = score_points(q, P, b, w, shifts)
        k = np.argmax(sco, axis=1)
        val = sco[np.arange(V * A), k]
        upd = val > best
        best = np.where(upd, val, best)
        best_s = np.where(upd, s[:, 0, 0], best_s)
        origin = q.centre - s[:, 0, :] * c0.reshape(V * A, 2)  # where the principal point lands
        best_o = np.where(upd[:, None], origin + shifts[k], best_o)
    return best.reshape(V, A), {"views": views, "angles": angles, "scale": best_s.reshape(V, A),
                                "origin": best_o.reshape(V, A, 2)}
