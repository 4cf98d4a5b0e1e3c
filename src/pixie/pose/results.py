"""What the estimator returns: pose hypotheses and the result record, with what their numbers mean.

:class:`Hypothesis` is one candidate pose with its PnP support; :class:`PoseResult` the chosen pose, its
distinct runners-up and the inputs it came from; :func:`set_confidences` the (uncalibrated) confidence of each.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from pixie._version import __version__

__all__ = ["Hypothesis", "PoseResult", "set_confidences", "FRAME", "SCORE_NOTE", "CONFIDENCE_NOTE", "CALIBRATED_NOTE",
           "NO_BOX_MESSAGE", "NO_BOX_WHY", "no_box_message"]

FRAME = ("OpenCV camera (x right, y down, z forward); T_cam_from_obj maps object points (mm, the mesh's frame) "
         "to camera points: x_cam = R x_obj + t")
SCORE_NOTE = ("support of the pose: summed match similarity of its PnP inliers above the photo's background level, "
              "times rotation-consistency and box-agreement factors (pose.scoring); comparable between the "
              "hypotheses of one photo only")
CONFIDENCE_NOTE = ("score / (score + the best distinct alternative's score): how much a hypothesis stands out, "
                   "0.5 = a tie. Not calibrated: it is not a probability that the pose is correct")

CALIBRATED_NOTE = ("estimated probability that the pose is right (ADD(-S) < 0.1 diameter), from the terms "
                   "config.align.confidence_terms names (by default its aligned edge fit, the object's projected size and "
                   "its margin over the best distinct alternative); calibrated on LM-O dev photos with ground-truth "
                   "boxes (AUC 0.84 on held-out targets; bench/RESULTS.md, 'Session 28'): other objects, cameras or boxes may be "
                   "calibrated differently")

NO_BOX_WHY = "pixie does not guess where the object is (the box sets the crop and the object's distance)"


def no_box_message(box: str, mask: str, whole: str) -> str:
    """The one "no object box" message, in the words of one interface (Python, the command line)."""
    return (f"no object box: pass {box} in pixels (w, h counting pixels) or {mask} (white = object); {NO_BOX_WHY}. "
            f"To use the whole image on purpose pass {whole}")


NO_BOX_MESSAGE = no_box_message("bbox=(x, y, w, h)", "mask=... (boolean array or mask image)", "bbox=(0, 0, width, height)")


UNIT_MM = {"mm": 1.0, "cm": 10.0, "m": 1000.0}
VIEW_NOTE = ("view / roll: the reference view (0..views-1) and in-plane roll (0..rolls-1) whose matches gave the "
             "pose's hypothesis; -1 / -1 when it came from a contour template, the edge alignment or a prior, and "
             "n_inliers is then 0 by construction (not a sign of failure: see confidence and message)")
SOURCE_NOTE = ("source of the returned pose: 'reference' / 'view_selection' / 'recrop' (matcher + PnP), 'edges' "
               "(contour template), 'region' (region-refined), 'aligned' (edge alignment of one of those), 'flip' "
               "(the alignment of a 180-degree flip twin), 'prior' (refined from --init-pose / tracking)")


@dataclass(kw_only=True)
class Hypothesis:
    """One candidate pose: from reference (view, roll), with its PnP support; built with keywords only.

    Every score is its own field and kept: ``match_score`` (the matcher's: PnP support, :data:`SCORE_NOTE`),
    ``edge`` and ``region`` (shape-cue agreement), ``fused`` (their fusion, ``pixie.cues.shape.fused_score``),
    ``fit`` (the aligned edge fit, ``config.align``). ``score`` is the ranking score: the matcher's until shape
    verification, then the fused one, then ``fused + w_fit * fit`` for the aligned candidates.
    """

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
    source: str = "reference"  # 'reference' (first pass), 'view_selection', 'recrop' or 'render' (render-at-estimate)
    confidence: float = 0.0  # set for returned hypotheses: score / (score + the best other distinct score)
    # shape cues (config.shape): source may also be 'edges' (contour template) or 'region' (region-refined)
    match_score: float = 0.0  # the matcher's score (kept when shape verification sets ``score`` to ``fused``)
    edge: float = float("nan")  # edge agreement (pixie.cues.shape), when verified
    region: float = float("nan")  # region agreement, when verified
    fused: float = float("nan")  # the fused verification score (the ranking ``score`` once verified)
    fit: float = float("nan")  # aligned edge fit (pixie.cues.edge_align.edge_fit), when config.align scored it;
    # then ``score`` = fused + align.w_fit * fit
    terms: dict = field(default_factory=dict)  # every verification term (pixie.cues.shape.ShapeCues.verify_terms)
    matcher_best: bool = False  # the matcher's own choice (what the pipeline returns without shape cues)
    # the PnP inliers it was solved from: photo px (n, 2) and object mm (n, 3); None for edge-template, flip or
    # prior hypotheses (the edge alignment keeps them as residuals, config.align.w_matches)
    support_uv: np.ndarray | None = field(default=None, repr=False)
    support_xyz: np.ndarray | None = field(default=None, repr=False)


@dataclass
class PoseResult:
    """What :meth:`PoseEstimator.estimate` returns. ``failed`` results still carry the best guess.

    ``T_cam_from_obj`` is in mm, OpenCV camera frame (:data:`FRAME`). ``confidence`` (:data:`CONFIDENCE_NOTE`)
    is not calibrated. The inputs used are recorded: ``K``, ``box_xyxy`` (the crop box, clipped to the image)
    and ``box_source`` ('bbox' or 'mask'), the mesh's sha256, the preset, config digest and matcher device.
    """

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
    K: np.ndarray | None = None
    box_xyxy: np.ndarray | None = None
    box_source: str | None = None
    mesh_name: str | None = None
    mesh_sha256: str | None = None
    mesh_file_units: str | None = None  # the units the mesh file was read in ('mm', 'cm', 'm'); poses are in mm
    preset: str | None = None
    config_digest: str | None = None
    device: str | None = None
    # unusual but accepted inputs (intrinsics for the image size, a box leaving the image) and poses that their
    # inputs make doubtful (pixie.pose.plausibility.pose_warnings); the app adds the console's warnings (EXIF ...)
    warnings: list[str] = field(default_factory=list)
    candidates: list[Hypothesis] = field(default_factory=list, repr=False)  # every ranked hypothesis (studies; not saved)
    confidence_calibrated: bool = False  # confidence is the calibrated probability (config.align.confidence)
    settings: dict = field(default_factory=dict)  # what ran where the reference set decides (pixie.app.notes)
    # the part report (meshes with parts, config.parts): one record per part (pixie.cues.parts.PartSupport.as_dict)
    parts: list[dict] = field(default_factory=list)
    part_support: list = field(default_factory=list, repr=False)  # the PartSupport objects (points for overlays)

    @property
    def suspect_parts(self) -> list[str]:
        """Names of the parts judged missing or displaced (empty without a part report)."""
        return [p["name"] for p in self.parts if p.get("verdict") in SUSPECT_VERDICTS]

    def to_dict(self) -> dict:
        """Everything as JSON-able data (poses as nested lists, mm)."""
        box = None
        if self.box_xyxy is not None:
            x0, y0, x1, y1 = (float(v) for v in self.box_xyxy)
            box = {"xywh": [x0, y0, x1 - x0, y1 - y0], "source": self.box_source}
        return {
            "pixie_version": __version__,
            "units": "mm",
            "frame": FRAME,
            "T_cam_from_obj": None if self.T_cam_from_obj is None else self.T_cam_from_obj.tolist(),
            "failed": self.failed, "message": self.message,
            "score": self.score, "score_note": SCORE_NOTE,
            "confidence": self.confidence,
            "confidence_note": CALIBRATED_NOTE if self.confidence_calibrated else CONFIDENCE_NOTE,
            "n_inliers": self.n_inliers, "view": self.view, "roll": self.roll, "view_note": VIEW_NOTE,
            "source": self.hypotheses[0].source if self.hypotheses else None, "source_note": SOURCE_NOTE,
            "fit": (float(self.hypotheses[0].fit) if self.hypotheses and np.isfinite(self.hypotheses[0].fit)
                    else None), "fit_note": FIT_NOTE,
            "K": None if self.K is None else np.asarray(self.K).tolist(),
            "box": box,
            "mesh": {"name": self.mesh_name, "sha256": self.mesh_sha256, "file_units": self.mesh_file_units,
                     "scale_to_mm": None if self.mesh_file_units is None else UNIT_MM.get(self.mesh_file_units),
                     "note": "the mesh file's coordinates x scale_to_mm = the model frame of T_cam_from_obj (mm)"},
            "mesh_sha256": self.mesh_sha256,
            "preset": self.preset, "config_digest": self.config_digest, "device": self.device,
            "timings": self.timings,
            "warnings": self.warnings,
            "settings": self.settings,
            **({"parts": self.parts, "parts_note": PARTS_NOTE, "suspect_parts": self.suspect_parts}
               if self.parts else {}),
            "hypotheses": [
                {"T_cam_from_obj": h.T_cam_from_obj.tolist(), "score": h.score, "confidence": h.confidence,
                 "n_inliers": h.n_inliers, "view": h.view, "roll": h.roll, "source": h.source} for h in self.hypotheses
            ],
        }


FIT_NOTE = ("the pose's aligned edge fit: the share of the model's visible contour points (rendered at the pose) "
            "within align.fit_px of a same-orientation photo edge (pixie.cues.edge_align.edge_fit); null when the "
            "alignment did not score the pose")
SUSPECT_VERDICTS = ("missing", "displaced", "wrong")  # the part report's verdicts that flag a part (pixie.cues.parts)
PARTS_NOTE = ("per part of the CAD model at the final pose: support = share of its visible contour pixels "
              "(silhouette, depth steps, seams) within parts.fit_px of a same-orientation photo edge; relative = "
              "support / the median part's; shifted_support = the best support with the contour slid up to "
              "parts.shift_frac of the box (shift_px: by how far, photo px); visible = share of the part in view; "
              "move / move_gain = the 3D move of the part (along / about the model's axes) that the photo supports "
              "best and its support gain where the moved contour differs (parts supported below parts.move_below of "
              "the median part only); "
              "verdict present / missing / displaced / not visible (thresholds config.parts, calibrated on the "
              "synthetic defects benchmark; meaningful when the pose is right)")


def set_confidences(hyps: list[Hypothesis]) -> None:
    """Each hypothesis's confidence: its score / (its score + the best score among the others); 0 for score 0.

    For the best of ``hyps`` (distinct poses, best first) this is best / (best + second).
    """
    for i, h in enumerate(hyps):
        other = max((g.score for j, g in enumerate(hyps) if j != i), default=0.0)
        h.confidence = float(h.score / (h.score + other)) if h.score > 0 else 0.0
