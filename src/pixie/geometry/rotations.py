"""Small helpers every stage shares: rotations, nearest-pixel lookups and image checks.

Rotations
    :func:`rodrigues` (axis-angle -> matrix), :func:`rotation_between` (the smallest rotation taking one
    unit vector to another), :func:`orthonormalize` (nearest proper rotation of a 4x4 pose).
Pixel lookups
    :func:`nearest_pixel` (the integer pixel under each keypoint, clipped to the image) and
    :func:`lookup` (the values of a map there).
Image checks
    :func:`check_image` (the one rule for RGB input: ``uint8`` ``HxW``, ``HxWx1``, ``HxWx3`` or ``HxWx4``,
    alpha dropped) and :func:`check_mask`.

Conventions: keypoints are ``(x, y)`` pixels whose integer values are pixel centres (OpenCV).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from pixie.errors import ImageError

# ------------------------------------------------------------------------------------------------ rotations


def skew(v: np.ndarray) -> np.ndarray:
    """The 3x3 cross-product matrix ``[v]x`` (``skew(v) @ w == np.cross(v, w)``)."""
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def rodrigues(axis: np.ndarray, angle: float) -> np.ndarray:
    """Rotation matrix (3x3) of ``angle`` radians about ``axis`` (any length > 0), Rodrigues' formula."""
    a = np.asarray(axis, dtype=np.float64)
    k = skew(a / np.linalg.norm(a))
    return np.eye(3) + math.sin(angle) * k + (1.0 - math.cos(angle)) * (k @ k)


def rotation_between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The smallest rotation taking unit vector ``a`` onto unit vector ``b`` (identity when they coincide).

    Used to turn a camera so that a point seen along ``a`` is seen along ``b`` (keeping the in-plane roll), e.g.
    the optical axis onto a viewing ray. Parallel vectors (``|a x b| < 1e-12``) give exactly the identity; opposite
    ones, which have no unique answer, the half turn about the unit axis nearest the first coordinate axis
    perpendicular to ``a`` (about x for ``a = z``).
    """
    v, c = np.cross(a, b), float(np.dot(a, b))
    if np.linalg.norm(v) < 1e-12:
        if c > 0:
            return np.eye(3)
        a = np.asarray(a, np.float64)
        e = np.eye(3)[int(np.argmin(np.abs(a)))]
        u = e - np.dot(e, a) * a
        u /= np.linalg.norm(u)
        return 2.0 * np.outer(u, u) - np.eye(3)
    vx = skew(v)
    return np.eye(3) + vx + vx @ vx / (1.0 + c)


def orthonormalize(T: np.ndarray) -> np.ndarray:
    """Copy of a 4x4 pose whose rotation is replaced by the nearest proper rotation (SVD).

    BOP poses (GT included) are stored with few decimals and are only approximately
    orthonormal; the renderer requires exact rotations.
    """
    T = np.array(T, dtype=np.float64)
    u, _, vt = np.linalg.svd(T[:3, :3])
    if np.linalg.det(u @ vt) < 0:
        u[:, -1] *= -1
    T[:3, :3] = u @ vt
    return T


# ------------------------------------------------------------------------------------------ pixel lookups


def nearest_pixel(keypoints: np.ndarray, shape: tuple[int, ...]) -> tuple[np.ndarray, np.ndarray]:
    """Column and row (int64) of the pixel nearest to each ``(x, y)`` keypoint, clipped to ``shape`` ``(h, w)``."""
    h, w = int(shape[0]), int(shape[1])
    kp = np.asarray(keypoints).reshape(-1, 2)
    cols = np.clip(np.rint(kp[:, 0]).astype(np.int64), 0, w - 1)
    rows = np.clip(np.rint(kp[:, 1]).astype(np.int64), 0, h - 1)
    return cols, rows


def lookup(image: np.ndarray, keypoints: np.ndarray) -> np.ndarray:
    """Values of ``image`` (``HxW[xC]``) at the nearest pixel of each keypoint."""
    cols, rows = nearest_pixel(keypoints, image.shape)
    return image[rows, cols]


def in_mask(keypoints: np.ndarray, mask: np.ndarray | None) -> np.ndarray:
    """Boolean selector of the keypoints whose nearest pixel lies inside ``mask`` (all when no mask)."""
    if mask is None or len(keypoints) == 0:
        return np.ones(len(keypoints), dtype=bool)
    return lookup(mask, keypoints)


# ------------------------------------------------------------------------------------------- image checks


def check_image(image: Any, what: str = "image", min_side: int = 1) -> np.ndarray:
    """Validate an image and return it as contiguous ``uint8`` ``HxWx3`` RGB.

    Grey (``HxW``, ``HxWx1``) is repeated to three channels; an alpha channel (``HxWx4``) is dropped.

    Raises
    ------
    ImageError
        If it is not a uint8 array of one of those shapes, or a side is below ``min_side`` pixels.
    """
    if not isinstance(image, np.ndarray):
        raise ImageError(f"{what} must be a numpy array, got {type(image).__name__}")
    if image.dtype != np.uint8:
        raise ImageError(f"{what} must be uint8, got {image.dtype}")
    if image.ndim == 3 and image.shape[2] == 1:
        image = image[:, :, 0]
    if image.ndim == 2:
        image = np.repeat(image[:, :, None], 3, axis=2)
    if image.ndim != 3 or image.shape[2] not in (3, 4):
        raise ImageError(f"{what} must be HxW, HxWx3 (RGB) or HxWx4 (RGBA), got shape {image.shape}")
    if min(image.shape[:2]) < max(min_side, 1):
        raise ImageError(f"{what} is empty or too small: shape {image.shape}, needs at least {max(min_side, 1)} px "
                         "on each side")
    return np.ascontiguousarray(image[:, :, :3])


def check_mask(mask: Any, shape: tuple[int, int]) -> np.ndarray | None:
    """Validate an optional mask against an image ``(h, w)``; return a boolean ``HxW`` array or ``None``.

    Raises
    ------
    ImageError
        On a shape mismatch or a non-numeric mask.
    """
    if mask is None:
        return None
    arr = np.asarray(mask)
    if arr.ndim == 3 and arr.shape[2] == 1:
        arr = arr[:, :, 0]
    if arr.shape != tuple(shape):
        raise ImageError(f"mask shape {arr.shape} does not match the image size {tuple(shape)}")
    if arr.dtype != np.bool_:
        if not (np.issubdtype(arr.dtype, np.integer) or np.issubdtype(arr.dtype, np.floating)):
            raise ImageError(f"mask must be boolean, got {arr.dtype}")
        arr = arr != 0
    return arr
