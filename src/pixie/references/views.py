"""Reference viewpoints: 6 canonical box-aligned views + a Fibonacci sphere, with in-plane rolls.

Every view looks at the centre of the mesh's bounding box. In-plane rotations are made by rolling
the camera about its optical axis, so every rotated reference is a true render (no black corners).
"""

from __future__ import annotations

import numpy as np

from pixie.geometry.camera import crop_K, look_at, make_K, make_T, rot_z

# Box-aligned viewing directions (camera position relative to the centre, object frame) and up vectors.
CANONICAL_DIRECTIONS = np.array(
    [[0, 0, 1], [0, 0, -1], [1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0]], dtype=np.float64
)
CANONICAL_NAMES = ["top", "bottom", "right", "left", "back", "front"]


def fibonacci_sphere(n: int) -> np.ndarray:
    """``n`` unit vectors spread evenly over the sphere (Fibonacci lattice)."""
    if n <= 0:
        return np.zeros((0, 3))
    i = np.arange(n) + 0.5
    z = 1.0 - 2.0 * i / n
    r = np.sqrt(np.clip(1.0 - z * z, 0.0, None))
    phi = i * np.pi * (3.0 - np.sqrt(5.0))
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)


def max_angular_gap_deg(dirs: np.ndarray, n_probe: int = 20000) -> float:
    """Largest angle from any direction on the sphere to its nearest view direction (covering radius)."""
    probes = fibonacci_sphere(n_probe)
    d = dirs / np.linalg.norm(dirs, axis=1, keepdims=True)
    cos = np.clip((probes @ d.T).max(axis=1), -1.0, 1.0)
    return float(np.degrees(np.arccos(cos.min())))


def view_directions(n_fibonacci: int = 115, canonical: bool = True) -> np.ndarray:
    """Camera positions on the unit sphere (object frame): canonical first, then Fibonacci."""
    parts = [CANONICAL_DIRECTIONS] if canonical else []
    parts.append(fibonacci_sphere(n_fibonacci))
    return np.concatenate(parts, axis=0)


def up_vector(direction: np.ndarray) -> np.ndarray:
    """A stable 'up' for a camera at ``direction``: +z, or +y when looking along z."""
    return np.array([0.0, 1.0, 0.0]) if abs(direction[2]) > 0.95 else np.array([0.0, 0.0, 1.0])


def camera_distance(bounding_radius: float, focal_px: float, size_px: int, fill: float) -> float:
    """Distance at which a sphere of ``bounding_radius`` spans ``fill`` of a ``size_px`` image."""
    half_angle = np.arctan(fill * 0.5 * size_px / focal_px)
    return float(bounding_radius / np.sin(half_angle))


def view_poses(
    center: np.ndarray, distance: float, n_fibonacci: int = 115, canonical: bool = True
) -> np.ndarray:
    """``T_cam_from_obj`` (V, 4, 4) of every reference view, roll 0."""
    dirs = view_directions(n_fibonacci, canonical)
    return np.stack([look_at(center + distance * d, center, up_vector(d)) for d in dirs])


def roll(T_cam_from_obj: np.ndarray, angle_rad: float) -> np.ndarray:
    """Roll the camera by ``angle_rad`` about its optical axis (image content turns by -angle)."""
    return make_T(rot_z(angle_rad), np.zeros(3)) @ T_cam_from_obj


def roll_angles(rotations: int) -> np.ndarray:
    """In-plane angles (radians) 0, 2π/n, ..."""
    return np.arange(rotations) * (2.0 * np.pi / max(rotations, 1))


def square_crop_K(
    K: np.ndarray, T_cam_from_obj: np.ndarray, vertices: np.ndarray, size: int, pad: float
) -> tuple[np.ndarray, np.ndarray]:
    """Intrinsics of an object-centred square crop rendered directly at ``size`` px.

    The crop is centred on the bounding box of the projected vertices (= the silhouette's box)
    with side ``pad * max(w, h)``.

    Returns
    -------
    K_crop : (3, 3)
    box : (4,) x0, y0 (window corner in pixel-edge coordinates of ``K``, as :func:`crop_K`), side, and
        the scale size/side
    """
    X = vertices @ T_cam_from_obj[:3, :3].T + T_cam_from_obj[:3, 3]
    uv = (X[:, :2] / X[:, 2:3]) * [K[0, 0], K[1, 1]] + [K[0, 2], K[1, 2]]
    lo, hi = uv.min(axis=0), uv.max(axis=0)
    # the box centre in pixel-edge coordinates (crop_K's convention): pixel centres sit at +0.5
    centre = 0.5 * (lo + hi) + 0.5
    side = max(float((hi - lo).max()) * pad, 1.0)
    x0, y0 = centre[0] - side / 2, centre[1] - side / 2
    return crop_K(K, x0, y0, side, size), np.array([x0, y0, side, size / side])


def start_K(size: int, focal_factor: float) -> np.ndarray:
    """K_start: a square image of ``size`` px with the principal point at its centre."""
    f = focal_factor * size
    return make_K(f, f, (size - 1) / 2.0, (size - 1) / 2.0)
