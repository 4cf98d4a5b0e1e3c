"""The object without a box: propose (:class:`pixie.cues.detect.TemplateDetector`), estimate each proposal, keep the
poses the photo supports. "Not found" is a result, not a guess.

Each of the ``config.detect.proposals`` best proposals is estimated as if it were the given box
(:meth:`PoseEstimator.estimate`). Its named scores (:func:`proposal_terms`: the estimate's confidence and aligned
fit, the LINE-2D similarity, the pose's fit inside its own projected box ...) give its acceptance
(:func:`acceptance`, ``config.detect.accept``: the probability that the pose is right, calibrated on proposals of
the defects benchmark); a pose is kept when it is not ``failed`` and its acceptance reaches ``min_accept``. Kept
poses whose projected boxes overlap (IoU ≥ 0.5) are one instance: the most accepted stays. At most
``max_instances`` are returned, best first.

>>> found = find_objects(est, image, K, top_k=3)
>>> found.found, [r.T_cam_from_obj for r in found.poses], found.proposals[0].box_xywh
"""

from __future__ import annotations

import copy
import time
from dataclasses import dataclass, field
from typing import Callable

import cv2
import numpy as np

from pixie.cues.detect import Proposal, TemplateDetector
from pixie.cues.edge_align import edge_fit, photo_edges_kwargs
from pixie.cues.edge_photo import photo_edges
from pixie.errors import PixieError
from pixie.pose.results import PoseResult
from pixie.pose.solve import box_iou, projected_box, projected_box_in_image
from pixie.references.templates import ContourTemplates

__all__ = ["FindResult", "find_objects", "detector_for", "propose_kwargs"]


@dataclass(kw_only=True)
class FindResult:
    """What :func:`find_objects` found: the accepted poses (best first), every proposal and its verdict."""

    found: bool
    poses: list[PoseResult] = field(default_factory=list)
    accepts: list[float] = field(default_factory=list)  # per pose: its acceptance (how likely it is right)
    proposals: list[Proposal] = field(default_factory=list)
    verdicts: list[str] = field(default_factory=list)  # per proposal: 'kept', 'duplicate' or why it was rejected
    estimates: list[PoseResult | None] = field(default_factory=list)  # per proposal: its estimate (None: not estimated)
    terms: list[dict[str, float]] = field(default_factory=list)  # per proposal: its named scores (proposal_terms)
    timings: dict[str, float] = field(default_factory=dict)

    def to_dict(self) -> dict:
        return {"found": self.found, "instances": len(self.poses), "accepts": self.accepts,
                "proposals": [{"box_xywh": [float(v) for v in p.box_xywh], "score": p.score, "verdict": v,
                               **({"accept": x["accept"]} if "accept" in x else {})}
                              for p, v, x in zip(self.proposals, self.verdicts, self.terms)],
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
                                      diameter=est.refs.mesh.diameter, renderer=est.object_renderer(), **kw)
    return cache[key]


def propose_kwargs(dc) -> dict:
    """The keywords of :meth:`TemplateDetector.propose` that a ``config.detect`` section sets (all but ``top_k``)."""
    return dict(threshold=dc.threshold, nms_iou=dc.nms_iou, grow_ratio=dc.grow_ratio or None, vote_pool=dc.vote_pool,
                vote_weight=dc.vote_weight, vote_inside=dc.vote_inside, region_pool=dc.region_pool,
                region_weight=dc.region_weight, region_band=dc.region_band)


def _instance_mask(est, T: np.ndarray, K: np.ndarray, shape: tuple[int, int], grow_px: int = 4) -> np.ndarray:
    """The image pixels of the object at pose ``T``, grown by ``grow_px`` (what one found instance covers)."""
    m = est.object_renderer().render(T, np.asarray(K, np.float64), shape[0], shape[1]).mask.astype(np.uint8)
    return cv2.dilate(m, np.ones((2 * grow_px + 1, 2 * grow_px + 1), np.uint8)) > 0


def _without(image: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """``image`` with the ``mask`` region filled from its surroundings (``cv2.inpaint``): found instances no longer
    draw the next search, and the fill adds no contour of its own."""
    return cv2.inpaint(np.ascontiguousarray(image), mask.astype(np.uint8), 5, cv2.INPAINT_TELEA)


def find_objects(est, image: np.ndarray, K: np.ndarray, top_k: int | None = None, max_instances: int = 1,
                 min_accept: float | None = None, min_box_iou: float | None = None, threshold: float | None = None,
                 nms_iou: float | None = None, grow_ratio: float | None = None, stop_confidence: float | None = None,
                 progress: Callable[[str], None] | None = None, **detector_kw) -> FindResult:
    """Propose, estimate each of the ``top_k`` proposals, keep the supported poses (see the module docstring).

    Every option left ``None`` comes from the estimator's ``config.detect``. ``threshold``, ``nms_iou`` and
    ``grow_ratio`` (0: plain suppression) go to :meth:`TemplateDetector.propose`, the other keywords to
    :class:`TemplateDetector`. The remaining proposals are not estimated once ``max_instances`` poses are accepted
    at ``stop_confidence`` or more (their verdict says so; 0: every proposal is estimated).

    With ``max_instances`` > 1 the search is repeated: the photo's pixels covered by the instances found so far
    (their rendered masks, grown by 4 px) are filled in from their surroundings, the filled photo is searched again
    and its new proposals are estimated on the original photo, until ``max_instances`` are found or a round finds
    none (a copy's proposals would otherwise all sit on the first instance's parts)."""
    dc = copy.deepcopy(est.cfg.detect)
    for key, value in (("proposals", top_k), ("min_accept", min_accept), ("min_box_iou", min_box_iou),
                       ("threshold", threshold), ("nms_iou", nms_iou), ("grow_ratio", grow_ratio),
                       ("stop_confidence", stop_confidence)):
        if value is not None:
            setattr(dc, key, value)  # validated
    dc.check_accept()
    t0 = time.perf_counter()
    K = np.asarray(K, np.float64)
    det = detector_for(est, K, **detector_kw)
    t_build = time.perf_counter() - t0
    n_max = max(int(max_instances), 1)
    kept: list[tuple[PoseResult, np.ndarray, float]] = []  # pose, its projected box, its acceptance
    props_all: list[Proposal] = []
    verdicts: list[str] = []
    estimates: list[PoseResult | None] = []
    terms: list[dict[str, float]] = []
    t_propose = 0.0
    search, covered = image, np.zeros(image.shape[:2], bool)
    for _round in range(n_max):
        t = time.perf_counter()
        props = [p for p in det.propose(search, top_k=dc.proposals, **propose_kwargs(dc))
                 if not any(box_iou(p.box_xyxy, q) >= 0.5 for _, q, _ in kept)]
        t_propose += time.perf_counter() - t
        n_before = len(kept)
        for p in props:
            props_all.append(p)
            if dc.stop_confidence > 0 and sum(a >= dc.stop_confidence for _, _, a in kept) >= n_max:
                verdicts.append(f"not estimated: {n_max} accepted at {dc.stop_confidence:.2f} or more")
                estimates.append(None)
                terms.append({"line2d": p.score / 100.0})
                continue
            if progress is not None:
                progress(f"proposal {len(props_all)}")
            res = est.estimate(image, K, bbox=p.box_xywh)
            x = proposal_terms(est, image, K, p, res)
            x["accept"] = acceptance(dc, x)
            verdicts.append(_judge(est, K, res, x, dc, kept))
            estimates.append(res)
            terms.append(x)
        if len(kept) >= n_max or len(kept) == n_before:
            break
        for res, _, _ in kept[n_before:]:
            covered |= _instance_mask(est, res.T_cam_from_obj, K, image.shape[:2])
        search = _without(image, covered)
    kept.sort(key=lambda k: -k[2])
    return FindResult(found=bool(kept), poses=[r for r, _, _ in kept[:n_max]], accepts=[a for _, _, a in kept[:n_max]],
                      proposals=props_all, verdicts=verdicts, estimates=estimates, terms=terms,
                      timings={"templates": t_build, "propose": t_propose, "total": time.perf_counter() - t0})


def acceptance(dc, x: dict[str, float]) -> float:
    """How likely an estimated proposal's pose is right, from its named scores ``x`` (:func:`proposal_terms`):
    ``logistic(dc.accept[0] + dc.accept[1] * x[term1] + ...)`` over ``dc.accept_terms`` (``config.detect``), or,
    without coefficients, the estimate's own confidence. 0 for a failed estimate."""
    if x.get("failed", 1.0):
        return 0.0
    if not dc.accept:
        return float(x["confidence"])
    z = dc.accept[0] + sum(c * float(x.get(t, 0.0)) for c, t in zip(dc.accept[1:], dc.accept_terms))
    return float(1.0 / (1.0 + np.exp(-np.clip(z, -500.0, 500.0))))


def proposal_terms(est, image: np.ndarray, K: np.ndarray, p: Proposal, res: PoseResult) -> dict[str, float]:
    """The named scores of proposal ``p`` and its estimate ``res``: ``line2d`` (LINE-2D similarity / 100),
    ``confidence`` (the estimate's), ``box_iou`` (its pose's projected box against the proposal), the chosen
    hypothesis's terms (``fit``, ``fit_visible`` ...: the alignment's, inside the proposal box) and ``full_fit`` /
    ``full_silhouette`` / ``full_visible``: the pose's edge fit inside its *own* projected box (clipped to the image, grown
    as the alignment grows a box). A proposal on a part of the object can hold a pose of the whole whose contour leaves the
    proposal box; inside the box that contour is taken for occluded, inside the pose's own box it is judged."""
    x: dict[str, float] = {"line2d": p.score / 100.0, "confidence": float(res.confidence),
                           "failed": float(bool(res.failed or res.T_cam_from_obj is None))}
    if res.T_cam_from_obj is None:
        return x
    T = res.T_cam_from_obj
    pb = projected_box(T, K, est.box_points)
    x["box_iou"] = box_iou(pb, p.box_xyxy)
    if res.hypotheses:
        x.update({k: float(v) for k, v in res.hypotheses[0].terms.items() if v is not None})
    own = projected_box_in_image(T, K, est.box_points, image.shape)
    if own is None:
        x.update(full_fit=0.0, full_silhouette=0.0, full_visible=0.0)
        return x
    ac = est.cfg.align
    f = edge_fit(est.object_renderer(), photo_edges(image, K, own, **photo_edges_kwargs(ac)), T, fit_px=ac.fit_px)
    x.update(full_fit=f.share, full_silhouette=f.silhouette_share, full_visible=f.visible)
    return x


def _judge(est, K: np.ndarray, res: PoseResult, x: dict[str, float], dc, kept: list) -> str:
    """The verdict of an estimated proposal (its estimate ``res``, its terms ``x`` with ``accept``); an accepted pose
    joins ``kept`` (or replaces a less accepted duplicate: projected boxes at IoU >= 0.5)."""
    if res.T_cam_from_obj is None or res.failed:
        return f"rejected: {res.message or 'no pose'}"
    a = x["accept"]
    if a < dc.min_accept:
        what = "acceptance" if dc.accept else "confidence"
        return f"rejected: {what} {a:.2f} < {dc.min_accept:.2f}"
    if not dc.accept and x["box_iou"] < dc.min_box_iou:
        return f"rejected: the pose's box overlaps the proposal by IoU {x['box_iou']:.2f} < {dc.min_box_iou:.2f}"
    pb = projected_box(res.T_cam_from_obj, K, est.box_points)
    j = next((j for j, (_, q, _) in enumerate(kept) if box_iou(pb, q) >= 0.5), None)
    if j is not None:
        if a > kept[j][2]:
            kept[j] = (res, pb, a)
        return "duplicate"
    kept.append((res, pb, a))
    return "kept"
