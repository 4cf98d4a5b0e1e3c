"""Region cue: does an object silhouette split the photo's colours from its surroundings?

Whatever its paint, an object's projected region tends to hold colours that are rarer in a band around it.
For a silhouette mask, colour histograms of the inside and of a surrounding band give each pixel a foreground
posterior ``P_f(c) = h_f(c) / (h_f(c) + h_b(c))`` (PWP3D, Prisacariu & Reid); the agreement score is the mean
probability of the right label, ``0.5 * (mean_inside P_f + mean_band (1 - P_f))``: 0.5 for a silhouette
that separates nothing, 1 for a perfect split.

:func:`refine_pose` is region-based pose refinement along correspondence lines (in the spirit of RBOT / SRT3D,
Stoiber et al.): the object is rendered at the current pose, points along its projected contour search along
their 2D normals for the strongest foreground/background transition of the posterior, and a robust
Gauss-Newton step moves the pose (6 DoF) to bring the contour onto those transitions.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from pixie.geometry.camera import make_T, transform_points
from pixie.geometry.render import Renderer


def colour_index(image: np.ndarray, bits: int = 3) -> np.ndarray:
    """(H, W) int32 joint RGB bin of every pixel, ``2**(3*bits)`` bins."""
    q = (image.astype(np.int32) >> (8 - bits))
    return (q[..., 0] << (2 * bits)) | (q[..., 1] << bits) | q[..., 2]


def posterior(idx: np.ndarray, inside: np.ndarray, outside: np.ndarray, n_bins: int, prior: float = 1.0) -> np.ndarray:
    """Foreground posterior per colour bin, (n_bins,), from the histograms of two pixel sets (Laplace-smoothed)."""
    hf = np.bincount(idx[inside], minlength=n_bins).astype(np.float64) + prior
    hb = np.bincount(idx[outside], minlength=n_bins).astype(np.float64) + prior
    hf /= hf.sum()
    hb /= hb.sum()
    return hf / (hf + hb)


def band(mask: np.ndarray, width: int, valid: np.ndarray | None = None) -> np.ndarray:
    """Pixels within ``width`` px outside ``mask`` (and inside ``valid``).

    The dilation runs on the mask's bounding box grown by the kernel's radius only (no pixel farther from the mask
    can be reached), which gives the whole image's result at a fraction of the work on object-sized masks.
    """
    r = int(max(width, 1))
    k = 2 * r + 1
    out = np.zeros(mask.shape, bool)
    rows, cols = np.flatnonzero(mask.any(axis=1)), np.flatnonzero(mask.any(axis=0))
    if len(rows):
        y0, y1 = max(rows[0] - r, 0), min(rows[-1] + r + 1, mask.shape[0])
        x0, x1 = max(cols[0] - r, 0), min(cols[-1] + r + 1, mask.shape[1])
        sub = mask[y0:y1, x0:x1]
        kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (k, k))
        out[y0:y1, x0:x1] = (cv2.dilate(sub.astype(np.uint8), kernel) > 0) & ~sub
    return out if valid is None else out & valid


def separation(idx: np.ndarray, mask: np.ndarray, outside: np.ndarray, n_bins: int) -> float:
    """Mean probability of the right label (inside / outside) under the two regions' colour posteriors."""
    if not mask.any() or not outside.any():
        return 0.5
    pf = posterior(idx, mask, outside, n_bins)
    return float(0.5 * (pf[idx[mask]].mean() + (1.0 - pf[idx[outside]]).mean()))


def polygon_scores(image: np.ndarray, polys: np.ndarray, band_px: int, valid: np.ndarray | None = None,
                   bits: int = 3) -> np.ndarray:
    """Region agreement of T silhouette polygons (T, M, 2) (image px, ordered outline) on one image, (T,)."""
    idx = colour_index(image, bits)
    n_bins = 1 << (3 * bits)
    H, W = idx.shape
    out = np.zeros(len(polys))
    for i, P in enumerate(polys):
        m = np.zeros((H, W), np.uint8)
        cv2.fillPoly(m, [np.round(P).astype(np.int32)], 1)
        mask = m > 0
        if valid is not None:
            mask &= valid
        out[i] = separation(idx, mask, band(mask, band_px, valid), n_bins)
    return out


# ----------------------------------------------------------------------------------- refinement


@dataclass
class RegionRefineResult:
    T_cam_from_obj: np.ndarray
    score: float  # region separation at the final pose
    iterations: int
    n_lines: int  # correspondence lines used in the last step


def _contour_points(depth: np.ndarray, step: int) -> tuple[np.ndarray, np.ndarray]:
    """Outer-contour pixels (every ``step``-th) of a depth render and their outward unit normals."""
    mask = (depth > 0).astype(np.uint8)
    cs, _ = cv2.findContours(mask, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    if not cs:
        return np.zeros((0, 2)), np.zeros((0, 2))
    pts = np.concatenate([c[:, 0, :] for c in cs]).astype(np.float64)
    mf = cv2.GaussianBlur(mask.astype(np.float32), (0, 0), 1.5)
    gx = cv2.Sobel(mf, cv2.CV_32F, 1, 0, ksize=3)
    gy = cv2.Sobel(mf, cv2.CV_32F, 0, 1, ksize=3)
    pts = pts[:: max(int(step), 1)]
    r, c = pts[:, 1].astype(int), pts[:, 0].astype(int)
    n = -np.stack([gx[r, c], gy[r, c]], 1).astype(np.float64)  # mask gradient points inwards
    norm = np.linalg.norm(n, axis=1)
    ok = norm > 1e-6
    return pts[ok], n[ok] / norm[ok, None]


def _line_targets(pf_img: np.ndarray, pts: np.ndarray, nrm: np.ndarray, reach: int) -> tuple[np.ndarray, np.ndarray]:
    """Along each contour normal, the signed offset (px) of the best foreground→background step, and its strength.

    The step maximises ``mean P_f`` over the inner segment minus over the outer segment (segments of 4 px) among
    offsets in [-reach, reach]; strength is that difference (0..1).
    """
    H, W = pf_img.shape
    offs = np.arange(-reach - 4, reach + 5)
    xs = pts[:, None, 0] + nrm[:, None, 0] * offs[None]
    ys = pts[:, None, 1] + nrm[:, None, 1] * offs[None]
    inside_img = (xs >= 0) & (xs <= W - 1) & (ys >= 0) & (ys <= H - 1)
    vals = cv2.remap(pf_img.astype(np.float32), xs.astype(np.float32), ys.astype(np.float32), cv2.INTER_LINEAR,
                     borderMode=cv2.BORDER_CONSTANT, borderValue=0.5)
    vals = np.where(inside_img, vals, 0.5)
    cs = np.concatenate([np.zeros((len(pts), 1)), np.cumsum(vals, axis=1)], axis=1)
    k = np.arange(4, len(offs) - 4)  # candidate step between offs[k-1] and offs[k]
    inner = (cs[:, k] - cs[:, k - 4]) / 4.0  # offsets k-4..k-1 (inside: smaller offsets, normal points out)
    outer = (cs[:, k + 4] - cs[:, k]) / 4.0
    diff = inner - outer
    j = np.argmax(diff, axis=1)
    rows = np.arange(len(pts))
    # sub-pixel: vertex of the parabola through the peak and its neighbours
    a = diff[rows, np.maximum(j - 1, 0)]
    b = diff[rows, j]
    c = diff[rows, np.minimum(j + 1, diff.shape[1] - 1)]
    den = a - 2 * b + c
    sub = np.where(den < -1e-9, 0.5 * (a - c) / np.where(den < -1e-9, den, -1.0), 0.0)
    # the contour pixel is the last one inside: the silhouette edge sits half a pixel out, and the step
    # between samples k-1 and k half a pixel before offs[k]; at the right pose offs[k] = 1
    return (offs[k[j]] - 1.0 + np.clip(sub, -0.5, 0.5)).astype(np.float64), b


def refine_pose(renderer: Renderer, T0: np.ndarray, K: np.ndarray, image: np.ndarray, iterations: int = 4,
                reach: tuple[int, ...] | int = (16, 8, 4), step: int = 3, band_px: int | None = None, bits: int = 3,
                min_strength: float = 0.15, damping: float = 1e-3, valid: np.ndarray | None = None) -> RegionRefineResult:
    """Region-based 6-DoF refinement of ``T0`` in ``image`` (intrinsics ``K``; crop images work with crop K).

    Each iteration renders the object, rebuilds colour posteriors from the rendered silhouette and a
    ``band_px`` band around it (default: a quarter of the silhouette's longer side), finds each contour point's best transition along its normal (within
    ``reach`` px) and takes a Levenberg-Marquardt step on the point-to-line distances (Tukey-weighted by the
    transition strength). Coarse to fine: up to ``iterations`` steps at each reach of the schedule; a scale
    ends when the update moves the contour by less than 0.05 px on average.
    """
    H, W = image.shape[:2]
    idx = colour_index(image, bits)
    n_bins = 1 << (3 * bits)
    T = np.asarray(T0, np.float64).copy()
    n_used, it = 0, 0
    for reach_px in (reach if isinstance(reach, (tuple, list)) else (reach,)):
        for _ in range(iterations):
            T, n, moved = _region_step(renderer, T, K, idx, n_bins, int(reach_px), step, band_px, min_strength,
                                       damping, valid)
            it += 1
            n_used = n or n_used
            if n == 0 or moved < 0.05:
                break
    r = renderer.render(T, K, H, W)
    mask = r.mask if valid is None else r.mask & valid
    score = separation(idx, mask, band(mask, band_px or _band_width(mask), valid), n_bins) if mask.any() else 0.5
    return RegionRefineResult(T, score, it, n_used)


def _band_width(mask: np.ndarray, frac: float = 0.25) -> int:
    """``frac`` of the longer side of the mask's box, at least 3 px."""
    ys, xs = np.nonzero(mask)
    if len(xs) == 0:
        return 3
    return max(int(round(frac * max(np.ptp(xs), np.ptp(ys)))), 3)


def _region_step(renderer, T, K, idx, n_bins, reach, step, band_px, min_strength, damping, valid):
    """One correspondence-line step; returns (new pose, lines used (0 = could not step), mean contour motion px)."""
    H, W = idx.shape
    r = renderer.render(T, K, H, W)
    mask = r.mask if valid is None else r.mask & valid
    if mask.sum() < 20:
        return T, 0, 0.0
    out = band(mask, band_px or _band_width(mask), valid)
    pf = posterior(idx, mask, out, n_bins)
    pf_img = pf[idx]
    pts, nrm = _contour_points(r.depth, step)
    if len(pts) < 10:
        return T, 0, 0.0
    d, s = _line_targets(pf_img, pts, nrm, reach)
    ok = s > min_strength
    if ok.sum() < 10:
        return T, 0, 0.0
    pts, nrm, d, s = pts[ok], nrm[ok], d[ok], s[ok]
    rr, cc = pts[:, 1].astype(int), pts[:, 0].astype(int)
    X = r.xyz[rr, cc].astype(np.float64)  # object points under the contour pixels
    Xc = transform_points(T, X)
    # residual along the normal: the contour should move by d; Jacobian of the projection along n
    fx, fy = K[0, 0], K[1, 1]
    x, y, z = Xc[:, 0], Xc[:, 1], Xc[:, 2]
    Ju = np.stack([fx / z, np.zeros_like(z), -fx * x / z ** 2], 1)  # du/dXc
    Jv = np.stack([np.zeros_like(z), fy / z, -fy * y / z ** 2], 1)
    Jn = nrm[:, :1] * Ju + nrm[:, 1:] * Jv  # d(n.uv)/dXc, (M, 3)
    # dXc = dt + w x Xc  (left perturbation):  d/dw = -[Xc]x
    J = np.concatenate([np.cross(Xc, Jn), Jn], axis=1)  # (M, 6): rotation (w), translation
    # robust weights: strength x Tukey on the line offset
    c = max(float(reach), 1.0)
    wt = s * np.clip(1 - (d / c) ** 2, 0, None) ** 2
    A = J.T @ (J * wt[:, None])
    b = J.T @ (wt * d)
    A += damping * np.diag(np.diag(A)) + 1e-12 * np.eye(6)
    try:
        delta = np.linalg.solve(A, b)
    except np.linalg.LinAlgError:
        return T, 0, 0.0
    w, t = delta[:3], delta[3:]
    th = np.linalg.norm(w)
    Rw = cv2.Rodrigues(w.reshape(3, 1))[0] if th > 0 else np.eye(3)
    T = make_T(Rw @ T[:3, :3], Rw @ T[:3, 3] + t)
    return T, len(pts), float(np.sqrt(np.mean((J @ delta) ** 2)))
