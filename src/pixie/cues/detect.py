"""Finding the object without a box: LINE-2D proposals from the reference set's own contour templates.

The contour templates (:mod:`pixie.references.templates`: silhouette and crease points with their gradient
orientation, per view, stored in the reference set) are turned into LINE-2D templates (Hinterstoisser et al.,
TPAMI 2012; OpenCV's ``cv2.linemod``, colour-gradient modality): every chosen view, rolled in the image plane and
scaled to each plausible distance, becomes a set of (x, y, orientation label) features at two pyramid levels.
No second template set is rendered; ``cv2.linemod`` only does the fast search (quantised gradient orientations,
spreading, response maps). Matches become object boxes (the template's rolled, scaled outline), non-maximum
suppression keeps the best few; :func:`pixie.pipeline.find.find_objects` then verifies each with the pose
pipeline and keeps those whose pose the photo supports.

Measured (bench/RESULTS.md, "Detection"): on rendered scenes with clutter and distractors the object's box is the
best proposal in 3 of 4 scenes (4 of 4 with the region term); on the 288 held-out photos of the defects benchmark
the right box comes first for 90 % and is among the best 5 for 96 % (LINE-2D's order alone: 50 % and 89 %; with
the part votes only: 87 % and 93 %; a part of the assembly often scores above the whole: see ``grow_ratio`` and
``vote_weight``). On LM-O's real clutter LINE-2D ranks background higher; weighing each box's colour-region
separation (``region_weight``: the template pose's rendered silhouette against a band around it) puts the right box
among the best 5 for 33 % of 104 held-out targets instead of 16 % (13 s per photo): still, give boxes or external
detections there (``pixie run --detections``).

>>> det = TemplateDetector(ContourTemplates.from_arrays(refs.templates), K, diameter=refs.mesh.diameter)
>>> props = det.propose(image, top_k=5)                  # list[Proposal], best first
"""

from __future__ import annotations

import hashlib
import os
import tempfile
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from pixie.cues.region import band, colour_index, separation
from pixie.errors import PixieError
from pixie.geometry.camera import transform_points
from pixie.geometry.render import Renderer
from pixie.geometry.rotations import rotation_between
from pixie.paths import write_atomic
from pixie.pose.solve import box_iou, projected_box
from pixie.references.templates import ContourTemplates

__all__ = ["Proposal", "TemplateDetector", "linemod_available", "template_region"]

_LEVELS = 2  # cv2.linemod.getDefaultLINE(): pyramid levels with spreading T = 5 (fine) and 8 (coarse)


def linemod_available() -> bool:
    """OpenCV was built with the contrib ``rgbd`` module (``opencv-contrib-python-headless``)."""
    return hasattr(cv2, "linemod")


@dataclass(kw_only=True)
class Proposal:
    """One place where the object may be: its box, the LINE-2D similarity (0–100) and the template that fired."""

    box_xyxy: np.ndarray  # x0, y0, x1, y1 image px (pixel-edge extent of the template's outline)
    score: float
    view: int  # contour-template view
    angle: float  # in-plane roll, radians
    scale: float  # template px -> image px
    centre: np.ndarray  # image px of the object centre's projection
    votes: int = 0  # other proposals of the pool lying inside this box (parts of the object that fired on their own)
    # colour-region separation (0.5 = none, 1 = perfect) of the template pose's rendered silhouette against a band
    # around it (:func:`template_region`); NaN where not computed
    region: float = float("nan")
    # what the proposals are ordered by: score + vote_weight * votes + region_weight * 100 * (region - 0.5)
    rank_score: float = float("nan")

    @property
    def box_xywh(self) -> np.ndarray:
        b = self.box_xyxy
        return np.array([b[0], b[1], b[2] - b[0], b[3] - b[1]], np.float64)


def _labels(ori: np.ndarray) -> np.ndarray:
    """LINE-MOD's 8 orientation labels of unsigned gradient orientations (radians): 22.5° bins over [0, 180°)."""
    return (np.floor(np.mod(np.degrees(ori), 180.0) / 22.5).astype(int)) % 8


def _spread(n: int, k: int) -> np.ndarray:
    return np.linspace(0, n - 1, k).round().astype(int) if n > k else np.arange(n)


@dataclass(kw_only=True)
class _Placement:
    view: int
    angle: float
    scale: float
    box: np.ndarray  # outline box relative to the features' top-left at level 0 (x0, y0, x1, y1)
    origin: np.ndarray  # the object centre relative to the features' top-left at level 0


def _area(b: np.ndarray) -> float:
    return float(max(b[2] - b[0], 0.0) * max(b[3] - b[1], 0.0))


def _inside_share(a: np.ndarray, b: np.ndarray) -> float:
    """Share of box ``a``'s area inside box ``b`` (x0, y0, x1, y1)."""
    w = min(a[2], b[2]) - max(a[0], b[0])
    h = min(a[3], b[3]) - max(a[1], b[1])
    return float(max(w, 0.0) * max(h, 0.0)) / max(_area(a), 1e-9)


def votes_inside(boxes: list[np.ndarray], inside: float = 0.8) -> np.ndarray:
    """For each box, how many of the other ``boxes`` lie inside it (at least ``inside`` of their area)."""
    return np.array([sum(_inside_share(b, a) >= inside for j, b in enumerate(boxes) if j != i)
                     for i, a in enumerate(boxes)], int)


def rank_scores(scores: np.ndarray, votes: np.ndarray, vote_weight: float, regions: np.ndarray | None = None,
                region_weight: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """What proposals are ordered by, and the order, best first (stable: ties keep LINE-2D's order):
    ``scores + vote_weight * votes + region_weight * 100 * (regions - 0.5)``, a NaN region (not computed) adding
    nothing."""
    rank = np.asarray(scores, np.float64) + vote_weight * np.asarray(votes, np.float64)
    if regions is not None and region_weight > 0:
        reg = np.asarray(regions, np.float64)
        rank = rank + np.where(np.isfinite(reg), region_weight * 100.0 * (reg - 0.5), 0.0)
    return rank, np.argsort(-rank, kind="stable")


def template_region(idx: np.ndarray, mask: np.ndarray, band_share: float = 0.15, n_bins: int = 512) -> float:
    """How well the photo's colours inside ``mask`` (a proposal's rendered silhouette) separate from those in a band
    around it (``band_share`` of the silhouette's longer side wide): :func:`pixie.cues.region.separation` of the
    colour indices ``idx`` (:func:`pixie.cues.region.colour_index`); 0.5 (no evidence) for an empty silhouette.

    An object is a region that differs from its surroundings; a box where LINE-2D fired on background clutter
    (edges of shelves, other objects) mostly is not: the silhouette there shares the colours around it."""
    mask = np.asarray(mask, bool)
    if mask.sum() < 20:
        return 0.5
    ys, xs = np.nonzero(mask)
    side = max(int(xs.max() - xs.min()) + 1, int(ys.max() - ys.min()) + 1)
    return float(separation(idx, mask, band(mask, max(int(round(band_share * side)), 2)), n_bins))


def _suppresses(better: np.ndarray, box: np.ndarray, nms_iou: float, grow_ratio: float | None) -> bool:
    """Whether a kept box ``better`` suppresses ``box`` (see :meth:`TemplateDetector.propose`)."""
    if box_iou(better, box) < nms_iou:
        return False
    return grow_ratio is None or _area(box) <= grow_ratio * _area(better)


class TemplateDetector:
    """LINE-2D search of the rolled, scaled contour templates of one object in photos taken with focal ``K``.

    Parameters
    ----------
    templates : the reference set's contour templates
    K : photo intrinsics (the focal length sets the scales; the principal point does not matter)
    diameter : the object's diameter, mm (with ``sizes_px`` it sets the distances searched)
    sizes_px : smallest and largest projected diameter searched, photo px
    distance_mm : or the distance range searched, mm (overrides ``sizes_px``)
    n_views, roll_deg, scale_step : views used (spread over the stored ones; all 300 by default: LINE-2D's
        spreading tolerates a few pixels, so sparser views miss), in-plane roll step, ratio between scales
    n_features : features per template (LINE-MOD's default 63)
    cache_dir : where the LINE-2D template file is kept between processes (keyed by the templates and every
        setting above); without it each detector writes its own (~10 s for 36 000 templates, reading it ~2 s)
    renderer : the object's renderer (its mesh, mm): needed for ``propose(region_weight > 0)``, which renders each
        proposal's template pose to weigh its colour-region separation

    Templates = views x rolls x scales (300 x 24 x 4 = 28 800 for a 1.8:1 distance range: ~6 s to build, 0.1–2 s
    per 640 x 480 photo); a narrower distance range is faster and more selective.
    """

    def __init__(self, templates: ContourTemplates, K: np.ndarray, diameter: float,
                 sizes_px: tuple[float, float] = (60.0, 360.0), distance_mm: tuple[float, float] | None = None,
                 n_views: int = 300, roll_deg: float = 15.0, scale_step: float = 1.2, n_features: int = 63,
                 cache_dir: str | os.PathLike | None = None, renderer: Renderer | None = None):
        if not linemod_available():
            raise PixieError("finding the object without a box needs OpenCV's contrib modules (cv2.linemod): "
                             "pip install opencv-contrib-python-headless")
        self.tpl = templates
        self.K = np.asarray(K, np.float64)
        self.renderer = renderer
        f = float(K[0, 0])
        f_t = float(templates.K[0, 0])
        z_t = float(np.median(np.linalg.norm(templates.poses[:, :3, 3], axis=1)))  # template camera distance
        if distance_mm is None:
            distance_mm = (f * diameter / sizes_px[1], f * diameter / sizes_px[0])
        lo, hi = float(min(distance_mm)), float(max(distance_mm))
        if not (lo > 0 and np.isfinite(hi)):
            raise PixieError(f"the distance range to search must be positive mm, got {distance_mm!r}")
        n_scales = int(np.ceil(np.log(hi / lo) / np.log(scale_step))) + 1 if hi > lo * 1.0001 else 1
        z = np.geomspace(lo, hi, n_scales) if n_scales > 1 else np.array([lo])
        self.scales = (f / z) / (f_t / z_t)
        self.views = _spread(templates.n_views, n_views)
        self.angles = np.radians(np.arange(0.0, 360.0, roll_deg))
        self.n_features = int(n_features)
        self.placements: list[_Placement] = []
        self._det = self._build(None if cache_dir is None else Path(cache_dir))

    def _key(self) -> str:
        h = hashlib.sha256(b"line2d-v1")
        for a in (self.tpl.xy, self.tpl.ori, self.tpl.kind, self.tpl.outline, self.views, self.angles, self.scales):
            h.update(np.ascontiguousarray(a).tobytes())
        h.update(str(self.n_features).encode())
        return h.hexdigest()[:16]

    def _build(self, cache: Path | None):
        """A ``cv2.linemod`` detector holding one class ("obj") of every (view, roll, scale) template, read from a
        YAML file in OpenCV's FileStorage layout (the Python bindings cannot set a template's fields): written
        into ``cache`` once per key (atomically), or into a temporary folder."""
        folder = None if cache is None else cache / f"line2d-{self._key()}"
        lines = self._placements_and_yaml(write=folder is None or not (folder / "obj.yml").is_file())
        det = cv2.linemod.getDefaultLINE()
        if folder is not None:
            if lines is not None:
                folder.mkdir(parents=True, exist_ok=True)
                write_atomic(folder / "obj.yml", "\n".join(lines) + "\n")
            det.readClasses(["obj"], str(folder).replace("%", "%%") + "/%s.yml")  # cv::format(pattern, class id)
        else:
            with tempfile.TemporaryDirectory(prefix="pixie-line2d-") as d:
                with open(os.path.join(d, "obj.yml"), "w") as fh:
                    fh.write("\n".join(lines) + "\n")
                det.readClasses(["obj"], d.replace("%", "%%") + "/%s.yml")
        if det.numTemplates() != len(self.placements):
            raise PixieError(f"cv2.linemod read {det.numTemplates()} of {len(self.placements)} templates")
        return det

    def _placements_and_yaml(self, write: bool = True) -> list[str] | None:
        """Fill :attr:`placements`; the YAML lines of the templates when ``write``."""
        tpl = self.tpl
        heads, feats = [], []  # per template and level: (width, height, level), its (n, 3) features
        for v in self.views:
            ok = tpl.kind[v] >= 0
            sel = _spread(int(ok.sum()), self.n_features)
            xy0, ori0 = tpl.xy[v][ok][sel].astype(np.float64), tpl.ori[v][ok][sel].astype(np.float64)
            outline = tpl.outline[v].astype(np.float64)
            for a in self.angles:
                R = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
                xy, ol, lab = xy0 @ R.T, outline @ R.T, _labels(ori0 + a)
                olo, ohi = ol.min(axis=0), ol.max(axis=0)
                for s in self.scales:
                    if (ohi - olo).max() * s < 16:  # too small to say anything at this scale
                        continue
                    p = xy * s
                    for lv in range(_LEVELS):
                        q = np.rint(p / 2 ** lv).astype(np.int64)
                        lo = q.min(axis=0)
                        q -= lo
                        if lv == 0:
                            lo0 = lo
                        if write:
                            heads.append((int(q[:, 0].max()) + 1, int(q[:, 1].max()) + 1, lv))
                            feats.append(np.column_stack([q, lab]))
                    # pixie's box convention: x0 = first covered pixel, x1 = last + 1 (the outline points are pixel
                    # centres of a silhouette that reaches half a template pixel further)
                    box = np.r_[olo * s - 0.5 * s + 0.5 - lo0, ohi * s + 0.5 * s + 0.5 - lo0]
                    self.placements.append(_Placement(view=int(v), angle=float(a), scale=float(s), box=box,
                                                      origin=-lo0.astype(np.float64)))
        if not write:
            return None
        lines = ["%YAML:1.0", "class_id: obj", "modalities: [ ColorGradient ]", f"pyramid_levels: {_LEVELS}",
                 "template_pyramids:"]
        flat = np.concatenate(feats).tolist() if feats else []  # one conversion: per-array tolist is slow
        at = 0
        for i, (w, h, lv) in enumerate(heads):
            if lv == 0:
                lines += ["   -", f"      template_id: {i // _LEVELS}", "      templates:"]
            n = len(feats[i])
            lines += ["         -", f"            width: {w}", f"            height: {h}", f"            pyramid_level: {lv}",
                      f"            features: {flat[at:at + n]}"]  # a flow sequence of [x, y, label]
            at += n
        return lines

    def pose(self, p: Proposal, K: np.ndarray, center: np.ndarray, points: np.ndarray | None = None) -> np.ndarray:
        """The 6D pose (T_cam_from_obj, mm) a proposal's template stands for in a photo with intrinsics ``K``.

        The template's view rolled by the proposal's angle, turned so that the object centre ``center`` (object
        frame, mm; the point the template cameras look at) lies on the viewing ray of ``p.centre``, at the distance
        the proposal's scale gives (the template camera's distance x photo focal / template focal / scale). Off the
        optical axis a 2D template stands for a farther object (the image of an object there is stretched by up to
        1 / cos² of the ray's angle): with ``points`` (e.g. the mesh's hull vertices) the distance is then set so
        that their projected box has the proposal box's area. A coarse start (views ~7° apart, rolls ``roll_deg``,
        scales ``scale_step``) for the edge alignment.
        """
        K = np.asarray(K, np.float64)
        T0 = self.tpl.pose(p.view, p.angle)
        center = np.asarray(center, np.float64)
        z_t = float((T0[:3, :3] @ center + T0[:3, 3])[2])  # the template camera's distance to the centre
        dist = z_t * float(K[0, 0]) / (float(self.tpl.K[0, 0]) * p.scale)
        ray = np.linalg.solve(K, np.array([p.centre[0], p.centre[1], 1.0]))
        ray /= np.linalg.norm(ray)
        R = rotation_between(np.array([0.0, 0.0, 1.0]), ray) @ T0[:3, :3]
        T = np.eye(4)
        T[:3, :3] = R

        def area(b: np.ndarray) -> float:
            return float(max(b[2] - b[0], 1e-9) * max(b[3] - b[1], 1e-9))

        for _ in range(3 if points is not None else 0):
            T[:3, 3] = dist * ray - R @ center
            if (transform_points(T, points)[:, 2] <= 0).any():
                break
            dist *= np.sqrt(area(projected_box(T, K, points)) / area(p.box_xyxy))
        T[:3, 3] = dist * ray - R @ center
        return T

    @property
    def n_templates(self) -> int:
        return len(self.placements)

    def propose(self, image: np.ndarray, top_k: int = 5, threshold: float = 70.0, nms_iou: float = 0.3,
                grow_ratio: float | None = 1.3, vote_pool: int = 10, vote_weight: float = 3.0,
                vote_inside: float = 0.8, region_pool: int = 50, region_weight: float = 0.0,
                region_band: float = 0.15, max_matches: int = 20000) -> list[Proposal]:
        """The ``top_k`` best distinct boxes of RGB ``image``, best first.

        Non-maximum suppression: a box overlapping a better one by IoU >= ``nms_iou`` is dropped, unless its area is
        more than ``grow_ratio`` times the better box's (``None``: plain suppression). A template scaled down to a
        part of the object often fires on that part's edges above the whole object's template: plain suppression
        would then let the part hide the whole (on the defects benchmark's first 48 targets, the right box among the
        best 5: 0.62 with plain suppression, 0.90 with ``grow_ratio`` 1.3; bench/RESULTS.md, "Detection").

        Those part matches are then evidence for the whole: the best ``vote_pool`` distinct boxes get
        ``vote_weight`` x the number of other pool boxes lying inside them (``vote_inside`` of their area;
        :func:`votes_inside`). On the defects benchmark's 288 held-out photos the right box then comes first for
        0.87 instead of 0.50, and is among the best 5 for 0.93 instead of 0.89 (bench/RESULTS.md, "Session 18").

        With ``region_weight`` > 0 (needs the detector's ``renderer``) the best ``region_pool`` distinct boxes also
        get ``region_weight`` x 100 x (separation - 0.5): their template pose (:meth:`pose`) is rendered and the
        photo's colours inside the silhouette are compared with a band around it (:func:`template_region`). On
        LM-O's real clutter, where LINE-2D fires on background edges, this doubles the right boxes among the best 5
        (bench/RESULTS.md, "Session 22"). The boxes are returned in the order of LINE-2D similarity + both terms.
        """
        if region_weight > 0 and self.renderer is None:
            raise PixieError("propose(region_weight > 0) renders each proposal's pose: build the TemplateDetector "
                             "with the object's renderer")
        bgr = np.ascontiguousarray(image[..., ::-1])
        matches, _ = self._det.match([bgr], float(threshold))
        n_pool = max(top_k, vote_pool if vote_weight > 0 else 0, region_pool if region_weight > 0 else 0)
        out: list[Proposal] = []
        for m in matches[:max_matches]:
            pl = self.placements[m.template_id]
            box = np.array([m.x + pl.box[0], m.y + pl.box[1], m.x + pl.box[2], m.y + pl.box[3]], np.float64)
            if any(_suppresses(o.box_xyxy, box, nms_iou, grow_ratio) for o in out):
                continue
            out.append(Proposal(box_xyxy=box, score=float(m.similarity), view=pl.view, angle=pl.angle,
                                scale=pl.scale, centre=np.array([m.x, m.y], np.float64) + pl.origin))
            if len(out) >= n_pool:
                break
        pool = out[: max(top_k, vote_pool)]  # (the vote's pool is never smaller than what is returned)
        votes = np.zeros(len(out), int)
        if vote_weight > 0 and pool:
            votes[: len(pool)] = votes_inside([p.box_xyxy for p in pool], vote_inside)
        if region_weight > 0 and out:
            self._add_regions(image, out[: max(region_pool, 0)], region_band)
        rank, order = rank_scores([p.score for p in out], votes, vote_weight, [p.region for p in out], region_weight)
        for p, v, r in zip(out, votes, rank):
            p.votes, p.rank_score = int(v), float(r)
        return [out[i] for i in order[:top_k]]

    def _add_regions(self, image: np.ndarray, props: list[Proposal], band_share: float) -> None:
        """Set each proposal's ``region`` (:func:`template_region` of its template pose rendered at photo size)."""
        H, W = image.shape[:2]
        idx = colour_index(image, 3)
        mesh = self.renderer.mesh
        for p in props:
            T = self.pose(p, self.K, mesh.center, mesh.hull_vertices)
            if (transform_points(T, mesh.hull_vertices)[:, 2] <= 0).any():
                p.region = 0.5  # partly behind the camera: no silhouette to judge
                continue
            p.region = template_region(idx, self.renderer.render(T, self.K, H, W).mask, band_share)
