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


# pose_warnings: a pose that its inputs make doubtful, said in the result's warnings (not failed: it may be right)
BOX_OUTSIDE_PX = 2.0  # a given box may run this far past the image edge (rounding, BOP's +1) without a word
WHOLE_IMAGE_FRACTION = 0.9  # a box covering this much of the image is not the object's box
MIN_DISTANCE_MM = 100.0  # nearer than this the object would fill the box only in macro photography
MAX_DISTANCE_MM = 20_000.0  # farther than this a part seen in a box of >= 10 px is implausible
WEAK_FIT = 0.2  # without PnP inliers, less edge agreement (aligned fit or shape-cue edge score) than this is no support


def box_warnings(given_xywh, image_shape: tuple[int, int]) -> list[str]:
    """Why a box (x, y, w, h as given, before clipping) does not look like the object's box in an image of
    (height, width): it runs past the image edge (x1,y1,x2,y2 given as x,y,w,h?), or it is (nearly) the whole image."""
    if given_xywh is None:
        return []
    x, y, w, h = (float(v) for v in np.asarray(given_xywh, np.float64).ravel()[:4])
    H, W = image_shape
    out = []
    over = {"left": -x, "top": -y, "right": x + w - W, "bottom": y + h - H}
    past = {k: v for k, v in over.items() if v > BOX_OUTSIDE_PX}
    if past:
        where = ", ".join(f"{v:.0f} px past the {k}" for k, v in past.items())
        hint = (f"; if it is x1,y1,x2,y2, give x,y,w,h = {x:g},{y:g},{w - x:g},{h - y:g}"
                if w > x and h > y and w <= W and h <= H else "")
        out.append(f"the box x,y,w,h = {x:g},{y:g},{w:g},{h:g} runs {where} edge of the {W}x{H} image and was "
                   f"clipped to it{hint}")
    inside = max(0.0, min(x + w, W) - max(x, 0.0)) * max(0.0, min(y + h, H) - max(y, 0.0))
    if inside >= WHOLE_IMAGE_FRACTION * W * H:
        out.append(f"the box covers {100 * inside / (W * H):.0f} % of the image: pixie does not search for the object, "
                   "it poses what fills the box, so give the object's own box")
    return out


def pose_warnings(K: np.ndarray, box_xyxy: np.ndarray, given_xywh, image_shape: tuple[int, int], diameter: float,
                  best=None) -> list[str]:
    """Why a pose may be wrong although nothing contradicts it outright: one sentence each, empty when none.

    * the box (:func:`box_warnings`);
    * the object's size against its distance: a ``diameter`` mm object fills the box only nearer than
      ``MIN_DISTANCE_MM`` (a mesh in cm read as mm, or a box far larger than the object), or the pose puts it
      beyond ``MAX_DISTANCE_MM``;
    * ``best`` (the chosen :class:`~pixie.pose.results.Hypothesis`) has no PnP inliers and little edge agreement.
    """
    out = box_warnings(given_xywh, image_shape)
    b = np.asarray(box_xyxy, np.float64)
    side = max(b[2] - b[0], b[3] - b[1], 1.0)
    f = float(np.mean([K[0, 0], K[1, 1]]))
    z_far = f * diameter / side  # the farthest the object can be and still span the box
    if z_far < MIN_DISTANCE_MM:
        out.append(f"a {diameter:.1f} mm object spans the {b[2] - b[0]:.0f}x{b[3] - b[1]:.0f} px box only within "
                   f"{z_far:.0f} mm of the camera (f {f:.0f} px): is the mesh in the right units (--units) and the "
                   "box the object's?")
    if best is None:
        return out
    T = np.asarray(best.T_cam_from_obj, np.float64)
    if np.all(np.isfinite(T)) and T[2, 3] > MAX_DISTANCE_MM:
        out.append(f"the pose puts the {diameter:.1f} mm object {T[2, 3] / 1000:.1f} m from the camera: is the mesh "
                   "in the right units (--units)?")
    edge = best.terms.get("fit", best.edge) if isinstance(getattr(best, "terms", None), dict) else best.edge
    if best.n_inliers == 0 and not (np.isfinite(edge) and edge >= WEAK_FIT):
        how = f"only {100 * edge:.0f} % edge agreement" if np.isfinite(edge) else "no edge check (shape, align off)"
        out.append(f"the pose has no PnP inliers and {how}: little supports it")
    return out
