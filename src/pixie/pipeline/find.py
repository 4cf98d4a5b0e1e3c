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


def find_objects(est, image: np.ndarray, K: np.ndarray, top_k: int = 3, max_instances: int = 1,
                 min_confidence: float = 0.5, min_box_iou: float = 0.5,
                 progress: Callable[[str], None] | None = None, **detector_kw) -> FindResult:
    """Propose, estimate each of the ``top_k`` proposals, keep the supported poses (see the module docstring)."""
    t0 = time.perf_counter()
    det = detector_for(est, np.asarray(K, np.float64), **detector_kw)
    t_build = time.perf_counter() - t0
    props = det.propose(image, top_k=top_k)
    t_propose = time.perf_counter() - t0 - t_build
    kept: list[tuple[PoseResult, np.ndarray]] = []
    verdicts: list[str] = []
    for i, p in enumerate(props):
        if progress is not None:
            progress(f"proposal {i + 1}/{len(props)}")
        res = est.estimate(image, K, bbox=p.box_xywh)
        if res.T_cam_from_obj is None or res.failed:
            verdicts.append(f"rejected: {res.message or 'no pose'}")
            continue
        pb = projected_box(res.T_cam_from_obj, K, est.box_points)
        iou = box_iou(pb, p.box_xyxy)
        if res.confidence < min_confidence:
            verdicts.append(f"rejected: confidence {res.confidence:.2f} < {min_confidence:.2f}")
        elif iou < min_box_iou:
            verdicts.append(f"rejected: the pose's box overlaps the proposal by IoU {iou:.2f} < {min_box_iou:.2f}")
        elif (j := next((j for j, (_, q) in enumerate(kept) if box_iou(pb, q) >= 0.5), None)) is not None:
            verdicts.append("duplicate")
            if res.confidence > kept[j][0].confidence:
                kept[j] = (res, pb)
        else:
            verdicts.append("kept")
            kept.append((res, pb))
    kept.sort(key=lambda rp: -rp[0].confidence)
    poses = [r for r, _ in kept[:max(int(max_instances), 1)]]
    return FindResult(found=bool(poses), poses=poses, proposals=props, verdicts=verdicts,
                      timings={"templates": t_build, "propose": t_propose, "total": time.perf_counter() - t0})
