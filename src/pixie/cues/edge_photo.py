"""The photo side of edge alignment: colour-gradient Canny edges of a crop around the object box, sub-pixel,
split into orientation bins with one distance transform (and nearest-edge label) per bin.

The crop is resampled so that the box's longer side spans ``object_px`` pixels; thresholds are in grey levels per
*photo* pixel so the same edges are found whatever the resampling. :func:`pixie.geometry.camera.crop_intrinsics` gives the crop's pinhole camera.

>>> pe = photo_edges(image, K, box_xyxy)          # once per photo; pe.K projects into the crop
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from pixie.cues.region import colour_index
from pixie.geometry.camera import crop_intrinsics
from pixie.pipeline.query import QueryCrop, square_crop

__all__ = ["DETECTORS", "PhotoEdges", "photo_edges"]

DETECTORS = ("canny", "edpf")


@dataclass(kw_only=True)
class PhotoEdges:
    """The photo's edges in a crop around the object box, ready for directional chamfer lookups.

    Attributes
    ----------
    crop : the (unrotated) square crop; ``crop.A`` maps crop px to photo px
    K : (3, 3) intrinsics of the crop's pixel grid
    size : crop side, px
    scale : photo px per crop px
    n_bins : orientation bins over [0, pi)
    dist : (n_bins, size, size) float32 distance (crop px) to the nearest edge pixel of each bin
    nearest : (n_bins, size, size) int32 index into ``edge_xy`` of that nearest edge
    index : (n_bins, size, size) int32 index into ``edge_xy`` of the edge at each pixel, -1 where none
    edge_xy : (M, 2) float64 sub-pixel edge positions (crop px); edge_dir : (M, 2) unit gradient directions
    edge_bin : (M,) int orientation bin of each edge
    allowed : (size, size) bool, where model points count as visible (the box + margin, the mask, the photo)
    box : (4,) the object box in crop px (x0, y0, x1, y1)
    box_sides : (4,) the box's outer pixel edges in crop px, pixel-centre coordinates (x0 - 0.5, ..., y1 - 0.5 in
        the photo): where the projected object's extremes lie when the box is exact
    valid : (size, size) bool, crop pixels inside the photo
    colour : (size, size) int32 joint RGB bin of each crop pixel (:func:`pixie.region.colour_index`)
    sil_inset : photo px by which this photo's silhouette edges lie inside the object's geometric outline (blur, and
        shading that falls off towards a curved outline); the alignment and the aligned fit move the model's
        silhouette points inwards by as much (:func:`pixie.cues.edge_align.silhouette_outset`; the part report's
        contour pixels are not moved)
    """

    crop: QueryCrop
    K: np.ndarray
    size: int
    scale: float
    n_bins: int
    dist: np.ndarray
    nearest: np.ndarray
    index: np.ndarray
    edge_xy: np.ndarray
    edge_dir: np.ndarray
    edge_bin: np.ndarray
    allowed: np.ndarray
    box: np.ndarray
    box_sides: np.ndarray
    valid: np.ndarray
    colour: np.ndarray
    sil_inset: float = 0.0

    def to_photo(self, xy: np.ndarray) -> np.ndarray:
        return self.crop.to_original(xy)


def _colour_gradients(image: np.ndarray, sigma: float) -> tuple[np.ndarray, np.ndarray]:
    """Sobel gradients (x, y) of the colour channel of largest magnitude per pixel (float32, raw Sobel units)."""
    img = image.astype(np.float32)
    if sigma > 0:
        img = cv2.GaussianBlur(img, (0, 0), sigma)
    gx = cv2.Sobel(img, cv2.CV_32F, 1, 0, ksize=3)
    gy = cv2.Sobel(img, cv2.CV_32F, 0, 1, ksize=3)
    if img.ndim == 3:
        ch = np.argmax(gx * gx + gy * gy, axis=2)[..., None]
        gx = np.take_along_axis(gx, ch, 2)[..., 0]
        gy = np.take_along_axis(gy, ch, 2)[..., 0]
    return gx, gy


def _subpixel(mag: np.ndarray, ys: np.ndarray, xs: np.ndarray, dx: np.ndarray, dy: np.ndarray) -> np.ndarray:
    """Offsets (along the unit gradient ``(dx, dy)``) of the magnitude's parabola vertex through 3 samples."""
    H, W = mag.shape
    sx, sy = np.rint(dx).astype(int), np.rint(dy).astype(int)
    x1, y1 = np.clip(xs + sx, 0, W - 1), np.clip(ys + sy, 0, H - 1)
    x0, y0 = np.clip(xs - sx, 0, W - 1), np.clip(ys - sy, 0, H - 1)
    step = np.hypot(sx, sy)  # 1 or sqrt(2) px between the samples
    return _parabola_vertex(mag[y0, x0], mag[ys, xs], mag[y1, x1]) * step


def _parabola_vertex(m0: np.ndarray, mc: np.ndarray, m1: np.ndarray, ok: np.ndarray | bool = True,
                     eps: float = 1e-6) -> np.ndarray:
    """Vertex of the parabola through samples ``m0, mc, m1`` (one step apart), in steps from ``mc``, clipped to
    [-0.5, 0.5]; 0 where not ``ok`` or the parabola is flat (|curvature| <= ``eps``)."""
    den = m0 - 2 * mc + m1
    ok = ok & (np.abs(den) > eps)
    return np.clip(np.where(ok, 0.5 * (m0 - m1) / np.where(ok, den, 1.0), 0.0), -0.5, 0.5)


def _srgb_to_linear(image: np.ndarray) -> np.ndarray:
    """Linear light (float32, 0..255) of an 8-bit sRGB image (the sRGB transfer curve)."""
    lut = np.arange(256, dtype=np.float64) / 255.0
    lut = np.where(lut <= 0.04045, lut / 12.92, ((lut + 0.055) / 1.055) ** 2.4) * 255.0
    return lut.astype(np.float32)[image]


def _linear_light_peaks(lin: np.ndarray, sigma: float, exy: np.ndarray, g: np.ndarray, reach: float,
                        step: float = 1.0) -> np.ndarray:
    """Offsets (crop px, along ``g``) from each edge position ``exy`` to the nearest maximum of the gradient magnitude
    of ``lin`` (the crop in *linear light*, :func:`_srgb_to_linear` before resampling) along ``g`` within ``reach``.

    A camera blurs light linearly and then encodes it with a concave curve (sRGB); the encoded gradient of a blurred
    step peaks on its dark side (by ~0.3-0.6 px for a blur of 1 px and a contrast of 4-10: bright objects look larger,
    dark ones smaller). In linear light the peak is the step itself. Hill-climbs from the edge (parabola vertex at the
    end), so a neighbouring stronger edge is not taken.
    """
    gx, gy = _colour_gradients(lin, sigma)  # the channel of largest magnitude = the largest magnitude
    mag = np.sqrt(gx * gx + gy * gy)
    n = max(int(np.ceil(reach / step)), 1)
    t = np.arange(-n, n + 1) * step
    q = exy[:, None, :] + t[None, :, None] * g[:, None, :]  # (M, 2n+1, 2)
    m = cv2.remap(mag, q[..., 0].astype(np.float32), q[..., 1].astype(np.float32), cv2.INTER_LINEAR,
                  borderMode=cv2.BORDER_REPLICATE).astype(np.float64)
    rows = np.arange(len(exy))
    k = np.full(len(exy), n)
    up = m[:, n + 1] > m[:, n - 1]  # climb towards the larger neighbour
    d = np.where(up, 1, -1)
    for _ in range(n):
        nxt = k + d
        ok = (nxt >= 0) & (nxt <= 2 * n) & (m[rows, np.clip(nxt, 0, 2 * n)] > m[rows, k])
        if not ok.any():
            break
        k = np.where(ok, nxt, k)
    km, kp = np.clip(k - 1, 0, 2 * n), np.clip(k + 1, 0, 2 * n)
    inner = (k > 0) & (k < 2 * n)  # a peak at the end of the reach has no vertex
    return t[k] + _parabola_vertex(m[rows, km], m[rows, k], m[rows, kp], inner, eps=1e-9) * step


def photo_edges(image: np.ndarray, K: np.ndarray, box_xyxy: np.ndarray, mask: np.ndarray | None = None,
                object_px: float = 200.0, pad: float = 1.5, n_bins: int = 16, sigma: float = 1.0,
                canny_low: float = 5.0, canny_high: float = 12.0, margin: float = 0.04,
                margin_px: float = 3.0, detector: str = "canny", linear: bool = False,
                sil_inset: float = 0.0) -> PhotoEdges:
    """Edges of the photo around ``box_xyxy`` (x0, y0, x1, y1), resampled so the box's longer side is ``object_px``.

    Parameters
    ----------
    image : (H, W, 3) uint8 RGB
    K : (3, 3) photo intrinsics
    mask : optional (H, W) bool object mask: model points outside it (dilated by the margin) are occluded
    object_px : the box's longer side in the crop, px
    pad : crop side / box's longer side
    n_bins : unsigned orientation bins
    sigma : Gaussian blur of the crop before the gradients, px
    canny_low, canny_high : hysteresis thresholds in grey levels per *photo* pixel (so the same edges are
        found whatever the resampling)
    margin, margin_px : the allowed region is the box grown by ``margin`` of its longer side + ``margin_px`` (photo px)
    detector : which pixels are edges: 'canny' (hysteresis on the colour gradient, ``canny_low`` / ``canny_high``),
        'edpf' (OpenCV's parameter-free Edge Drawing, ``cv2.ximgproc``, on each colour channel: edge chains kept only when
        their gradient is unlikely under noise, Helmholtz principle; the union over the channels). Orientation and
        sub-pixel position come from the colour gradient in both cases.
    linear : each edge's position is the nearest peak of the *linear-light* gradient along its gradient direction
        (within 1.5 photo px, :func:`_linear_light_peaks`): the sRGB curve moves an encoded edge towards the darker side
    sil_inset : photo px by which the photo's silhouette edges lie inside the geometric outline (kept on the result,
        :attr:`PhotoEdges.sil_inset`; ``config.align.silhouette_inset_px``)
    """
    if detector not in DETECTORS:
        raise ValueError(f"photo_edges: detector must be one of {DETECTORS}, got {detector!r}")
    box = np.asarray(box_xyxy, np.float64)
    L = float(max(box[2] - box[0], box[3] - box[1], 1.0))
    size = int(round(object_px * pad))
    crop = square_crop(image, box, pad, size)
    Kc = crop_intrinsics(K, crop.A)
    s = float(np.hypot(crop.A[0, 0], crop.A[1, 0]))  # photo px per crop px
    valid = cv2.warpAffine(np.full(image.shape[:2], 255, np.uint8), crop.A, (size, size),
                           flags=cv2.WARP_INVERSE_MAP | cv2.INTER_NEAREST, borderValue=0) > 0
    gx, gy = _colour_gradients(crop.image, sigma)
    # Sobel of a ramp of 1 grey level per crop px is 8; per photo px that ramp is 1/s levels
    lo, hi = 8.0 * canny_low * s, 8.0 * canny_high * s
    if detector == "edpf":
        ex = _edpf(crop.image)
    else:
        ex = cv2.Canny(np.clip(gx, -32767, 32767).astype(np.int16), np.clip(gy, -32767, 32767).astype(np.int16),
                       lo, hi, L2gradient=True) > 0
    ex &= cv2.erode(valid.astype(np.uint8), np.ones((5, 5), np.uint8)) > 0
    ys, xs = np.nonzero(ex)
    mag = np.hypot(gx, gy)
    g = np.stack([gx[ys, xs], gy[ys, xs]], 1).astype(np.float64)
    g /= np.maximum(np.linalg.norm(g, axis=1, keepdims=True), 1e-9)
    off = _subpixel(mag, ys, xs, g[:, 0], g[:, 1])
    exy = np.stack([xs, ys], 1).astype(np.float64) + off[:, None] * g
    if linear and len(xs):
        lin = square_crop(_srgb_to_linear(image), box, pad, size).image  # resampled in linear light
        exy = exy + _linear_light_peaks(lin, sigma, exy, g, max(1.5 / s, 2.0))[:, None] * g
        # the edge pixels follow their positions (one edge per pixel, the first kept)
        xs = np.clip(np.rint(exy[:, 0]).astype(int), 0, size - 1)
        ys = np.clip(np.rint(exy[:, 1]).astype(int), 0, size - 1)
        _, first = np.unique(ys * size + xs, return_index=True)
        first = np.sort(first)
        xs, ys, exy, g = xs[first], ys[first], exy[first], g[first]
    ang = np.mod(np.arctan2(g[:, 1], g[:, 0]), np.pi)
    eb = (np.floor(ang / (np.pi / n_bins) + 0.5).astype(int)) % n_bins
    dist = np.full((n_bins, size, size), 1e4, np.float32)
    nearest = np.full((n_bins, size, size), -1, np.int32)
    order = np.full((size, size), -1, np.int64)
    order[ys, xs] = np.arange(len(xs))
    for b in range(n_bins):
        sel = eb == b
        if not sel.any():
            continue
        src = np.ones((size, size), np.uint8)
        src[ys[sel], xs[sel]] = 0
        d, lab = cv2.distanceTransformWithLabels(src, cv2.DIST_L2, 5, labelType=cv2.DIST_LABEL_PIXEL)
        # label -> the edge pixel that carries it
        lut = np.full(int(lab.max()) + 1, -1, np.int64)
        lut[lab[ys[sel], xs[sel]]] = order[ys[sel], xs[sel]]
        dist[b] = d
        nearest[b] = lut[lab]
    # where model points count as visible
    box_c = np.concatenate([_to_crop(crop, box[:2]), _to_crop(crop, box[2:])])
    grow = (margin * L + margin_px) / s
    xx = np.arange(size)
    allowed = ((xx[None, :] >= box_c[0] - grow) & (xx[None, :] <= box_c[2] + grow)
               & (xx[:, None] >= box_c[1] - grow) & (xx[:, None] <= box_c[3] + grow)) & valid
    if mask is not None:
        mc = cv2.warpAffine(np.asarray(mask, np.uint8), crop.A, (size, size),
                            flags=cv2.WARP_INVERSE_MAP | cv2.INTER_NEAREST, borderValue=0)
        k = max(int(round(2 * grow)) | 1, 3)
        allowed &= cv2.dilate(mc, np.ones((k, k), np.uint8)) > 0
    index = np.full((n_bins, size, size), -1, np.int32)
    index[eb, ys, xs] = np.arange(len(xs))
    return PhotoEdges(crop=crop, K=Kc, size=size, scale=s, n_bins=n_bins, dist=dist, nearest=nearest, index=index,
                      edge_xy=exy, edge_dir=g, edge_bin=eb, allowed=allowed, box=box_c, valid=valid,
                      box_sides=np.concatenate([_to_crop(crop, box[:2] - 0.5), _to_crop(crop, box[2:] - 0.5)]),
                      colour=colour_index(crop.image), sil_inset=float(sil_inset))


def _edpf(image: np.ndarray) -> np.ndarray:
    """(H, W) bool edge pixels of parameter-free Edge Drawing (``cv2.ximgproc.createEdgeDrawing``, PFmode): the union
    of its edges on each colour channel."""
    ed = cv2.ximgproc.createEdgeDrawing()
    p = cv2.ximgproc_EdgeDrawing_Params()
    p.PFmode = True
    ed.setParams(p)
    out = np.zeros(image.shape[:2], bool)
    for c in range(image.shape[2]):
        ed.detectEdges(np.ascontiguousarray(image[..., c]))
        out |= ed.getEdgeImage() > 0
    return out


def _to_crop(crop: QueryCrop, uv: np.ndarray) -> np.ndarray:
    M, b = crop.A[:, :2], crop.A[:, 2]
    return np.linalg.solve(M, np.asarray(uv, np.float64) - b)


