"""Pose tracking over an ordered sequence of photos: each result is the next frame's prior (``pixie track``).

Per frame, the previous pose is refined by :meth:`pixie.pipeline.estimator.PoseEstimator.estimate_from_prior`
(edge alignment only: no matching, no view search). When its aligned fit falls below ``align.reset_fit`` (or the
refinement fails) the pose is taken as lost and the frame gets the full search
(:meth:`~pixie.pipeline.estimator.PoseEstimator.estimate`) in the frame's box if one is given, else in the last
good pose's projected box; ``align.reset_ratio`` of the recent frames' median fit is the threshold when higher
(a wrong pose of a part keeps some fit: on the bench a 90° wrong prior aligns to 0.31-0.39, a tracked one to
0.57-0.64). The first frame starts from ``init_pose`` if given, else from the full search.

>>> steps = track(est, frames, init_pose=T0)        # frames: iterable of Frame
>>> [s.mode for s in steps]                         # 'prior' or 'search' per frame
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Iterable, Iterator

import numpy as np

from pixie.errors import PixieError
from pixie.geometry.camera import make_T, validate_pose
from pixie.pipeline.estimator import PoseEstimator
from pixie.pose.results import PoseResult
from pixie.pose.solve import projected_box_in_image

__all__ = ["Frame", "TrackStep", "Tracker", "track", "read_pose_file", "frame_paths"]


@dataclass(kw_only=True)
class Frame:
    """One photo of the sequence: RGB uint8 image, 3x3 K, optional box (x, y, w, h) and a name."""

    image: np.ndarray
    K: np.ndarray
    bbox: tuple[float, float, float, float] | None = None
    name: str = ""


@dataclass(kw_only=True)
class TrackStep:
    """What tracking did on one frame: ``mode`` 'prior' (refined the previous pose) or 'search' (full search,
    ``reason`` says why), the result and the seconds it took."""

    name: str
    mode: str
    reason: str
    result: PoseResult
    seconds: float


def _box_of(est: PoseEstimator, T: np.ndarray, K: np.ndarray, shape: tuple[int, int]) -> tuple[float, ...] | None:
    """The projected box (x, y, w, h) of pose ``T``, clipped to the image; None when it leaves the image."""
    b = projected_box_in_image(T, K, est.box_points, shape)
    return None if b is None else (b[0], b[1], b[2] - b[0], b[3] - b[1])


class Tracker:
    """The tracking state (the prior, the last good pose) and :meth:`step` for one frame.

    ``prior`` may be set between frames (a robot's expectation, a test's forced loss).
    """

    def __init__(self, est: PoseEstimator, init_pose: np.ndarray | None = None, reset_fit: float | None = None):
        self.est = est
        self.reset = est.cfg.align.reset_fit if reset_fit is None else float(reset_fit)
        self.prior = None if init_pose is None else np.asarray(init_pose, np.float64)
        self.last_good = self.prior
        self.ratio = est.cfg.align.reset_ratio
        self.fits: list[float] = []  # aligned fits of the frames tracked well so far (the recent ones count)

    def threshold(self) -> float:
        """The fit below which a refined prior counts as lost: ``align.reset_fit``, or ``align.reset_ratio`` of the
        median fit of the last 10 well-tracked frames when that is higher (a part's usual fit depends on its shape)."""
        recent = self.fits[-10:]
        return max(self.reset, self.ratio * float(np.median(recent))) if recent else self.reset

    def step(self, fr: Frame) -> TrackStep:
        """Refine the prior in ``fr`` (or search when it is lost or absent); the result becomes the next prior."""
        est, t0 = self.est, time.perf_counter()
        res, mode, reason = None, "prior", ""
        if self.prior is not None:
            try:
                res = est.estimate_from_prior(fr.image, fr.K, self.prior, bbox=fr.bbox)
            except PixieError as exc:  # the prior left the image, or sits behind the camera
                res, reason = None, f"prior unusable: {exc}"
            th = self.threshold()
            if res is not None and (res.failed or res.confidence < th):
                reason = (f"lost: {res.message}" if res.failed
                          else f"lost: aligned fit {res.confidence:.2f} < {th:.2f}")
                res = None
            elif res is not None:
                self.fits.append(float(res.confidence))
        if res is None:
            mode, reason = "search", reason or "no prior"
            box = fr.bbox
            for T in (self.last_good, self.prior):  # the last good pose: the object moved little since
                if box is None and T is not None:
                    box = _box_of(est, T, fr.K, fr.image.shape[:2])
            if box is None:
                raise PixieError(f"frame {fr.name or '?'}: no prior to refine and no box to search in "
                                 "(give the first frame's --bbox or an --init-pose)")
            res = est.estimate(fr.image, fr.K, bbox=box)
        if not res.failed and res.T_cam_from_obj is not None:
            self.last_good = res.T_cam_from_obj
        self.prior = self.last_good
        return TrackStep(name=fr.name, mode=mode, reason=reason, result=res, seconds=time.perf_counter() - t0)


def track(est: PoseEstimator, frames: Iterable[Frame], init_pose: np.ndarray | None = None,
          reset_fit: float | None = None) -> Iterator[TrackStep]:
    """Track the object over ``frames`` (in order); yields one :class:`TrackStep` per frame.

    Parameters
    ----------
    est : the estimator (its ``config.align`` sets the refinement)
    frames : the photos, in order
    init_pose : (4, 4) prior of the first frame (mm, OpenCV camera); None: the first frame is searched (it then
        needs a box)
    reset_fit : aligned fit below which a refined prior counts as lost (default ``align.reset_fit``)
    """
    tr = Tracker(est, init_pose, reset_fit)
    for fr in frames:
        yield tr.step(fr)


def read_pose_file(path: str | Path) -> np.ndarray:
    """A pose (4x4, mm, OpenCV camera) from a JSON file: a pixie result (``T_cam_from_obj``), ``{"R": ..., "t": ...}``
    (3x3 or 9 numbers; t in mm), BOP's ``cam_R_m2c`` / ``cam_t_m2c``, or a bare 4x4 list.

    Raises
    ------
    PixieError
        The file is missing or unreadable, or holds no valid rigid pose (the message names what is wrong).
    """
    p = Path(path)
    if not p.is_file():
        raise PixieError(f"pose file not found: {p}")
    try:
        d = json.loads(p.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise PixieError(f"pose file {p} is not readable JSON: {exc}") from None
    try:
        if isinstance(d, dict) and d.get("T_cam_from_obj") is not None:
            T = np.asarray(d["T_cam_from_obj"], np.float64)
        elif isinstance(d, dict) and ("R" in d or "cam_R_m2c" in d):
            R = np.asarray(d.get("R", d.get("cam_R_m2c")), np.float64).reshape(3, 3)
            t = np.asarray(d.get("t", d.get("cam_t_m2c")), np.float64).reshape(3)
            T = make_T(R, t)
        elif isinstance(d, list):
            T = np.asarray(d, np.float64)
        else:
            raise ValueError("expected T_cam_from_obj, R and t, cam_R_m2c and cam_t_m2c, or a 4x4 list")
        return validate_pose(T, f"pose in {p}")
    except (ValueError, TypeError) as exc:
        raise PixieError(f"pose file {p}: {exc}") from None


def frame_paths(folder: str | Path) -> list[Path]:
    """The photos of a sequence folder in name order (png, jpg, jpeg, bmp, tif)."""
    f = Path(folder)
    if not f.is_dir():
        raise PixieError(f"frames folder not found: {f}")
    out = sorted(p for p in f.iterdir() if p.suffix.lower() in (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff"))
    if not out:
        raise PixieError(f"no photos (png, jpg, bmp, tif) in {f}")
    return out
