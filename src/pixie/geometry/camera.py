"""Pinhole camera (OpenCV convention) and rigid-pose helpers; the one reader of numbers, K and boxes from text.

Camera frame: x right, y down, z forward. A pixel's centre has integer coordinates,
so pixel (u, v) spans [u - 0.5, u + 0.5]. Poses are 4x4 ``T_cam_from_obj`` matrices.
"""

from __future__ import annotations

import re
import warnings
from typing import Any

import numpy as np

from pixie.errors import CameraError


def make_K(fx: float, fy: float, cx: float, cy: float) -> np.ndarray:
    """Build a 3x3 intrinsic matrix."""
    return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]], dtype=np.float64)


def _split_numbers(value: Any, kind: type = float) -> list:
    """Numbers of a text (separated by commas, semicolons or spaces) or a sequence; ValueError if one is not."""
    if isinstance(value, str):
        return [kind(v) for v in re.split(r"[,;\s]+", value.strip()) if v != ""]
    vals = np.asarray(value, dtype=np.float64).ravel()
    if kind is int and not all(float(v).is_integer() for v in vals if np.isfinite(v)):
        raise ValueError(value)
    return [kind(v) if np.isfinite(v) else float(v) for v in vals]


def parse_numbers(value: Any, what: str, count: int | None = None, kind: type = float, where: str = "",
                  error: type[Exception] = CameraError) -> list:
    """The one reader of comma-separated numbers (command-line options, manifest cells, K, boxes).

    ``what`` (an option or field name) and ``where`` (a manifest row ...) are named in the ``error`` raised for
    text that is not numbers, non-finite numbers, or not ``count`` of them.
    """
    at = f"{where}: " if where else ""
    try:
        vals = _split_numbers(value, kind)
    except (TypeError, ValueError):
        raise error(f"{at}{what} expects comma-separated {'whole ' if kind is int else ''}numbers, "
                    f"got {value!r}") from None
    if not all(np.isfinite(vals)):
        raise error(f"{at}{what} expects finite numbers, got {value!r}")
    if not vals or (count is not None and len(vals) != count):
        raise error(f"{at}{what} expects {count or 'some'} comma-separated numbers, got {value!r}")
    return vals


def parse_box(value: Any, what: str = "bbox", where: str = "", error: type[Exception] = CameraError) -> np.ndarray:
    """A box ``x,y,w,h`` (text or 4 numbers) as a float64 array (checked against an image by ``check_bbox``)."""
    return np.asarray(parse_numbers(value, what, 4, where=where, error=error), np.float64)


def parse_K(value: Any, what: str = "intrinsics", where: str = "", error: type[Exception] = CameraError) -> np.ndarray:
    """The one K reader: ``"fx,fy,cx,cy"``, nine row-major values (text or a sequence), or a 3x3 matrix.

    A 2-D array is returned as float64 unchanged (:func:`validate_K` checks it); text or a flat sequence of
    another length raises ``error`` naming ``what`` (and ``where``).
    """
    at = f"{where}: " if where else ""
    if not isinstance(value, str) and np.ndim(value) == 2:
        return np.asarray(value, dtype=np.float64)
    try:
        vals = _split_numbers(value)
    except (TypeError, ValueError) as exc:
        raise error(f"{at}cannot parse {what} {value!r}: expected 'fx,fy,cx,cy'") from exc
    if not all(np.isfinite(vals)):
        raise error(f"{at}{what} {value!r} have non-finite entries")
    if len(vals) == 4:
        return make_K(*vals)
    if len(vals) == 9:
        return np.asarray(vals, dtype=np.float64).reshape(3, 3)
    raise error(f"{at}{what} needs 4 values fx,fy,cx,cy (or 9), got {len(vals)} values: {value!r}")


def crop_K(K: np.ndarray, x0: float, y0: float, side: float, size: int) -> np.ndarray:
    """Intrinsics after cropping the square [x0, x0+side) x [y0, y0+side) and resizing it to ``size``.

    Uses the pixel-centre convention: the crop's pixel i covers original [x0 + i*s, x0 + (i+1)*s).
    """
    s = size / side
    return make_K(
        K[0, 0] * s,
        K[1, 1] * s,
        (K[0, 2] + 0.5 - x0) * s - 0.5,
        (K[1, 2] + 0.5 - y0) * s - 0.5,
    )


def crop_intrinsics(K: np.ndarray, A: np.ndarray) -> np.ndarray:
    """Intrinsics of the camera that sees an unrotated crop's pixel grid, the crop's pixels mapping to the photo's
    by ``A`` (2 x 3, ``u = M x + b``): ``A⁻¹ K``. With :func:`crop_K` (a square window resized) the one home of
    crop intrinsics.

    Raises
    ------
    CameraError
        For a rotated crop (its camera is not an upper-triangular K; render a rolled pose instead).
    """
    M, b = A[:, :2], A[:, 2]
    if abs(M[0, 1]) > 1e-9 or abs(M[1, 0]) > 1e-9:
        raise CameraError("crop_intrinsics needs an unrotated crop (angle 0)")
    Minv = np.linalg.inv(M)
    A_inv = np.eye(3)
    A_inv[:2, :2] = Minv
    A_inv[:2, 2] = -Minv @ b
    return A_inv @ np.asarray(K, np.float64)


def validate_K(K: np.ndarray, image_size: tuple[int, int] | None = None) -> np.ndarray:
    """Check that K is a usable pinhole matrix and return it as float64.

    Parameters
    ----------
    K : array_like, shape (3, 3)
    image_size : (height, width), optional
        When given, the principal point must lie inside the image.

    Raises
    ------
    CameraError
        Wrong shape, non-finite entries, non-positive focal lengths, a bottom row other than
        (0, 0, 1), or a principal point outside the image.
    """
    try:
        K = np.asarray(K, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise CameraError(f"K must be a 3x3 matrix of numbers, got {type(K).__name__}") from exc
    if K.shape != (3, 3):
        raise CameraError(f"K must be 3x3, got shape {K.shape}")
    if not np.all(np.isfinite(K)):
        raise CameraError("K has non-finite entries")
    if K[0, 0] <= 0 or K[1, 1] <= 0:
        raise CameraError(f"K has non-positive focal length (fx={K[0, 0]}, fy={K[1, 1]})")
    if not np.allclose(K[2], [0, 0, 1]) or abs(K[1, 0]) > 1e-9:
        raise CameraError(f"K's last row must be (0, 0, 1) and K[1,0] zero, got {K[2].tolist()}")
    if image_size is not None:
        h, w = image_size
        if not (0 <= K[0, 2] <= w and 0 <= K[1, 2] <= h):
            raise CameraError(
                f"principal point ({K[0, 2]:.1f}, {K[1, 2]:.1f}) lies outside the {w}x{h} image"
            )
    return K


def validate_pose(T: np.ndarray, name: str = "T_cam_from_obj") -> np.ndarray:
    """Check that T is a finite 4x4 rigid transform (orthonormal rotation, det +1)."""
    T = np.asarray(T, dtype=np.float64)
    if T.shape != (4, 4):
        raise CameraError(f"{name} must be 4x4, got shape {T.shape}")
    if not np.all(np.isfinite(T)):
        raise CameraError(f"{name} has non-finite entries")
    R = T[:3, :3]
    if not np.allclose(R @ R.T, np.eye(3), atol=1e-2) or np.linalg.det(R) < 0:  # BOP GT is off by ~2e-3
        raise CameraError(f"{name} rotation is not a proper rotation matrix")
    return T


def make_T(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Stack a rotation (3x3) and a translation (3,) into a 4x4 transform."""
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = np.asarray(t, dtype=np.float64).reshape(3)
    return T


def invert_T(T: np.ndarray) -> np.ndarray:
    """Inverse of a rigid 4x4 transform."""
    R, t = T[:3, :3], T[:3, 3]
    return make_T(R.T, -R.T @ t)


def transform_points(T: np.ndarray, X: np.ndarray) -> np.ndarray:
    """Apply a 4x4 transform to points of shape (..., 3)."""
    return X @ T[:3, :3].T + T[:3, 3]


def project(K: np.ndarray, X_cam: np.ndarray) -> np.ndarray:
    """Project camera-frame points (..., 3) to pixel coordinates (..., 2)."""
    z = X_cam[..., 2:3]
    uv1 = (X_cam / z) @ K.T
    return uv1[..., :2]


def backproject(K: np.ndarray, uv: np.ndarray, depth: np.ndarray) -> np.ndarray:
    """Back-project pixels (..., 2) with z-depth (...) to camera-frame points (..., 3)."""
    uv = np.asarray(uv, dtype=np.float64)
    x = (uv[..., 0] - K[0, 2]) / K[0, 0]
    y = (uv[..., 1] - K[1, 2]) / K[1, 1]
    z = np.asarray(depth, dtype=np.float64)
    return np.stack([x * z, y * z, z], axis=-1)


def backproject_depth(K: np.ndarray, depth: np.ndarray) -> np.ndarray:
    """Back-project a whole depth map (H, W) to camera-frame points (H, W, 3); 0 depth gives 0."""
    h, w = depth.shape
    v, u = np.mgrid[0:h, 0:w]
    return backproject(K, np.stack([u, v], axis=-1), depth)


def pixel_rays(K: np.ndarray, height: int, width: int) -> np.ndarray:
    """Ray directions (H, W, 3) through pixel centres, scaled so that z = 1."""
    v, u = np.mgrid[0:height, 0:width].astype(np.float64)
    d = np.empty((height, width, 3))
    d[..., 0] = (u - K[0, 2]) / K[0, 0]
    d[..., 1] = (v - K[1, 2]) / K[1, 1]
    d[..., 2] = 1.0
    return d


def rot_z(angle_rad: float) -> np.ndarray:
    """Rotation about the camera's optical axis (z) by ``angle_rad``."""
    c, s = np.cos(angle_rad), np.sin(angle_rad)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def look_at(eye: np.ndarray, target: np.ndarray, up: np.ndarray) -> np.ndarray:
    """``T_cam_from_obj`` of a camera at ``eye`` looking at ``target`` (object frame).

    The camera's -y axis (image up) is as close to ``up`` as possible.
    """
    eye, target, up = (np.asarray(a, dtype=np.float64) for a in (eye, target, up))
    z = target - eye
    z /= np.linalg.norm(z)
    if abs(np.dot(z, up / np.linalg.norm(up))) > 0.999:  # up parallel to the view: pick another
        up = np.array([1.0, 0.0, 0.0]) if abs(z[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    x = np.cross(z, up)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    R_obj_from_cam = np.stack([x, y, z], axis=1)
    return invert_T(make_T(R_obj_from_cam, eye))


def rotation_angle_deg(R_a: np.ndarray, R_b: np.ndarray) -> float:
    """Geodesic angle between two rotations, degrees."""
    c = (np.trace(R_a.T @ R_b) - 1.0) / 2.0
    return float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0))))


def optical_axis_in_object(T: np.ndarray) -> np.ndarray:
    """Unit viewing direction (camera z axis) expressed in the object frame."""
    return T[:3, :3].T @ np.array([0.0, 0.0, 1.0])


def scale_K(K: np.ndarray, sx: float, sy: float | None = None) -> np.ndarray:
    """Intrinsics of an image resized by (sx, sy), pixel-centre convention preserved."""
    sy = sx if sy is None else sy
    K2 = K.copy()
    K2[0, 0] *= sx
    K2[1, 1] *= sy
    K2[0, 2] = (K[0, 2] + 0.5) * sx - 0.5
    K2[1, 2] = (K[1, 2] + 0.5) * sy - 0.5
    return K2


# Fields of view a pinhole K can describe: outside them K is for another image size or in other units (mm).
FOV_LIMITS_DEG = (0.1, 170.0)
# Usual fields of view and pixel aspect: outside them K gets a warning.
FOV_USUAL_DEG = (1.0, 140.0)
ASPECT_USUAL = (0.8, 1.25)


def fields_of_view_deg(K: np.ndarray, image_size: tuple[int, int]) -> tuple[float, float]:
    """Horizontal and vertical field of view (degrees) of K over an image of (height, width)."""
    h, w = image_size
    return (float(np.degrees(2 * np.arctan2(w / 2.0, K[0, 0]))), float(np.degrees(2 * np.arctan2(h / 2.0, K[1, 1]))))


def intrinsics_warnings(K: np.ndarray, image_size: tuple[int, int]) -> list[str]:
    """Why a valid K looks unusual for an image of (height, width): field of view, pixel aspect, principal
    point far from the centre. Empty when nothing is unusual."""
    h, w = image_size
    out = []
    fov = fields_of_view_deg(K, image_size)
    lo, hi = FOV_USUAL_DEG
    if not all(lo <= f <= hi for f in fov):
        out.append(f"K gives a {fov[0]:.1f} x {fov[1]:.1f} deg field of view over the {w}x{h} image "
                   f"(usual: {lo:g}..{hi:g} deg); is K for this image size?")
    aspect = K[0, 0] / K[1, 1]
    if not ASPECT_USUAL[0] <= aspect <= ASPECT_USUAL[1]:
        out.append(f"K has fx/fy = {aspect:.2f} (fx {K[0, 0]:g}, fy {K[1, 1]:g}); square pixels give 1")
    off = max(abs(K[0, 2] - (w - 1) / 2) / w, abs(K[1, 2] - (h - 1) / 2) / h)
    if off > 0.3:
        out.append(f"K's principal point ({K[0, 2]:.1f}, {K[1, 2]:.1f}) is far from the centre of the {w}x{h} image")
    return out


def check_image_K(K: np.ndarray, image_size: tuple[int, int], warn: bool = True) -> np.ndarray:
    """:func:`validate_K` for a query image of (height, width), plus a field of view a pinhole camera can have.

    Unusual but possible intrinsics (:func:`intrinsics_warnings`) give a ``UserWarning`` when ``warn``.

    Raises
    ------
    CameraError
        As :func:`validate_K`, or a field of view outside ``FOV_LIMITS_DEG`` (a focal length of 4.2 px on a
        640 px image: K in mm, or for another resolution).
    """
    K = validate_K(K, image_size)
    h, w = image_size
    fov = fields_of_view_deg(K, image_size)
    lo, hi = FOV_LIMITS_DEG
    if not all(lo <= f <= hi for f in fov):
        raise CameraError(f"K (fx {K[0, 0]:g}, fy {K[1, 1]:g} px) gives a {fov[0]:.2f} x {fov[1]:.2f} deg field of "
                          f"view over the {w}x{h} image, impossible for a pinhole camera ({lo:g}..{hi:g} deg): "
                          "is the focal length in pixels and for this image size?")
    if warn:
        for msg in intrinsics_warnings(K, image_size):
            warnings.warn(msg, UserWarning, stacklevel=2)
    return K
