"""Plausibility of an estimated pose against the box and intrinsics it was estimated from.

A pose can satisfy PnP and still contradict its own inputs: the object would lie behind the camera, or it
projects to a fraction (or a huge multiple) of the box it was found in, or mostly outside it. Such a pose
is flagged failed with the reason instead of being reported with confidence.
"""

from __future__ import annotations

import numpy as np

from pixie.geometry.camera import project, transform_points

# The object's projection may exceed the box of its visible part (occlusion) up to this factor along its
# longer side, and may be at most this much smaller than it.
MAX_PROJECTION_OVER_BOX = 4.0
MIN_PROJECTION_OVER_BOX = 0.5
MIN_BOX_COVERED = 0.5  # fraction of the box that the projection's box must cover


def pose_contradictions(T_cam_from_obj: np.ndarray, K: np.ndarray, box_xyxy: np.ndarray, points: np.ndarray,
                        center: np.ndarray, radius: float) -> list[str]:
    """Reasons why a pose contradicts the box (and K) it was estimated from; empty when it does not.

    Parameters
    ----------
    T_cam_from_obj : (4, 4) the pose, mm
    K : (3, 3) intrinsics of the image
    box_xyxy : (4,) the object's (visible) box in the image, pixel edges (x0, y0, x1, y1)
    points : (N, 3) object points whose projection bounds the object's (hull vertices), mm
    center, radius : the object's bounding sphere, mm

    Returns
    -------
    list of str
        One sentence per contradiction: camera inside the object or the object behind it; projection much
        smaller or larger than the box; the box mostly outside the projection.
    """
    T = np.asarray(T_cam_from_obj, np.float64)
    if not np.all(np.isfinite(T)):
        return ["the pose has non-finite entries"]
    c = transform_points(T, np.asarray(center, np.float64)[None])[0]
    if np.linalg.norm(c) <= radius:
        return [f"the camera would be inside the object (its centre {np.linalg.norm(c):.0f} mm away, "
                f"radius {radius:.0f} mm)"]
    pc = transform_points(T, np.asarray(points, np.float64))
    if pc[:, 2].min() <= 1e-6:
        return [f"the object would lie (partly) behind the camera (nearest point at z = {pc[:, 2].min():.0f} mm)"]
    uv = project(K, pc)
    # continuous extent [min, max] of the projected points -> pixel edges [min + 0.5, max + 0.5]
    p0, p1 = uv.min(0) + 0.5, uv.max(0) + 0.5
    b = np.asarray(box_xyxy, np.float64)
    bw, bh = b[2] - b[0], b[3] - b[1]
    pw, ph = p1 - p0
    out = []
    ratio = max(pw, ph) / max(bw, bh, 1e-9)
    if ratio < MIN_PROJECTION_OVER_BOX:
        out.append(f"the pose projects to {pw:.0f}x{ph:.0f} px, under {MIN_PROJECTION_OVER_BOX:g}x the "
                   f"{bw:.0f}x{bh:.0f} px box: the object would be {1 / ratio:.1f}x too far ({c[2]:.0f} mm)")
    elif ratio > MAX_PROJECTION_OVER_BOX:
        out.append(f"the pose projects to {pw:.0f}x{ph:.0f} px, over {MAX_PROJECTION_OVER_BOX:g}x the "
                   f"{bw:.0f}x{bh:.0f} px box: the object would be {ratio:.1f}x too close ({c[2]:.0f} mm)")
    iw = max(0.0, min(p1[0], b[2]) - max(p0[0], b[0]))
    ih = max(0.0, min(p1[1], b[3]) - max(p0[1], b[1]))
    covered = iw * ih / max(bw * bh, 1e-9)
    if covered < MIN_BOX_COVERED:
        out.append(f"only {100 * covered:.0f} % of the box lies inside the pose's projection "
                   f"(projected box {np.round([*p0, *p1]).astype(int).tolist()}, box {np.round(b).astype(int).tolist()})")
    return out
