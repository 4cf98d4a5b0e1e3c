"""Step 5 beyond the paper: render-at-estimate refinement.

The precomputed references sample the view sphere (121 views, 45° rolls) with a long-lens camera, so the
pose read off the best reference is 10–35° from the truth when the matcher is weak. Here the object is
rendered *at a pose hypothesis, inside the query crop itself*: the intrinsics of the crop follow from the
photo's K and the crop's affine map, so the render is pixel-aligned with the query when the hypothesis is
right, in the photo's own perspective. Matching the query against that render is the oracle setting
(the reference at the true view) as soon as the hypothesis is close; PnP on its matches gives the next
hypothesis.

Functions here are pure: the estimator owns the loop (:meth:`pixie.pipeline.estimator.PoseEstimator.render_refine`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pixie.references.encode import encode
from pixie.geometry.camera import crop_intrinsics
from pixie.geometry.rotations import lookup
from pixie.pose.solve import lift
from pixie.pipeline.query import QueryCrop
from pixie.geometry.render import Renderer


@dataclass
class AlignedRender:
    """The object rendered at ``T_cam_from_obj`` in the pixel grid of a query crop."""

    images: dict[str, np.ndarray]  # encoding name -> uint8 image (size x size)
    xyz: np.ndarray  # (size, size, 3) object-frame points, NaN off the object
    mask: np.ndarray  # (size, size) bool
    K_crop: np.ndarray
    T_cam_from_obj: np.ndarray


def render_in_crop(renderer: Renderer, T_cam_from_obj: np.ndarray, K: np.ndarray, crop: QueryCrop,
                   encodings: list[str]) -> AlignedRender:
    """Render the object at ``T_cam_from_obj`` (photo camera ``K``) into ``crop``'s pixel grid and encode it."""
    size = crop.image.shape[0]
    Kc = crop_intrinsics(K, crop.A)
    r = renderer.render(T_cam_from_obj, Kc, size, size)
    mask = r.mask
    xyz = r.xyz.astype(np.float32).copy()
    xyz[~mask] = np.nan
    images = {e: encode(e, r.depth, r.normals, mask) for e in encodings}
    return AlignedRender(images, xyz, mask, Kc, np.asarray(T_cam_from_obj, np.float64))


def keypoint_xyz(xyz: np.ndarray, keypoints: np.ndarray) -> np.ndarray:
    """Object point under each keypoint's nearest pixel of an :class:`AlignedRender` (NaN off the object)."""
    if len(keypoints) == 0:
        return np.zeros((0, 3), np.float32)
    return lookup(xyz, keypoints)


def aligned_correspondences(matcher, query_feats, crop: QueryCrop,
                            aligned: AlignedRender) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """2D (photo px) – 3D (object mm) correspondences and similarities, query crop vs. its aligned render.

    All encodings of ``aligned`` are matched and concatenated; render keypoints off the object are dropped
    (:func:`pixie.pose.solve.lift`).
    """
    p2s, p3s, scs = [], [], []
    for img in aligned.images.values():
        rf = matcher.extract(img, mask=aligned.mask)
        if len(rf.keypoints) == 0:
            continue
        p2, p3, sc = lift(query_feats.keypoints, keypoint_xyz(aligned.xyz, rf.keypoints), matcher.match(query_feats, rf))
        if not len(p2):
            continue
        p2s.append(crop.to_original(p2))
        p3s.append(p3)
        scs.append(sc)
    if not p2s:
        return np.zeros((0, 2)), np.zeros((0, 3)), np.zeros(0)
    return np.concatenate(p2s), np.concatenate(p3s), np.concatenate(scs)
