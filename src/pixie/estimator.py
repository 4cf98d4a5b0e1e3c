"""The pose pipeline in one place: crop → match → lift → PnP → score → view selection.

>>> refs = load_reference_set("ape.npz")
>>> est = PoseEstimator(refs, PixieConfig())
>>> result = est.estimate(image, K, bbox=(x, y, w, h))
>>> result.T_cam_from_obj, result.score, result.failed
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field

import numpy as np

from pixie.camera import check_image_K, optical_axis_in_object, rotation_angle_deg
from pixie.config import PixieConfig
from pixie.errors import ConfigError, ReferenceSetError
from pixie.pose import PnPResult, box_iou, depth_from_box, lift, projected_box, solve_pnp_ransac
from pixie.query import QueryCrop, bbox_from_mask, check_bbox, check_query_image, square_crop
from pixie.references import ReferenceSet, add_features
from pixie.views import roll_angles

log = logging.getLogger(__name__)

_MIN_BACKGROUND_PAIRS = 8  # (view, roll) pairs with matches needed to estimate a query's background similarity


@dataclass
class Hypothesis:
    """One candidate pose: from reference (view, roll), with its PnP support."""

    T_cam_from_obj: np.ndarray
    score: float
    n_inliers: int
    n_matches: int
    view: int
    roll: int
    rot_to_ref_deg: float
    box_iou: float
    sim_sum: float = 0.0  # summed matcher similarity (cosine for NN backends) of the PnP inliers
    sim_mean: float = 0.0  # its mean over the inliers
    source: str = "reference"  # 'reference' (first pass), 'view_selection', 'recrop', 'render' (render-at-estimate),
    # 'edges' (contour template) or 'region' (region-refined)
    match_score: float = 0.0  # the matcher's score before shape verification replaced ``score``
    edge: float = float("nan")  # shape verification terms (pixie.shape), when run
    region: float = float("nan")
    terms: dict = field(default_factory=dict)  # every verification term (pixie.shape.ShapeCues.verify_terms)
    matcher_best: bool = False  # the matcher's own choice (what the pipeline returns without shape cues)


@dataclass
class PoseResult:
    """What :meth:`PoseEstimator.estimate` returns. ``failed`` results still carry the best guess."""

    T_cam_from_obj: np.ndarray | None
    score: float
    n_inliers: int
    failed: bool
    message: str
    view: int = -1
    roll: int = -1
    confidence: float = 0.0
    hypotheses: list[Hypothesis] = field(default_factory=list)
    timings: dict[str, float] = field(default_factory=dict)

    def to_dict(self) -> dict:
        return {
            "T_cam_from_obj": None if self.T_cam_from_obj is None else self.T_cam_from_obj.tolist(),
            "score": self.score, "n_inliers": self.n_inliers, "failed": self.failed, "message": self.message,
            "view": self.view, "roll": self.roll, "confidence": self.confidence, "timings": self.timings,
            "hypotheses": [
                {"T_cam_from_obj": h.T_cam_from_obj.tolist(), "score": h.score, "n_inliers": h.n_inliers,
                 "view": h.view, "roll": h.roll, "source": h.source, "match_score": h.match_score,
                 "edge": None if not np.isfinite(h.edge) else h.edge,
                 "region": None if not np.isfinite(h.region) else h.region} for h in self.hypotheses
            ],
        }


class PoseEstimator:
    """Estimate ``T_cam_from_obj`` of the reference set's object in RGB photos.

    Parameters
    ----------
    refs : ReferenceSet
    config : PixieConfig
    matcher : pixie.matching.Matcher, optional
        Built from ``config.match`` when omitted. Reference features missing for this matcher are
        extracted once here (slow; store them with ``pixie refs build --matcher``).
    """

    def __init__(self, refs: ReferenceSet, config: PixieConfig | None = None, matcher=None):
        from pixie.matching import matcher_from_config, unpack_features

        self.refs = refs
        self.cfg = config or PixieConfig()
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
        self._rolls = list(range(R)) if self.cfg.match.in_plane == "reference" else [0]
        self._banks, self._xyz = {}, {}
        for e in self.encodings:
            packed = refs.features[refs.feature_key(self.matcher.name, e)]
            feats = unpack_features(packed)
            Re = refs.feature_rolls(self.matcher.name, e)
            offs = np.cumsum([0] + [len(f) for f in feats])
            xyz = [packed["xyz"][offs[k]:offs[k + 1]] for k in range(len(feats))]
            keep = [v * Re + r for v in range(refs.n_views) for r in self._rolls]
            self._banks[e] = self.matcher.prepare_refs([feats[k] for k in keep])
            self._xyz[e] = [xyz[k] for k in keep]
        self._pairs = [(v, r) for v in range(refs.n_views) for r in self._rolls]
        self._sim_background = 0.0  # set per query by estimate()
        self._pair_index = {p: i for i, p in enumerate(self._pairs)}
        self._axes = np.stack([optical_axis_in_object(T) for T in refs.poses[:, 0]])
        # exact projected boxes (a vertex subsample makes them ~0.6 % small on LM-O, i.e. z ~0.6 % short)
        self._box_points = refs.mesh.hull_vertices
        self._renderer = None  # built on first use by render-at-estimate refinement
        self._shape = None
        if self.cfg.shape.enabled:
            from pixie.shape import shape_cues

            self._shape = shape_cues(refs, self.cfg.shape)
        self._ranked_pairs: list[tuple[int, int]] = []  # (view, roll) pairs of the last query, best first

    # ------------------------------------------------------------------------------------------------
    def estimate(self, image: np.ndarray, K: np.ndarray, bbox=None, mask: np.ndarray | None = None) -> PoseResult:
        """Pose of the object in ``image`` (RGB uint8) with intrinsics ``K``; crop from ``bbox`` or ``mask``.

        ``bbox`` is (x, y, w, h) with ``w``, ``h`` counting pixels (OpenCV ``boundingRect``, COCO); BOP's stored
        boxes are one pixel smaller (:attr:`pixie.datasets.GtInstance.box_visib` converts). Its size sets the
        object's distance (``pose.depth_from_bbox``), so a pixel matters on small objects.
        """
        t_all = time.perf_counter()
        timings: dict[str, float] = {}
        image = check_query_image(image)
        K = check_image_K(K, image.shape[:2])
        if bbox is None:
            bbox = bbox_from_mask(mask) if mask is not None else np.array([0, 0, image.shape[1], image.shape[0]])
        box = check_bbox(bbox, image.shape[:2])
        use_mask = mask if (mask is not None and self.cfg.query.mask_keypoints) else None

        t = time.perf_counter()
        crops = self._crops(image, box, use_mask)
        qfeats = [self.matcher.extract(c.image, mask=c.mask) for c in crops]
        timings["extract"] = time.perf_counter() - t

        t = time.perf_counter()
        corr = self._match_all(crops, qfeats, pairs=None)
        # Background similarity of this query: the median over all (view, roll) pairs of their mean match
        # similarity. Windowed mutual NN matches every view about equally often; what tells the right view
        # apart is how much more similar its (inlier) matches are than this level ('*excess' scorings).
        # Needs many pairs to be a background: with fewer (e.g. a one-view reference set) it is 0.
        means = [float(np.mean(c[2])) for c in corr.values() if len(c[2])]
        self._sim_background = float(np.median(means)) if len(means) >= _MIN_BACKGROUND_PAIRS else 0.0
        timings["match"] = time.perf_counter() - t

        t = time.perf_counter()
        self._ranked_pairs = sorted(corr, key=lambda k: -self._pair_rank_score(corr[k][2]))  # seeds for refinement
        hyps = self._solve(corr, K, box, self._px_scale(crops[0]))
        timings["pnp"] = time.perf_counter() - t

        t = time.perf_counter()
        hyps = self._view_selection(hyps, crops, qfeats, K, box, image, use_mask)
        timings["view_selection"] = time.perf_counter() - t

        shape_first = self._shape is not None and self.cfg.shape.before_render
        if shape_first:  # fused ranking chooses what render refinement refines
            hyps, edge_q, best_match = self._shape_stage(hyps, image, K, box, timings)
        if self.cfg.refine.render_iters > 0 and hyps:
            t = time.perf_counter()
            hyps = self._render_refine(hyps, crops[0], qfeats[0], K, box)
            timings["render_refine"] = time.perf_counter() - t
        if shape_first:
            t = time.perf_counter()
            hyps = self._shape_verify(hyps, edge_q, K, best_match)
            timings["verify"] += time.perf_counter() - t
        elif self._shape is not None:
            hyps = self._shape_stage(hyps, image, K, box, timings)[0]
        timings["total"] = time.perf_counter() - t_all
        return self._result(hyps, box, K, timings)

    # ------------------------------------------------------------------------------------------------
    def _crops(self, image: np.ndarray, box: np.ndarray, mask: np.ndarray | None) -> list[QueryCrop]:
        q, S = self.cfg.query, self.refs.size
        if self.cfg.match.in_plane == "reference":
            return [square_crop(image, box, q.crop_pad, S, 0.0, mask)]
        return [square_crop(image, box, q.crop_pad, S, a, mask) for a in roll_angles(self.refs.n_rolls)]

    def _px_scale(self, crop: QueryCrop) -> float:
        """Original-image pixels per threshold pixel (1 in 'image' space, side/size in 'crop' space)."""
        if self.cfg.pose.threshold_space == "crop":
            return float(np.hypot(crop.A[0, 0], crop.A[1, 0]))
        return 1.0

    def _match_all(self, crops, qfeats, pairs: list[tuple[int, int]] | None) -> dict:
        """2D (original image px) – 3D correspondences per (view, roll), all encodings concatenated."""
        out: dict[tuple[int, int], tuple[np.ndarray, np.ndarray, np.ndarray]] = {}
        for e in self.encodings:
            bank = self._banks[e]
            if pairs is None:
                idx = list(range(len(self._pairs)))
            else:
                idx = [self._pair_index[(v, r if self.cfg.match.in_plane == "reference" else 0)] for v, r in pairs]
            sub = bank if pairs is None else self.matcher.prepare_refs([bank.features[i] for i in idx])
            for ci, (crop, qf) in enumerate(zip(crops, qfeats)):
                matches = self.matcher.match_many(qf, sub)
                for k, m in zip(idx, matches):
                    v, r = self._pairs[k]
                    if self.cfg.match.in_plane == "query":
                        # The crop turned by angle a looks like a camera rolled by a; it matched the roll-0
                        # reference, so the query camera is that reference rolled by -a: roll (-ci) mod R.
                        r = (-ci) % len(crops)
                    if pairs is not None and (v, r) not in pairs:
                        continue
                    p2, p3, sc = self._lift(qf, e, k, m)
                    if len(p2) == 0:
                        continue
                    p2 = crop.to_original(p2)
                    if (v, r) in out:
                        a2, a3, a4 = out[(v, r)]
                        out[(v, r)] = (np.concatenate([a2, p2]), np.concatenate([a3, p3]), np.concatenate([a4, sc]))
                    else:
                        out[(v, r)] = (p2, p3, sc)
        return out

    def _lift(self, qf, e: str, k: int, m):
        """:func:`lift` that also returns each correspondence's match similarity."""
        xyz = self._xyz[e][k]
        keep = np.all(np.isfinite(xyz[m.idx_r]), axis=1)
        p2, p3 = lift(qf.keypoints, xyz, m.idx_q[keep], m.idx_r[keep])
        return p2, p3, m.scores[keep].astype(np.float64)

    def _solve(self, corr: dict, K: np.ndarray, box: np.ndarray, px_scale: float = 1.0) -> list[Hypothesis]:
        p = self.cfg.pose
        thr = p.reprojection_px * px_scale
        ranked = sorted(corr.items(), key=lambda kv: -self._pair_rank_score(kv[1][2]))
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
            p2 = np.concatenate([c[0] for _, c in cands])
            p3 = np.concatenate([c[1] for _, c in cands])
            sc = np.concatenate([c[2] for _, c in cands])
            cands = [(cands[0][0], (p2, p3, sc))]
        elif p.mode != "per_view":
            raise ConfigError(f"pose.mode must be 'per_view' or 'concat', got {p.mode!r}")
        hyps = []
        for (v, r), (p2, p3, sc) in cands:
            res = solve_pnp_ransac(p2, p3, K, p.ransac_iterations, thr, p.confidence, p.min_inliers, p.solver)
            h = self._hypothesis(res, v, r, K, box, sc)
            if h is not None:
                hyps.append(h)
        return sorted(hyps, key=lambda h: -h.score)

    def _pair_rank_score(self, sims: np.ndarray) -> float:
        """How strongly a (view, roll) pair's matches support it before PnP (``pose.candidate_ranking``).

        'excess' (default): summed similarity above the query's background level; 'count': the number of
        matches, which hardly separates views for windowed NN (every pair gets 60-100 matches on LM-O).
        """
        rk = self.cfg.pose.candidate_ranking
        if rk == "count":
            return float(len(sims))
        if rk == "excess":
            return float(np.clip(sims - self._sim_background, 0.0, None).sum()) + 1e-6 * len(sims)
        raise ConfigError(f"pose.candidate_ranking must be 'excess' or 'count', got {rk!r}")

    def _hypothesis(self, res: PnPResult, v: int, r: int, K: np.ndarray, box: np.ndarray,
                    sims: np.ndarray | None = None, T_ref: np.ndarray | None = None) -> Hypothesis | None:
        """Score a PnP solution found from reference (v, r), or from a render at ``T_ref`` when given."""
        if not res.ok:
            return None
        s_in = sims[res.inliers] if sims is not None and len(sims) == res.n_correspondences else np.ones(res.n_inliers)
        sim_sum = float(s_in.sum())
        sim_mean = float(s_in.mean()) if len(s_in) else 0.0
        T = res.T_cam_from_obj
        rot = rotation_angle_deg(T[:3, :3], (self.refs.poses[v, r] if T_ref is None else T_ref)[:3, :3])
        iou = box_iou(projected_box(T, K, self._box_points), box)
        if self.cfg.pose.depth_from_bbox:
            T = depth_from_box(T, K, self._box_points, box)
        sc = self.cfg.pose.scoring
        # (+ a tiny inlier term: ties break by support and a valid pose never scores 0, i.e. 'failed')
        excess = max(0.0, float(np.sum(s_in - self._sim_background))) + 1e-3 * res.n_inliers
        support = {"inliers": float(res.n_inliers), "combined": float(res.n_inliers),
                   "similarity": sim_sum, "combined_similarity": sim_sum,
                   "excess": excess, "combined_excess": excess}.get(sc)
        if support is None:
            raise ConfigError("pose.scoring must be one of 'inliers', 'combined', 'similarity', 'combined_similarity', "
                              f"'excess', 'combined_excess', got {sc!r}")
        if sc.startswith("combined"):
            # Matching only works between similar viewpoints: penalise solutions far from the
            # reference view they came from (flips), and solutions whose box disagrees with the crop.
            score = support * float(np.exp(-((rot / 35.0) ** 2))) * (0.25 + 0.75 * iou)
        else:
            score = support
        return Hypothesis(T, score, res.n_inliers, res.n_correspondences, v, r, rot, iou, sim_sum, sim_mean)

    def _nearest_view(self, T: np.ndarray) -> tuple[int, int]:
        """The paper's view selection: the view whose optical axis is closest, and its closest roll."""
        v = int(np.argmax(self._axes @ optical_axis_in_object(T)))
        r = int(np.argmin([rotation_angle_deg(T[:3, :3], P[:3, :3]) for P in self.refs.poses[v]]))
        return v, r

    def _view_selection(self, hyps, crops, qfeats, K, box, image=None, mask=None) -> list[Hypothesis]:
        if not hyps:
            return hyps
        best = hyps[0]
        tried = {(best.view, best.roll)}
        scale = self._px_scale(crops[0])
        for _ in range(self.cfg.refine.view_selection_iters):
            v, r = self._nearest_view(best.T_cam_from_obj)
            if (v, r) in tried:
                break  # the selected view repeats: converged
            tried.add((v, r))
            corr = self._match_all(crops, qfeats, pairs=[(v, r)])
            new = self._solve(corr, K, box, scale)
            for h in new:
                h.source = "view_selection"
            hyps = sorted(hyps + new, key=lambda h: -h.score)
            if not new:
                break
            best = hyps[0]
        if self.cfg.refine.recrop and image is not None:
            hyps = self._recrop(hyps, image, K, box, mask)
        return hyps

    def _recrop(self, hyps, image, K, box, mask) -> list[Hypothesis]:
        """Crop the query again around the best pose's projected box (the references' crop convention:
        the full silhouette, not the visible part) and match it against the best pose's nearest view."""
        best = hyps[0]
        pb = projected_box(best.T_cam_from_obj, K, self._box_points)
        h, w = image.shape[:2]
        if not np.all(np.isfinite(pb)) or pb[2] - pb[0] < 2 or pb[3] - pb[1] < 2:
            return hyps
        # Keep the crop near the given box: a wild pose must not move the crop off the object.
        if box_iou(pb, box) < 0.3:
            return hyps
        v, r = self._nearest_view(best.T_cam_from_obj)
        q, S = self.cfg.query, self.refs.size
        ref_roll = r if self.cfg.match.in_plane == "reference" else 0
        angle = 0.0 if self.cfg.match.in_plane == "reference" else -float(roll_angles(self.refs.n_rolls)[r])
        crop = square_crop(image, pb, q.crop_pad, S, angle, mask)
        qf = self.matcher.extract(crop.image, mask=crop.mask)
        k = self._pair_index.get((v, ref_roll))
        if k is None:
            return hyps
        p2s, p3s, scs = [], [], []
        for e in self.encodings:
            m = self.matcher.match_many(qf, self.matcher.prepare_refs([self._banks[e].features[k]]))[0]
            p2, p3, sc = self._lift(qf, e, k, m)
            if len(p2):
                p2s.append(crop.to_original(p2))
                p3s.append(p3)
                scs.append(sc)
        if not p2s:
            return hyps
        new = self._solve({(v, r): (np.concatenate(p2s), np.concatenate(p3s), np.concatenate(scs))}, K, box,
                          self._px_scale(crop))
        for h in new:
            h.source = "recrop"
        return sorted(hyps + new, key=lambda h: -h.score)

    def _render_refine(self, hyps: list[Hypothesis], crop, qf, K: np.ndarray, box: np.ndarray) -> list[Hypothesis]:
        """Render-at-estimate refinement (:mod:`pixie.refine`) of the best distinct hypotheses.

        ``crop`` must be unrotated (angle 0) and ``qf`` its features. Refined hypotheses keep the view/roll
        of the hypothesis they started from; their rotation-consistency term compares with the rendered pose.
        """
        from pixie.refine import aligned_correspondences, render_in_crop

        rc, p = self.cfg.refine, self.cfg.pose
        if self._renderer is None:
            from pixie.render import Renderer

            self._renderer = Renderer(self.refs.mesh, smooth_normals=self.refs.config.smooth_normals)
        window = None if rc.render_window is None else rc.render_window * self.refs.size
        thr = p.reprojection_px * self._px_scale(crop)
        new: list[Hypothesis] = []
        seeds = self._distinct(hyps, rc.render_hypotheses)
        seeds += self._reference_seeds(K, box, seeds)
        for h in seeds:
            cur = h
            for _ in range(rc.render_iters):
                aligned = render_in_crop(self._renderer, cur.T_cam_from_obj, K, crop, self.encodings)
                if not aligned.mask.any():
                    break
                p2, p3, sc = aligned_correspondences(self.matcher, qf, crop, aligned, window)
                res = solve_pnp_ransac(p2, p3, K, p.ransac_iterations, thr, p.confidence, p.min_inliers, p.solver)
                nh = self._hypothesis(res, h.view, h.roll, K, box, sc, T_ref=cur.T_cam_from_obj)
                if nh is None:
                    break
                nh.source = "render"
                new.append(nh)
                if rotation_angle_deg(nh.T_cam_from_obj[:3, :3], cur.T_cam_from_obj[:3, :3]) < 1.0:
                    break  # converged
                cur = nh
        return sorted(hyps + new, key=lambda x: -x.score)

    def _reference_seeds(self, K: np.ndarray, box: np.ndarray, taken: list[Hypothesis]) -> list[Hypothesis]:
        """Poses of the best-ranked reference (view, roll) pairs themselves (``refine.render_seeds``), moved into
        the photo, for render-at-estimate refinement: PnP on a weak matcher's output often fails even at the
        right view, while refinement converges from the reference pose (10-15° away at most)."""
        from pixie.refine import pose_from_reference

        out: list[Hypothesis] = []
        centre = self.refs.mesh.center
        for v, r in self._ranked_pairs[: max(0, self.cfg.refine.render_seeds) * 3]:
            if len(out) >= self.cfg.refine.render_seeds:
                break
            T = pose_from_reference(self.refs.poses[v, r], K, box, centre, self._box_points)
            if any(rotation_angle_deg(T[:3, :3], h.T_cam_from_obj[:3, :3]) < 10 for h in taken + out):
                continue
            out.append(Hypothesis(T, 0.0, 0, 0, v, r, 0.0, 0.0, source="seed"))
        return out

    def _shape_stage(self, hyps: list[Hypothesis], image, K, box, timings: dict) -> tuple[list[Hypothesis], object, float]:
        """Shape cues (``config.shape``): add the best edge-template poses to the best distinct matcher hypotheses,
        verify every candidate by edge and region agreement, re-rank by the fused score and region-refine the best
        few. Returns the ranked pool, the edge query (for later verification) and the matcher score scale."""
        sc, cues = self.cfg.shape, self._shape
        t = time.perf_counter()
        q = cues.query(image, box)
        cands = cues.retrieve(q, K, sc.candidates)
        timings["edge_retrieval"] = time.perf_counter() - t
        t = time.perf_counter()
        best_match = max([h.score for h in hyps], default=0.0)
        pool = self._distinct(hyps, sc.verify_matcher)
        if pool:
            pool[0].matcher_best = True
        for c in cands:
            T = depth_from_box(c.T_cam_from_obj, K, self._box_points, box) if self.cfg.pose.depth_from_bbox else c.T_cam_from_obj
            pool.append(Hypothesis(T, 0.0, 0, 0, -1, -1, 0.0, box_iou(projected_box(T, K, self._box_points), box),
                                   source="edges"))
        pool = self._shape_verify(pool, q, K, best_match)
        timings["verify"] = time.perf_counter() - t
        if sc.refine_hypotheses > 0:
            t = time.perf_counter()
            for h in self._distinct(pool, sc.refine_hypotheses):
                res = cues.refine(image, K, h.T_cam_from_obj, box, sc.refine_box_px)
                pool.append(Hypothesis(res.T_cam_from_obj, h.match_score, h.n_inliers, h.n_matches, h.view, h.roll,
                                       0.0, box_iou(projected_box(res.T_cam_from_obj, K, self._box_points), box),
                                       h.sim_sum, h.sim_mean, source="region"))
            pool = self._shape_verify(pool, q, K, best_match)
            timings["region_refine"] = time.perf_counter() - t
        return pool, q, best_match

    def _shape_verify(self, hyps: list[Hypothesis], q, K, best_match: float) -> list[Hypothesis]:
        """Verify the hypotheses not yet verified (their ``score`` is the matcher's) and rank all by fused score."""
        from pixie.shape import fused_score

        sc = self.cfg.shape
        for h in hyps:
            if h.terms:
                continue
            h.match_score = h.score if h.source != "edges" else 0.0
            h.terms = self._shape.verify_terms(q, K, h.T_cam_from_obj)
            h.edge, h.region = h.terms["edge"], h.terms["region"]
            h.score = fused_score(sc, h.match_score, best_match, h.edge, h.region)
        return sorted(hyps, key=lambda h: -h.score)

    @staticmethod
    def _distinct(hyps: list[Hypothesis], n: int, min_deg: float = 10.0) -> list[Hypothesis]:
        """The first ``n`` hypotheses that differ by more than ``min_deg`` in rotation (hyps sorted by score)."""
        out: list[Hypothesis] = []
        for h in hyps:
            if len(out) >= n:
                break
            if all(rotation_angle_deg(h.T_cam_from_obj[:3, :3], d.T_cam_from_obj[:3, :3]) > min_deg for d in out):
                out.append(h)
        return out

    def _result(self, hyps: list[Hypothesis], box, K, timings) -> PoseResult:
        if not hyps:
            return PoseResult(None, 0.0, 0, True, "no pose: too few 2D-3D matches survived PnP+RANSAC", timings=timings)
        best = hyps[0]
        distinct = self._distinct(hyps, self.cfg.refine.n_hypotheses)
        distinct += [h for h in hyps if h.matcher_best and all(h is not d for d in distinct)][:1]  # kept for comparisons
        second = distinct[1].score if len(distinct) > 1 else 0.0
        confidence = float(best.score / (best.score + second)) if best.score > 0 else 0.0
        shape_pose = best.source in ("edges", "region") or np.isfinite(best.edge)
        failed = (best.n_inliers < max(self.cfg.pose.min_inliers, 1) and not shape_pose) or best.score <= 0
        msg = "ok" if not failed else "low support"
        return PoseResult(best.T_cam_from_obj, best.score, best.n_inliers, failed, msg, best.view, best.roll,
                          confidence, distinct, timings)
