"""Scores (bop_toolkit's ``score`` half): BOP greedy matching, recall, AR and their aggregation, and the
records of an evaluation (:class:`TargetResult` per GT instance, :class:`Scores` overall)."""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field
from typing import Iterable, Sequence

import numpy as np

from pixie.errors import ConfigError
from pixie.eval.datasets import GtInstance
from pixie.eval import pose_error as M
from pixie.eval.pose_error import MSPD_THRESHOLDS

ALL_METRICS = ("mssd", "mspd", "vsd", "add", "adds", "ad", "aps")
DEFAULT_METRICS = ("mssd", "mspd", "vsd", "add", "adds", "ad")
METRIC_ALIASES = {"add-s": "adds", "add_s": "adds", "add(-s)": "ad", "adds_or_add": "ad"}
ADD_NAMES = {"add": "ADD", "adds": "ADD-S", "ad": "ADD(-S)"}
ADD_ABS_THRESHOLDS_MM = (5.0, 10.0, 50.0)  # 0.5 / 1 / 5 cm (paper Table II)
ADD_REL_THRESHOLD = 0.1  # fraction of the diameter


# --------------------------------------------------------------------------------------------
# Records
# --------------------------------------------------------------------------------------------


@dataclass
class TargetResult:
    """Errors of one valid GT instance against the estimate assigned to it.

    The assignment is BOP's greedy one without a threshold (by decreasing score, each estimate
    takes the valid unmatched instance with the smallest MSSD, or the first metric evaluated).
    ``errors`` holds inf for metrics of a target without an estimate (``has_estimate`` False).
    Units: mssd, add, adds, ad in mm; mspd in px; vsd = mean of the per-tau errors; aps in [0, 1].
    """

    scene_id: int
    im_id: int
    obj_id: int
    gt_id: int
    visib_fract: float | None
    has_estimate: bool
    score: float | None
    T_gt: np.ndarray
    T_est: np.ndarray | None
    errors: dict[str, float] = field(default_factory=dict)
    vsd_per_tau: list[float] | None = None

    def to_dict(self) -> dict:
        d = asdict(self)
        d["T_gt"] = self.T_gt.tolist()
        d["T_est"] = None if self.T_est is None else self.T_est.tolist()
        d["errors"] = {k: _json_num(v) for k, v in self.errors.items()}
        return d


@dataclass
class Scores:
    """Aggregate and per-target results of :func:`evaluate`.

    Attributes
    ----------
    overall : dict
        Keys (present when the metric was evaluated): ``AR``, ``AR_noVSD``, ``AR_MSSD``,
        ``AR_MSPD``, ``AR_VSD`` (None without depth), ``ADD(-S)<0.1d``, ``ADD<0.5cm``,
        ``ADD<1cm``, ``ADD<5cm``, ``mean_ADD``, ``median_ADD`` (mm) and the same for
        ``ADD-S`` / ``ADD(-S)``, ``mean_APS``, ``n_targets``, ``n_missing``.
    per_object : {obj_id: dict} with the same keys.
    curves : {metric: {"thresholds": [...], "recall": [...]}} overall recall curves.
    """

    dataset: str
    metrics: list[str]
    vsd_available: bool
    vsd_note: str
    n_targets: int
    n_estimates: int
    n_ignored_estimates: int
    overall: dict[str, float | None]
    per_object: dict[int, dict[str, float | None]]
    curves: dict[str, dict]
    targets: list[TargetResult]
    avg_time_per_image: float | None
    time_s: float

    def to_dict(self, with_targets: bool = True) -> dict:
        d = {
            "dataset": self.dataset,
            "metrics": self.metrics,
            "vsd_available": self.vsd_available,
            "vsd_note": self.vsd_note,
            "n_targets": self.n_targets,
            "n_estimates": self.n_estimates,
            "n_ignored_estimates": self.n_ignored_estimates,
            "overall": {k: _json_num(v) for k, v in self.overall.items()},
            "per_object": {str(o): {k: _json_num(v) for k, v in s.items()} for o, s in self.per_object.items()},
            "curves": self.curves,
            "avg_time_per_image": self.avg_time_per_image,
            "eval_time_s": self.time_s,
        }
        if with_targets:
            d["targets"] = [t.to_dict() for t in self.targets]
        return d


def _json_num(v):
    if isinstance(v, (float, np.floating)):
        v = float(v)
        return v if math.isfinite(v) else None
    if isinstance(v, np.integer):
        return int(v)
    return v


# --------------------------------------------------------------------------------------------
# Matching, recall, AR
# --------------------------------------------------------------------------------------------


def count_matches(errors: np.ndarray, valid: np.ndarray, thresholds: np.ndarray) -> np.ndarray:
    """BOP greedy matching of estimates to GT instances, for several thresholds at once.

    Estimates (rows, already sorted by decreasing score) are taken in order; each is matched
    to the not-yet-matched valid GT with the smallest error, provided that error is strictly
    below the threshold.

    Parameters
    ----------
    errors : (E, G) errors of each estimate w.r.t. each GT instance of the same object
    valid : (G,) bool, GT instances that count as targets
    thresholds : (T,)

    Returns
    -------
    (T,) int, number of matched valid GT instances per threshold.
    """
    errors = np.asarray(errors, dtype=np.float64)
    ths = np.asarray(thresholds, dtype=np.float64).reshape(-1)
    valid = np.asarray(valid, dtype=bool)
    E, G = errors.shape
    matched = np.zeros((len(ths), G), dtype=bool)
    if E == 0 or G == 0:
        return matched.sum(axis=1)
    for e in range(E):
        cand = valid[None, :] & ~matched & (errors[e][None, :] < ths[:, None])
        if not cand.any():
            continue
        masked = np.where(cand, errors[e][None, :], np.inf)
        best = masked.argmin(axis=1)
        rows = np.nonzero(cand.any(axis=1))[0]
        matched[rows, best[rows]] = True
    return matched.sum(axis=1)


def recall_at(errors: np.ndarray, thresholds: Sequence[float]) -> np.ndarray:
    """Fraction of targets with ``error < threshold`` for each threshold (single-instance
    shortcut of BOP matching; missing estimates should be passed as ``inf``)."""
    e = np.asarray(errors, dtype=np.float64).reshape(-1)
    ths = np.asarray(thresholds, dtype=np.float64)
    if e.size == 0:
        return np.zeros(len(ths))
    return (e[None, :] < ths[:, None]).mean(axis=1)


def average_recall(recalls: Sequence[float]) -> float:
    """Mean of recall values (AR of one BOP error function)."""
    r = np.asarray(recalls, dtype=np.float64)
    return float(r.mean()) if r.size else float("nan")


def mspd_thresholds(image_width: int) -> np.ndarray:
    """MSPD thresholds in px for an image of this width (BOP: 5..50 px at 640 px)."""
    return MSPD_THRESHOLDS * (image_width / 640.0)


def normalize_metrics(metrics: Iterable[str]) -> list[str]:
    """Lower-case, resolve aliases, check names, keep order without duplicates."""
    out: list[str] = []
    for m in metrics:
        key = METRIC_ALIASES.get(m.strip().lower(), m.strip().lower())
        if key not in ALL_METRICS:
            raise ConfigError(f"unknown metric {m!r}; choose from {', '.join(ALL_METRICS)}")
        if key not in out:
            out.append(key)
    return out


def valid_gt_mask(gts: list[GtInstance], inst_count: int) -> np.ndarray:
    """The ``inst_count`` most visible instances are valid (BOP'19 with visib_gt_min = -1)."""
    order = sorted(range(len(gts)), key=lambda i: -(gts[i].visib_fract if gts[i].visib_fract is not None else 1.0))
    valid = np.zeros(len(gts), dtype=bool)
    valid[order[:inst_count]] = True
    return valid


def _assign(primary: np.ndarray, valid: np.ndarray) -> dict[int, int]:
    """Threshold-free greedy assignment {gt index: estimate index} on a primary error matrix."""
    taken: dict[int, int] = {}
    for e in range(primary.shape[0]):
        best, best_err = -1, math.inf
        for g in range(primary.shape[1]):
            if valid[g] and g not in taken and (primary[e, g] < best_err or best < 0):
                best, best_err = g, primary[e, g]
        if best >= 0:
            taken[best] = e
    return taken


@dataclass
class _Acc:
    """Matched counts per threshold, overall and per object."""

    thresholds: np.ndarray
    total: np.ndarray = None
    per_obj: dict[int, np.ndarray] = field(default_factory=dict)

    def __post_init__(self):
        self.total = np.zeros(self.thresholds.shape, dtype=np.int64)

    def add(self, obj_id: int, counts: np.ndarray) -> None:
        self.total += counts
        self.per_obj.setdefault(obj_id, np.zeros(self.thresholds.shape, dtype=np.int64))
        self.per_obj[obj_id] += counts


def _make_accumulators(mets: list[str]) -> dict[str, _Acc]:
    accs: dict[str, _Acc] = {}
    if "mssd" in mets:
        accs["mssd"] = _Acc(M.MSSD_THRESHOLDS.copy())
    if "mspd" in mets:
        accs["mspd"] = _Acc(M.MSPD_THRESHOLDS.copy())
    for m in ("add", "adds", "ad"):
        if m in mets:
            accs[m + "_rel"] = _Acc(np.array([ADD_REL_THRESHOLD]))
            accs[m + "_abs"] = _Acc(np.array(ADD_ABS_THRESHOLDS_MM))
    return accs


def _recall(acc: _Acc, n: int, obj_id: int | None) -> np.ndarray:
    counts = acc.total if obj_id is None else acc.per_obj.get(obj_id, np.zeros_like(acc.total))
    return counts / n if n else np.zeros(acc.thresholds.shape)


def _aggregate(
    accs: dict[str, _Acc],
    vsd_accs: list[_Acc] | None,
    n: int,
    obj_id: int | None,
    records: list[TargetResult],
    mets: list[str],
    want_vsd: bool,
) -> dict[str, float | None]:
    out: dict[str, float | None] = {"n_targets": n, "n_missing": sum(not r.has_estimate for r in records)}
    ar = {}
    if "mssd" in accs:
        ar["MSSD"] = out["AR_MSSD"] = average_recall(_recall(accs["mssd"], n, obj_id))
    if "mspd" in accs:
        ar["MSPD"] = out["AR_MSPD"] = average_recall(_recall(accs["mspd"], n, obj_id))
    if want_vsd:
        out["AR_VSD"] = None
        if vsd_accs is not None:
            ar["VSD"] = out["AR_VSD"] = float(np.mean([_recall(a, n, obj_id) for a in vsd_accs]))
    if "MSSD" in ar and "MSPD" in ar:
        out["AR_noVSD"] = 0.5 * (ar["MSSD"] + ar["MSPD"])
        out["AR"] = (ar["MSSD"] + ar["MSPD"] + ar["VSD"]) / 3.0 if "VSD" in ar else None
    for m in ("ad", "add", "adds"):
        if m not in mets:
            continue
        name = ADD_NAMES[m]
        out[f"{name}<0.1d"] = float(_recall(accs[m + "_rel"], n, obj_id)[0])
        for th, r in zip(ADD_ABS_THRESHOLDS_MM, _recall(accs[m + "_abs"], n, obj_id)):
            out[f"{name}<{th / 10:g}cm"] = float(r)
        vals = np.array([r.errors[m] for r in records if r.has_estimate], dtype=np.float64)
        out[f"mean_{name}"] = float(vals.mean()) if vals.size else None
        out[f"median_{name}"] = float(np.median(vals)) if vals.size else None
    if "aps" in mets:
        vals = np.array([r.errors["aps"] for r in records], dtype=np.float64)
        out["mean_APS"] = float(vals.mean()) if vals.size else None
    return out


def _curves(accs: dict[str, _Acc], vsd_accs: list[_Acc] | None, n: int) -> dict[str, dict]:
    out = {}
    for key, acc in accs.items():
        out[key] = {"thresholds": acc.thresholds.tolist(), "recall": _recall(acc, n, None).tolist()}
    if vsd_accs is not None:
        out["vsd"] = {
            "taus": M.VSD_TAUS.tolist(),
            "thresholds": M.VSD_THRESHOLDS.tolist(),
            "recall": [_recall(a, n, None).tolist() for a in vsd_accs],
        }
    return out
