"""Edge-based 6-DoF alignment of a pose to the photo (the D2CO / FDCM family of directional chamfer fits).

Photo side (:mod:`pixie.cues.edge_photo`, once per query): sub-pixel colour-Canny edges of a crop around the box in
16 orientation bins, one distance transform per bin. Correspondences (``search``): each model point takes
either the nearest photo edge in a bin within ``max_bin_gap`` of its own orientation (``'nearest'``, the
directional chamfer distance of Liu et al., CVPR 2010, each bin away costing ``bin_penalty`` px) or the nearest
such edge *along its normal* (``'normal'``, RAPID-style 1D search), optionally only across a drop of the colour
foreground posterior (``min_contrast``), or (``'region'``, the default since session 23) for silhouette points the
offset along the normal where that posterior (colours inside the current silhouette against a band around it) most
likely steps from object to background (:func:`_region_steps`, the region boundary of PWP3D / SRT3D), snapped to an
edge within ``region_snap`` px, the edge kept where there is no clear step (``region_fallback``); creases as
``'normal'``. Residuals are measured along the target's direction in every case.

Model side: the hypothesis is rendered in the crop's own camera and its silhouette and crease points are kept
with their 3D object points (:func:`pixie.references.templates.view_points`); it is re-rendered ``rerender`` times per
truncation level (visibility changes) when the pose has moved since the last render. Silhouette points are moved half a render pixel outwards (the boundary pixel's centre
lies inside the true outline by that much on average).

Solver: Levenberg–Marquardt on se(3) (rotation about the object's centre, translation in the camera frame) on
point-to-line residuals ``g . (p - e)`` (``g`` the photo edge's gradient direction at its sub-pixel position
``e``) with a Tukey biweight whose scale follows the schedule (8 → 4 → 2 px: graduated non-convexity). A model
point outside the given box (+ a margin) or the mask is occluded by definition and dropped. The box sides are
residuals too (``w_box``): a projection that falls short of a visible side costs quadratically, one that reaches
past it (occlusion) only within the Tukey scale, so depth, rotation and translation are refined jointly and an
occluded side no longer sets depth.

The fit of a pose (:func:`edge_fit`) is the share of its visible model contour points within ``fit_px`` of a
same-orientation photo edge; it predicts whether a pose is right (the estimator's calibrated confidence).

>>> pe = photo_edges(image, K, box_xyxy)                                  # once per photo
>>> res = align(renderer, pe, T0, hull=mesh.hull_vertices, w_box=1.0)    # AlignResult: pose, fit, iterations
>>> fit = edge_fit(renderer, pe, res.T_cam_from_obj)                      # EdgeFit

Longer than 500 lines on purpose: the matching, the LM step, its robust cost and the fit share one set of per-point
conventions (crop px, half-pixel silhouette offsets, orientation bins) that splitting would spread over modules.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np

from pixie.cues.edge_photo import PhotoEdges, photo_edges
from pixie.cues.region import band, posterior
from pixie.config import FLIP_AXES
from pixie.errors import ConfigError
from pixie.geometry.camera import make_T
from pixie.geometry.render import Renderer
from pixie.geometry.rotations import rodrigues
from pixie.references.templates import CREASE, SILHOUETTE, view_points

__all__ = ["PhotoEdges", "AlignResult", "EdgeFit", "photo_edges", "model_points", "align", "align_kwargs", "coarse_kwargs", "coarse_levels", "photo_edges_kwargs", "calibrated_confidence", "confidence_size", "edge_fit",
           "edge_distances", "flip_twins", "silhouette_outset"]


@dataclass(kw_only=True)
class EdgeFit:
    """How well a pose's contour agrees with the photo's edges (crop px of :class:`PhotoEdges`).

    Attributes
    ----------
    share : share of visible model contour points with a same-orientation edge within ``fit_px``
    silhouette_share : the same for silhouette points only
    visible : share of the model's contour points inside the allowed region (box + margin, mask)
    mean_dist : mean truncated directional chamfer distance of the visible points, px
    n_points : visible points
    region_share : share of visible silhouette points where the colour foreground posterior (inside the silhouette
        against a band around it) steps to background within ``fit_px`` along the normal (:func:`_region_steps`);
        NaN when not computed (``edge_fit(region=False)``)
    support_share : share of visible points with either support: a same-orientation edge within ``fit_px``, or (a
        silhouette point) such a region step; NaN when not computed
    """

    share: float
    silhouette_share: float
    visible: float
    mean_dist: float
    n_points: int
    region_share: float = float("nan")
    support_share: float = float("nan")

    def as_dict(self) -> dict[str, float]:
        return {"fit": self.share, "fit_silhouette": self.silhouette_share, "fit_visible": self.visible,
                "fit_dist": self.mean_dist, "fit_region": self.region_share, "fit_support": self.support_share}


@dataclass(kw_only=True)
class AlignResult:
    """The aligned pose and its fit."""

    T_cam_from_obj: np.ndarray
    T_init: np.ndarray
    fit: EdgeFit
    iterations: int
    converged: bool
    history: list[float] = field(default_factory=list)  # robust cost after each level


# ------------------------------------------------------------------------------------------ model side


@dataclass(kw_only=True)
class ModelPoints:
    """Contour points of one render: object points, their kind, 2D orientation and outward offset."""

    xyz: np.ndarray  # (N, 3) object frame, mm
    kind: np.ndarray  # (N,) SILHOUETTE / CREASE
    ori: np.ndarray  # (N,) unsigned orientation of the edge's gradient at render time, radians
    offset: np.ndarray  # (N, 2) crop px added to the projection (silhouette: half a pixel outwards)
    outward: np.ndarray  # (N, 2) unit outward normal of silhouette points, 0 for creases
    T_render: np.ndarray  # the pose they were rendered at
    mask: np.ndarray  # (size, size) bool, the render's silhouette
    tri: np.ndarray | None = None  # (N,) the mesh triangle under each point (parts: mesh.face_parts[tri])

    def subset(self, keep: np.ndarray) -> "ModelPoints":
        """The points where ``keep`` (N,) is true."""
        return ModelPoints(xyz=self.xyz[keep], kind=self.kind[keep], ori=self.ori[keep], offset=self.offset[keep],
                           outward=self.outward[keep], T_render=self.T_render, mask=self.mask,
                           tri=None if self.tri is None else self.tri[keep])


def model_points(renderer: Renderer, T: np.ndarray, K: np.ndarray, size: int, n_points: int = 240,
                 crease_share: float = 0.3, outset: float = 0.5) -> ModelPoints | None:
    """Silhouette and crease points of the object rendered at ``T`` in a ``size`` x ``size`` camera ``K``; silhouette
    points are moved ``outset`` render px outwards (0.5: the boundary pixel's centre to the outline, on average)."""
    r = renderer.render(T, K, size, size)
    m = r.mask
    if m.sum() < 20:
        return None
    vp = view_points(r.depth, r.normals, K, T, n_points, crease_share, n_outline=8)
    if len(vp["kind"]) < 6:
        return None
    P = np.rint(vp["xy"] + K[:2, 2]).astype(np.int64)
    kind = vp["kind"].astype(np.int8)
    xyz = r.xyz[P[:, 1], P[:, 0]].astype(np.float64)
    ori = vp["ori"]
    # outward normal of the silhouette: minus the smoothed mask's gradient
    mf = cv2.GaussianBlur(m.astype(np.float32), (0, 0), 1.0)
    gx = cv2.Sobel(mf, cv2.CV_32F, 1, 0, ksize=3)[P[:, 1], P[:, 0]]
    gy = cv2.Sobel(mf, cv2.CV_32F, 0, 1, ksize=3)[P[:, 1], P[:, 0]]
    n = -np.stack([gx, gy], 1).astype(np.float64)
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-9)
    sil = (kind == SILHOUETTE)[:, None]
    return ModelPoints(xyz=xyz, kind=kind, ori=np.asarray(ori, np.float64), offset=np.where(sil, float(outset) * n, 0.0),
                       outward=np.where(sil, n, 0.0), T_render=np.asarray(T, np.float64).copy(), mask=m,
                       tri=r.tri_ids[P[:, 1], P[:, 0]].astype(np.int64))


def foreground_map(pe: PhotoEdges, mask: np.ndarray, band_frac: float = 0.15) -> np.ndarray:
    """(size, size) float32 foreground posterior of every crop pixel from the colours inside ``mask`` (the
    visible part: within the allowed region) against a band around it (:func:`pixie.region.posterior`)."""
    inside = mask & pe.allowed
    w = max(int(round(band_frac * max(pe.box[2] - pe.box[0], pe.box[3] - pe.box[1]))), 2)
    outside = band(mask, w, pe.valid)
    if inside.sum() < 10 or outside.sum() < 10:
        return np.full(mask.shape, 0.5, np.float32)
    return posterior(pe.colour, inside, outside, 512)[pe.colour].astype(np.float32)


# ------------------------------------------------------------------------------------------ matching


def _match(pe: PhotoEdges, xy: np.ndarray, ori: np.ndarray, max_bin_gap: int,
           bin_penalty: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Directional chamfer match of points ``xy`` (crop px) with orientations ``ori``.

    Returns
    -------
    cost : (N,) distance + bin_penalty * bin gap of the best edge (1e4 where none / off the crop)
    edge : (N,) index into ``pe.edge_xy`` (-1 where none)
    inside : (N,) the point lies in the allowed region
    """
    S, B = pe.size, pe.n_bins
    xi, yi = np.rint(xy[:, 0]).astype(int), np.rint(xy[:, 1]).astype(int)
    ok = (xi >= 0) & (xi < S) & (yi >= 0) & (yi < S)
    xi, yi = np.clip(xi, 0, S - 1), np.clip(yi, 0, S - 1)
    inside = ok & pe.allowed[yi, xi]
    b0 = (np.floor(np.mod(ori, np.pi) / (np.pi / B) + 0.5).astype(int)) % B
    best = np.full(len(xy), 1e4)
    edge = np.full(len(xy), -1, np.int64)
    for gap in range(-max_bin_gap, max_bin_gap + 1):
        b = (b0 + gap) % B
        d = pe.dist[b, yi, xi] + bin_penalty * abs(gap)
        e = pe.nearest[b, yi, xi]
        upd = (d < best) & (e >= 0)
        best = np.where(upd, d, best)
        edge = np.where(upd, e, edge)
    best[~ok] = 1e4
    edge[~ok] = -1
    return best, edge, inside


def _match_normal(pe: PhotoEdges, xy: np.ndarray, ori: np.ndarray, reach: float, max_bin_gap: int,
                  fg: np.ndarray | None = None, outward: np.ndarray | None = None, min_contrast: float = 0.0,
                  probe_px: float = 2.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Match each point to the nearest same-orientation photo edge *along its normal* (RAPID-style 1D search).

    With a foreground map ``fg`` and outward normals (silhouette points), an edge only counts for a silhouette
    point when the foreground posterior ``probe_px`` inside it exceeds the one outside by ``min_contrast``
    (an object boundary, not clutter or texture). Returns cost (|offset| along the normal, px; 1e4 where none
    within ``reach``), edge index (-1: none) and whether the point lies in the allowed region, as :func:`_match`.
    """
    S, B = pe.size, pe.n_bins
    if len(pe.edge_xy) == 0:  # a photo crop without edges: nothing to match
        return np.full(len(xy), 1e4), np.full(len(xy), -1, np.int64), np.zeros(len(xy), bool)
    n = np.stack([np.cos(ori), np.sin(ori)], 1)
    steps = np.arange(0.0, reach + 1e-9, 0.5)
    offs = np.concatenate([[0.0], np.stack([steps[1:], -steps[1:]], 1).ravel()])  # 0, +.5, -.5, +1, -1, ...
    q = xy[:, None, :] + offs[None, :, None] * n[:, None, :]  # (N, O, 2)
    qx, qy = np.rint(q[..., 0]).astype(int), np.rint(q[..., 1]).astype(int)
    okq = (qx >= 0) & (qx < S) & (qy >= 0) & (qy < S)
    qx, qy = np.clip(qx, 0, S - 1), np.clip(qy, 0, S - 1)
    b0 = (np.floor(np.mod(ori, np.pi) / (np.pi / B) + 0.5).astype(int)) % B
    hit = np.full(qx.shape, -1, np.int64)
    for gap in sorted(range(-max_bin_gap, max_bin_gap + 1), key=abs):
        b = ((b0 + gap) % B)[:, None]
        e = pe.index[b, qy, qx]
        hit = np.where((hit < 0) & (e >= 0) & okq, e, hit)
    if fg is not None and outward is not None and min_contrast > 0:
        sil = np.abs(outward).sum(axis=1) > 0
        ex = pe.edge_xy[np.maximum(hit, 0)]  # (N, O, 2)
        o = outward[:, None, :]
        a = np.clip(np.rint(ex - probe_px * o).astype(int), 0, S - 1)
        b = np.clip(np.rint(ex + probe_px * o).astype(int), 0, S - 1)
        contrast = fg[a[..., 1], a[..., 0]] - fg[b[..., 1], b[..., 0]]
        hit = np.where(sil[:, None] & (contrast < min_contrast), -1, hit)
    has = hit >= 0
    first = np.argmax(has, axis=1)
    any_ = has.any(axis=1)
    edge = np.where(any_, hit[np.arange(len(xy)), first], -1)
    cost = np.where(any_, np.abs(offs[first]), 1e4)
    xi, yi = np.rint(xy[:, 0]).astype(int), np.rint(xy[:, 1]).astype(int)
    ok = (xi >= 0) & (xi < S) & (yi >= 0) & (yi < S)
    inside = ok & pe.allowed[np.clip(yi, 0, S - 1), np.clip(xi, 0, S - 1)]
    return cost, edge, inside


def _tukey_rho(r: np.ndarray, tau: float) -> np.ndarray:
    """Tukey's biweight loss of residuals ``r`` with scale ``tau`` (``tau² / 6`` beyond it)."""
    return tau ** 2 / 6 * (1 - (1 - np.minimum((r / tau) ** 2, 1.0)) ** 3)


def _tukey_weight(r: np.ndarray, tau: float) -> np.ndarray:
    """Tukey's IRLS weight ``(1 - (r / tau)²)²`` inside the scale, 0 beyond it."""
    return (1.0 - (r / tau) ** 2) ** 2 * (np.abs(r) < tau)


def _project(K: np.ndarray, Xc: np.ndarray) -> np.ndarray:
    z = np.maximum(Xc[:, 2], 1e-6)
    return np.stack([K[0, 0] * Xc[:, 0] / z + K[0, 2], K[1, 1] * Xc[:, 1] / z + K[1, 2]], 1)


def _roll_delta(R_now: np.ndarray, R_then: np.ndarray) -> float:
    """Angle (radians) of the rotation R_now R_then^T about the camera's optical axis (its in-plane part)."""
    D = R_now @ R_then.T
    return float(np.arctan2(D[1, 0] - D[0, 1], D[0, 0] + D[1, 1]))


def _lm_step(K: np.ndarray, T: np.ndarray, mp: ModelPoints, pe: PhotoEdges, tau: float, cfg: dict,
             lam: float) -> tuple[np.ndarray | None, float, int]:
    """One Levenberg–Marquardt step; returns (new T or None, robust cost at T, points used)."""
    R, t = T[:3, :3], T[:3, 3]
    Xc = mp.xyz @ R.T + t
    p = _project(K, Xc) + mp.offset
    ori = mp.ori + _roll_delta(R, mp.T_render[:3, :3])
    cost, tgt, dirs, inside = _matcher(pe, p, ori, tau, cfg, mp)
    use = inside & (cost < tau)
    if use.sum() < 6:
        return None, float("inf"), int(use.sum())
    e, g = tgt[use], dirs[use]
    X = Xc[use]
    r = np.einsum("ij,ij->i", g, p[use] - e)
    w = _tukey_weight(r, tau)
    w = w * np.where(mp.kind[use] == CREASE, cfg["crease_weight"], 1.0)
    c = R @ cfg["center"] + t  # rotation about the object's centre
    J = _jacobian(K, X, g, c)
    H = J.T @ (J * w[:, None])
    b = J.T @ (w * r)
    rho = float(np.sum(_tukey_rho(r, tau)))
    if cfg["w_box"] > 0:
        rb, wb, Jb = _box_terms(K, T, cfg, tau)
        wb = wb * cfg["w_box"] * float(use.sum())
        H += Jb.T @ (Jb * wb[:, None])
        b += Jb.T @ (wb * rb)
    if cfg["m_xyz"] is not None:
        rm, wm, Jm = _match_terms(K, T, cfg, tau)
        wm = wm * cfg["w_matches"] * float(use.sum()) / len(wm)
        H += Jm.T @ (Jm * wm[:, None])
        b += Jm.T @ (wm * rm)
    if cfg["rot_prior"] > 0:  # pull the rotation towards the start's: a deviation of 1 rad costs rot_prior px² per point
        wsum = float(w.sum())
        H[:3, :3] += cfg["rot_prior"] * wsum * np.eye(3)
        b[:3] += cfg["rot_prior"] * wsum * _rotvec(R @ cfg["R0"].T)
    if cfg["dof"] == "t":  # translation only
        H[:3, :] = 0.0
        H[:, :3] = 0.0
        H[:3, :3] = np.eye(3)
        b[:3] = 0.0
    A = H + lam * np.diag(np.diag(H) + 1e-9)
    try:
        d = -np.linalg.solve(A, b)
    except np.linalg.LinAlgError:
        return None, rho, int(use.sum())
    ang = float(np.linalg.norm(d[:3]))
    dR = rodrigues(d[:3], ang) if ang > 1e-12 else np.eye(3)
    Rn = dR @ R
    tn = c + d[3:] - Rn @ cfg["center"]
    return make_T(Rn, tn), rho, int(use.sum())


def _jacobian(K: np.ndarray, X: np.ndarray, a: np.ndarray, c: np.ndarray) -> np.ndarray:
    """(n, 6) derivatives of ``a . p`` (``p`` the projection of camera points ``X``, ``a`` (n, 2)) with respect to
    (omega, v): ``X' = exp(omega) (X - c) + c + v`` (rotation about ``c``)."""
    z = np.maximum(X[:, 2], 1e-6)
    fx, fy = K[0, 0], K[1, 1]
    du = np.stack([fx / z, np.zeros_like(z), -fx * X[:, 0] / z ** 2], 1)
    dv = np.stack([np.zeros_like(z), fy / z, -fy * X[:, 1] / z ** 2], 1)
    dr_dX = a[:, :1] * du + a[:, 1:] * dv
    return np.concatenate([np.cross(X - c, dr_dX), dr_dX], 1)  # (Y x dr) . omega = dr . (omega x Y)


def _box_terms(K: np.ndarray, T: np.ndarray, cfg: dict, tau: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Residuals, weights and Jacobian rows of the four box sides.

    ``d`` = how far the pose's projected box (its hull vertices) reaches past each observed side. A projection
    that falls short of a visible side (d < 0) is impossible and costs quadratically; one that reaches past it
    (d > 0) may be occlusion, so it costs with a Tukey biweight of scale ``tau`` (small overshoots pulled in,
    large ones taken as an occluded side and ignored).
    """
    Xc = cfg["hull"] @ T[:3, :3].T + T[:3, 3]
    p = _project(K, Xc)
    x0, y0, x1, y1 = cfg["box_sides"]
    idx = [int(np.argmin(p[:, 0])), int(np.argmax(p[:, 0])), int(np.argmin(p[:, 1])), int(np.argmax(p[:, 1]))]
    a = np.array([[-1.0, 0.0], [1.0, 0.0], [0.0, -1.0], [0.0, 1.0]])
    d = np.array([x0 - p[idx[0], 0], p[idx[1], 0] - x1, y0 - p[idx[2], 1], p[idx[3], 1] - y1])
    w = np.where(d < 0, 1.0, _tukey_weight(d, tau))
    c = T[:3, :3] @ cfg["center"] + T[:3, 3]
    return d, w, _jacobian(K, Xc[idx], a, c)


def _match_terms(K: np.ndarray, T: np.ndarray, cfg: dict, tau: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Residuals (2n,), Tukey weights and Jacobian rows (2n, 6) of the matcher's 2D–3D correspondences: the
    projection of each object point minus its photo point (crop px), x then y rows, one weight per point (on its
    distance) with scale ``max(match_px, tau)``."""
    Xc = cfg["m_xyz"] @ T[:3, :3].T + T[:3, 3]
    d = _project(K, Xc) - cfg["m_uv"]
    w = _tukey_weight(np.linalg.norm(d, axis=1), max(cfg["match_px"], tau))
    c = T[:3, :3] @ cfg["center"] + T[:3, 3]
    n = len(Xc)
    ex, ey = np.tile([1.0, 0.0], (n, 1)), np.tile([0.0, 1.0], (n, 1))
    J = np.concatenate([_jacobian(K, Xc, ex, c), _jacobian(K, Xc, ey, c)])
    return np.concatenate([d[:, 0], d[:, 1]]), np.concatenate([w, w]), J


def _match_cost(K: np.ndarray, T: np.ndarray, cfg: dict, tau: float) -> float:
    """Mean Tukey cost of the matcher's correspondences (see :func:`_match_terms`)."""
    Xc = cfg["m_xyz"] @ T[:3, :3].T + T[:3, 3]
    return float(np.mean(_tukey_rho(np.linalg.norm(_project(K, Xc) - cfg["m_uv"], axis=1), max(cfg["match_px"], tau))))


def _box_cost(K: np.ndarray, T: np.ndarray, cfg: dict, tau: float) -> float:
    d, _, _ = _box_terms(K, T, cfg, tau)
    rho = np.where(d < 0, 0.5 * d ** 2, _tukey_rho(d, tau))
    return float(rho.sum())


def _region_steps(fg: np.ndarray, xy: np.ndarray, outward: np.ndarray, reach: float,
                  min_step: float = 0.2) -> tuple[np.ndarray, np.ndarray]:
    """Where the foreground posterior ``fg`` steps from object to background along each point's outward normal.

    Samples ``fg`` every crop px over ``[-reach, reach]`` along ``outward`` from ``xy`` and takes the boundary
    ``d`` that maximises the likelihood of a step: foreground before ``d``, background after it
    (``sum log fg`` inside + ``sum log (1 - fg)`` outside), the region-based contour of PWP3D / SRT3D found by a 1D
    search instead of a density. Returns the offsets ``d`` (crop px, + = outwards) and whether each point has a
    step: the mean posterior inside it exceeds the one outside by ``min_step`` (points off the crop have none).
    """
    S = fg.shape[0]
    r = max(int(np.ceil(reach)), 1)
    offs = np.arange(-r, r + 1, dtype=np.float64)  # sample offsets; boundaries lie between them
    q = xy[:, None, :] + offs[None, :, None] * outward[:, None, :]
    qx, qy = np.rint(q[..., 0]).astype(int), np.rint(q[..., 1]).astype(int)
    ok = (qx >= 0) & (qx < S) & (qy >= 0) & (qy < S)
    f = np.clip(fg[np.clip(qy, 0, S - 1), np.clip(qx, 0, S - 1)].astype(np.float64), 1e-3, 1 - 1e-3)
    f = np.where(ok, f, 0.5)
    lin, lout = np.log(f), np.log(1.0 - f)
    # boundary after sample k (k = 0 .. n-2): inside = samples 0..k, outside = k+1..n-1
    cin = np.cumsum(lin, axis=1)[:, :-1]
    cout = (np.cumsum(lout[:, ::-1], axis=1)[:, ::-1])[:, 1:]
    k = np.argmax(cin + cout, axis=1)
    d = offs[k] + 0.5
    n = len(offs)
    idx = np.arange(n)[None, :]
    inside = idx <= k[:, None]
    m_in = (f * inside).sum(1) / np.maximum(inside.sum(1), 1)
    m_out = (f * ~inside).sum(1) / np.maximum((~inside).sum(1), 1)
    has = (m_in - m_out >= min_step) & ok.all(axis=1)
    return d, has


def _matcher(pe, p, ori, tau, cfg, mp=None) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Each model point's correspondence: (cost (1e4 where none), target position (N, 2) crop px, target direction
    (N, 2) unit, along which the residual is measured, inside the allowed region). Edge search ('normal' or
    'nearest'), or with 'region' the silhouette points' targets are the foreground posterior's step along their
    outward normal (:func:`_region_steps`) and the creases keep their edges."""
    if cfg["search"] in ("normal", "region"):
        fg = cfg.get("fg")
        cost, edge, inside = _match_normal(pe, p, ori, tau, cfg["max_bin_gap"], fg,
                                           None if mp is None else mp.outward, cfg["min_contrast"])
    else:
        cost, edge, inside = _match(pe, p, ori, cfg["max_bin_gap"], cfg["bin_penalty"])
    has = edge >= 0
    tgt, dirs = np.full((len(p), 2), np.nan), np.full((len(p), 2), np.nan)
    tgt[has], dirs[has] = pe.edge_xy[edge[has]], pe.edge_dir[edge[has]]
    if cfg["search"] == "region" and mp is not None and cfg.get("fg") is not None:
        sil = mp.kind == SILHOUETTE
        d, ok = _region_steps(cfg["fg"], p[sil], mp.outward[sil], tau)
        n = mp.outward[sil]
        t_reg = p[sil] + d[:, None] * n
        # an edge within snap px of the region's step is the boundary, to sub-pixel; else the step itself
        near = has[sil] & (np.abs(np.einsum("ij,ij->i", np.nan_to_num(tgt[sil]) - t_reg, n)) <= cfg["region_snap"])
        take = ok & ~near
        if not cfg["region_fallback"]:  # a point without a step has no correspondence
            cost[sil] = np.where(ok, cost[sil], 1e4)
        cost[sil] = np.where(take, np.abs(d), cost[sil])
        tgt[sil] = np.where(take[:, None], t_reg, tgt[sil])
        dirs[sil] = np.where(take[:, None], n, dirs[sil])
    return cost, tgt, dirs, inside


def _rotvec(R: np.ndarray) -> np.ndarray:
    """Rotation vector (axis * angle, radians) of ``R``."""
    return cv2.Rodrigues(np.asarray(R, np.float64))[0].ravel()


def _robust_cost(K, T, mp, pe, tau, cfg) -> tuple[float, int]:
    R, t = T[:3, :3], T[:3, 3]
    p = _project(K, mp.xyz @ R.T + t) + mp.offset
    ori = mp.ori + _roll_delta(R, mp.T_render[:3, :3])
    cost, tgt, dirs, inside = _matcher(pe, p, ori, tau, cfg, mp)
    use = inside & (cost < 1e4)
    if not use.any():
        return float("inf"), 0
    e, g = tgt[use], dirs[use]
    r = np.einsum("ij,ij->i", g, p[use] - e)
    r = np.where(cost[use] < tau, r, tau)  # unmatched count as truncated
    rho = _tukey_rho(r, tau)
    w = np.where(mp.kind[use] == CREASE, cfg["crease_weight"], 1.0)
    # points that left the visible region count as truncated too, so a pose cannot win by hiding its points
    n_out = int((~use).sum())
    prior = cfg["rot_prior"] * float(np.sum(_rotvec(R @ cfg["R0"].T) ** 2)) / 2 if cfg["rot_prior"] > 0 else 0.0
    if cfg["w_box"] > 0:
        prior += cfg["w_box"] * _box_cost(K, T, cfg, tau)
    if cfg["m_xyz"] is not None:  # the same balance as in _lm_step: w_matches x the used contour points' weight
        prior += cfg["w_matches"] * _match_cost(K, T, cfg, tau) * float(use.sum()) / len(use)
    return float((np.sum(rho * w) + cfg["out_cost"] * n_out * tau ** 2 / 6) / len(use)) + prior, int(use.sum())


SEARCHES = ("normal", "nearest", "region")  # align()'s correspondence searches (config: align.search)


def align(renderer: Renderer, pe: PhotoEdges, T0: np.ndarray, center: np.ndarray | None = None,
          schedule: tuple[float, ...] = (8.0, 4.0, 2.0), iters: int = 6, n_points: int = 240,
          crease_weight: float = 0.5, crease_share: float = 0.3, max_bin_gap: int = 1, bin_penalty: float = 2.0,
          fit_px: float = 1.5, rerender: int = 2, rot_prior: float = 0.0, dof: str = "6",
          search: str = "normal", min_contrast: float = 0.0, w_box: float = 0.0,
          hull: np.ndarray | None = None, coarse: PhotoEdges | None = None,
          coarse_schedule: tuple[float, ...] = (8.0, 4.0), out_cost: float = 1.0,
          matches: tuple[np.ndarray, np.ndarray] | None = None, w_matches: float = 0.0,
          match_px: float = 10.0, face_parts: np.ndarray | None = None, drop_parts=(),
          box_taper: float = 1.0, region_snap: float = 0.0, region_fallback: bool = False) -> AlignResult:
    """Levenberg–Marquardt alignment of ``T0`` (photo camera) to the photo's edges, coarse to fine.

    Parameters
    ----------
    renderer : the object's renderer
    pe : :func:`photo_edges` of the photo
    T0 : (4, 4) starting pose (T_cam_from_obj, the photo's camera)
    center : rotation centre in the object frame (default: the mesh's centre)
    schedule : Tukey scales (crop px), one level each; the model is re-rendered ``rerender`` times per level
    iters : LM iterations per level
    rot_prior : pull towards the starting rotation: a deviation of 1 rad costs ``rot_prior`` px² per point
    dof : '6' (rotation and translation) or 't' (translation only)
    search : 'nearest' (directional chamfer: nearest same-orientation edge), 'normal' (along the model normal) or
        'region' (silhouette points: where the colour foreground posterior of the current silhouette against a band
        around it steps from object to background along the normal, :func:`_region_steps`; creases: 'normal')
    region_snap : with ``search='region'``: a silhouette point whose same-orientation edge along the normal lies
        within this many crop px of the region's step takes the edge (sub-pixel) instead; 0 = the step always
    region_fallback : with ``search='region'``: a silhouette point without a clear step (the posterior inside it
        exceeds the one outside by less than 0.2) keeps its edge; False = it has no correspondence
    min_contrast : with ``search='normal'``: silhouette points only take edges across which the foreground
        posterior (colours inside the current silhouette against a band around it) drops by this much
    w_box, hull : weight of each side of the given box against the contour points (its projection from the
        object points ``hull``, e.g. ``mesh.hull_vertices``; see :func:`_box_terms`); 0 = the box is not used
    out_cost : cost of a model point outside the allowed region (occluded), in units of a truncated point's
    coarse, coarse_schedule : a coarser :func:`photo_edges` of the same photo (e.g. half ``object_px``) aligned first
        over ``coarse_schedule`` (its crop px): a wider basin at the same Tukey scales
    matches, w_matches, match_px : 2D–3D correspondences (photo px (n, 2), object mm (n, 3)), e.g. the PnP inliers
        the start was solved from, as residuals of total weight ``w_matches`` x the contour points', Tukey scale
        ``max(match_px, tau)`` crop px: interior evidence the silhouette does not give; None or 0 = unused
    box_taper : the box sides' weight is ``w_box * box_taper ** k`` at the k-th Tukey scale (0 = the box only at the
        first, coarsest scale: it sets depth in the wide basin and leaves the final fit to the contour)
    face_parts, drop_parts : the mesh's part index per triangle and parts whose points are left out (parts the
        photo does not support, e.g. a missing part: :func:`pixie.cues.parts.robust_part_fit`)

    The model's silhouette points sit ``pe.sil_inset`` (and ``coarse.sil_inset``) photo px inside the outline, at every
    level and in the final fit (:func:`silhouette_outset`).
    """
    if search not in SEARCHES:
        raise ValueError(f"align: search must be one of {SEARCHES}, got {search!r}")
    if int(rerender) < 1:
        raise ValueError(f"align: rerender must be at least 1, got {rerender!r}")
    rerender = int(rerender)
    center = renderer.mesh.center if center is None else np.asarray(center, np.float64)
    cfg = {"max_bin_gap": int(max_bin_gap), "bin_penalty": float(bin_penalty), "crease_weight": float(crease_weight),
           "center": center, "rot_prior": float(rot_prior), "dof": str(dof), "search": str(search),
           "min_contrast": float(min_contrast), "w_box": float(w_box) if hull is not None or w_box == 0 else 0.0,
           "hull": None if hull is None else np.asarray(hull, np.float64), "box_sides": pe.box_sides,
           "out_cost": float(out_cost), "R0": np.asarray(T0, np.float64)[:3, :3], "m_xyz": None, "m_uv": None,
           "w_matches": float(w_matches), "match_px": float(match_px), "region_snap": float(region_snap),
           "region_fallback": bool(region_fallback)}
    use_matches = matches is not None and w_matches > 0 and len(matches[0]) >= 6
    T = np.asarray(T0, np.float64).copy()
    history, n_it, converged = [], 0, False
    levels = ([(coarse, tuple(coarse_schedule))] if coarse is not None else []) + [(pe, tuple(schedule))]
    w_box0, k_scale = cfg["w_box"], 0
    last = None  # (level, pose, its model points, those used: without dropped parts) of the latest render
    for lv, sched in levels:
        cfg["box_sides"] = lv.box_sides
        K = lv.K
        if use_matches:  # photo px -> this level's crop px (crop.A maps crop px to photo px)
            A = lv.crop.A
            cfg["m_uv"] = (np.asarray(matches[0], np.float64) - A[:, 2]) @ np.linalg.inv(A[:, :2]).T
            cfg["m_xyz"] = np.asarray(matches[1], np.float64)
        for tau in sched:
            cfg["w_box"] = w_box0 * float(box_taper) ** k_scale
            k_scale += 1
            cur = float("nan")  # no cost at this scale if no model point is left (e.g. every part dropped)
            for _ in range(rerender):
                if last is None or last[0] is not lv or not np.array_equal(last[1], T):
                    # a render (and its foreground map) depends on the pose and the level's camera only: the
                    # pose has not moved since the last one (LM converged or refused every step) -> reuse it
                    full = mp = model_points(renderer, T, K, lv.size, n_points, crease_share,
                                             silhouette_outset(lv))
                    if mp is not None and face_parts is not None and len(drop_parts):
                        mp = mp.subset(~np.isin(np.asarray(face_parts)[mp.tri], np.asarray(list(drop_parts))))
                        mp = mp if len(mp.xyz) >= 6 else None
                    if mp is None:
                        break
                    if min_contrast > 0 or search == "region":
                        cfg["fg"] = foreground_map(lv, mp.mask)
                    last = (lv, T.copy(), full, mp)
                mp = last[3]
                lam = 1e-3
                cur, _ = _robust_cost(K, T, mp, lv, tau, cfg)
                for _ in range(max(1, iters // rerender)):
                    Tn, _, n_used = _lm_step(K, T, mp, lv, tau, cfg, lam)
                    n_it += 1
                    if Tn is None:
                        break
                    new, _ = _robust_cost(K, Tn, mp, lv, tau, cfg)
                    if new <= cur:
                        step = np.linalg.norm(Tn[:3, 3] - T[:3, 3])
                        T, cur, lam = Tn, new, max(lam / 3, 1e-6)
                        if step < 1e-3:
                            converged = True
                            break
                    else:
                        lam *= 10
                        if lam > 1e4:
                            break
            history.append(cur if np.isfinite(cur) else float("nan"))
    same = last is not None and last[0] is pe and np.array_equal(last[1], T)  # the fit counts every part's points
    fit = edge_fit(renderer, pe, T, n_points=n_points, fit_px=fit_px, max_bin_gap=max_bin_gap,
                   points=last[2] if same else None, region=True, fg=cfg.get("fg") if same else None)
    return AlignResult(T_cam_from_obj=T, T_init=np.asarray(T0, np.float64), fit=fit, iterations=n_it,
                       converged=converged, history=history)


def silhouette_outset(pe: PhotoEdges) -> float:
    """Render px by which model silhouette points move outwards in ``pe``'s crop: half a pixel (the boundary pixel's
    centre to the outline) less the photo's silhouette inset ``pe.sil_inset`` (photo px; ``pe.scale`` photo px per
    crop px)."""
    return 0.5 - float(pe.sil_inset) / float(pe.scale)


def align_kwargs(ac) -> dict:
    """The keywords of :func:`align` that ``config.align`` (:class:`pixie.config.AlignConfig`) sets: the one map from
    the config to the solver (the estimator, the part report's re-alignment, benches and tests use it). The caller
    adds what belongs to the object and photo (``hull``, ``matches``, ``coarse``)."""
    return dict(schedule=tuple(ac.schedule), iters=ac.iters, rerender=ac.rerender, crease_weight=ac.crease_weight,
                rot_prior=ac.rot_prior,
                fit_px=ac.fit_px, search=ac.search, min_contrast=ac.min_contrast, w_box=ac.w_box,
                box_taper=ac.box_taper, w_matches=ac.w_matches, match_px=ac.match_px, region_snap=ac.region_snap,
                region_fallback=ac.region_fallback)


def coarse_levels(ac) -> int:
    """How many of ``ac.schedule``'s Tukey scales run on the coarse crop (``config.align``): 0 when ``coarse_px`` is 0;
    at most all but the last (the final fit is measured on the fine crop)."""
    return min(int(ac.coarse_levels), len(ac.schedule) - 1) if ac.coarse_px > 0 else 0


def coarse_kwargs(ac, coarse: PhotoEdges) -> dict:
    """The keywords of :func:`align` that run the first :func:`coarse_levels` Tukey scales of ``ac.schedule`` on
    ``coarse`` (:func:`photo_edges` of the same photo and box with ``object_px=ac.coarse_px``), their scales converted
    to its px."""
    n = coarse_levels(ac)
    f = float(ac.coarse_px) / float(ac.object_px)
    return {"coarse": coarse, "coarse_schedule": tuple(float(s) * f for s in ac.schedule[:n]),
            "schedule": tuple(float(s) for s in ac.schedule[n:])}


# The confidence's ``size`` term: the object's projected diameter / 100 px, clipped to what LM-O dev covers (its 1st
# to 99th percentile, 43-199 px): outside it the calibration says nothing, and a linear term would extrapolate.
SIZE_RANGE = (0.4, 2.0)


def confidence_size(diameter_px: float) -> float:
    """The calibrated confidence's ``size`` term of an object whose diameter projects to ``diameter_px`` photo px."""
    return float(np.clip(diameter_px / 100.0, *SIZE_RANGE))


def calibrated_confidence(ac, inputs: dict[str, float]) -> float:
    """``logistic(c0 + c1 * x1 + ...)``: ``config.align.confidence`` (intercept, then one coefficient per name of
    ``confidence_terms``) applied to a pose's ``inputs`` (its terms by name: fit, margin, size, ...).

    Raises
    ------
    ConfigError : the coefficients do not match the terms, or a term is not among ``inputs``
    """
    ac.check_confidence()
    coef, terms = list(ac.confidence), list(ac.confidence_terms)
    missing = [t for t in terms if t not in inputs or not np.isfinite(inputs[t])]
    if missing:
        raise ConfigError(f"align.confidence_terms uses {', '.join(missing)}, which this pose does not have "
                          f"(it has {', '.join(sorted(inputs))})")
    z = coef[0] + sum(c * float(inputs[t]) for c, t in zip(coef[1:], terms))
    return float(1.0 / (1.0 + np.exp(-np.clip(z, -500.0, 500.0))))


def photo_edges_kwargs(ac) -> dict:
    """The keywords of :func:`photo_edges` that ``config.align`` sets (the estimator, benches): the crop's object size
    the edge detector, the Canny thresholds and the silhouette inset."""
    return dict(object_px=ac.object_px, canny_low=ac.canny_low, canny_high=ac.canny_high, detector=ac.edge_detector,
                linear=ac.linear_edges, sil_inset=ac.silhouette_inset_px)


def edge_distances(pe: PhotoEdges, p: np.ndarray, ori: np.ndarray, max_bin_gap: int = 1,
                   fit_px: float = 1.5) -> tuple[np.ndarray, np.ndarray]:
    """Directional chamfer distance of points ``p`` (crop px, orientations ``ori``) to the nearest edge within
    ``max_bin_gap`` orientation bins: sub-pixel (to the matched edge's line) within ``fit_px`` + 1 px, the
    distance transform's beyond. Returns (distance (N,), 1e4 where none; the point lies in the allowed region (N,))."""
    cost, edge, inside = _match(pe, p, ori, max_bin_gap, 0.0)
    d = np.full(len(p), 1e4)
    ok = edge >= 0
    d[ok] = np.abs(np.einsum("ij,ij->i", pe.edge_dir[edge[ok]], p[ok] - pe.edge_xy[edge[ok]]))
    return np.where(cost < fit_px + 1.0, np.minimum(d, cost), cost), inside


def edge_fit(renderer: Renderer, pe: PhotoEdges, T: np.ndarray, n_points: int = 240, fit_px: float = 1.5,
             max_bin_gap: int = 1, crease_share: float = 0.3, points: ModelPoints | None = None,
             region: bool = False, fg: np.ndarray | None = None) -> EdgeFit:
    """The aligned fit of pose ``T``: see :class:`EdgeFit`. ``points``: :func:`model_points` of ``T`` in ``pe``'s
    camera with the same ``n_points`` / ``crease_share`` when the caller has them (not rendered again). ``region``:
    also the region and support shares, from ``fg`` (:func:`foreground_map` of those points' render) when given.
    Silhouette points rendered here sit ``pe.sil_inset`` photo px inside the outline (:func:`silhouette_outset`)."""
    mp = (model_points(renderer, T, pe.K, pe.size, n_points, crease_share, silhouette_outset(pe))
          if points is None else points)
    unsupported = 0.0 if region else float("nan")  # the region shares of a pose with no visible point
    none = EdgeFit(share=0.0, silhouette_share=0.0, visible=0.0, mean_dist=float("inf"), n_points=0,
                   region_share=unsupported, support_share=unsupported)
    if mp is None:
        return none
    p = _project(pe.K, mp.xyz @ T[:3, :3].T + T[:3, 3]) + mp.offset
    d, inside = edge_distances(pe, p, mp.ori, max_bin_gap, fit_px)
    if not inside.any():
        return none
    hit = d <= fit_px
    sil = mp.kind == SILHOUETTE
    vis_sil = inside & sil
    reg_share = sup_share = float("nan")
    if region:
        fg = foreground_map(pe, mp.mask) if fg is None else fg
        step, has = _region_steps(fg, p[sil], mp.outward[sil], fit_px + 2.0)
        reg = np.zeros(len(p), bool)
        reg[sil] = has & (np.abs(step) <= fit_px)
        reg_share = float(reg[vis_sil].mean()) if vis_sil.any() else 0.0
        sup_share = float((hit | reg)[inside].mean())
    return EdgeFit(share=float(hit[inside].mean()),
                   silhouette_share=float(hit[vis_sil].mean()) if vis_sil.any() else 0.0,
                   visible=float(inside.mean()), mean_dist=float(np.minimum(d[inside], 10.0).mean()),
                   n_points=int(inside.sum()), region_share=reg_share, support_share=sup_share)


# ------------------------------------------------------------------------------------------ pool helpers


def flip_twins(T: np.ndarray, center: np.ndarray, axes: str = "camera") -> list[np.ndarray]:
    """The pose turned 180° about axes through the object's centre: the camera's x and y axes (``axes='camera'``:
    silhouette flips, the outline mirrored), the object's own x, y and z axes (``'object'``: a near-box-shaped part
    modelled on its axes looks almost the same turned about one of them), or all five (``'both'``)."""
    if axes not in FLIP_AXES:
        raise ValueError(f"flip axes must be one of {FLIP_AXES}, not {axes!r}")
    R0 = np.asarray(T, np.float64)[:3, :3]
    c = R0 @ center + T[:3, 3]
    halves = [np.diag(d) for d in ([1.0, -1.0, -1.0], [-1.0, 1.0, -1.0], [-1.0, -1.0, 1.0])]  # about x, y, z
    Rs = [F @ R0 for F in halves[:2]] if axes in ("camera", "both") else []  # the camera's axes act on the left
    Rs += [R0 @ F for F in halves] if axes in ("object", "both") else []  # the model's own axes on the right
    return [make_T(R, c - R @ center) for R in Rs]
