"""The query side: loading photos and object-centred square crops (optionally rotated)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from pixie.errors import ImageError


@dataclass
class QueryCrop:
    """A square crop of the query photo, resampled to ``size`` px.

    ``A`` maps crop pixels to original pixels: ``[u, v] = A @ [x, y, 1]``.
    """

    image: np.ndarray  # (size, size, 3) uint8
    mask: np.ndarray | None  # (size, size) bool
    A: np.ndarray  # (2, 3) crop -> original
    box_xyxy: np.ndarray  # the object's box in the original image
    angle_rad: float = 0.0

    def to_original(self, pts: np.ndarray) -> np.ndarray:
        """Crop pixel coordinates (N, 2) → original image coordinates."""
        return pts @ self.A[:, :2].T + self.A[:, 2]


def load_image(path: str | Path) -> np.ndarray:
    """Read an image as RGB uint8 (H, W, 3), with a clear error for missing or corrupt files."""
    path = Path(path)
    if not path.is_file():
        raise ImageError(f"image not found: {path}")
    img = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if img is None:
        raise ImageError(f"cannot decode image {path} (corrupt or not an image)")
    return img[..., ::-1].copy()


def bbox_from_mask(mask: np.ndarray) -> np.ndarray:
    """(x, y, w, h) box of a boolean mask; ImageError when the mask is empty."""
    ys, xs = np.nonzero(mask)
    if len(xs) == 0:
        raise ImageError("the object mask is empty")
    return np.array([xs.min(), ys.min(), xs.max() - xs.min() + 1, ys.max() - ys.min() + 1], np.float64)


def check_bbox(bbox, image_shape: tuple[int, int]) -> np.ndarray:
    """Validate an (x, y, w, h) box against the image; returns (x0, y0, x1, y1) clipped to the image."""
    b = np.asarray(bbox, dtype=np.float64).ravel()
    if b.shape != (4,) or not np.all(np.isfinite(b)):
        raise ImageError(f"bbox must be 4 finite numbers x,y,w,h; got {bbox!r}")
    h, w = image_shape
    x0, y0 = max(b[0], 0.0), max(b[1], 0.0)
    x1, y1 = min(b[0] + b[2], w), min(b[1] + b[3], h)
    if b[2] <= 1 or b[3] <= 1 or x1 - x0 < 2 or y1 - y0 < 2:
        raise ImageError(f"empty crop: bbox {b.tolist()} covers no part of the {w}x{h} image")
    return np.array([x0, y0, x1, y1])


def square_crop(image: np.ndarray, box_xyxy: np.ndarray, pad: float, size: int,
                angle_rad: float = 0.0, mask: np.ndarray | None = None) -> QueryCrop:
    """Object-centred square crop of side ``pad * max(w, h)``, resampled to ``size``.

    With ``angle_rad`` the crop is turned about its centre (content rotates by -angle, like a
    camera rolled by ``angle_rad``); pixels are sampled from the full photo, so no corners go black
    unless the crop leaves the photo.
    """
    # Box centre in pixel-centre coordinates (a box [x0, x1) of pixels has its centre at (x0+x1)/2 - 0.5).
    centre = 0.5 * np.array([box_xyxy[0] + box_xyxy[2], box_xyxy[1] + box_xyxy[3]]) - 0.5
    side = max(box_xyxy[2] - box_xyxy[0], box_xyxy[3] - box_xyxy[1]) * pad
    s = side / size
    c, si = np.cos(angle_rad), np.sin(angle_rad)
    Rm = np.array([[c, si], [-si, c]])  # Rz(angle)^T: crop offsets -> original offsets
    half = np.full(2, (size - 1) / 2.0)
    A = np.zeros((2, 3))
    A[:, :2] = s * Rm
    A[:, 2] = centre - s * Rm @ half
    src = image
    if s > 1.5:  # shrinking: low-pass first so the warp does not alias
        src = cv2.GaussianBlur(image, (0, 0), sigmaX=0.5 * s)
    img = cv2.warpAffine(src, A, (size, size), flags=cv2.WARP_INVERSE_MAP | cv2.INTER_LINEAR,
                         borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    m = None
    if mask is not None:
        m = cv2.warpAffine(mask.astype(np.uint8), A, (size, size), flags=cv2.WARP_INVERSE_MAP | cv2.INTER_NEAREST) > 0
    return QueryCrop(image=img, mask=m, A=A, box_xyxy=np.asarray(box_xyxy, np.float64), angle_rad=angle_rad)
