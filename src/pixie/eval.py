"""Evaluation of pose estimates on a BOP dataset: per-target errors, BOP'19 AR, ADD family, APS.

Typical use (what ``pixie eval DATASET --results results.csv -o OUT`` calls)::

    from pixie.eval import run_eval
    scores = run_eval("data/lmo", "results.csv", "out/eval")

Protocol (BOP'19, localisation with known instance counts):

* for each target (image, object, ``inst_count = k``) only the ``k`` highest-scored estimates
  are evaluated, and the ``k`` most visible GT instances of the object are the valid targets;
* each estimate's error is computed against every GT instance of its object in the image;
* for each threshold, estimates are greedily matched (decreasing score) to the valid,
  unmatched GT of smallest error if that error is below the threshold;
* recall = matched / valid GT instances, over the whole dataset (and per object);
* AR_MSSD, AR_MSPD = mean recall over their 10 thresholds, AR_VSD over 10 taus x 10
  thresholds, AR = mean of the three. Without depth images VSD is *not* computed and only
  ``AR (no VSD)`` = mean(AR_MSSD, AR_MSPD) is reported.

Speed: model points, symmetry sets and KD-trees are built once per object from the BOP
evaluation models; only VSD (and the optional APS) render, with the GT render cached per
instance. Everything runs in one process.
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Callable, Iterable, Sequence

import numpy as np

from pixie import metrics as M
from pixie.datasets import (
    BopDataset,
    GtInstance,
    PoseEstimate,
    is_symmetric,
    orthonormalize,
    read_results_csv,
    symmetry_transforms,
)
from pixie.errors import ConfigError

ALL_METRICS = ("mssd", "mspd", "vsd", "add", "adds", "ad", "aps")
DEFAULT_METRICS = ("mssd", "mspd", "vsd", "add", "adds", "ad")
METRIC_ALIASES = {"add-s": "adds", "add_s": "adds", "add(-s)": "ad", "adds_or_add": "ad"}
ADD_NAMES = {"add": "ADD", "adds": "ADD-S", "ad": "ADD(-S)"}
ADD_ABS_THRESHOLDS_MM = (5.0, 10.0, 50.0)  # 0.5 / 1 / 5 cm (paper Table II)
ADD_REL_THRESHOLD = 0.1  # fraction of the diameter
VSD_DELTAS = {"itodd": 5.0}  # mm; 15 for every other BOP dataset


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


def write_scores_json(scores: Scores, path: str | Path, with_targets: bool = True) -> Path:
    """Write ``scores.json`` (non-finite numbers become null). Returns the path."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(scores.to_dict(with_targets), indent=1), encoding="utf-8")
    return path


def write_per_target_csv(scores: Scores, path: str | Path) -> Path:
    """One row per valid GT instance with its errors."""
    path = Path(path)
    keys = sorted({k for t in scores.targets for k in t.errors})
    with open(path, "w", newline="", encoding="utf-8") as f:
        w = csv.writer(f)
        w.writerow(["scene_id", "im_id", "obj_id", "gt_id", "visib_fract", "has_estimate", "score", *keys])
        for t in scores.targets:
            w.writerow(
                [t.scene_id, t.im_id, t.obj_id, t.gt_id, t.visib_fract, int(t.has_estimate), t.score]
                + [f"{t.errors.get(k, float('nan')):.6g}" for k in keys]
            )
    return path


# --------------------------------------------------------------------------------------------
# Per-object data, built once
# --------------------------------------------------------------------------------------------


@dataclass
class ObjectData:
    """Everything the metrics need about one object, computed once per evaluation."""

    obj_id: int
    diameter: float
    symmetric: bool
    syms: np.ndarray  # (S, 4, 4)
    pts: np.ndarray  # evaluation-model vertices (MSSD, MSPD)
    add_pts: np.ndarray  # points for ADD / ADD-S
    mesh: object
    _tree: object = None
    _renderer: object = None

    @property
    def tree(self):
        if self._tree is None:
            from scipy.spatial import cKDTree

            self._tree = cKDTree(self.add_pts)
        return self._tree

    @property
    def renderer(self):
        if self._renderer is None:
            from pixie.render import Renderer

            self._renderer = Renderer(self.mesh)
        return self._renderer


def load_object_data(
    dataset: BopDataset, obj_id: int, n_points: int | None = None, max_sym_disc_step: float = 0.01
) -> ObjectData:
    """Load the evaluation model and models_info entry of one object.

    ``n_points`` subsamples (deterministically) the vertices used by ADD / ADD-S; MSSD and
    MSPD always use every vertex of the evaluation model, as BOP does.
    """
    from pixie.mesh import load_mesh

    info = dataset.model_info(obj_id, eval=True)
    mesh = load_mesh(dataset.model_path(obj_id, eval=True), units="mm")
    pts = np.asarray(mesh.vertices, dtype=np.float64)
    add_pts = pts
    if n_points is not None and 0 < n_points < len(pts):
        idx = np.random.default_rng(obj_id).choice(len(pts), size=n_points, replace=False)
        add_pts = pts[np.sort(idx)]
    return ObjectData(
        obj_id=obj_id,
        diameter=float(info["diameter"]),
        symmetric=is_symmetric(info),
        syms=symmetry_transforms(info, max_sym_disc_step),
        pts=pts,
        add_pts=add_pts,
        mesh=mesh,
    )


# --------------------------------------------------------------------------------------------
# Core
# --------------------------------------------------------------------------------------------


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


def _group_estimates(results: Sequence[PoseEstimate]) -> dict[tuple[int, int, int], list[PoseEstimate]]:
    groups: dict[tuple[int, int, int], list[PoseEstimate]] = {}
    for e in results:
        groups.setdefault((e.scene_id, e.im_id, e.obj_id), []).append(e)
    for g in groups.values():
        g.sort(key=lambda e: -e.score)  # stable: ties keep file order
    return groups


def _avg_time_per_image(results: Sequence[PoseEstimate]) -> float | None:
    times: dict[tuple[int, int], float] = {}
    for e in results:
        if e.time < 0:
            return None
        times.setdefault((e.scene_id, e.im_id), e.time)
    return float(np.mean(list(times.values()))) if times else None


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


def _pair_errors(
    od: ObjectData,
    est_list: list[PoseEstimate],
    gts: list[GtInstance],
    K: np.ndarray,
    mets: list[str],
    depth_test: np.ndarray | None,
    delta: float,
) -> tuple[dict[str, np.ndarray], np.ndarray | None]:
    """Errors of every (estimate, GT instance) pair of one object in one image.

    Returns ``{metric: (E, G)}`` in natural units (mm, px) and the (E, G, n_tau) VSD errors
    (None when ``depth_test`` is None). The GT depth render is made once per instance.
    """
    E, G = len(est_list), len(gts)
    err = {m: np.full((E, G), np.inf) for m in mets if m not in ("vsd", "aps")}
    vsd_err = np.ones((E, G, len(M.VSD_TAUS))) if depth_test is not None else None
    gt_depth: dict[int, np.ndarray] = {}
    for ei, est in enumerate(est_list):
        Te = est.T_cam_from_obj
        for gi, g in enumerate(gts):
            Tg = g.T_cam_from_obj
            if "mssd" in err:
                err["mssd"][ei, gi] = M.mssd(Te, Tg, od.pts, od.syms)
            if "mspd" in err:
                err["mspd"][ei, gi] = M.mspd(Te, Tg, K, od.pts, od.syms)
            if "add" in err or ("ad" in err and not od.symmetric):
                e_add = M.add(Te, Tg, od.add_pts)
                if "add" in err:
                    err["add"][ei, gi] = e_add
                if "ad" in err and not od.symmetric:
                    err["ad"][ei, gi] = e_add
            if "adds" in err or ("ad" in err and od.symmetric):
                e_s = M.adds(Te, Tg, od.add_pts, od.tree)
                if "adds" in err:
                    err["adds"][ei, gi] = e_s
                if "ad" in err and od.symmetric:
                    err["ad"][ei, gi] = e_s
            if vsd_err is not None:
                if gi not in gt_depth:
                    h, w = depth_test.shape
                    gt_depth[gi] = od.renderer.render(orthonormalize(Tg), K, h, w).depth
                vsd_err[ei, gi] = M.vsd_poses(
                    od.renderer, Te, Tg, depth_test, K, od.diameter, delta, M.VSD_TAUS, gt_depth[gi]
                )
    return err, vsd_err


def _accumulate(
    accs: dict[str, _Acc],
    vsd_accs: list[_Acc],
    od: ObjectData,
    err: dict[str, np.ndarray],
    vsd_err: np.ndarray | None,
    valid: np.ndarray,
    width: int,
) -> None:
    """Add the matched counts of one (image, object) group to the accumulators."""
    oid, d = od.obj_id, od.diameter
    if "mssd" in accs:
        accs["mssd"].add(oid, M.count_matches(err["mssd"] / d, valid, accs["mssd"].thresholds))
    if "mspd" in accs:
        accs["mspd"].add(oid, M.count_matches(err["mspd"] * (640.0 / width), valid, accs["mspd"].thresholds))
    for m in ("add", "adds", "ad"):
        if m in err:
            accs[m + "_rel"].add(oid, M.count_matches(err[m] / d, valid, accs[m + "_rel"].thresholds))
            accs[m + "_abs"].add(oid, M.count_matches(err[m], valid, accs[m + "_abs"].thresholds))
    if vsd_err is not None:
        for k, acc in enumerate(vsd_accs):
            acc.add(oid, M.count_matches(vsd_err[:, :, k], valid, acc.thresholds))


def _target_records(
    od: ObjectData,
    est_list: list[PoseEstimate],
    gts: list[GtInstance],
    valid: np.ndarray,
    err: dict[str, np.ndarray],
    vsd_err: np.ndarray | None,
    image: tuple[int, int],
    K: np.ndarray,
    size: tuple[int, int],
    mets: list[str],
) -> list[TargetResult]:
    """One :class:`TargetResult` per valid GT instance, with its assigned estimate's errors."""
    E, G = len(est_list), len(gts)
    primary = next((err[m] for m in ("mssd", "mspd", "ad", "add", "adds") if m in err), None)
    if primary is None:
        primary = vsd_err.mean(axis=2) if vsd_err is not None else np.zeros((E, G))
    assigned = _assign(primary, valid) if E else {}
    out = []
    for gi in np.nonzero(valid)[0]:
        g = gts[gi]
        ei = assigned.get(int(gi))
        est = None if ei is None else est_list[ei]
        rec = TargetResult(
            scene_id=image[0],
            im_id=image[1],
            obj_id=od.obj_id,
            gt_id=g.gt_id,
            visib_fract=g.visib_fract,
            has_estimate=est is not None,
            score=None if est is None else est.score,
            T_gt=g.T_cam_from_obj,
            T_est=None if est is None else est.T_cam_from_obj,
        )
        for m, arr in err.items():
            rec.errors[m] = math.inf if ei is None else float(arr[ei, gi])
        if vsd_err is not None:
            rec.vsd_per_tau = None if ei is None else vsd_err[ei, gi].tolist()
            rec.errors["vsd"] = math.inf if ei is None else float(vsd_err[ei, gi].mean())
        if "aps" in mets:
            rec.errors["aps"] = 0.0
            if est is not None:
                r = od.renderer
                rec.errors["aps"] = M.aps(r, r, est.T_cam_from_obj, g.T_cam_from_obj, K, *size)
        out.append(rec)
    return out


def evaluate(
    dataset: BopDataset | str | Path,
    results: Sequence[PoseEstimate] | str | Path,
    metrics: Iterable[str] = DEFAULT_METRICS,
    n_points: int | None = None,
    vsd_delta: float | None = None,
    max_sym_disc_step: float = 0.01,
    targets: list | None = None,
    progress: bool = False,
    objects: dict[int, ObjectData] | None = None,
) -> Scores:
    """Score pose estimates against a BOP dataset's ground truth.

    Parameters
    ----------
    dataset : BopDataset or its root folder
    results : list of PoseEstimate or the path of a BOP'19 results CSV
    metrics : names among ``mssd, mspd, vsd, add, adds, ad`` (ADD(-S)) and ``aps``
    n_points : int, optional
        Number of evaluation-model vertices used by ADD / ADD-S (all when None).
    vsd_delta : float, optional
        VSD visibility tolerance in mm (BOP: 15, ITODD 5).
    max_sym_disc_step : float
        Discretisation of continuous symmetries (fraction of the diameter).
    targets : list of Target, optional
        Subset of the dataset's targets to evaluate (all by default).
    progress : bool
        Show a tqdm bar.
    objects : dict, optional
        Pre-loaded :class:`ObjectData` per object id (reused between calls).

    Returns
    -------
    Scores
    """
    t0 = time.perf_counter()
    ds = dataset if isinstance(dataset, BopDataset) else BopDataset(Path(dataset))
    ests = read_results_csv(results) if isinstance(results, (str, Path)) else list(results)
    mets = normalize_metrics(metrics)
    targets = ds.targets() if targets is None else list(targets)
    delta = vsd_delta if vsd_delta is not None else VSD_DELTAS.get(ds.name, M.VSD_DELTA_MM)

    want_vsd = "vsd" in mets
    vsd_ok = want_vsd
    vsd_note = "" if want_vsd else "VSD not requested"
    if want_vsd and not ds.has_depth():
        vsd_ok, vsd_note = False, "VSD unavailable: the dataset has no depth images"

    by_image: dict[tuple[int, int], dict[int, int]] = {}
    for tg in targets:
        by_image.setdefault((tg.scene_id, tg.im_id), {})[tg.obj_id] = tg.inst_count
    groups = _group_estimates(ests)
    target_keys = {(s, i, o) for (s, i), objs in by_image.items() for o in objs}
    n_ignored = sum(len(v) for k, v in groups.items() if k not in target_keys)

    objects = {} if objects is None else objects

    def obj(oid: int) -> ObjectData:
        if oid not in objects:
            objects[oid] = load_object_data(ds, oid, n_points, max_sym_disc_step)
        return objects[oid]

    accs = _make_accumulators(mets)
    vsd_accs = [_Acc(M.VSD_THRESHOLDS.copy()) for _ in M.VSD_TAUS] if want_vsd else []
    n_valid: dict[int, int] = {}
    records: list[TargetResult] = []
    n_evaluated = 0

    items = list(by_image.items())
    if progress:
        from tqdm import tqdm

        items = tqdm(items, desc="eval", unit="img")
    for (scene_id, im_id), objs in items:
        insts = ds.instances(scene_id, im_id)
        K = ds.camera(scene_id, im_id).K
        h, w = ds.image_size(scene_id, im_id)
        depth_test = None
        if vsd_ok:
            depth_test = ds.load_depth(scene_id, im_id)
            if depth_test is None:
                vsd_ok = False
                vsd_note = f"VSD unavailable: no depth image for scene {scene_id} image {im_id}"
        for obj_id, inst_count in objs.items():
            od = obj(obj_id)
            gts = [g for g in insts if g.obj_id == obj_id]
            valid = valid_gt_mask(gts, inst_count)
            n_valid[obj_id] = n_valid.get(obj_id, 0) + int(valid.sum())
            est_list = groups.get((scene_id, im_id, obj_id), [])[:inst_count]
            n_evaluated += len(est_list)
            err, vsd_err = _pair_errors(od, est_list, gts, K, mets, depth_test if vsd_ok else None, delta)
            _accumulate(accs, vsd_accs if vsd_err is not None else [], od, err, vsd_err, valid, w)
            records += _target_records(od, est_list, gts, valid, err, vsd_err, (scene_id, im_id), K, (h, w), mets)

    if want_vsd and not vsd_ok:
        for r in records:
            r.errors.pop("vsd", None)
            r.vsd_per_tau = None

    total_valid = sum(n_valid.values())
    overall = _aggregate(accs, vsd_accs if vsd_ok else None, total_valid, None, records, mets, want_vsd)
    per_object = {
        oid: _aggregate(
            accs,
            vsd_accs if vsd_ok else None,
            n_valid[oid],
            oid,
            [r for r in records if r.obj_id == oid],
            mets,
            want_vsd,
        )
        for oid in sorted(n_valid)
    }
    curves = _curves(accs, vsd_accs if vsd_ok else None, total_valid)
    return Scores(
        dataset=ds.name,
        metrics=mets,
        vsd_available=vsd_ok,
        vsd_note=vsd_note,
        n_targets=total_valid,
        n_estimates=n_evaluated,
        n_ignored_estimates=n_ignored,
        overall=overall,
        per_object=per_object,
        curves=curves,
        targets=records,
        avg_time_per_image=_avg_time_per_image(ests),
        time_s=time.perf_counter() - t0,
    )


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
        ar["MSSD"] = out["AR_MSSD"] = M.average_recall(_recall(accs["mssd"], n, obj_id))
    if "mspd" in accs:
        ar["MSPD"] = out["AR_MSPD"] = M.average_recall(_recall(accs["mspd"], n, obj_id))
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


# --------------------------------------------------------------------------------------------
# Table, CLI glue
# --------------------------------------------------------------------------------------------


def _fmt(v, digits: int = 3) -> str:
    if v is None:
        return "n/a"
    if isinstance(v, float):
        return f"{v:.{digits}f}" if math.isfinite(v) else "inf"
    return str(v)


def format_table(scores: Scores) -> str:
    """A short plain-text table: one row per object and an overall row."""
    cols: list[tuple[str, str, int]] = [("n", "n_targets", 0)]
    o = scores.overall
    ar_cols = (("AR_MSSD", "AR_MSSD"), ("AR_MSPD", "AR_MSPD"), ("AR_VSD", "AR_VSD"), ("AR_noVSD", "AR(noVSD)"), ("AR", "AR"))
    for key, label in ar_cols:
        if key in o:
            cols.append((label, key, 3))
    other_cols = (("ADD(-S)<0.1d", "ADD(-S)<.1d"), ("ADD<1cm", "ADD<1cm"), ("median_ADD", "medADD mm"), ("mean_APS", "APS"))
    for key, label in other_cols:
        if key in o:
            cols.append((label, key, 1 if key.startswith("median") else 3))
    widths = [max(len(c[0]), 7) for c in cols]
    lines = [f"{'obj':>5} " + " ".join(f"{c[0]:>{wd}}" for c, wd in zip(cols, widths))]
    rows = [(str(k), v) for k, v in scores.per_object.items()] + [("all", o)]
    for name, row in rows:
        cells = []
        for (label, key, digits), wd in zip(cols, widths):
            v = row.get(key)
            cells.append(f"{(_fmt(v, digits) if digits else _fmt(v)):>{wd}}")
        lines.append(f"{name:>5} " + " ".join(cells))
    head = (
        f"{scores.dataset}: {scores.n_targets} targets, {scores.n_estimates} estimates evaluated "
        f"({scores.n_ignored_estimates} ignored), {scores.time_s:.1f} s"
    )
    tail = []
    if o.get("AR") is not None:
        tail.append(f"AR = {o['AR']:.4f}  (mean of AR_VSD, AR_MSSD, AR_MSPD)")
    elif "AR_noVSD" in o:
        why = scores.vsd_note or "VSD not evaluated"
        tail.append(f"AR (no VSD) = {o['AR_noVSD']:.4f}  (mean of AR_MSSD, AR_MSPD; {why})")
    return "\n".join([head, *lines, *tail])


def run_eval(
    dataset_root: str | Path,
    results_csv: str | Path,
    out_dir: str | Path,
    metrics: Iterable[str] = DEFAULT_METRICS,
    n_points: int | None = None,
    report: bool = True,
    n_overlays: int = 4,
    progress: bool = False,
    echo: Callable[[str], None] | None = print,
    only_estimated: bool = False,
) -> Scores:
    """Evaluate a results CSV and write ``scores.json``, ``per_target.csv`` and ``report.html``.

    Parameters
    ----------
    dataset_root : BOP dataset folder
    results_csv : BOP'19 results file
    out_dir : output folder (created)
    metrics, n_points : see :func:`evaluate`
    report : write the HTML report (with ``n_overlays`` best and worst target overlays)
    echo : function printing the summary table (None = silent)
    only_estimated : score only the targets that have at least one row in the results (a subset run);
        by default every target of the dataset counts and a missing estimate is a miss, as in BOP

    Returns
    -------
    Scores
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    ds = BopDataset(Path(dataset_root))
    objects: dict[int, ObjectData] = {}
    targets = None
    if only_estimated:
        rows = {(e.scene_id, e.im_id, e.obj_id) for e in read_results_csv(results_csv)}
        targets = [t for t in ds.targets() if (t.scene_id, t.im_id, t.obj_id) in rows]
    scores = evaluate(ds, results_csv, metrics=metrics, n_points=n_points, progress=progress, objects=objects,
                      targets=targets)
    write_scores_json(scores, out / "scores.json")
    write_per_target_csv(scores, out / "per_target.csv")
    if report:
        from pixie.report import write_report

        write_report(scores, ds, out, n_overlays=n_overlays, objects=objects)
    if echo is not None:
        echo(format_table(scores))
        echo(f"wrote {out / 'scores.json'}" + (f", {out / 'report.html'}" if report else ""))
    return scores


def add_eval_arguments(parser: argparse.ArgumentParser) -> argparse.ArgumentParser:
    """Arguments of ``pixie eval`` (for the CLI owner to mount as a sub-command)."""
    parser.add_argument("dataset", help="BOP dataset folder (holding models/, test/, test_targets_bop19.json)")
    parser.add_argument("--results", required=True, help="BOP'19 results CSV")
    parser.add_argument("-o", "--out", default="out/eval", help="output folder")
    parser.add_argument(
        "--metrics", default=",".join(DEFAULT_METRICS), help=f"comma-separated, from {','.join(ALL_METRICS)}"
    )
    parser.add_argument("--n-points", type=int, default=None, help="vertices used by ADD/ADD-S (default: all)")
    parser.add_argument("--no-report", action="store_true", help="skip the HTML report")
    parser.add_argument("--progress", action="store_true")
    parser.add_argument("--only-estimated", action="store_true",
                        help="score only targets with a row in the results (subset runs); default: all targets, misses count")
    return parser


def main_eval(args: argparse.Namespace) -> int:
    """Entry point for ``pixie eval`` given parsed :func:`add_eval_arguments` arguments."""
    run_eval(
        args.dataset,
        args.results,
        args.out,
        metrics=[m for m in args.metrics.split(",") if m],
        n_points=args.n_points,
        report=not args.no_report,
        progress=args.progress,
        only_estimated=args.only_estimated,
    )
    return 0
