"""The query side: loading photos and object-centred square crops (optionally rotated)."""

from __future__ import annotations

import os
import re
import warnings
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from PIL import Image

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


MAX_IMAGE_PIXELS = 100_000_000  # 100 MP: larger photos are refused from their header, before decoding
_EXIF_ORIENTATION = {2: "mirrored", 3: "rotated 180°", 4: "mirrored vertically", 5: "transposed",
                     6: "rotated 90° clockwise", 7: "transversed", 8: "rotated 90° counter-clockwise"}


def load_image(path: str | Path, max_pixels: int = MAX_IMAGE_PIXELS) -> np.ndarray:
    """Read an image as RGB uint8 (H, W, 3): the pixels as stored in the file.

    Grey, grey+alpha, palette, RGBA (alpha dropped), CMYK and 16-bit images are converted to 8-bit RGB
    (16-bit values scaled by 1/257).

    EXIF orientation is NOT applied: K and boxes describe the stored pixels (as OpenCV calibration and BOP
    do). A file whose EXIF tag asks viewers to rotate it gets a ``UserWarning`` saying so; rotate its pixels
    yourself (and give K and the box of the rotated image) if that is the image you calibrated.

    Raises
    ------
    ImageError
        Missing, empty, undecodable or truncated file; more than ``max_pixels`` pixels (checked from the
        header, before decoding); floating-point pixels.
    """
    if not isinstance(path, (str, os.PathLike)):
        raise ImageError(f"image path must be a str or Path, got {type(path).__name__}")
    path = Path(path)
    if not path.is_file():
        raise ImageError(f"image not found: {path}")
    if path.stat().st_size == 0:
        raise ImageError(f"image file is empty: {path}")
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", Image.DecompressionBombWarning)
            im = Image.open(path)
    except Image.DecompressionBombError as exc:  # Pillow's own limit, above ours: refused from the header too
        n = re.search(r"\((\d+) pixels\)", str(exc))
        size = f"{int(n.group(1)) / 1e6:.0f} MP" if n else "too many pixels"
        raise ImageError(f"image {path}: its header claims {size}; pixie reads at most {max_pixels / 1e6:.0f} MP: "
                         "resize it (and scale K and the box with it)") from exc
    except (OSError, ValueError, SyntaxError) as exc:  # UnidentifiedImageError is an OSError
        raise ImageError(f"cannot decode image {path} (corrupt or not an image)") from exc
    with im:
        w, h = im.size
        if w * h > max_pixels:
            raise ImageError(f"image {path} is {w}x{h} px ({w * h / 1e6:.0f} MP); pixie reads at most "
                             f"{max_pixels / 1e6:.0f} MP: resize it (and scale K and the box with it)")
        try:
            orientation = int(im.getexif().get(0x0112, 1) or 1)
        except (OSError, ValueError, TypeError, SyntaxError):  # an unreadable EXIF block: no orientation
            orientation = 1
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", Image.DecompressionBombWarning)
                im.load()
            rgb = _pil_to_rgb(im, path)
        except ImageError:
            raise
        except (OSError, ValueError, SyntaxError, EOFError) as exc:
            raise ImageError(f"cannot decode image {path}: the file is truncated or corrupt ({exc})") from exc
    if orientation in _EXIF_ORIENTATION:
        warnings.warn(f"image {path} has EXIF orientation {orientation} ({_EXIF_ORIENTATION[orientation]} for "
                      "display); pixie uses the pixels as stored, so K and the box must describe the stored "
                      "image, not the rotated view", UserWarning, stacklevel=2)
    return rgb


def _pil_to_rgb(im, path: Path) -> np.ndarray:
    """A loaded Pillow image as RGB uint8 (H, W, 3)."""
    if im.mode == "F":
        raise ImageError(f"image {path} has floating-point pixels; save it as 8- or 16-bit")
    if im.mode.startswith("I"):  # 16-bit (I;16*) or 32-bit integer grey: scale 0..65535 to 0..255
        a = np.asarray(im).astype(np.float64)
        g = np.clip(np.round(a / 257.0), 0, 255).astype(np.uint8)
        return np.repeat(g[..., None], 3, axis=2)
    return np.array(im.convert("RGB"), dtype=np.uint8)


def bbox_from_mask(mask: np.ndarray) -> np.ndarray:
    """(x, y, w, h) box of a boolean mask; ImageError when the mask is empty."""
    ys, xs = np.nonzero(mask)
    if len(xs) == 0:
        raise ImageError("the object mask is empty")
    return np.array([xs.min(), ys.min(), xs.max() - xs.min() + 1, ys.max() - ys.min() + 1], np.float64)


MIN_BOX_PX = (10, 4)  # a box (inside the image) needs this many pixels along its longer and shorter side


def check_bbox(bbox, image_shape: tuple[int, int]) -> np.ndarray:
    """Validate an (x, y, w, h) box against the image; returns (x0, y0, x1, y1) clipped to the image.

    Raises
    ------
    ImageError
        Not 4 finite numbers, no part inside the image, or smaller (inside the image) than
        ``MIN_BOX_PX``: too few pixels to match, and the box size sets the object's distance.
    """
    try:
        b = np.asarray(bbox, dtype=np.float64).ravel()
    except (TypeError, ValueError) as exc:
        raise ImageError(f"bbox must be 4 finite numbers x,y,w,h; got {bbox!r}") from exc
    if b.shape != (4,) or not np.all(np.isfinite(b)):
        raise ImageError(f"bbox must be 4 finite numbers x,y,w,h; got {bbox!r}")
    h, w = image_shape
    x0, y0 = max(b[0], 0.0), max(b[1], 0.0)
    x1, y1 = min(b[0] + b[2], w), min(b[1] + b[3], h)
    if b[2] <= 1 or b[3] <= 1 or x1 - x0 < 2 or y1 - y0 < 2:
        raise ImageError(f"empty crop: bbox {b.tolist()} covers no part of the {w}x{h} image")
    bw, bh = x1 - x0, y1 - y0
    if max(bw, bh) < MIN_BOX_PX[0] or min(bw, bh) < MIN_BOX_PX[1]:
        raise ImageError(f"bbox {b.tolist()} is too small: {bw:g}x{bh:g} px inside the image; a pose needs at least "
                         f"{MIN_BOX_PX[0]} px along the longer side and {MIN_BOX_PX[1]} along the shorter")
    return np.array([x0, y0, x1, y1])


def check_query_mask(mask, image_shape: tuple[int, int], box_xyxy: np.ndarray | None = None) -> np.ndarray:
    """A query mask as bool (H, W), checked against the image and (optionally) the box.

    Raises
    ------
    ImageError
        Not 2-D, of another size than the image, empty, or without a pixel inside ``box_xyxy``.
    """
    m = np.asarray(mask)
    if m.ndim == 3 and m.shape[2] in (1, 3, 4):
        m = m[..., 0]
    if m.ndim != 2:
        raise ImageError(f"the object mask must be a 2-D image, got shape {m.shape}")
    h, w = image_shape
    if m.shape != (h, w):
        raise ImageError(f"the object mask is {m.shape[1]}x{m.shape[0]} px but the image is {w}x{h} px")
    m = m.astype(bool)
    if not m.any():
        raise ImageError("the object mask is empty")
    if box_xyxy is not None:
        x0, y0, x1, y1 = (int(np.floor(box_xyxy[0])), int(np.floor(box_xyxy[1])), int(np.ceil(box_xyxy[2])),
                          int(np.ceil(box_xyxy[3])))
        if not m[y0:y1, x0:x1].any():
            raise ImageError(f"the object mask has no pixel inside the box {[x0, y0, x1 - x0, y1 - y0]}: "
                             "they describe different objects")
    return m


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


def grabcut_mask(image: np.ndarray, bbox_xywh, grow_px: int = 3, context: float = 0.5,
                 iters: int = 5) -> np.ndarray | None:
    """The object's pixels inside a box, segmented by colour alone (OpenCV's GrabCut initialised from the box).

    The box's surroundings (``context`` x its size on each side) teach the background colours; the box (grown by
    ``grow_px``) holds the object. Returns an (H, W) bool mask, or None when GrabCut keeps nothing in the box.
    """
    h, w = image.shape[:2]
    x, y, bw, bh = (float(v) for v in bbox_xywh)
    x0, y0 = max(int(np.floor(x - context * bw)), 0), max(int(np.floor(y - context * bh)), 0)
    x1, y1 = min(int(np.ceil(x + bw + context * bw)), w), min(int(np.ceil(y + bh + context * bh)), h)
    roi = np.ascontiguousarray(image[y0:y1, x0:x1, :3])
    rx0, ry0 = max(int(np.floor(x)) - grow_px - x0, 0), max(int(np.floor(y)) - grow_px - y0, 0)
    rx1 = min(int(np.ceil(x + bw)) + grow_px - x0, x1 - x0)
    ry1 = min(int(np.ceil(y + bh)) + grow_px - y0, y1 - y0)
    if rx1 - rx0 < 2 or ry1 - ry0 < 2:
        return None
    gm = np.zeros(roi.shape[:2], np.uint8)
    bgd, fgd = np.zeros((1, 65), np.float64), np.zeros((1, 65), np.float64)
    cv2.setRNGSeed(0)  # GrabCut's colour models start from k-means on OpenCV's RNG: the same photo, the same mask
    cv2.grabCut(cv2.cvtColor(roi, cv2.COLOR_RGB2BGR), gm, (rx0, ry0, rx1 - rx0, ry1 - ry0), bgd, fgd, iters,
                cv2.GC_INIT_WITH_RECT)
    fg = (gm == cv2.GC_FGD) | (gm == cv2.GC_PR_FGD)
    if not fg.any():
        return None
    out = np.zeros((h, w), bool)
    out[y0:y1, x0:x1] = fg
    return out
