"""Shape cues for one object: edge-template retrieval, edge + region verification of poses, region refinement.

:class:`ShapeCues` ties :mod:`pixie.references.templates` (templates from geometry), :mod:`pixie.cues.edges` (gradient
orientation scoring) and :mod:`pixie.cues.region` (colour-region agreement and refinement) to photo poses:

>>> cues = ShapeCues(mesh, build_templates(mesh))
>>> q = cues.query(image, box_xyxy)                    # response maps of the box's crop
>>> cands = cues.retrieve(q, K, k=24)                  # best templates as photo poses, with their scores
>>> edge, region = cues.verify(q, K, T)                # agreement of any pose with the photo
>>> T_ref = cues.refine(image, K, T)                    # region-based refinement

Poses from templates: a template view looks at the object centre; its placement in the crop gives the image of
that centre (so the viewing ray) and the scale (so the distance, ``z = z_t f / (f_t s)``); the rotation is the
template's turned by the smallest rotation taking the optical axis onto that ray.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from pixie.geometry.camera import crop_intrinsics, make_T
from pixie.geometry.rotations import rotation_between
from pixie.references.store import ensure_templates
from pixie.references.templates import ContourTemplates, distinct_by_rotation, view_points
from pixie.cues.edges import EdgeQuery, orientation_bins, prepare_query, search, template_bank
from pixie.geometry.mesh import Mesh
from pixie.pipeline.query import square_crop
from pixie.cues.region import band, colour_index, polygon_scores, refine_pose, separation
from pixie.geometry.render import Renderer


@dataclass
class ShapeCandidate:
    """A template placed in the photo, as a pose, with its edge and region agreement."""

    T_cam_from_obj: np.ndarray
    view: int
    angle: float
    edge: float
    region: float

    @property
    def score(self) -> float:
        return self.edge + (self.region - 0.5)


OPTICAL_AXIS = np.array([0.0, 0.0, 1.0])


class ShapeCues:
    """Edge and region cues of one object (no per-query state).

    Parameters
    ----------
    mesh : Mesh
    templates : ContourTemplates
    n_rolls : in-plane angles of the coarse search (36: every 10°)
    crease_weight : weight of crease points against silhouette points
    query_kw : keywords of :func:`pixie.cues.edges.prepare_query` (box_px, pad, min_mag, spread, power)
    region_k : best (view, roll) pairs by edges that get a region score before ranking
    region_weight : fused score = edge + region_weight * (region - 0.5)
    band : region band width, fraction of the query box's longer side
    nms_deg : retrieved candidates are more than this apart in rotation (15: top-5 recall +4 points on 96 LM-O
        targets against one per view)
    """

    def __init__(self, mesh: Mesh, templates: ContourTemplates, n_rolls: int = 36, crease_weight: float = 0.5,
                 query_kw: dict | None = None, region_k: int = 300, region_weight: float = 1.0, band: float = 0.15,
                 nms_deg: float = 15.0):
        self.mesh = mesh
        self.tpl = templates
        self.bank = template_bank(templates, n_rolls, crease_weight)
        self.crease_weight = crease_weight
        self.query_kw = dict(query_kw or {})
        self.region_k = int(region_k)
        self.region_weight = float(region_weight)
        self.band = float(band)
        self.nms_deg = float(nms_deg)
        self._rot = templates.rotations(self.bank.angles)[self.bank.views]  # (V, A, 3, 3) template rotations
        self._renderer: Renderer | None = None
        # distance of each template camera to the object centre
        c = templates.poses[:, :3, :3] @ mesh.center + templates.poses[:, :3, 3]
        self._z_t = c[:, 2]
        self._axes = np.stack([P[:3, :3].T @ [0.0, 0.0, 1.0] for P in templates.poses])

    @property
    def renderer(self) -> Renderer:
        if self._renderer is None:
            self._renderer = Renderer(self.mesh, smooth_normals=True)
        return self._renderer

    # ------------------------------------------------------------------------------------ retrieval
    def query(self, image: np.ndarray, box_xyxy: np.ndarray, mask: np.ndarray | None = None) -> EdgeQuery:
        """Response maps of the box's crop (:func:`pixie.cues.edges.prepare_query`; with ``mask``, only the edges
        near the object mask)."""
        return prepare_query(image, box_xyxy, mask=mask, **self.query_kw)

    def template_pose(self, q: EdgeQuery, K: np.ndarray, view: int, angle: float, scale: float,
                      origin: np.ndarray) -> np.ndarray:
        """Photo pose of template (view, angle) placed with ``scale`` (template -> crop px) at ``origin`` (crop px)."""
        u = q.crop.to_original(np.asarray(origin, np.float64)[None])[0]
        d = np.linalg.solve(np.asarray(K, np.float64), [u[0], u[1], 1.0])
        d /= np.linalg.norm(d)
        a = float(np.hypot(q.crop.A[0, 0], q.crop.A[1, 0]))  # photo px per crop px
        f_p = 0.5 * (K[0, 0] + K[1, 1])
        z = self._z_t[view] * f_p / (self.tpl.K[0, 0] * scale * a)
        R = rotation_between(OPTICAL_AXIS, d / np.linalg.norm(d)) @ self.tpl.pose(view, angle)[:3, :3]
        C = d * (z / d[2])
        return make_T(R, C - R @ self.mesh.center)

    def retrieve(self, q: EdgeQuery, K: np.ndarray, k: int = 24) -> list[ShapeCandidate]:
        """The ``k`` best templates by fused edge + region score, more than ``nms_deg`` apart, as photo poses."""
        scores, info = search(self.bank, q)
        flat = scores.ravel()
        top = np.argsort(-flat, kind="stable")[: max(self.region_k, k)]
        v_i, a_i = np.unravel_index(top, scores.shape)
        reg = self.region_scores(q, info, v_i, a_i) if self.region_weight > 0 else np.full(len(top), 0.5)
        fused = flat[top] + self.region_weight * (reg - 0.5)
        order = np.argsort(-fused, kind="stable")
        keep = distinct_by_rotation(self._rot[v_i, a_i], order, k, self.nms_deg)
        out: list[ShapeCandidate] = []
        for j in keep:
            v = int(info["views"][v_i[j]])
            ang = float(info["angles"][a_i[j]])
            T = self.template_pose(q, K, v, ang, float(info["scale"][v_i[j], a_i[j]]), info["origin"][v_i[j], a_i[j]])
            out.append(ShapeCandidate(T, v, ang, float(flat[top[j]]), float(reg[j])))
        return out

    def region_scores(self, q: EdgeQuery, info: dict, v_i: np.ndarray, a_i: np.ndarray) -> np.ndarray:
        ang = info["angles"][a_i]
        c, s = np.cos(ang), np.sin(ang)
        R = np.stack([np.stack([c, -s], -1), np.stack([s, c], -1)], -2)
        out = np.einsum("kij,kmj->kmi", R, self.tpl.outline[info["views"][v_i]])
        polys = info["origin"][v_i, a_i][:, None, :] + info["scale"][v_i, a_i][:, None, None] * out
        return polygon_scores(q.crop.image, polys, max(int(round(self.band * q.box_wh.max())), 2), q.valid)

    # --------------------------------------------------------------------------------- verification
    def verify(self, q: EdgeQuery, K: np.ndarray, T: np.ndarray) -> tuple[float, float]:
        """Edge and region agreement of pose ``T`` with the query crop (rendered in the crop's own camera)."""
        terms = self.verify_terms(q, K, T)
        return terms["edge"], terms["region"]

    def verify_terms(self, q: EdgeQuery, K: np.ndarray, T: np.ndarray) -> dict[str, float]:
        """'edge' (weighted as in retrieval), 'silhouette' and 'crease' (mean response of those points; crease is
        NaN without crease points) and 'region' agreement of pose ``T`` with the query crop."""
        size = q.resp.shape[1]
        Kc = crop_intrinsics(K, q.crop.A)
        r = self.renderer.render(T, Kc, size, size)
        if r.mask.sum() < 10:
            return {"edge": 0.0, "silhouette": 0.0, "crease": float("nan"), "region": 0.5}
        vp = view_points(r.depth, r.normals, Kc, T, n_points=self.tpl.n_points)
        xy = vp["xy"] + Kc[:2, 2]
        crease = vp["kind"] == 1
        w = np.where(crease, self.crease_weight, 1.0)
        b = orientation_bins(vp["ori"])
        H, W = size, size
        x = np.clip(np.rint(xy[:, 0]).astype(int), 0, W - 1)
        y = np.clip(np.rint(xy[:, 1]).astype(int), 0, H - 1)
        inside = (xy[:, 0] >= 0) & (xy[:, 0] < W) & (xy[:, 1] >= 0) & (xy[:, 1] < H)
        resp = q.resp[b, y, x] * inside
        idx = colour_index(q.crop.image)
        mask = r.mask & q.valid
        reg = separation(idx, mask, band(mask, max(int(round(self.band * q.box_wh.max())), 2), q.valid), 512)
        return {"edge": float(np.sum(resp * w) / max(w.sum(), 1e-9)),
                "silhouette": float(resp[~crease].mean()) if (~crease).any() else 0.0,
                "crease": float(resp[crease].mean()) if crease.any() else float("nan"),
                "region": reg}

    # ----------------------------------------------------------------------------------- refinement
    def refine(self, image: np.ndarray, K: np.ndarray, T: np.ndarray, box_xyxy: np.ndarray, box_px: float = 96.0,
               pad: float = 1.6, **kw):
        """Region-based refinement of ``T`` in a crop around ``box_xyxy`` (longer side ``box_px`` px).

        Returns the :class:`pixie.cues.region.RegionRefineResult` with the pose in the photo's camera.
        """
        size = int(round(box_px * pad))
        crop = square_crop(image, box_xyxy, pad, size)
        Kc = crop_intrinsics(K, crop.A)
        valid = cv2.warpAffine(np.full(image.shape[:2], 255, np.uint8), crop.A, (size, size),
                               flags=cv2.WARP_INVERSE_MAP | cv2.INTER_NEAREST, borderValue=0) > 0
        return refine_pose(self.renderer, T, Kc, crop.image, valid=valid, **kw)


def fused_score(cfg, match_score: float, best_match: float, edge: float, region: float) -> float:
    """Verification score of a hypothesis (``config.shape`` weights): matcher support relative to the query's best,
    edge agreement and region agreement above chance. Always > 0 for a pose (a tiny floor)."""
    m = match_score / best_match if best_match > 0 else 0.0
    return max(cfg.w_match * m + cfg.w_edge * edge + cfg.w_region * (region - 0.5), 1e-6)


def shape_cues(refs, cfg) -> ShapeCues:
    """:class:`ShapeCues` of a reference set's object from its stored templates (``refs.templates``, arrays of
    :meth:`ContourTemplates.to_arrays`); a set without templates that fit ``cfg`` gets them built now
    (:func:`pixie.references.store.ensure_templates`, in memory, with an INFO message)."""
    ensure_templates(refs, cfg, save=False)
    tpl = ContourTemplates.from_arrays(refs.templates)
    return ShapeCues(refs.mesh, tpl, n_rolls=cfg.rolls, crease_weight=cfg.crease_weight,
                     query_kw={"min_mag": cfg.min_mag, "mask_grow_px": cfg.mask_px}, region_k=cfg.region_k, region_weight=cfg.region_weight)
