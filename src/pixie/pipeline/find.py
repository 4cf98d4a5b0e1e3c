"""The object without a box: propose (:class:`pixie.cues.detect.TemplateDetector`), estimate each proposal, keep the
poses the photo supports. "Not found" is a result, not a guess.

Each of the ``top_k`` proposals is estimated as if it were the given box (:meth:`PoseEstimator.estimate`); a pose
is kept when it is not ``failed``, its calibrated confidence (``config.align.confidence``: the estimated
probability that the pose is right, from its aligned edge fit) reaches ``min_confidence``, and its projected
box agrees with the proposal (IoU ≥ ``min_box_iou``: a pose that explains another part of the photo does not
confirm this proposal). Kept poses whose projected boxes overlap (IoU ≥ 0.5) are one instance: the most confident
stays. At most ``max_instances`` are returned, best first.

>>> found = find_objects(est, image, K, top_k=3)
>>> found.found, [r.T_cam_from_obj for r in found.poses], found.proposals[0].box_xywh
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Callable

import cv2
import numpy as np

from pixie.cues.detect import Proposal, TemplateDetector
from pixie.errors import PixieError
from pixie.pose.results import PoseResult
from pixie.pose.solve import box_iou, projected_box
from pixie.references.templates import ContourTemplates

__all__ = ["FindResult", "find_objects", "detector_for"]


@dataclass(kw_only=True)
class FindResult:
    """What :func:`find_objects` found: the accepted poses (best first), every proposal and its verdict."""

    found: bool
    poses: list[PoseResult] = field(default_factory=list)
    proposals: list[Proposal] = field(default_factory=list)
    verdicts: list[str] = field(default_factory=list)  # per proposal: 'kept', 'duplicate' or why it was rejected
    timings: dict[str, float] = field(default_factory=dict)

    def to_dict(self) -> dict:
        return {"found": self.found, "instances": len(self.poses),
                "proposals": [{"box_xywh": [float(v) for v in p.box_xywh], "score": p.score, "verdict": v}
                              for p, v in zip(self.proposals, self.verdicts)],
                "timings": self.timings}


def detector_for(est, K: np.ndarray, **kw) -> TemplateDetector:
    """The estimator's object as a :class:`TemplateDetector` for focal ``K`` (cached on the estimator per focal)."""
    if not est.refs.templates:
        raise PixieError("the reference set holds no contour templates: rebuild it with `pixie refs build`")
    cache = est.__dict__.setdefault("_detectors", {})
    key = (round(float(K[0, 0]), 3), tuple(sorted(kw.items())))
    if key not in cache:
        cache.clear()  # one focal at a time: templates are a few MB
        cache[key] = TemplateDetector(ContourTemplates.from_arrays(est.refs.templates), K,
                                      diameter=est.refs.mesh.diameter, **kw)
    return cache[key]


def _instance_mask(est, T: np.ndarray, K: np.ndarray, shape: tuple[int, int], grow_px: int = 4) -> np.ndarray:
    """The image pixels of the object at pose ``T``, grown by ``grow_px`` (what one found instance covers)."""
    m = est.object_renderer().render(T, np.asarray(K, np.float64), shape[0], shape[1]).mask.astype(np.uint8)
    return cv2.dilate(m, np.ones((2 * grow_px + 1, 2 * grow_px + 1), np.uint8)) > 0


def _without(image: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """``image`` with the ``mask`` region filled from its surroundings (``cv2.inpaint``): found instances no longer
    draw the next search, and the fill adds no contour of its own."""
    return cv2.inpaint(np.ascontiguousarray(image), mask.astype(np.uint8), 5, cv2.INPAINT_TELEA)


def find_objects(est, image: np.ndarray, K: np.ndarray, top_k: int = 3, max_instances: int = 1,
                 min_confidence: float = 0.5, min_box_iou: float = 0.5, threshold: float = 70.0,
                 nms_iou: float = 0.3, grow_ratio: float | None = 1.3, stop_confidence: float | None = 0.9,
                 progress: Callable[[str], None] | None = None, **detector_kw) -> FindResult:
    """Propose, estimate each of the ``top_k`` proposals, keep the supported poses (see the module docstring).

    ``threshold``, ``nms_iou`` and ``grow_ratio`` go to :meth:`TemplateDetector.propose`, the other keywords to
    :class:`TemplateDetector`. The remaining proposals are not estimated once ``max_instances`` poses are kept at
    ``stop_confidence`` or more (their verdict says so; ``None``: every proposal is estimated). On 56 held-out photos
    of the defects benchmark, 0.9 skipped 87 of 274 estimates with the same result for every photo (bench/RESULTS.md,
    "Session 17").

    With ``max_instances`` > 1 the search is repeated: the photo's pixels covered by the instances found so far
    (their rendered masks, grown by 4 px) are filled in from their surroundings, the filled photo is searched again
    and its new proposals are estimated on the original photo, until ``max_instances`` are found or a round finds
    none (a copy's proposals would otherwise all sit on the first instance's parts)."""
    t0 = time.perf_counter()
    K = np.asarray(K, np.float64)
    det = detector_for(est, K, **detector_kw)
    t_build = time.perf_counter() - t0
    n_max = max(int(max_instances), 1)
    kept: list[tuple[PoseResult, np.ndarray]] = []
    props_all: list[Proposal] = []
    verdicts: list[str] = []
    t_propose = 0.0
    search, covered = image, np.zeros(image.shape[:2], bool)
    for _round in range(n_max):
        t = time.perf_counter()
        props = [p for p in det.propose(search, top_k=top_k, threshold=threshold, nms_iou=nms_iou,
                                        grow_ratio=grow_ratio)
                 if not any(box_iou(p.box_xyxy, q) >= 0.5 for _, q in kept)]
        t_propose += time.perf_counter() - t
        n_before = len(kept)
        for p in props:
            props_all.append(p)
            if stop_confidence is not None and sum(r.confidence >= stop_confidence for r, _ in kept) >= n_max:
                verdicts.append(f"not estimated: {n_max} kept at confidence >= {stop_confidence:.2f}")
                continue
            if progress is not None:
                progress(f"proposal {len(props_all)}")
            verdicts.append(_verify(est, image, K, p, kept, min_confidence, min_box_iou))
        if len(kept) >= n_max or len(kept) == n_before:
            break
        for res, _ in kept[n_before:]:
            covered |= _instance_mask(est, res.T_cam_from_obj, K, image.shape[:2])
        search = _without(image, covered)
    kept.sort(key=lambda rp: -rp[0].confidence)
    poses = [r for r, _ in kept[:n_max]]
    return FindResult(found=bool(poses), poses=poses, proposals=props_all, verdicts=verdicts,
                      timings={"templates": t_build, "propose": t_propose, "total": time.perf_counter() - t0})


def _verify(est, image: np.ndarray, K: np.ndarray, p: Proposal, kept: list, min_confidence: float,
            min_box_iou: float) -> str:
    """Estimate proposal ``p``; a supported pose joins ``kept`` (or replaces a less confident duplicate). Returns the
    proposal's verdict."""
    res = est.estimate(image, K, bbox=p.box_xywh)
    if res.T_cam_from_obj is None or res.failed:
        return f"rejected: {res.message or 'no pose'}"
    pb = projected_box(res.T_cam_from_obj, K, est.box_points)
    iou = box_iou(pb, p.box_xyxy)
    if res.confidence < min_confidence:
        return f"rejected: confidence {res.confidence:.2f} < {min_confidence:.2f}"
    if iou < min_box_iou:
        return f"rejected: the pose's box overlaps the proposal by IoU {iou:.2f} < {min_box_iou:.2f}"
    j = next((j for j, (_, q) in enumerate(kept) if box_iou(pb, q) >= 0.5), None)
    if j is not None:
        if res.confidence > kept[j][0].confidence:
            kept[j] = (res, pb)
        return "duplicate"
    kept.append((res, pb))
    return "kept"
