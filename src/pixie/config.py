"""One configuration object with the paper's defaults, overridable from YAML and the CLI.

Sections follow the pipeline: ``refs`` (offline reference views), ``query`` (cropping),
``match`` (cross-modality matcher), ``pose`` (lifting + PnP/RANSAC) and ``refine`` (view selection).
Override from the command line with ``--set section.key=value`` (values parsed as YAML).

Presets (``src/pixie/configs/<name>.yaml``: ``fast``, ``default``, ``paper``) are YAML files of the same
sections layered on top of the dataclass defaults; :meth:`PixieConfig.from_preset` loads one and every
``pixie`` command starts from ``--preset default``. The dataclass defaults themselves (``PixieConfig()``) are
the paper's settings plus pixie's extras and are not a preset.

Longer than 500 lines on purpose: it is the one validated config object, and each key keeps its range, choices and
the measurement behind its default next to it; split, a key's check would sit in another file than its default.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from pixie.errors import ConfigError

# Allowed values, checked whenever a value is set (constructor, attribute assignment, YAML, --set).
CHOICES: dict[str, tuple[str, ...]] = {
    "refs.feature_rolls": ("all", "first"),
    "match.in_plane": ("reference", "query"),
    "pose.threshold_space": ("image", "crop"),
    "pose.solver": ("poselib", "opencv"),
    "pose.mode": ("per_view", "concat"),
    "pose.scoring": ("inliers", "combined", "similarity", "combined_similarity", "excess", "combined_excess"),
    "pose.candidate_ranking": ("excess", "count"),
    "pose.views": ("all", "canonical"),
    "query.segment": ("none", "grabcut"),
}
# Lists of numbers that may be empty or negative, and allowed list lengths.
SIGNED_LISTS = {"align.confidence"}
# What the calibrated confidence may be computed from (config.align.confidence_terms; pixie.pipeline.estimator).
CONFIDENCE_TERMS = ("fit", "fit_silhouette", "fit_visible", "fit_dist", "edge", "region", "fused", "margin", "size")
LIST_LENGTHS = {"align.confidence": tuple(range(0, len(CONFIDENCE_TERMS) + 2))}  # [] or intercept + a term each
# (low, high, low_inclusive): numbers outside are refused; None bounds are open.
RANGES: dict[str, tuple[float | None, float | None, bool]] = {
    "refs.n_fibonacci": (0, 100_000, True),
    "refs.rotations": (1, 360, True),
    "refs.size": (16, 4096, True),
    "refs.focal_factor": (0, 1000, False),
    "refs.crop_pad": (1.0, 10.0, True),
    "query.crop_pad": (1.0, 10.0, True),
    "match.max_keypoints": (1, 100_000, True),
    "match.detection_threshold": (-1.0, 1.0, True),  # <= 0: the max_keypoints strongest
    "match.window": (0, 10, False),
    "pose.ransac_iterations": (1, 10_000_000, True),
    "pose.reprojection_px": (0, 10_000, False),
    "pose.confidence": (0, 1, False),
    "pose.min_inliers": (4, None, True),  # PnP needs 4 points
    "pose.top_k_views": (1, None, True),
    "refine.view_selection_iters": (0, 100, True),
    "refine.n_hypotheses": (1, None, True),
    "refine.render_iters": (0, 100, True),
    "refine.render_hypotheses": (0, None, True),
    "refine.render_seeds": (0, None, True),
    "refine.render_window": (0, 10, False),
    "shape.views": (1, 100_000, True),
    "shape.size": (16, 4096, True),
    "shape.points": (1, 100_000, True),
    "shape.rolls": (1, 360, True),
    "shape.crease_weight": (0, None, True),
    "shape.min_mag": (0, None, True),
    "shape.region_k": (1, None, True),
    "shape.region_weight": (0, None, True),
    "shape.candidates": (0, None, True),
    "shape.verify_matcher": (0, None, True),
    "shape.w_match": (0, None, True),
    "shape.w_edge": (0, None, True),
    "shape.w_region": (0, None, True),
    "shape.refine_hypotheses": (0, None, True),
    "shape.refine_box_px": (8, 4096, True),
    "shape.mask_px": (0, 100, True),
}


def check_value(dotted: str, annotation: str, value: Any) -> Any:
    """``value`` converted to the type ``annotation`` names and checked against CHOICES / RANGES.

    Parameters
    ----------
    dotted : str
        ``section.key``, named in the error.
    annotation : str
        The dataclass field's annotation (``'int'``, ``'float | None'``, ``'list[str]'`` ...).
    value : any
        A Python value (already parsed from YAML where it came from text).

    Returns
    -------
    The value as the field's type: whole floats become ints, ints become floats, a text for a list
    becomes its comma-separated items.

    Raises
    ------
    ConfigError
        Wrong type, a value outside its range or not among the allowed choices.
    """
    parts = [a.strip() for a in annotation.split("|")]
    optional = "None" in parts
    base = next(a for a in parts if a != "None")
    if value is None:
        if optional:
            return None
        raise ConfigError(f"{dotted} cannot be null (expects {base})")
    if base == "bool":
        if not isinstance(value, bool):
            raise ConfigError(f"{dotted} expects true/false, got {value!r}")
    elif base in ("int", "float"):
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ConfigError(f"{dotted} expects a number, got {value!r}")
        if not math.isfinite(value):
            raise ConfigError(f"{dotted} must be a finite number, got {value!r}")
        if base == "int":
            if value != int(value):
                raise ConfigError(f"{dotted} expects a whole number, got {value!r}")
            value = int(value)
        else:
            value = float(value)
        lo, hi, lo_incl = RANGES.get(dotted, (None, None, True))
        if (lo is not None and (value < lo or (value == lo and not lo_incl))) or (hi is not None and value > hi):
            low = "" if lo is None else (f">= {lo}" if lo_incl else f"> {lo}")
            high = "" if hi is None else f"<= {hi}"
            raise ConfigError(f"{dotted} must be {' and '.join(x for x in (low, high) if x)}, got {value!r}")
    elif base == "str":
        if not isinstance(value, str):
            raise ConfigError(f"{dotted} expects text, got {value!r}")
        if dotted in CHOICES and value not in CHOICES[dotted]:
            raise ConfigError(f"{dotted} must be one of {', '.join(CHOICES[dotted])}; got {value!r}")
    elif base == "list[str]":
        if isinstance(value, str):
            value = [v.strip() for v in value.split(",") if v.strip()]
        if not isinstance(value, (list, tuple)) or not all(isinstance(v, str) for v in value):
            raise ConfigError(f"{dotted} expects a list of names, got {value!r}")
        if not value:
            raise ConfigError(f"{dotted} must not be empty")
        bad = [v for v in value if dotted in CHOICES and v not in CHOICES[dotted]]
        if bad:
            raise ConfigError(f"{dotted}: unknown {', '.join(map(repr, bad))}; choose from {', '.join(CHOICES[dotted])}")
        value = list(value)
    elif base == "list[float]":
        if isinstance(value, str):
            value = [v.strip() for v in value.split(",") if v.strip()]
        try:
            value = [float(v) for v in value] if isinstance(value, (list, tuple)) else None
        except (TypeError, ValueError):
            value = None
        signed = dotted in SIGNED_LISTS
        if value is None or (not value and not signed) or not all(math.isfinite(v) and (signed or v > 0) for v in value):
            raise ConfigError(f"{dotted} expects a {'list of numbers' if signed else 'non-empty list of positive numbers'}")
        if dotted in LIST_LENGTHS and len(value) not in LIST_LENGTHS[dotted]:
            raise ConfigError(f"{dotted} expects {' or '.join(map(str, LIST_LENGTHS[dotted]))} numbers, got {len(value)}")
    return value


class _Section:
    """Validates every assignment of a config section's field (:func:`check_value`)."""

    def __setattr__(self, name: str, value: Any) -> None:
        section = _SECTION_NAMES.get(type(self), type(self).__name__)
        annotations = type(self).__annotations__
        if name not in annotations:
            raise ConfigError(f"unknown key {name!r} in section {section!r}; keys: {sorted(annotations)}")
        object.__setattr__(self, name, check_value(f"{section}.{name}", annotations[name], value))


@dataclass
class RefsConfig(_Section):
    """Step 1: reference views rendered offline."""

    n_fibonacci: int = 115  # + 6 canonical box-aligned views = 121
    canonical: bool = True
    rotations: int = 8  # in-plane rotations, 360/rotations degrees apart (45°)
    size: int = 256  # side of the square, object-centred reference images, px (512 measured no better on LM-O, 6x the build)
    focal_factor: float = 4.0  # K_start focal = focal_factor * size (a long lens: weak perspective like far-away objects)
    crop_pad: float = 1.2  # square crop side = pad * max(bbox w, h) of the object's projection
    encodings: list[str] = field(default_factory=lambda: ["shade3_edges", "depth", "normal"])
    smooth_normals: bool = True
    store_rotated_encodings: bool = False  # keep the 8-bit images of every rotation (large); roll 0 always kept
    feature_rolls: str = "all"  # extract matcher features of 'all' rolls, or 'first' only (enough for match.in_plane=query)


@dataclass
class QueryConfig(_Section):
    """Step 2: the query crop."""

    crop_pad: float = 1.2  # same meaning as refs.crop_pad, applied to the given bbox / mask box
    mask_keypoints: bool = True  # drop query keypoints outside a given mask
    # a box without a mask: 'grabcut' segments the object's pixels in it by colour (pixie.pipeline.query.grabcut_mask)
    # and uses them as a given mask would be used; 'none' keeps the box alone
    segment: str = "none"


@dataclass
class MatchConfig(_Section):
    """Step 3: cross-modality matching."""

    matcher: str = "aliked-nn"
    max_keypoints: int = 1024
    detection_threshold: float | None = 0.0  # <= 0: keep the max_keypoints strongest (ALIKED's own 0.2 leaves ~10-100 on LM-O crops); None: backend default
    window: float | None = 0.125  # spatial window for NN matchers, fraction of refs.size (32 px at 256)
    in_plane: str = "reference"  # 'reference': rotated references (features precomputed); 'query': rotate the query crop
    weights_dir: str | None = None
    device: str = "cpu"


@dataclass
class PoseConfig(_Section):
    """Step 4: lifting and PnP + RANSAC."""

    ransac_iterations: int = 1000
    reprojection_px: float = 5.0  # RANSAC inlier threshold, in the pixels named by threshold_space
    threshold_space: str = "crop"  # 'image': original-image px; 'crop': px of the size x size query crop (scales with the object)
    confidence: float = 0.9999
    min_inliers: int = 6
    solver: str = "poselib"  # 'poselib' (LO-RANSAC/P3P + bundle adjustment, ~20x faster here) or 'opencv' (EPnP+RANSAC, LM refinement)
    mode: str = "per_view"  # 'per_view': best view wins; 'concat': all views in one PnP problem
    # 'inliers' (paper); 'combined': inliers x rotation-to-reference x box agreement; 'similarity' /
    # 'combined_similarity': summed inlier match similarity instead of the count; 'excess' / 'combined_excess':
    # summed inlier similarity above the query's background (median over all (view, roll) pairs of their mean
    # match similarity), which separates views where counts do not (bench/RESULTS.md, LM-O scoring experiments)
    scoring: str = "combined_excess"
    depth_from_bbox: bool = True  # re-derive z from the crop scale where PnP depth is unreliable
    top_k_views: int = 24  # coarse candidates kept for scoring / multi-hypothesis output
    # which (view, roll) pairs get PnP: 'excess' ranks them by summed match similarity above the query's
    # background level, 'count' by number of matches (on LM-O the view within 20° of the truth is in the top 24
    # for 18/48 targets by excess, 5/48 by count: bench/RESULTS.md)
    candidate_ranking: str = "excess"
    views: str = "all"  # 'all' reference views or 'canonical' (the paper's 6 coarse views) for the first pass


@dataclass
class RefineConfig(_Section):
    """Step 5: iterative view selection (the paper's), optional extras."""

    view_selection_iters: int = 1
    recrop: bool = True  # view selection re-crops the query around the best pose's projected (amodal) box, like the references
    n_hypotheses: int = 5
    # Render-at-estimate refinement (pixie.cues.refine): render the object at a hypothesis inside the query crop,
    # match the crop against that aligned render, re-solve PnP; repeated render_iters times for each of the
    # render_hypotheses best distinct hypotheses. 0 iterations = the paper's pipeline;
    # on LM-O (48 targets) 2 iterations x 6 hypotheses doubled ADD(-S)<0.1d (bench/RESULTS.md).
    render_iters: int = 2
    render_hypotheses: int = 6


PRESETS_DIR = Path(__file__).resolve().parent / "configs"
DEFAULT_PRESET = "default"


def preset_names() -> list[str]:
    """Names of the presets shipped in ``pixie/configs`` (sorted)."""
    return sorted(p.stem for p in PRESETS_DIR.glob("*.yaml"))


def preset_about(name: str) -> str:
    """The one-line description (``about:``) of a shipped preset."""
    return str(_read_yaml(_preset_path(name)).get("about", ""))


def _preset_path(name: str) -> Path:
    path = PRESETS_DIR / f"{name}.yaml"
    if not path.is_file():
        raise ConfigError(f"unknown preset {name!r}; presets: {', '.join(preset_names())}")
    return path


def _read_yaml(path: str | Path) -> dict[str, Any]:
    try:
        data = yaml.safe_load(Path(path).read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, yaml.YAMLError) as exc:
        raise ConfigError(f"cannot read config {path}: {type(exc).__name__}: {exc}") from exc
    if data is not None and not isinstance(data, dict):
        raise ConfigError(f"config {path} must be a mapping of sections, got {type(data).__name__}")
    return data or {}

@dataclass
class ShapeConfig(_Section):
    """Shape cues beside the matcher (pixie.cues.shape): contour templates, edge + region verification, region refinement.

    Measured on LM-O dev (bench/RESULTS.md, "Shape cues"): fusing them with the matcher raised ADD(-S)<0.1d on 96
    targets from 17 (the matcher's own choice in the same run) to 28. ``enabled=false`` is the pipeline without them.
    """

    enabled: bool = True
    views: int = 300  # template views (Fibonacci; nearest-view gap ~7°), rendered at `size` px (depth + normals)
    size: int = 128
    points: int = 96  # oriented contour points per template (silhouette + creases)
    rolls: int = 36  # in-plane angles searched (every 10°)
    crease_weight: float = 0.5
    min_mag: float = 6.0  # query gradient threshold (grey levels / px)
    region_k: int = 300  # best (view, roll) pairs by edges that get a region score before ranking
    region_weight: float = 1.0  # template ranking: edge + region_weight * (region - 0.5)
    candidates: int = 16  # best template poses (15° apart) added as hypotheses
    verify_matcher: int = 8  # best distinct matcher hypotheses verified beside them
    # verification score = w_match * matcher score / best matcher score + w_edge * edge + w_region * (region - 0.5);
    # set by bench/lmo_fusion.py's rule (most ADD hits, then most rotations < 15°, then the smallest total weight)
    # on 96 LM-O dev targets over the grid w_match {0..2} x w_edge {0..4} x w_region {0..4}
    w_match: float = 0.25
    w_edge: float = 0.5
    w_region: float = 4.0
    before_render: bool = False  # verify before render-at-estimate refinement (which then refines the best fused)
    refine_hypotheses: int = 0  # best verified hypotheses refined by region-based refinement (pixie.cues.region); 0: off
    refine_box_px: float = 96.0  # refinement crop: the box's longer side in px
    # with an object mask (given, or segmented: query.segment), the templates answer only to the photo's edges
    # within mask_px crop px of it (the clutter's edges around the object are left out)
    use_mask: bool = False
    mask_px: int = 5


def parse_override(item: str) -> tuple[str, str]:
    """The one reader of a ``section.key=value`` override (``--set``, study variants): ``(key, value text)``."""
    if not isinstance(item, str) or "=" not in item:
        raise ConfigError(f"override {item!r} must look like section.key=value")
    k, v = item.split("=", 1)
    return k.strip(), v.strip()


_SECTION_NAMES = {RefsConfig: "refs", QueryConfig: "query", MatchConfig: "match", PoseConfig: "pose",
                  RefineConfig: "refine", ShapeConfig: "shape"}


@dataclass
class AlignConfig(_Section):
    """Edge-based 6-DoF alignment of the best hypotheses to the photo (pixie.edge_align), then selection on the fit.

    The ``hypotheses`` best distinct candidates (after the shape stage) and the 180° flip twins of the best
    ``flips`` are aligned by Levenberg–Marquardt on the directional chamfer distance, coarse to fine over
    ``schedule`` (Tukey scales, px of a crop where the box's longer side spans ``object_px``). Every candidate's
    ranking score becomes the shape stage's fused score + ``w_fit`` * its aligned fit (share of visible
    contour points within ``fit_px`` of a same-orientation photo edge).
    """

    enabled: bool = True
    hypotheses: int = 4  # best distinct hypotheses aligned
    flips: int = 1  # ... and the 180° flip twins of this many of them
    # about which axes through the object's centre the twins turn: 'camera' (x, y: the outline mirrored), 'object'
    # (the model's own x, y, z: a near-box-shaped part modelled on its axes looks almost the same turned about one of
    # them) or 'both'. 'object', LM-O 716 on the same starts: 260 ADD(-S) hits / AR 0.496 against 261 / 0.499; defects
    # benchmark 92.3 % ADD < 1 cm either way (2 flips fixed, 2 made): not the default (bench/RESULTS.md, session 32)
    flip_axes: str = "camera"
    object_px: float = 200.0  # the box's longer side in the alignment crop, px
    # > 0: the first coarse_levels Tukey scales of schedule run on a second crop where the box spans coarse_px (the
    # scales converted to its px); its renders have (coarse_px / object_px)^2 of the pixels. 0: every scale on one crop.
    # LM-O 716 on the same starts, coarse_px 100: 233 ADD(-S) hits / AR 0.494 / median rotation 11.7° against 245 / 0.490
    # / 12.0°, align stage 1.35 vs 1.94 s per target (16 targets alone); it loses more than 1 % of the hits, so it is not
    # the default (bench/RESULTS.md, session 26)
    coarse_px: float = 0.0
    coarse_levels: int = 2
    # Tukey scales per level, crop px: 16 first widens the basin (rendered photos, box_taper 0: 12/12 within 1° / 1 % from
    # 10° / 5 %, 11/12 with half the part covered; LM-O 96 targets: 31 vs 29 ADD(-S) hits, median rotation 11.7° vs 14.0°)
    schedule: list[float] = field(default_factory=lambda: [16.0, 8.0, 4.0, 2.0])
    iters: int = 6  # LM iterations per level
    rerender: int = 2  # renders of the model (its contour points, visibility, colour posterior) per level
    # correspondences: 'region': silhouette points go where the colour foreground posterior (inside the current
    # silhouette against a band around it) steps to background along the normal, snapped to a same-orientation edge
    # within region_snap crop px (a point without a clear step keeps its edge: region_fallback), creases to the nearest
    # edge along the normal; 'normal': every point to the nearest same-orientation edge along its normal; 'nearest':
    # the nearest edge. LM-O dev, all 716 targets on the same starts: 247 ADD(-S) hits / AR 0.491 / median rotation
    # 11.9° against 216 / 0.474 / 13.5° for 'normal', better on both halves (snap 2 and the fallback chosen on the
    # 96-target basin; bench/RESULTS.md, session 23)
    search: str = "region"
    # a second correspondence search ('none', or one of search's choices): every start is also aligned with it and
    # both aligned poses join the pool (twice the alignments). LM-O 716, 'normal' with rerender 1: a right aligned
    # candidate for 383 targets (default 313) but 240 chosen (245); not the default (bench/RESULTS.md, session 25)
    extra_search: str = "none"
    region_snap: float = 2.0
    region_fallback: bool = True
    min_contrast: float = 0.0  # >0: silhouette points take only edges with this drop of the colour foreground posterior
    w_box: float = 1.0  # weight of each side of the given box (occlusion-aware: overshoot is robust) against the points
    # the box's weight is w_box * box_taper**k at the k-th Tukey scale. 0: the box sets depth at the coarsest scale only
    # and the finer scales fit the contour (rendered photos: 10/12 vs 5/12 within 1° / 1 %; LM-O 96 targets: same ADD,
    # median rotation 14.0° vs 18.8°; bench/RESULTS.md "Session 12: the box at the coarsest scale only")
    box_taper: float = 0.0
    crease_weight: float = 0.5
    # photo px by which a real photo's silhouette edge lies inside the object's geometric outline (blur, and shading
    # that falls off towards a curved outline): the model's silhouette points move inwards by as much. LM-O 716 on the
    # same starts: 0.25 -> 261 ADD(-S) hits / AR 0.499 / median rotation 11.4° (halves 125 / 136), 0.5 -> 234 (112 / 122),
    # 0 -> 245 / 0.490 / 12.0° (122 / 123); chosen on half 0, better on half 1 (bench/RESULTS.md, session 27)
    silhouette_inset_px: float = 0.25
    # a matcher hypothesis's PnP inliers as residuals too (interior points the contour does not constrain): their
    # total weight is w_matches x the contour points', Tukey scale match_px (crop px); 0 = contour and box only
    w_matches: float = 0.0
    match_px: float = 10.0
    rot_prior: float = 0.0  # pull towards the start rotation (px² per point per rad²); 0 = free
    # the photo's edge pixels: 'canny' (colour gradient, canny_low / canny_high) or 'edpf' (parameter-free Edge Drawing
    # per colour channel, cv2.ximgproc); LM-O basin from 10° / 3 %, 96 targets: 0.49 both (bench/RESULTS.md, session 23)
    edge_detector: str = "canny"
    # each photo edge where the linear-light gradient peaks (the sRGB curve moves an encoded blurred edge towards its
    # darker side by ~0.3-0.6 px: bright objects look larger, dark ones smaller)
    linear_edges: bool = False
    canny_low: float = 5.0  # Canny hysteresis thresholds, grey levels per photo pixel
    canny_high: float = 12.0
    fit_px: float = 1.5  # aligned fit: a contour point is supported by an edge this close (crop px)
    w_fit: float = 1.0  # ranking score = the shape stage's fused score + w_fit * aligned fit
    # ... + w_support * the aligned support: the share of visible contour points on an edge or (silhouette points) on
    # a step of the colour region within fit_px (EdgeFit.support_share: evidence that does not favour the edge search)
    # LM-O 716: no weight beats 0 on both halves, with or without extra_search (bench/RESULTS.md, session 25)
    w_support: float = 0.0
    # ... + w_silhouette * the aligned fit of the silhouette points alone (EdgeFit.silhouette_share). With object twins,
    # 0.1-1.5 on LM-O 716: 260-264 hits (noise); the rule (LM-O half 0 + the defects benchmark's even ids) picks 0
    # (bench/RESULTS.md, session 32)
    w_silhouette: float = 0.0
    # calibrated confidence = logistic(c0 + c1 * term1 + ...) of the chosen pose over confidence_terms (CONFIDENCE_TERMS;
    # size = projected diameter / 100 px, clipped), refitted by bench/lmo_select.py on the even half of the current
    # default's LM-O 716 poses (session 27's run): AUC 0.840 (0.80-0.88) on the odd half, reliable per bin (the session-14
    # fit said 0.4-0.6 for poses right 71 % of the time); bench/RESULTS.md "Session 28"; [] = the uncalibrated ratio
    confidence: list[float] = field(default_factory=lambda: [-5.641, 4.612, 1.955, 5.79])
    confidence_terms: list[str] = field(default_factory=lambda: ["fit", "size", "margin"])
    min_fit: float = 0.05  # a chosen pose with less aligned fit than this is flagged failed ("no edge support")
    prior_margin: float = 0.25  # estimate_from_prior without a box: the prior's box grown by this share of its size
    reset_fit: float = 0.3  # pixie track: a refined prior with less aligned fit is lost -> full search (bench/track.py)
    reset_ratio: float = 0.75  # ... or with less than this share of the recent frames' median fit (bench/track.py)

    def check_confidence(self) -> None:
        """Raise :class:`ConfigError` unless ``confidence`` is empty or holds the intercept and one coefficient per
        ``confidence_terms`` name (checked when a config is loaded, and again where the confidence is computed)."""
        if self.confidence and len(self.confidence) != 1 + len(self.confidence_terms):
            raise ConfigError(f"align.confidence has {len(self.confidence)} coefficients but align.confidence_terms "
                              f"names {len(self.confidence_terms)} terms: give the intercept and one coefficient per "
                              f"term ({1 + len(self.confidence_terms)} numbers), or [] for the uncalibrated ratio")


_SECTION_NAMES[AlignConfig] = "align"
CHOICES["align.search"] = ("normal", "nearest", "region")
FLIP_AXES = ("camera", "object", "both")  # pixie.cues.edge_align.flip_twins: about which axes the twins turn
CHOICES["align.flip_axes"] = FLIP_AXES
CHOICES["align.extra_search"] = ("none",) + CHOICES["align.search"]
CHOICES["align.edge_detector"] = ("canny", "edpf")
CHOICES["align.confidence_terms"] = CONFIDENCE_TERMS
RANGES.update({"align.region_snap": (0, 100, True), "align.min_contrast": (0, 1, True), "align.w_box": (0, None, True), "align.box_taper": (0, 1, True), "align.hypotheses": (0, 64, True), "align.flips": (0, 64, True), "align.object_px": (32, 2048, True),
               "align.coarse_px": (0, 2048, True), "align.coarse_levels": (0, 16, True),
               "align.iters": (1, 100, True), "align.rerender": (1, 100, True), "align.crease_weight": (0, 10, True),
               "align.silhouette_inset_px": (-10, 10, True), "align.rot_prior": (0, None, True),
               "align.canny_low": (0, None, True), "align.canny_high": (0, None, True), "align.fit_px": (0, 100, False),
               "align.w_fit": (0, None, True), "align.w_support": (0, None, True), "align.w_silhouette": (0, None, True), "align.min_fit": (0, 1, True),
               "align.w_matches": (0, None, True), "align.match_px": (0, 100, False),
               "align.prior_margin": (0, 4, True), "align.reset_fit": (0, 1, True),
               "align.reset_ratio": (0, 1, True)})


@dataclass
class PartsConfig(_Section):
    """The part report (pixie.cues.parts): each part's support at the final pose and a verdict, for meshes with parts
    (a GLB's sub-meshes, or connected components). flag_below, colour_weight, revealed_weight and shift_weight were
    chosen on the fitting half of the 336-photo defects benchmark by bench/defects_parts.py's rule (bench/RESULTS.md
    "Part verdicts", session 11)."""

    enabled: bool = True  # report parts when the mesh has them (median 0.4 s per photo on the defects benchmark)
    robust: bool = True  # re-align without the parts judged missing / displaced, then judge again (pixie.cues.parts)
    fit_px: float = 1.5  # a part's contour pixel is supported by a same-orientation photo edge this close (crop px)
    kinds: list[str] = field(default_factory=lambda: ["silhouette", "step", "seam"])  # contour pixels that count
    step_frac: float = 0.0  # a depth step counts when deeper than this share of the diameter (and 1 % of the depth)
    # the exclusive / revealed contours leave out pieces smaller than this, crop px (a stud a missing brick uncovers:
    # detail the photo does not resolve); 0 keeps them
    detail_px: float = 0.0
    # a contour pixel of the model with (without) the part is exclusive (revealed) only when the model without (with)
    # it has no contour pixel of a like orientation within this many crop px (a photo edge 2 px from both models' lines
    # is no evidence either way). Defects benchmark, 336 photos, estimated poses, configured thresholds: 1 -> 0.19 false
    # alarms per correct assembly (mean recall 0.79), 3 -> 0.06 (0.76); cross-fit 0.74 @ 0.17 -> 0.77 @ 0.10; 2 and 5
    # worse (bench/RESULTS.md, session 30)
    contrast_px: int = 3
    shift_frac: float = 0.12  # displaced-part search: slide the part's contour up to this share of the box's side
    min_points: int = 12  # fewer visible contour pixels: 'not visible'
    min_visible: float = 0.2  # less of the part in view (hidden by other parts, outside the box / mask): 'not visible'
    flag_below: float = 0.0  # a part whose score (below) is under this is flagged ('missing' ...
    colour_weight: float = 1.0  # score = relative edge support + this x (relative paint consistency, at most 1, - 1)
    # ... - this x the relative support of the contour its absence would reveal (pixie.cues.parts: the edges of what
    # is behind it); with revealed_weight > 0 the edge support is the part's exclusive contour's (what only it explains)
    revealed_weight: float = 1.0
    shift_weight: float = 0.0  # ... - this x the relative support a slide of its contour gains (displaced parts)
    colour_ab: float = 12.0  # chroma distance (CIELAB a*, b*) of "the same paint"
    supported_above: float = 1.0  # ... but never a part whose relative edge support is at least this (colour alone)
    shift_gain: float = 0.4  # ... 'displaced' when a shift raises its support by this (relative to the median)
    found_shifted: float = 0.97  # ... to at least this share of the median part's support)
    # 3D moves (pixie.cues.part_moves: along / about the model's axes) of the parts supported less than move_below x
    # the median part; 'displaced' when the best move gains move_gain of support where its contour differs. Off by
    # default: on the physical defects benchmark's report half shifted parts are found 0.61 -> 0.72 but false alarms
    # rise 0.21 -> 0.29 (move_gain 0.3; flips of bricks whose studs the photo cannot resolve), and the rule picks no
    # threshold (bench/RESULTS.md "Session 16"). --set parts.moves=true turns it on
    moves: bool = False
    move_below: float = 0.9
    move_gain: float = 0.3
    move_changed: float = 0.3  # a move is judged when it changes this share of the part's visible contour pixels ...
    move_px: float = 4.0  # ... and shifts some vertex of the part by this many crop px (pose errors are smaller)
    # ... and does not pass the part into another (pixie.geometry.collide: deeper than the CAD's own overlaps x 1.5;
    # parts whose surface is not closed are never said to collide)
    move_collide: bool = True
    # resizes (pixie.cues.part_moves.part_resizes: a part 1.5, 2 or 3x as long along one of the model's axes, one end
    # kept) of the parts the moves would test; 'wrong' (a part of another size: a longer bolt, a 2x6 brick for a 2x4)
    # when the best resize gains resize_gain of support where its contour differs. Off by default: on the defects
    # benchmark (two-fold cross-fit, bench/RESULTS.md session 34) the wrong part 0.72 -> 0.73 and missing 0.79 -> 0.83,
    # but false alarms 0.10 -> 0.15 per correct assembly (correct bricks fit a longer copy as well). --set
    # parts.resizes=true turns it on
    resizes: bool = False
    resize_gain: float = 0.25
    # the lengths a resize tries, x the CAD part's (along one model axis, one end kept). Shorter ones (0.5, 0.75) found
    # no wrong part more per assembly on the defects benchmark's seeds 0-3 (they are tried only on parts supported
    # less than move_below x the median, and a part a little too short keeps most of its contour; session 38)
    resize_factors: list[float] = field(default_factory=lambda: [1.5, 2.0, 3.0])
    # one photo's resizes are tried on the parts supported less than this x the median part (as the moves)
    resize_below: float = 0.9
    # one assembly in several photos (pixie.cues.part_views.combine_views; a batch's 'assembly' groups): a part whose
    # best 3D move (resize) gains on average over its photos at least this is 'displaced' ('wrong'); above 1: never
    # (a gain is at most 1). Chosen on the defects benchmark's seed 0 (bench/defects_seeds.py 'views': the best mean
    # recall per assembly adding no false alarm; move 0.4, resizes none) and judged on seeds 1 and 2 (new assemblies):
    # mean recall per assembly 0.717 -> 0.800 and 0.637 -> 0.738, false alarms 0.083 -> 0.083 and 0 -> 0.083 per
    # correct assembly (bench/RESULTS.md, session 37). On seed 3 (session 38, generated after this choice): missing /
    # shifted / rotated / wrong 0.94 / 0.47 / 0.75 / 0.73 per assembly at 0.083 false alarms (0.94 / 0.80 / 0.83 / 0.67
    # at the true poses: the shifted bricks it misses are in photos whose pose is wrong)
    views_move_gain: float = 0.4
    # the resizes (views_resize_factors, on views_resize_below): session 38's longer ones on weakly supported parts,
    # fitted on seeds 0-2, added false alarms on seed 3 (0.083 -> 0.25) and did not ship. Session 40: parts *shorter*
    # along one model axis (0.5, 0.75, one end kept), tried on every part in view, one resize's gain averaged over the
    # photos (views_resize_same). Rule written before any such row was scored: the grid of factors {0.5,0.75 | 0.75 |
    # 0.5 | all five} x same {true, false} x gain {0.05 ... 0.4}, the best mean wrong-part recall per assembly on seeds
    # 0-3 at the true poses adding no false alarm on any of them -> 0.5 and 0.75, same, 0.4 (wrong 0.80 / 0.56 / 0.53 /
    # 0.67 -> 0.80 / 0.56 / 0.73 / 0.73). Judged on seed 4 (not looked at): true poses 0.47 -> 0.60, estimated poses
    # 0.40 -> 0.53, false alarms per correct assembly 0 -> 0 at both (bench/RESULTS.md, session 40)
    views_resize_gain: float = 0.4
    # ... the gain of one resize averaged over all the photos (true: one physical change every photo must support), or
    # of each photo's best resize (false)
    views_resize_same: bool = True
    # the resizes an assembly's verdict reads (views_resize_gain), tried on every part supported less than
    # views_resize_below x the median part (100: every part in view: a part a little too short keeps most of its contour)
    views_resize_factors: list[float] = field(default_factory=lambda: [0.5, 0.75])
    views_resize_below: float = 100.0
    # an assembly's verdict leaves out its photos whose pose's aligned fit (the result's 'fit') is below this (when all
    # are, none is left out): a part report at a wrong pose is noise. Session 38 chose 0.3 on the defects benchmark's
    # seeds 0-2; session 39 refitted it on seeds 0-3 by the same rule (best mean recall per assembly over 0.3 / 0.4 /
    # 0.45 / 0.5 / 0.55 / 0.6, no seed's false alarms above 0.3's): 0.5 (0.816 -> 0.824), then judged it on seed 4
    # (generated after): mean recall per assembly 0.708 -> 0.741 (shifted 0.73 -> 0.80, wrong 0.40 -> 0.47), false
    # alarms 0 -> 0 per correct assembly (bench/RESULTS.md, session 39)
    views_min_fit: float = 0.5
    # compute that evidence for every photo even with parts.moves / parts.resizes off; no single photo is judged on it
    # (a batch with 'assembly' groups turns it on itself when views_move_gain / views_resize_gain can flag)
    evidence: bool = False
    # a part not visible at the chosen pose takes its verdict at the runner-up (the best distinct hypothesis) when that
    # one is turned at least alt_min_deg from it and scores within alt_gap (pixie.cues.parts.is_flip_runner_up): the
    # defect of a near-symmetric assembly is often its only asymmetric detail, and the pose that hides it fits the
    # contour as well. Defects benchmark, the estimator's runner-ups (bench/defects_parts.py, bench/RESULTS.md session
    # 33): the rule (best mean recall at <= 0.05 false alarms on one half; ties: the middle gap) picks 0.25 on both
    # halves, the plateau is 0.15-0.5; configured thresholds, all 336 photos: missing 0.75 -> 0.81, wrong 0.70 -> 0.73,
    # false alarms 0.062 unchanged. 0: off
    alt_gap: float = 0.25
    alt_min_deg: float = 150.0
    # paint spill (pixie.cues.part_paint): each photo measures how much of each part's paint shows in a band around it
    # where the model at the pose shows another paint or the background (the result's 'paint_spill'; ~0.1 s a photo).
    # An assembly's part whose spill, capped at spill_cap per photo, averages at least views_spill over its photos is
    # 'wrong' (a larger part than the CAD's: its contour is all there, and more paint around it); above 1: never.
    # Off: fitted on the defects benchmark's seeds 0-3 (0.3, cap 0.5: wrong parts per assembly 0.50 / 0.40 -> 0.67 /
    # 0.53 on seeds 1 / 2, no false alarm added), it found no wrong part more on seed 4 (0.40; its wrong parts are
    # mostly smaller than the CAD's, or grey); correct parts there spill <= 0.09 (bench/RESULTS.md, session 39)
    spill: bool = True
    views_spill: float = 2.0
    spill_cap: float = 0.5


_SECTION_NAMES[PartsConfig] = "parts"
PART_KINDS = ("silhouette", "step", "seam", "crease")  # pixie.cues.parts.part_contours' kinds 0..3
CHOICES["parts.kinds"] = PART_KINDS
RANGES.update({"parts.fit_px": (0, 100, False), "parts.shift_frac": (0, 1, True), "parts.min_points": (1, None, True),
               "parts.min_visible": (0, 1, True), "parts.flag_below": (-10, 10, True), "parts.shift_gain": (0, None, True),
               "parts.found_shifted": (0, None, True), "parts.colour_weight": (0, 100, True), "parts.supported_above": (0, 100, True),
               "parts.colour_ab": (0, 300, False), "parts.step_frac": (0, 1, True),
               "parts.detail_px": (0, 1000, True), "parts.contrast_px": (1, 20, True),
               "parts.revealed_weight": (0, 100, True), "parts.shift_weight": (0, 100, True),
               "parts.move_below": (0, 100, True), "parts.resize_below": (0, 100, True), "parts.views_resize_below": (0, 1000, True), "parts.move_gain": (-1, 1, True), "parts.move_changed": (0, 10, True),
               "parts.move_px": (0, 1000, True), "parts.alt_gap": (0, None, True),
               "parts.resize_gain": (-1, 1, True), "parts.views_min_fit": (0, 1, True), "parts.views_resize_gain": (0, 2, False),
               "parts.views_move_gain": (0, 2, False), "parts.views_spill": (0, 2, False),
               "parts.spill_cap": (0, 1, False),
               "parts.alt_min_deg": (0, 180, True)})


@dataclass
class DetectConfig(_Section):
    """Finding the object without a box (``pixie estimate --detect``, :func:`pixie.pipeline.find.find_objects`):
    LINE-2D proposals (pixie.cues.detect), each estimated, the poses the photo supports kept.

    An estimate is accepted when ``logistic(accept[0] + accept[1] * term1 + ...)`` over ``accept_terms`` (its named
    scores, :func:`pixie.pipeline.find.proposal_terms`) reaches ``min_accept``; [] = the estimate's own calibrated
    confidence reaches ``min_accept`` and its pose's box overlaps the proposal by ``min_box_iou``.
    """

    proposals: int = 5  # proposals estimated per round (best first)
    threshold: float = 70.0  # LINE-2D similarity (0-100) a match needs
    nms_iou: float = 0.3  # a box overlapping a better one by this IoU is suppressed ...
    grow_ratio: float = 1.3  # ... unless its area is more than this x the better box's (0: plain suppression)
    # the best vote_pool distinct boxes ordered by LINE-2D similarity + vote_weight x the other pool boxes inside them
    # (vote_inside of their area: parts of the object that fired on their own); 0 = LINE-2D's order. Rule (session 18,
    # the defects benchmark's first 48 targets): most right boxes among the best 5, then among the best 1, then the
    # smallest weight, on the grid weight 0/1/2/3/5/8 x pool 10/20
    vote_pool: int = 10
    vote_weight: float = 3.0
    vote_inside: float = 0.8
    # ... + region_weight x 100 x (colour-region separation - 0.5) of the best region_pool boxes' rendered template poses
    # (pixie.cues.detect.template_region; band region_band of the silhouette's side). Rule (session 22, LM-O's first 24
    # of select_targets(48)): most right boxes among the best 5, then the best 1, then the smaller weight, on the grid
    # 0/0.1/0.2/0.3/0.5/1 x pool 20/50/100; checked on the defects benchmark (bench/RESULTS.md "Session 22")
    region_pool: int = 50
    region_weight: float = 0.5
    region_band: float = 0.15
    stop_confidence: float = 0.9  # no more proposals are estimated once a pose is accepted at this (0: never stop)
    min_accept: float = 0.5
    min_box_iou: float = 0.5  # (the rule without accept coefficients)
    accept: list[float] = field(default_factory=list)
    accept_terms: list[str] = field(default_factory=lambda: ["confidence"])

    def check_accept(self) -> None:
        """Raise :class:`ConfigError` unless ``accept`` is empty or holds the intercept and a coefficient per term."""
        if self.accept and len(self.accept) != 1 + len(self.accept_terms):
            raise ConfigError(f"detect.accept has {len(self.accept)} coefficients but detect.accept_terms names "
                              f"{len(self.accept_terms)} terms: give the intercept and one coefficient per term "
                              f"({1 + len(self.accept_terms)} numbers), or [] for the confidence rule")


_SECTION_NAMES[DetectConfig] = "detect"
# what an estimated proposal's acceptance may be computed from (pixie.pipeline.find.proposal_terms)
ACCEPT_TERMS = ("confidence", "line2d", "box_iou", "fit", "fit_silhouette", "fit_visible", "fit_dist", "edge",
                "region", "fused", "margin", "size", "full_fit", "full_silhouette", "full_visible")
CHOICES["detect.accept_terms"] = ACCEPT_TERMS
SIGNED_LISTS.add("detect.accept")
LIST_LENGTHS["detect.accept"] = tuple(range(0, len(ACCEPT_TERMS) + 2))
RANGES.update({"detect.proposals": (1, 1000, True), "detect.threshold": (0, 100, True), "detect.nms_iou": (0, 1, True),
               "detect.grow_ratio": (0, None, True),
               "detect.vote_pool": (1, 1000, True), "detect.vote_weight": (0, None, True),
               "detect.vote_inside": (0, 1, False), "detect.stop_confidence": (0, 1, True),
               "detect.region_pool": (0, 1000, True), "detect.region_weight": (0, None, True),
               "detect.region_band": (0, 1, False),
               "detect.min_accept": (0, 1, True), "detect.min_box_iou": (0, 1, True)})


@dataclass
class PixieConfig:
    refs: RefsConfig = field(default_factory=RefsConfig)
    query: QueryConfig = field(default_factory=QueryConfig)
    match: MatchConfig = field(default_factory=MatchConfig)
    pose: PoseConfig = field(default_factory=PoseConfig)
    refine: RefineConfig = field(default_factory=RefineConfig)
    shape: ShapeConfig = field(default_factory=ShapeConfig)
    align: AlignConfig = field(default_factory=AlignConfig)
    parts: PartsConfig = field(default_factory=PartsConfig)
    detect: DetectConfig = field(default_factory=DetectConfig)
    preset: str | None = field(default=None, compare=False)  # name of the preset it started from (None: dataclass defaults)

    def to_dict(self) -> dict[str, Any]:
        """The config sections as plain data (the preset name is not part of it: only values count)."""
        d = dataclasses.asdict(self)
        d.pop("preset", None)
        return d

    def digest(self) -> str:
        """sha256 (hex, 16 characters) of :meth:`to_dict`: equal digests mean equal settings."""

        return hashlib.sha256(json.dumps(self.to_dict(), sort_keys=True).encode()).hexdigest()[:16]

    def update(self, data: dict[str, Any] | None) -> "PixieConfig":
        """Set every ``{section: {key: value}}`` of ``data`` (a top-level ``about`` string is ignored), each
        value validated (:class:`ConfigError` naming ``section.key``)."""
        if data is not None and not isinstance(data, dict):
            raise ConfigError(f"a config must be a mapping of sections, got {type(data).__name__}")
        for section, values in (data or {}).items():
            if section == "about" or values is None:
                continue
            if not isinstance(values, dict):
                raise ConfigError(f"config section {section!r} must be a mapping of key: value, got {values!r}")
            for key, value in values.items():
                self.set(f"{section}.{key}", value)
        return self.check()

    def check(self) -> "PixieConfig":
        """Checks between keys (each key alone is checked when set): the calibrated confidence and the detection's
        acceptance have one coefficient per term plus the intercept."""
        self.align.check_confidence()
        self.detect.check_accept()
        return self

    @classmethod
    def from_dict(cls, data: dict[str, Any] | None) -> "PixieConfig":
        return cls().update(data)

    @classmethod
    def from_yaml(cls, path: str | Path) -> "PixieConfig":
        return cls().update_from_yaml(path)

    @classmethod
    def from_preset(cls, name: str = DEFAULT_PRESET) -> "PixieConfig":
        """The dataclass defaults with the preset ``name`` (``fast``, ``default``, ``paper``) applied."""
        cfg = cls().update_from_yaml(_preset_path(name))
        cfg.preset = name
        return cfg

    def update_from_yaml(self, path: str | Path) -> "PixieConfig":
        """Apply a YAML file of sections on top of this config (e.g. a user file over a preset); errors name the file."""
        data = _read_yaml(path)
        try:
            return self.update(data)
        except ConfigError as exc:
            raise ConfigError(f"{path}: {exc}") from exc

    def set(self, dotted: str, value: Any) -> None:
        """Set ``section.key`` to ``value`` (strings are parsed as YAML scalars/lists)."""
        if "." not in dotted:
            raise ConfigError(f"config key {dotted!r} must look like section.key")
        section, key = dotted.split(".", 1)
        sec = getattr(self, section, None)
        if sec is None or not dataclasses.is_dataclass(sec):
            raise ConfigError(f"unknown config section {section!r}; sections: {[f.name for f in dataclasses.fields(self)]}")
        names = {f.name: f for f in dataclasses.fields(sec)}
        if key not in names:
            raise ConfigError(f"unknown key {key!r} in section {section!r}; keys: {sorted(names)}")
        if isinstance(value, str) and value != "":
            try:
                value = yaml.safe_load(value)
            except yaml.YAMLError as exc:
                raise ConfigError(f"{dotted}: cannot parse {value!r} as a YAML value") from exc
        setattr(sec, key, value)  # validated by the section (_Section.__setattr__)

    def apply_overrides(self, overrides: list[str] | None) -> "PixieConfig":
        for item in overrides or []:
            self.set(*parse_override(item))
        return self.check()
