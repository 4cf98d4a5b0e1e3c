"""From matches to scored poses: the one lift (2D–2D matches -> 2D–3D), PnP + RANSAC (PoseLib or OpenCV),
hypothesis scoring and the distance from the box.

Pure functions; the estimator (:mod:`pixie.pipeline.estimator`) chains them.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from pixie.geometry.camera import make_T, project, transform_points
from pixie.errors import ConfigError
from pixie.features import Matches

SCORINGS = ("inliers", "combined", "similarity", "combined_similarity", "excess", "combined_excess")
MIN_BACKGROUND_PAIRS = 8  # (view, roll) pairs with matches needed to estimate a query's background similarity


@dataclass
class PnPResult:
    """One PnP solution."""

    T_cam_from_obj: np.ndarray | None  # None when PnP failed
    inliers: np.ndarray  # indices into the correspondences
    n_correspondences: int
    reprojection_rmse: float = float("nan")

    @property
    def n_inliers(self) -> int:
        return int(len(self.inliers))

    @property
    def ok(self) -> bool:
        return self.T_cam_from_obj is not None


def lift(kpts_q: np.ndarray, ref_xyz: np.ndarray, matches: Matches) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """2D–3D correspondences from matches: query pixels, the object-space XYZ of the matched reference
    keypoints and each match's similarity. Every stage lifts with this function.

    Matches whose reference keypoint lies off the object (NaN XYZ) are dropped.

    Parameters
    ----------
    kpts_q : (N, 2) query keypoints
    ref_xyz : (M, 3) object point (mm) of each reference keypoint, NaN off the object
    matches : Matches between the two

    Returns
    -------
    pts2d : (K, 2) float64, query pixels
    pts3d : (K, 3) float64, object points (mm)
    sims : (K,) float64, the matcher's confidence of each kept match
    """
    X = ref_xyz[matches.idx_r]
    ok = np.all(np.isfinite(X), axis=1)
    return (kpts_q[matches.idx_q[ok]].astype(np.float64), X[ok].astype(np.float64),
            matches.scores[ok].astype(np.float64))


def solve_pnp_ransac(
    pts2d: np.ndarray,
    pts3d: np.ndarray,
    K: np.ndarray,
    iterations: int = 1000,
    threshold_px: float = 5.0,
    confidence: float = 0.9999,
    min_inliers: int = 6,
    solver: str = "opencv",
    seed: int = 0,
) -> PnPResult:
    """Robust PnP: RANSAC over EPnP/P3P minimal solutions, then refinement on the inliers.

    Parameters
    ----------
    pts2d : (N, 2) pixels (undistorted)
    pts3d : (N, 3) object points, mm
    K : (3, 3)
    iterations, threshold_px, confidence : RANSAC settings (the paper: 1000 iterations, 5 px)
    min_inliers : a solution with fewer inliers is reported as failed
    solver : 'opencv' or 'poselib'
    """
    n = len(pts2d)
    if n < max(min_inliers, 4):
        return PnPResult(None, np.zeros(0, int), n)
    if solver == "opencv":
        cv2.setRNGSeed(seed)
        ok, rvec, tvec, inl = cv2.solvePnPRansac(
            pts3d.reshape(-1, 1, 3), pts2d.reshape(-1, 1, 2), K, None,
            iterationsCount=int(iterations), reprojectionError=float(threshold_px),
            confidence=float(confidence), flags=cv2.SOLVEPNP_EPNP,
        )
        if not ok or inl is None or len(inl) < min_inliers:
            return PnPResult(None, np.zeros(0, int), n)
        inl = inl.ravel()
        rvec, tvec = cv2.solvePnPRefineLM(pts3d[inl].reshape(-1, 1, 3), pts2d[inl].reshape(-1, 1, 2), K, None, rvec, tvec)
        T = make_T(cv2.Rodrigues(rvec)[0], tvec.ravel())
    elif solver == "poselib":
        T = _poselib_pnp(pts2d, pts3d, K, iterations, threshold_px, confidence, seed)
        if T is None:
            return PnPResult(None, np.zeros(0, int), n)
    else:
        raise ConfigError(f"unknown PnP solver {solver!r}; use 'opencv' or 'poselib'")
    Xc = transform_points(T, pts3d)
    if np.any(Xc[:, 2] <= 0) and np.mean(Xc[:, 2] <= 0) > 0.5:  # behind the camera: not a pose
        return PnPResult(None, np.zeros(0, int), n)
    err = np.linalg.norm(project(K, Xc) - pts2d, axis=1)
    inl = np.nonzero((err < threshold_px) & (Xc[:, 2] > 0))[0]
    if len(inl) < min_inliers:
        return PnPResult(None, inl, n)
    return PnPResult(T, inl, n, float(np.sqrt(np.mean(err[inl] ** 2))))


def _poselib_pnp(pts2d, pts3d, K, iterations, threshold_px, confidence=0.9999, seed=0) -> np.ndarray | None:
    """PoseLib's LO-RANSAC over P3P with bundle adjustment on the inliers (about 20x faster than OpenCV here)."""
    try:
        import poselib
    except ImportError as exc:
        raise ConfigError("pose.solver=poselib needs the 'poselib' package (pip install poselib)") from exc
    h, w = 2 * K[1, 2] + 1, 2 * K[0, 2] + 1
    cam = {"model": "PINHOLE", "width": int(w), "height": int(h), "params": [K[0, 0], K[1, 1], K[0, 2], K[1, 2]]}
    pose, info = poselib.estimate_absolute_pose(
        pts2d, pts3d, cam,
        {"max_iterations": int(iterations), "max_reproj_error": float(threshold_px), "success_prob": float(confidence),
         "seed": int(seed)}, {}
    )
    if info.get("num_inliers", 0) == 0:
        return None
    return make_T(pose.R, pose.t)


def projected_box(T: np.ndarray, K: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Axis-aligned box (x0, y0, x1, y1) of projected object points."""
    uv = project(K, transform_points(T, points))
    return np.concatenate([uv.min(axis=0), uv.max(axis=0)])


def projected_box_in_image(T: np.ndarray, K: np.ndarray, points: np.ndarray, image_shape: tuple[int, int],
                           grow: float = 0.0) -> np.ndarray | None:
    """:func:`projected_box` grown by ``grow`` x its longer side on every side and clipped to the image
    (``image_shape`` = (H, W)); None when less than 2 px of it (either way) lies inside."""
    x0, y0, x1, y1 = projected_box(T, K, points)
    m = grow * max(x1 - x0, y1 - y0)
    h, w = image_shape[:2]
    b = np.array([max(x0 - m, 0.0), max(y0 - m, 0.0), min(x1 + m, w), min(y1 + m, h)])
    return b if b[2] - b[0] >= 2 and b[3] - b[1] >= 2 else None


def box_iou(a: np.ndarray, b: np.ndarray) -> float:
    """IoU of two (x0, y0, x1, y1) boxes."""
    iw = max(0.0, min(a[2], b[2]) - max(a[0], b[0]))
    ih = max(0.0, min(a[3], b[3]) - max(a[1], b[1]))
    inter = iw * ih
    union = (a[2] - a[0]) * (a[3] - a[1]) + (b[2] - b[0]) * (b[3] - b[1]) - inter
    return float(inter / union) if union > 0 else 0.0


def depth_from_box(T: np.ndarray, K: np.ndarray, points: np.ndarray, box_xyxy: np.ndarray, iterations: int = 3) -> np.ndarray:
    """Re-derive the distance of a pose from the size of the observed box, keeping its rotation.

    The object is moved along the ray through its centre (so it stays where PnP put it in the image) until
    its projected box matches the observed one; the larger of the width and height ratios is used, since
    occlusion shrinks a visible box along one side more often than along both. Perspective makes box size
    only nearly inverse to distance, so the ratio is applied ``iterations`` times.
    """
    ow, oh = box_xyxy[2] - box_xyxy[0], box_xyxy[3] - box_xyxy[1]
    out = T.copy()
    Rc = T[:3, :3] @ (0.5 * (points.min(axis=0) + points.max(axis=0)))
    for _ in range(max(1, iterations)):
        pb = projected_box(out, K, points)
        pw, ph = pb[2] - pb[0], pb[3] - pb[1]
        if min(pw, ph, ow, oh) <= 0 or not np.isfinite(pw + ph):
            return T
        s = max(ow / pw, oh / ph)
        out[:3, 3] = (Rc + out[:3, 3]) / s - Rc
    return out


def depth_from_visible_sides(T: np.ndarray, K: np.ndarray, points: np.ndarray, box_xyxy: np.ndarray,
                             tol_px: float = 2.0, iterations: int = 3) -> np.ndarray:
    """Distance (and image position) of a pose from the box sides that are not occluded.

    The pose's full projected box is compared with the observed box side by side: a side more than ``tol_px``
    inside the projection is taken as cut by an occluder and ignored. The object is then scaled about the
    image of its centre and shifted (least squares over the kept sides: ``side = c + d + s (side0 - c)``);
    with no complete pair of opposite sides the scale stays as it is and only the shift is fitted. Applied
    ``iterations`` times (perspective makes box size only nearly inverse to distance).
    """
    out = np.asarray(T, np.float64).copy()
    box = np.asarray(box_xyxy, np.float64)
    Rc = out[:3, :3] @ (0.5 * (points.min(axis=0) + points.max(axis=0)))
    for _ in range(max(1, iterations)):
        pb = projected_box(out, K, points)
        if not np.all(np.isfinite(pb)) or pb[2] - pb[0] < 1 or pb[3] - pb[1] < 1:
            return np.asarray(T, np.float64)
        obs = box[[0, 2, 1, 3]]  # x0, x1, y0, y1
        prj = pb[[0, 2, 1, 3]]
        # an observed side inside the projection by more than tol: cut by an occluder
        keep = np.array([obs[0] - prj[0], prj[1] - obs[1], obs[2] - prj[2], prj[3] - obs[3]]) <= tol_px
        ratios = [(obs[2 * k + 1] - obs[2 * k]) / (prj[2 * k + 1] - prj[2 * k]) for k in (0, 1) if keep[2 * k] and keep[2 * k + 1]]
        s = float(np.mean(ratios)) if ratios else 1.0
        C = out[:3, :3] @ (0.5 * (points.min(axis=0) + points.max(axis=0))) + out[:3, 3]
        uvC = np.array([K[0, 0] * C[0] / C[2] + K[0, 2], K[1, 1] * C[1] / C[2] + K[1, 2]])
        new_c = uvC.copy()
        for k in (0, 1):  # scale about the box centre, then shift onto the kept sides
            mid = 0.5 * (prj[2 * k] + prj[2 * k + 1])
            sides = [obs[j] - (mid + s * (prj[j] - mid)) for j in (2 * k, 2 * k + 1) if keep[j]]
            new_c[k] = mid + s * (uvC[k] - mid) + (float(np.mean(sides)) if sides else 0.0)
        z_new = C[2] / max(s, 1e-6)
        Cn = np.array([(new_c[0] - K[0, 2]) / K[0, 0] * z_new, (new_c[1] - K[1, 2]) / K[1, 1] * z_new, z_new])
        out[:3, 3] = Cn - Rc
    return out


# ------------------------------------------------------------------------------------------------ scoring


def background_similarity(sims_per_pair: list[np.ndarray]) -> float:
    """A query's background similarity: the median over (view, roll) pairs of their mean match similarity.

    Windowed mutual NN matches every view about equally often; what tells the right view apart is how much
    more similar its (inlier) matches are than this level ('*excess' scorings). It needs many pairs to be a
    background: with fewer than :data:`MIN_BACKGROUND_PAIRS` (e.g. a one-view reference set) it is 0.
    """
    means = [float(np.mean(s)) for s in sims_per_pair if len(s)]
    return float(np.median(means)) if len(means) >= MIN_BACKGROUND_PAIRS else 0.0


def pair_rank_score(sims: np.ndarray, background: float, ranking: str) -> float:
    """How strongly a (view, roll) pair's matches support it before PnP (``pose.candidate_ranking``).

    'excess' (default): summed similarity above the query's ``background`` level; 'count': the number of
    matches, which hardly separates views for windowed NN (every pair gets 60-100 matches on LM-O).
    """
    if ranking == "count":
        return float(len(sims))
    if ranking == "excess":
        return float(np.clip(sims - background, 0.0, None).sum()) + 1e-6 * len(sims)
    raise ConfigError(f"pose.candidate_ranking must be 'excess' or 'count', got {ranking!r}")


def hypothesis_score(scoring: str, n_inliers: int, inlier_sims: np.ndarray, background: float,
                     rot_to_ref_deg: float, iou: float) -> float:
    """Score of one PnP solution (``pose.scoring``, see :class:`pixie.config.PoseConfig`).

    The support is the inlier count ('inliers', 'combined'), the summed inlier similarity ('similarity',
    'combined_similarity') or that sum above the query's ``background`` ('excess', 'combined_excess'; plus a
    tiny inlier term: ties break by support and a valid pose never scores 0, i.e. 'failed'). The 'combined*'
    scorings multiply it by exp(-(rot/35°)²) of the angle to the reference view the solution came from
    (matching only works between similar viewpoints: this penalises flips) and by 0.25 + 0.75 IoU of the
    projected and observed boxes.
    """
    sim_sum = float(inlier_sims.sum())
    excess = max(0.0, float(np.sum(inlier_sims - background))) + 1e-3 * n_inliers
    support = {"inliers": float(n_inliers), "combined": float(n_inliers),
               "similarity": sim_sum, "combined_similarity": sim_sum,
               "excess": excess, "combined_excess": excess}.get(scoring)
    if support is None:
        raise ConfigError(f"pose.scoring must be one of {', '.join(repr(x) for x in SCORINGS)}, got {scoring!r}")
    if scoring.startswith("combined"):
        return support * float(np.exp(-((rot_to_ref_deg / 35.0) ** 2))) * (0.25 + 0.75 * iou)
    return support
