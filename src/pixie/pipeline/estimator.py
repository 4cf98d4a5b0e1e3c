"""The pose pipeline in one place: crop → match → lift → PnP → score → view selection → refinement.

>>> refs = load_reference_set("ape.npz")
>>> est = PoseEstimator(refs)                      # the shipped 'default' preset; or a PixieConfig
>>> result = est.estimate(image, K, bbox=(x, y, w, h))
>>> result.T_cam_from_obj, result.score, result.failed

Longer than 500 lines on purpose: it is the one class that orders every stage (matcher, shape cues,
view selection, render refinement, input and plausibility checks); each stage's work lives in its own module.

:meth:`PoseEstimator.estimate` is one screen of stage calls; every stage is a public method that takes the
per-query record :class:`Query` (and returns new values), so studies can run, replace or inspect any stage::

    q = est.prepare(image, K, bbox)            # checks, crops, query features
    corr = est.match(q)                        # (view, roll) -> 2D-3D correspondences + similarities
    q.background = background_similarity(...) # the query's background match similarity
    hyps = est.solve(q, corr)                  # PnP per candidate view, scored
    hyps = est.select_views(q, hyps)           # the paper's view selection (+ re-crop)
    hyps = est.render_refine(q, hyps)          # render-at-estimate refinement (config.refine; off in 'default')
    hyps = est.shape_stage(q, hyps, timings)   # edge templates + edge/region verification (config.shape)
    hyps = est.align_stage(q, hyps)            # edge-based 6-DoF alignment, selection on the fit (config.align)
    result = est.result(hyps, timings, q)

:meth:`PoseEstimator.estimate_from_prior` skips the search: it aligns a given starting pose (the previous frame's
result, a robot's expectation) to the photo's edges and scores it (``pixie track``, ``--init-pose``).

The estimator keeps no per-query state: everything a query needs lives in its :class:`Query`, so one estimator
can serve queries from several threads.
"""

from __future__ import annotations

import copy
import logging
import time
from dataclasses import dataclass
from typing import Callable, NamedTuple

import numpy as np

from pixie.geometry.camera import (
    check_image_K,
    intrinsics_warnings,
    optical_axis_in_object,
    rotation_angle_deg,
    validate_pose,
)
from pixie.config import PixieConfig
from pixie.errors import ConfigError, ImageError
from pixie.features import Features
from pixie.geometry.rotations import check_image
from pixie.matching import Matcher, matcher_from_config
from pixie.pose.solve import (
    PnPResult,
    background_similarity,
    box_iou,
    depth_from_box,
    hypothesis_score,
    lift,
    pair_rank_score,
    projected_box,
    projected_box_in_image,
    solve_pnp_ransac,
)
from pixie.pose.plausibility import pose_contradictions, pose_warnings
from pixie.pipeline.query import (QueryCrop, bbox_from_mask, check_bbox, check_query_mask, grabcut_mask,
                                  square_crop)
from pixie.references.set import ReferenceSet, add_features
from pixie.cues.refine import aligned_correspondences, render_in_crop
from pixie.geometry.collide import part_solids
from pixie.geometry.render import Renderer
from pixie.cues.edge_align import (align, align_kwargs, calibrated_confidence, coarse_kwargs, coarse_levels,
                                   confidence_size, edge_fit, flip_twins, photo_edges, photo_edges_kwargs)
from pixie.cues.edges import EdgeQuery
from pixie.cues.part_paint import set_spill
from pixie.cues.parts import (complement_renderers, hidden_from_runner_up, is_flip_runner_up, judge_parts,
                              part_renderers, part_support, report_kwargs, robust_part_fit)
from pixie.cues.shape import fused_score, shape_cues
from pixie.pose.results import NO_BOX_MESSAGE, Hypothesis, PoseResult, set_confidences
from pixie.threads import map_threads
from pixie.references.views import roll_angles

log = logging.getLogger(__name__)

MIN_CROP_CONTRAST = 2.0  # grey-level std of the query crop below which nothing in it can be matched


class Correspondence(NamedTuple):
    """2D-3D correspondences of the query with one reference (view, roll), float64 (a named tuple: unpacks
    as ``pts2d, pts3d, sims``)."""

    pts2d: np.ndarray  # (N, 2) photo px
    pts3d: np.ndarray  # (N, 3) object mm
    sims: np.ndarray  # (N,) matcher similarities


Correspondences = dict[tuple[int, int], Correspondence]  # (view, roll) -> its correspondences


def typed_correspondences(corr: dict) -> Correspondences:
    """``corr`` with every value a :class:`Correspondence` (plain ``(pts2d, pts3d, sims)`` tuples accepted)."""
    return {k: c if isinstance(c, Correspondence) else Correspondence(*c) for k, c in corr.items()}


@dataclass
class Query:
    """One query photo as the stages see it: built by :meth:`PoseEstimator.prepare`, never stored on the estimator.

    Attributes
    ----------
    image : (H, W, 3) uint8 RGB
    K : (3, 3) intrinsics of ``image``
    box : (4,) float64, the object's box ``(x0, y0, x1, y1)`` in ``image``
    mask : (H, W) bool or None, the object mask used to keep query keypoints (``query.mask_keypoints``)
    crops : the square crops (one, or one per roll for ``match.in_plane=query``; ``crops[0]`` is unrotated)
    features : the query features of each crop
    background : the query's background match similarity (:func:`pixie.pose.solve.background_similarity`),
        set after :meth:`PoseEstimator.match`; 0 until then
    """

    image: np.ndarray
    K: np.ndarray
    box: np.ndarray
    mask: np.ndarray | None
    crops: list[QueryCrop]
    features: list[Features]
    background: float = 0.0
    box_source: str = "bbox"  # where ``box`` came from: 'bbox' (given) or 'mask' (the mask's box)
    edges: EdgeQuery | None = None  # the shape stage's edge query (config.shape), set by shape_stage
    best_match: float = 0.0  # best matcher score before shape verification (its scale), set by shape_stage
    photo_edges: object = None  # the alignment stage's PhotoEdges (config.align), set by align_stage
    photo_edges_coarse: object = None  # ... and those of its coarse crop (align.coarse_px > 0)
    box_given: np.ndarray | None = None  # the box (x, y, w, h) as given, before clipping (None: from the mask)


class PoseEstimator:
    """Estimate ``T_cam_from_obj`` of the reference set's object in RGB photos.

    Parameters
    ----------
    refs : ReferenceSet
    config : PixieConfig, optional
        The shipped ``default`` preset (``PixieConfig.from_preset()``) when omitted.
    matcher : pixie.matching.Matcher, optional
        Built from ``config.match`` when omitted. Reference features missing for this matcher are
        extracted once here (slow; store them with ``pixie refs build --matcher``).

    Attributes
    ----------
    encodings : the reference encodings matched
    pairs : the reference (view, roll) pairs the first pass matches, in bank order
    box_points : object points whose projection gives the object's image box (the convex hull's vertices:
        a vertex subsample makes boxes ~0.6 % small on LM-O, i.e. z ~0.6 % short)
    """

    def __init__(self, refs: ReferenceSet, config: PixieConfig | None = None, matcher: Matcher | None = None):
        if config is not None and not isinstance(config, PixieConfig):
            raise ConfigError(f"config must be a PixieConfig, got {type(config).__name__}")
        if not isinstance(refs, ReferenceSet):
            raise ConfigError(f"refs must be a ReferenceSet (pixie.load_reference_set), got {type(refs).__name__}")
        self.refs = refs
        # a private copy: the caller's config is never rewritten (e.g. in_plane below), and later edits of it
        # cannot change an estimator that is serving queries
        # no config: the shipped 'default' preset (what every command runs), not the bare dataclass defaults
        self.cfg = copy.deepcopy(config) if config is not None else PixieConfig.from_preset()
        m = self.cfg.match
        if self.cfg.pose.threshold_space not in ("image", "crop"):
            raise ConfigError(f"pose.threshold_space must be 'image' or 'crop', got {self.cfg.pose.threshold_space!r}")
        if m.in_plane not in ("reference", "query"):
            raise ConfigError(f"match.in_plane must be 'reference' or 'query', got {m.in_plane!r}")
        self.matcher = matcher or matcher_from_config(m, refs.size)
        self.encodings = [e for e in self.cfg.refs.encodings if e in refs.config.encodings] or refs.config.encodings
        if not refs.has_features(self.matcher.name, self.encodings):
            log.warning("reference set has no %s features for %s: extracting them now", self.matcher.name, self.encodings)
            add_features(refs, self.matcher, self.encodings)
        R = min(refs.feature_rolls(self.matcher.name, e) for e in self.encodings)
        if R == 1 and m.in_plane == "reference" and refs.n_rolls > 1:
            log.info("reference features exist for roll 0 only: rotating the query instead")
            self.cfg.match.in_plane = "query"
        rolls = list(range(R)) if self.cfg.match.in_plane == "reference" else [0]
        self.pairs = [(v, r) for v in range(refs.n_views) for r in rolls]
        self._pair_index = {p: i for i, p in enumerate(self.pairs)}
        self._banks, self._xyz = {}, {}
        for e in self.encodings:
            feats, xyz = refs.features_for(self.matcher.name, e)
            Re = refs.feature_rolls(self.matcher.name, e)
            keep = [v * Re + r for v, r in self.pairs]
            self._banks[e] = self.matcher.prepare_refs([feats[k] for k in keep])
            self._xyz[e] = [xyz[k] for k in keep]
        self._axes = np.stack([optical_axis_in_object(T) for T in refs.poses[:, 0]])
        self.box_points = refs.mesh.hull_vertices
        self._renderer = (Renderer(refs.mesh, smooth_normals=refs.config.smooth_normals)
                          if self.cfg.refine.render_iters > 0 else None)
        self._align_renderer = Renderer(refs.mesh, smooth_normals=True) if self.cfg.align.enabled else None
        self._part_renderers: list[Renderer] | None = None  # per part of the mesh, made on the first part report
        self._part_complements: list | None = None  # the mesh without each part (cues.parts.complement_renderers)
        self._part_solids = None  # the parts' voxel solids for the move search (geometry.collide.part_solids)
        self._shape = None
        if self.cfg.shape.enabled:
            self._shape = shape_cues(refs, self.cfg.shape)

    # ------------------------------------------------------------------------------------------------
    def estimate(self, image: np.ndarray, K: np.ndarray, bbox=None, mask: np.ndarray | None = None,
                 progress: Callable[[str], None] | None = None) -> PoseResult:
        """Pose of the object in ``image`` (RGB uint8) with intrinsics ``K``; crop from ``bbox`` or ``mask``.

        ``progress(stage)`` is called as each stage starts ('features', 'matching', 'pnp', 'view selection',
        'shape cues', 'alignment'): a command line shows it, so that no step of a few seconds is silent.

        ``bbox`` is (x, y, w, h) with ``w``, ``h`` counting pixels (OpenCV ``boundingRect``, COCO); BOP's stored
        boxes are one pixel smaller (:attr:`pixie.eval.datasets.GtInstance.box_visib` converts). Its size sets
        the object's distance (``pose.depth_from_bbox``), so a pixel matters on small objects.
        """
        t_all = time.perf_counter()
        timings: dict[str, float] = {}

        say = progress or (lambda stage: None)
        t = time.perf_counter()
        say("features")
        q = self.prepare(image, K, bbox, mask)
        timings["extract"] = time.perf_counter() - t

        t = time.perf_counter()
        say("matching")
        corr = self.match(q)
        q.background = background_similarity([c.sims for c in corr.values()])
        timings["match"] = time.perf_counter() - t

        t = time.perf_counter()
        say("pnp")
        hyps = self.solve(q, corr)
        timings["pnp"] = time.perf_counter() - t

        t = time.perf_counter()
        say("view selection")
        hyps = self.select_views(q, hyps)
        timings["view_selection"] = time.perf_counter() - t

        shape_first = self._shape is not None and self.cfg.shape.before_render
        if self._shape is not None:
            say("shape cues")
        if shape_first:  # the fused ranking chooses what render refinement refines
            hyps = self.shape_stage(q, hyps, timings)
        if self.cfg.refine.render_iters > 0 and hyps:
            t = time.perf_counter()
            hyps = self.render_refine(q, hyps)
            timings["render_refine"] = time.perf_counter() - t
        if shape_first:
            t = time.perf_counter()
            hyps = self.shape_verify(q, hyps)
            timings["verify"] = timings.get("verify", 0.0) + time.perf_counter() - t
        elif self._shape is not None:
            hyps = self.shape_stage(q, hyps, timings)
        if self.cfg.align.enabled and hyps:
            t = time.perf_counter()
            say("alignment")
            hyps = self.align_stage(q, hyps)
            timings["align"] = time.perf_counter() - t
        res = self.result(hyps, timings, q)
        self.part_report(q, res)
        timings["total"] = time.perf_counter() - t_all
        return self.record_inputs(res, q)

    def part_report(self, q: Query, res: PoseResult) -> PoseResult:
        """Each part's support and verdict at the result's pose (``config.parts``, :mod:`pixie.cues.parts`), into
        ``res.parts`` / ``res.part_support``; nothing for a mesh without parts, a failed pose or ``parts.enabled``
        false. Timed as ``timings['parts']``."""
        pc, mesh = self.cfg.parts, self.refs.mesh
        if not pc.enabled or mesh.n_parts < 2 or res.T_cam_from_obj is None or res.failed:
            return res
        t = time.perf_counter()
        ren, _, align_kw = self._align_setup(q, photo=False)  # the alignment's photo edges when it ran
        if self._part_renderers is None:
            self._part_renderers = part_renderers(mesh)
            self._part_complements = complement_renderers(mesh, smooth_normals=ren.smooth_normals)
        support_kw, judge_kw = report_kwargs(pc)
        if (support_kw["moves"] or support_kw["resizes"]) and pc.move_collide and self._part_solids is None:
            self._part_solids = part_solids(mesh)
        if pc.robust and q.box_source == "prior":  # a grown search region, not the object's sides
            align_kw["w_box"] = 0.0

        def report(T: np.ndarray) -> tuple[np.ndarray, list, list[int]]:
            if pc.robust:
                return robust_part_fit(ren, mesh.face_parts, mesh.part_names, q.photo_edges, T, align_kw=align_kw,
                                       support_kw=support_kw, judge_kw=judge_kw, renderers=self._part_renderers,
                                       complements=self._part_complements, solids=self._part_solids)
            return T, judge_parts(part_support(ren, mesh.face_parts, mesh.part_names, q.photo_edges, T,
                                               renderers=self._part_renderers, complements=self._part_complements,
                                               solids=self._part_solids, **support_kw), **judge_kw), []

        T0 = res.T_cam_from_obj
        T, ps, dropped = report(T0)
        if dropped:
            res.T_cam_from_obj = T
            res.settings["parts_realigned_without"] = [mesh.part_names[k] for k in dropped]
        alt = self.runner_up(res, T0)
        if alt is not None and any(p.verdict == "not visible" for p in ps):
            hidden_from_runner_up(ps, report(alt.T_cam_from_obj)[1])
        if pc.spill:
            set_spill(ps, q.image, q.K, ren, mesh.face_parts, T, colour_ab=pc.colour_ab)
        res.part_support, res.parts = ps, [p.as_dict() for p in ps]
        res.timings["parts"] = time.perf_counter() - t
        return res

    def runner_up(self, res: PoseResult, T: np.ndarray) -> Hypothesis | None:
        """The result's best distinct alternative when it is a near-equal flip of the chosen pose ``T`` (turned at
        least ``parts.alt_min_deg`` and scoring within ``parts.alt_gap`` of it), else None."""
        pc = self.cfg.parts
        if len(res.hypotheses) < 2:
            return None
        alt = res.hypotheses[1]
        flip = is_flip_runner_up(T, res.score, alt.T_cam_from_obj, alt.score, alt_gap=pc.alt_gap,
                                 alt_min_deg=pc.alt_min_deg)
        return alt if flip else None

    def estimate_from_prior(self, image: np.ndarray, K: np.ndarray, T_init: np.ndarray, bbox=None,
                            mask: np.ndarray | None = None, margin: float | None = None) -> PoseResult:
        """Refine a starting pose ``T_init`` (mm, OpenCV camera) instead of searching all views.

        The prior is aligned to the photo's edges (:func:`pixie.cues.edge_align.align`, ``config.align``) inside
        ``bbox`` / ``mask`` if given, else inside the prior's projected box grown by ``margin`` (default
        ``align.prior_margin``) of its size on every side (the object may have moved since). The result's
        ``confidence`` is the aligned fit (share of the visible contour on a same-orientation photo edge, not
        calibrated); it is ``failed`` ("no edge support") below ``align.min_fit``: a tracker's cue to search again.
        """
        t_all = time.perf_counter()
        image = check_image(image, "query image", min_side=8)
        K = check_image_K(K, image.shape[:2])
        T_init = validate_pose(T_init, "init pose")
        ac = self.cfg.align
        z = (self.box_points @ T_init[:3, :3].T + T_init[:3, 3])[:, 2]
        if z.min() <= 0:
            raise ImageError(f"the init pose puts the object (partly) behind the camera (z = {T_init[2, 3]:.1f} mm)")
        if mask is not None:
            mask = check_query_mask(mask, image.shape[:2])
        if bbox is not None or mask is not None:
            box_source = "bbox" if bbox is not None else "mask"
            box = check_bbox(bbox if bbox is not None else bbox_from_mask(mask), image.shape[:2])
        else:
            box_source = "prior"
            grown = projected_box_in_image(T_init, K, self.box_points, image.shape,
                                           ac.prior_margin if margin is None else margin)
            if grown is None:
                h, w = image.shape[:2]
                raise ImageError("the init pose projects the object outside the image: nothing to refine "
                                 f"(its box {np.round(projected_box(T_init, K, self.box_points), 1).tolist()} in a "
                                 f"{w}x{h} image)")
            box = check_bbox([grown[0], grown[1], grown[2] - grown[0], grown[3] - grown[1]], image.shape[:2])
        crop = square_crop(image, box, self.cfg.query.crop_pad, self.refs.size, 0.0, mask)
        q = Query(image, K, box, mask, [crop], [], box_source=box_source)
        t = time.perf_counter()
        ren, pe, kw = self._align_setup(q)
        if box_source == "prior":  # the grown prior box is a search region, not the object's sides
            kw["w_box"] = 0.0
        res = align(ren, pe, T_init, **kw)
        T = res.T_cam_from_obj
        hyp = Hypothesis(T_cam_from_obj=T, score=res.fit.share, n_inliers=0, n_matches=0, view=-1, roll=-1,
                         rot_to_ref_deg=0.0, box_iou=box_iou(projected_box(T, K, self.box_points), box), source="prior")
        hyp.fit = res.fit.share
        hyp.terms = {"fit": res.fit.share, "fit_silhouette": res.fit.silhouette_share, "fit_visible": res.fit.visible,
                     "fit_dist": res.fit.mean_dist, "align_iterations": float(res.iterations)}
        if box_source == "prior":  # the search region was the prior's grown box: record the refined pose's own box
            pb = projected_box_in_image(T, K, self.box_points, image.shape)
            if pb is not None:
                q.box = pb
        timings = {"align": time.perf_counter() - t}
        res = self.part_report(q, self.result([hyp], timings, q))
        timings["total"] = time.perf_counter() - t_all
        return self.record_inputs(res, q)

    # ------------------------------------------------------------------------------------------ stages
    def prepare(self, image: np.ndarray, K: np.ndarray, bbox=None, mask: np.ndarray | None = None) -> Query:
        """Check the inputs, crop the query (one crop, or one per roll) and extract its features.

        Raises
        ------
        ImageError, CameraError
            For a bad image, box, mask or ``K`` (the message names the problem).
        """
        image = check_image(image, "query image", min_side=8)
        K = check_image_K(K, image.shape[:2])
        if bbox is None and mask is None:
            raise ImageError(NO_BOX_MESSAGE)
        box_source = "bbox" if bbox is not None else "mask"
        if mask is not None:
            mask = check_query_mask(mask, image.shape[:2])
        if bbox is None:
            bbox = bbox_from_mask(mask)
        box = check_bbox(bbox, image.shape[:2])
        if mask is not None:
            check_query_mask(mask, image.shape[:2], box)
        elif self.cfg.query.segment == "grabcut":  # the object's pixels in the box, by colour (None: it failed)
            mask = grabcut_mask(image, [box[0], box[1], box[2] - box[0], box[3] - box[1]])
        use_mask = mask if (mask is not None and self.cfg.query.mask_keypoints) else None
        crops = self.crops(image, box, use_mask)
        feats = [self.matcher.extract(c.image, mask=c.mask) for c in crops]
        return Query(image, K, box, use_mask, crops, feats, box_source=box_source,
                     box_given=np.asarray(bbox, np.float64).ravel() if box_source == "bbox" else None)

    def crops(self, image: np.ndarray, box: np.ndarray, mask: np.ndarray | None) -> list[QueryCrop]:
        """The query crop (``match.in_plane=reference``) or one crop per reference roll angle (``query``)."""
        q, S = self.cfg.query, self.refs.size
        if self.cfg.match.in_plane == "reference":
            return [square_crop(image, box, q.crop_pad, S, 0.0, mask)]
        return [square_crop(image, box, q.crop_pad, S, a, mask) for a in roll_angles(self.refs.n_rolls)]

    def px_scale(self, crop: QueryCrop) -> float:
        """Original-image pixels per threshold pixel (1 in 'image' space, side/size in 'crop' space)."""
        if self.cfg.pose.threshold_space == "crop":
            return float(np.hypot(crop.A[0, 0], crop.A[1, 0]))
        return 1.0

    def match(self, q: Query, pairs: list[tuple[int, int]] | None = None) -> Correspondences:
        """2D (original image px) – 3D correspondences per reference (view, roll), all encodings concatenated.

        ``pairs`` restricts matching to those (view, roll) pairs; ``None`` matches every pair of :attr:`pairs`.
        """
        out: Correspondences = {}
        for e in self.encodings:
            bank = self._banks[e]
            if pairs is None:
                idx = list(range(len(self.pairs)))
            else:
                idx = [self._pair_index[(v, r if self.cfg.match.in_plane == "reference" else 0)] for v, r in pairs]
            sub = bank if pairs is None else self.matcher.prepare_refs([bank.features[i] for i in idx])
            for ci, (crop, qf) in enumerate(zip(q.crops, q.features)):
                matches = self.matcher.match_many(qf, sub)
                for k, m in zip(idx, matches):
                    v, r = self.pairs[k]
                    if self.cfg.match.in_plane == "query":
                        # The crop turned by angle a looks like a camera rolled by a; it matched the roll-0
                        # reference, so the query camera is that reference rolled by -a: roll (-ci) mod R.
                        r = (-ci) % len(q.crops)
                    if pairs is not None and (v, r) not in pairs:
                        continue
                    p2, p3, sc = lift(qf.keypoints, self._xyz[e][k], m)
                    if len(p2) == 0:
                        continue
                    p2 = crop.to_original(p2)
                    if (v, r) in out:
                        a2, a3, a4 = out[(v, r)]
                        out[(v, r)] = Correspondence(np.concatenate([a2, p2]), np.concatenate([a3, p3]),
                                                     np.concatenate([a4, sc]))
                    else:
                        out[(v, r)] = Correspondence(p2, p3, sc)
        return out

    def rank_pairs(self, q: Query, corr: Correspondences) -> list[tuple[int, int]]:
        """The (view, roll) pairs of ``corr``, best supported first (``pose.candidate_ranking``)."""
        rk = self.cfg.pose.candidate_ranking
        corr = typed_correspondences(corr)
        return sorted(corr, key=lambda k: -pair_rank_score(corr[k].sims, q.background, rk))

    def solve(self, q: Query, corr: Correspondences, px_scale: float | None = None) -> list[Hypothesis]:
        """PnP + RANSAC on the ``pose.top_k_views`` best-ranked views (one roll each), scored, best first.

        ``px_scale`` converts the RANSAC threshold (default: that of the query's first crop).
        """
        p = self.cfg.pose
        thr = p.reprojection_px * (self.px_scale(q.crops[0]) if px_scale is None else px_scale)
        corr = typed_correspondences(corr)
        ranked = [(k, corr[k]) for k in self.rank_pairs(q, corr)]
        if p.views == "canonical":
            ranked = [kv for kv in ranked if self.refs.canonical[kv[0][0]]]
        # One candidate per view (its best roll), the top_k views by match count.
        seen, cands = set(), []
        for (v, r), c in ranked:
            if v in seen:
                continue
            seen.add(v)
            cands.append(((v, r), c))
            if len(cands) >= p.top_k_views:
                break
        if p.mode == "concat" and cands:
            p2 = np.concatenate([c.pts2d for _, c in cands])
            p3 = np.concatenate([c.pts3d for _, c in cands])
            sc = np.concatenate([c.sims for _, c in cands])
            cands = [(cands[0][0], Correspondence(p2, p3, sc))]
        elif p.mode != "per_view":
            raise ConfigError(f"pose.mode must be 'per_view' or 'concat', got {p.mode!r}")
        hyps = []
        for (v, r), (p2, p3, sc) in cands:
            res = solve_pnp_ransac(p2, p3, q.K, p.ransac_iterations, thr, p.confidence, p.min_inliers, p.solver)
            h = self.hypothesis(q, res, v, r, sc)
            if h is not None:
                h.support_uv, h.support_xyz = p2[res.inliers], p3[res.inliers]
                hyps.append(h)
        return sorted(hyps, key=lambda h: -h.score)

    def hypothesis(self, q: Query, res: PnPResult, v: int, r: int, sims: np.ndarray | None = None,
                   T_ref: np.ndarray | None = None) -> Hypothesis | None:
        """Score a PnP solution found from reference (v, r), or from a render at ``T_ref`` when given."""
        if not res.ok:
            return None
        s_in = sims[res.inliers] if sims is not None and len(sims) == res.n_correspondences else np.ones(res.n_inliers)
        sim_sum = float(s_in.sum())
        sim_mean = float(s_in.mean()) if len(s_in) else 0.0
        T = res.T_cam_from_obj
        rot = rotation_angle_deg(T[:3, :3], (self.refs.poses[v, r] if T_ref is None else T_ref)[:3, :3])
        iou = box_iou(projected_box(T, q.K, self.box_points), q.box)
        if self.cfg.pose.depth_from_bbox:
            T = depth_from_box(T, q.K, self.box_points, q.box)
        score = hypothesis_score(self.cfg.pose.scoring, res.n_inliers, s_in, q.background, rot, iou)
        return Hypothesis(T_cam_from_obj=T, score=score, match_score=score, n_inliers=res.n_inliers,
                          n_matches=res.n_correspondences, view=v, roll=r, rot_to_ref_deg=rot, box_iou=iou,
                          sim_sum=sim_sum, sim_mean=sim_mean)

    def nearest_view(self, T: np.ndarray) -> tuple[int, int]:
        """The paper's view selection: the view whose optical axis is closest, and its closest roll."""
        v = int(np.argmax(self._axes @ optical_axis_in_object(T)))
        r = int(np.argmin([rotation_angle_deg(T[:3, :3], P[:3, :3]) for P in self.refs.poses[v]]))
        return v, r

    def select_views(self, q: Query, hyps: list[Hypothesis]) -> list[Hypothesis]:
        """The paper's iterative view selection (``refine.view_selection_iters``), then :meth:`recrop`."""
        if not hyps:
            return hyps
        best = hyps[0]
        tried = {(best.view, best.roll)}
        for _ in range(self.cfg.refine.view_selection_iters):
            v, r = self.nearest_view(best.T_cam_from_obj)
            if (v, r) in tried:
                break  # the selected view repeats: converged
            tried.add((v, r))
            new = self.solve(q, self.match(q, pairs=[(v, r)]))
            for h in new:
                h.source = "view_selection"
            hyps = sorted(hyps + new, key=lambda h: -h.score)
            if not new:
                break
            best = hyps[0]
        if self.cfg.refine.recrop:
            hyps = self.recrop(q, hyps)
        return hyps

    def recrop(self, q: Query, hyps: list[Hypothesis]) -> list[Hypothesis]:
        """Crop the query again around the best pose's projected box (the references' crop convention:
        the full silhouette, not the visible part) and match it against the best pose's nearest view."""
        best = hyps[0]
        pb = projected_box(best.T_cam_from_obj, q.K, self.box_points)
        if not np.all(np.isfinite(pb)) or pb[2] - pb[0] < 2 or pb[3] - pb[1] < 2:
            return hyps
        # Keep the crop near the given box: a wild pose must not move the crop off the object.
        if box_iou(pb, q.box) < 0.3:
            return hyps
        v, r = self.nearest_view(best.T_cam_from_obj)
        qc, S = self.cfg.query, self.refs.size
        ref_roll = r if self.cfg.match.in_plane == "reference" else 0
        angle = 0.0 if self.cfg.match.in_plane == "reference" else -float(roll_angles(self.refs.n_rolls)[r])
        crop = square_crop(q.image, pb, qc.crop_pad, S, angle, q.mask)
        qf = self.matcher.extract(crop.image, mask=crop.mask)
        k = self._pair_index.get((v, ref_roll))
        if k is None:
            return hyps
        p2s, p3s, scs = [], [], []
        for e in self.encodings:
            m = self.matcher.match_many(qf, self.matcher.prepare_refs([self._banks[e].features[k]]))[0]
            p2, p3, sc = lift(qf.keypoints, self._xyz[e][k], m)
            if len(p2):
                p2s.append(crop.to_original(p2))
                p3s.append(p3)
                scs.append(sc)
        if not p2s:
            return hyps
        merged = Correspondence(np.concatenate(p2s), np.concatenate(p3s), np.concatenate(scs))
        new = self.solve(q, {(v, r): merged}, self.px_scale(crop))
        for h in new:
            h.source = "recrop"
        return sorted(hyps + new, key=lambda h: -h.score)

    def render_refine(self, q: Query, hyps: list[Hypothesis]) -> list[Hypothesis]:
        """Render-at-estimate refinement (:mod:`pixie.cues.refine`) of the best distinct hypotheses.

        Uses the query's unrotated first crop and its features. Refined hypotheses keep the view/roll of the
        hypothesis they started from; their rotation-consistency term compares with the rendered pose.
        """
        rc, p = self.cfg.refine, self.cfg.pose
        crop, qf = q.crops[0], q.features[0]
        renderer = self._renderer or Renderer(self.refs.mesh, smooth_normals=self.refs.config.smooth_normals)
        thr = p.reprojection_px * self.px_scale(crop)
        new: list[Hypothesis] = []
        for h in self.distinct(hyps, rc.render_hypotheses):
            cur = h
            for _ in range(rc.render_iters):
                aligned = render_in_crop(renderer, cur.T_cam_from_obj, q.K, crop, self.encodings)
                if not aligned.mask.any():
                    break
                p2, p3, sc = aligned_correspondences(self.matcher, qf, crop, aligned)
                res = solve_pnp_ransac(p2, p3, q.K, p.ransac_iterations, thr, p.confidence, p.min_inliers, p.solver)
                nh = self.hypothesis(q, res, h.view, h.roll, sc, T_ref=cur.T_cam_from_obj)
                if nh is None:
                    break
                nh.source = "render"
                new.append(nh)
                if rotation_angle_deg(nh.T_cam_from_obj[:3, :3], cur.T_cam_from_obj[:3, :3]) < 1.0:
                    break  # converged
                cur = nh
        return sorted(hyps + new, key=lambda x: -x.score)

    def shape_stage(self, q: Query, hyps: list[Hypothesis], timings: dict) -> list[Hypothesis]:
        """Shape cues (``config.shape``): add the best edge-template poses to the best distinct matcher hypotheses,
        verify every candidate by edge and region agreement, re-rank by the fused score and region-refine the best
        few. Sets ``q.edges`` (the edge query) and ``q.best_match`` (the matcher score scale) for :meth:`shape_verify`."""
        sc, cues = self.cfg.shape, self._shape
        K, box = q.K, q.box
        t = time.perf_counter()
        q.edges = cues.query(q.image, box, q.mask if sc.use_mask else None)
        cands = cues.retrieve(q.edges, K, sc.candidates)
        timings["edge_retrieval"] = time.perf_counter() - t
        t = time.perf_counter()
        q.best_match = max([h.score for h in hyps], default=0.0)
        pool = self.distinct(hyps, sc.verify_matcher)
        if pool:
            pool[0].matcher_best = True
        for c in cands:
            T = depth_from_box(c.T_cam_from_obj, K, self.box_points, box) if self.cfg.pose.depth_from_bbox else c.T_cam_from_obj
            pool.append(Hypothesis(T_cam_from_obj=T, score=0.0, n_inliers=0, n_matches=0, view=-1, roll=-1,
                                   rot_to_ref_deg=0.0, box_iou=box_iou(projected_box(T, K, self.box_points), box),
                                   source="edges"))
        pool = self.shape_verify(q, pool)
        timings["verify"] = time.perf_counter() - t
        if sc.refine_hypotheses > 0:
            t = time.perf_counter()
            for h in self.distinct(pool, sc.refine_hypotheses):
                res = cues.refine(q.image, K, h.T_cam_from_obj, box, sc.refine_box_px)
                iou = box_iou(projected_box(res.T_cam_from_obj, K, self.box_points), box)
                pool.append(Hypothesis(T_cam_from_obj=res.T_cam_from_obj, score=h.match_score, match_score=h.match_score,
                                       n_inliers=h.n_inliers, n_matches=h.n_matches, view=h.view, roll=h.roll,
                                       rot_to_ref_deg=0.0, box_iou=iou, sim_sum=h.sim_sum, sim_mean=h.sim_mean,
                                       source="region"))
            pool = self.shape_verify(q, pool)
            timings["region_refine"] = time.perf_counter() - t
        return pool

    def object_renderer(self) -> Renderer:
        """The object's renderer with smooth normals (the edge alignment's), made once per estimator: for the
        alignment, and for masks of found instances (:mod:`pixie.pipeline.find`)."""
        if self._align_renderer is None:
            self._align_renderer = Renderer(self.refs.mesh, smooth_normals=True)
        return self._align_renderer

    def _align_setup(self, q: Query, photo: bool = True) -> tuple[Renderer, object, dict]:
        """What the edge alignment of query ``q`` needs (``config.align``): the renderer, the photo's edges (also
        kept as ``q.photo_edges``; made again unless ``photo`` is false and they exist) and the keywords of
        :func:`pixie.cues.edge_align.align` (with ``align.coarse_px``, the coarse crop's edges, ``q.photo_edges_coarse``,
        and the scales that run on them)."""
        ac = self.cfg.align
        ren = self.object_renderer()
        if photo or q.photo_edges is None:
            q.photo_edges = photo_edges(q.image, q.K, q.box, q.mask, **photo_edges_kwargs(ac))
        kw = align_kwargs(ac) | {"hull": self.box_points}
        if coarse_levels(ac):
            if photo or q.photo_edges_coarse is None:
                q.photo_edges_coarse = photo_edges(q.image, q.K, q.box, q.mask,
                                                   **(photo_edges_kwargs(ac) | {"object_px": ac.coarse_px}))
            kw |= coarse_kwargs(ac, q.photo_edges_coarse)
        return ren, q.photo_edges, kw

    def align_stage(self, q: Query, hyps: list[Hypothesis]) -> list[Hypothesis]:
        """Edge-based 6-DoF alignment (``config.align``, :mod:`pixie.cues.edge_align`) of the best distinct hypotheses and
        the flip twins of the best few, then selection on the aligned fit.

        The aligned poses join the pool (source 'aligned'; a twin's source is 'flip'; with ``extra_search`` every job
        is aligned by that search too, term ``extra_search`` 1). The starts and the aligned poses are ranked by
        ``terms['fused']`` (the shape stage's score, recomputed for the new poses) + ``w_fit * terms['fit']`` +
        ``w_support * terms['fit_support']``; every other hypothesis follows them in its previous order.
        """
        ac = self.cfg.align
        ren, pe, kw = self._align_setup(q)
        starts = self.distinct(hyps, ac.hypotheses)
        jobs = [(h, h.T_cam_from_obj, "aligned") for h in starts]
        for h in starts[: ac.flips]:
            jobs += [(h, T, "flip") for T in flip_twins(h.T_cam_from_obj, self.refs.mesh.center, ac.flip_axes)]
        searches = [ac.search] + ([ac.extra_search] if ac.extra_search not in ("none", ac.search) else [])
        work = [(j, s_) for s_ in searches for j in jobs]

        def run(item):
            (h, T0, src), search = item
            sup = (h.support_uv, h.support_xyz) if src == "aligned" and h.support_uv is not None else None
            return align(ren, pe, T0, **(kw | {"search": search}), matches=sup)

        # the starts are independent: aligned by the process's threads at once (the same poses with any count)
        results = map_threads(run, work)
        new: list[Hypothesis] = []
        for ((h, T0, src), search), res in zip(work, results):
            T = res.T_cam_from_obj
            ms = h.match_score if src == "aligned" else 0.0  # a twin has no matcher support of its own
            nh = Hypothesis(T_cam_from_obj=T, score=0.0, match_score=ms, n_inliers=h.n_inliers if src == "aligned" else 0,
                            n_matches=h.n_matches, view=h.view, roll=h.roll, rot_to_ref_deg=0.0,
                            box_iou=box_iou(projected_box(T, q.K, self.box_points), q.box), sim_sum=h.sim_sum,
                            sim_mean=h.sim_mean, source=src)
            nh.terms = res.fit.as_dict() | {"align_iterations": float(res.iterations),
                                            "extra_search": float(search != ac.search)}
            new.append(nh)
        fits = map_threads(lambda h: edge_fit(ren, pe, h.T_cam_from_obj, fit_px=ac.fit_px, region=True), starts)
        for h, fit in zip(starts, fits):
            h.terms.update(fit.as_dict())
        cands = starts + new
        for h in cands:
            if self._shape is not None and q.edges is not None:
                if "edge" not in h.terms:
                    h.terms.update(self._shape.verify_terms(q.edges, q.K, h.T_cam_from_obj))
                    h.edge, h.region = h.terms["edge"], h.terms["region"]
                h.fused = fused_score(self.cfg.shape, h.match_score, q.best_match, h.edge, h.region)
            else:
                h.fused = h.score if h.source != "flip" else 0.0
            h.fit = h.terms["fit"]
            h.terms["fused"] = h.fused
            h.score = (h.fused + ac.w_fit * h.fit + ac.w_support * h.terms["fit_support"]
                       + ac.w_silhouette * h.terms["fit_silhouette"])
        cands = sorted(cands, key=lambda h: -h.score)
        floor = cands[-1].score if cands else 0.0
        rest = [h for h in hyps if all(h is not c for c in starts)]
        for h in rest:  # below every aligned candidate, in their previous order
            h.score = min(h.score, floor * 0.999)
        return cands + rest

    def shape_verify(self, q: Query, hyps: list[Hypothesis]) -> list[Hypothesis]:
        """Verify the hypotheses not yet verified (their ``score`` is the matcher's) and rank all by fused score."""
        sc = self.cfg.shape
        for h in hyps:
            if h.terms:
                continue
            h.match_score = h.score if h.source != "edges" else 0.0
            h.terms = self._shape.verify_terms(q.edges, q.K, h.T_cam_from_obj)
            h.edge, h.region = h.terms["edge"], h.terms["region"]
            h.fused = fused_score(sc, h.match_score, q.best_match, h.edge, h.region)
            h.score = h.fused
        return sorted(hyps, key=lambda h: -h.score)

    @staticmethod
    def distinct(hyps: list[Hypothesis], n: int, min_deg: float = 10.0) -> list[Hypothesis]:
        """The first ``n`` hypotheses that differ by more than ``min_deg`` in rotation (hyps sorted by score)."""
        out: list[Hypothesis] = []
        for h in hyps:
            if len(out) >= n:
                break
            if all(rotation_angle_deg(h.T_cam_from_obj[:3, :3], d.T_cam_from_obj[:3, :3]) > min_deg for d in out):
                out.append(h)
        return out

    def record_inputs(self, res: PoseResult, q: Query) -> PoseResult:
        """Note on ``res`` what it was computed from: K, the box and its source, the mesh, preset, config, device."""
        res.K, res.box_xyxy, res.box_source = np.asarray(q.K, np.float64), np.asarray(q.box, np.float64), q.box_source
        res.mesh_name, res.mesh_sha256 = self.refs.mesh.name, self.refs.mesh.source_hash
        res.mesh_file_units = self.refs.mesh.file_units
        res.preset, res.config_digest = self.cfg.preset, self.cfg.digest()
        res.device = str(getattr(self.matcher, "device", "cpu"))
        return res

    def confidence_inputs(self, h: Hypothesis, q: Query | None) -> dict[str, float]:
        """The terms the calibrated confidence may use (``config.CONFIDENCE_TERMS``) of hypothesis ``h``: its
        recorded terms, and ``size``, its projected diameter in photo px / 100, clipped to the calibrated range
        (:func:`pixie.cues.edge_align.confidence_size`; needs the query's K)."""
        x = {k: float(v) for k, v in h.terms.items() if v is not None}
        if q is not None:
            c = h.T_cam_from_obj[:3, :3] @ self.refs.mesh.center + h.T_cam_from_obj[:3, 3]
            x["size"] = confidence_size(float(q.K[0, 0]) * self.refs.mesh.diameter / max(float(c[2]), 1e-9))
        return x

    def result(self, hyps: list[Hypothesis], timings: dict[str, float] | None = None,
               q: Query | None = None) -> PoseResult:
        """The best hypothesis as a :class:`PoseResult` with its confidence and the distinct runners-up.

        With the query ``q``, a pose that contradicts its box or K (:func:`pixie.pose.plausibility.pose_contradictions`:
        behind the camera, far too small or large for the box, beside it) is flagged failed with the reason,
        and intrinsics unusual for the image size are listed in ``warnings``.
        """
        timings = {} if timings is None else timings
        warns = [] if q is None else intrinsics_warnings(q.K, q.image.shape[:2]) + pose_warnings(
            q.K, q.box, q.box_given, q.image.shape[:2], self.refs.mesh.diameter, hyps[0] if hyps else None)
        if not hyps:
            return PoseResult(None, 0.0, 0, True, "no pose: too few 2D-3D matches survived PnP+RANSAC", timings=timings,
                              warnings=warns)
        best = hyps[0]
        distinct = self.distinct(hyps, self.cfg.refine.n_hypotheses)
        set_confidences(distinct)
        confidence = distinct[0].confidence
        ac = self.cfg.align
        aligned = ac.enabled and "fit" in best.terms and best.source != "prior"
        if best.source == "prior":  # a refined prior: its aligned fit is the confidence (not calibrated)
            confidence = float(best.fit)
        elif aligned and ac.confidence:  # calibrated on LM-O dev (bench/lmo_select.py)
            best.terms["margin"] = best.score - (distinct[1].score if len(distinct) > 1 else 0.0)
            inputs = self.confidence_inputs(best, q)
            if "size" in inputs:
                best.terms["size"] = inputs["size"]
            confidence = calibrated_confidence(ac, inputs)
        distinct += [h for h in hyps if h.matcher_best and all(h is not d for d in distinct)][:1]  # for comparisons
        shape_pose = best.source in ("edges", "region", "prior") or np.isfinite(best.edge)
        failed = (best.n_inliers < max(self.cfg.pose.min_inliers, 1) and not shape_pose) or best.score <= 0
        msg = "ok" if not failed else "low support"
        if "fit" in best.terms and (aligned or best.source == "prior") and best.terms["fit"] < ac.min_fit:
            failed, msg = True, (f"no edge support: {100 * best.terms['fit']:.0f} % of the pose's visible contour lies on "
                                 "a photo edge (align.min_fit)")
        if q is not None:
            mesh = self.refs.mesh
            reasons = pose_contradictions(best.T_cam_from_obj, q.K, q.box, self.box_points, mesh.center,
                                          mesh.bounding_radius)
            if reasons:
                failed, msg = True, "implausible: " + "; ".join(reasons)
            contrast = float(np.std(q.crops[0].image))
            if contrast < MIN_CROP_CONTRAST:
                failed, msg = True, (f"the object crop has no contrast (grey-level std {contrast:.1f}): a blank or "
                                     "saturated image, or a box on a featureless area")
        res = PoseResult(best.T_cam_from_obj, best.score, best.n_inliers, failed, msg, best.view, best.roll,
                         confidence, distinct, timings, warnings=warns, candidates=list(hyps))
        res.confidence_calibrated = bool(aligned and ac.confidence)
        return res
