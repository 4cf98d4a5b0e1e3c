"""Evaluation of pose estimates on a BOP dataset (bop_toolkit's ``calc_errors`` + ``calc_scores`` orchestration):
per-target errors (:mod:`pixie.eval.pose_error`), BOP'19 AR, ADD family, APS (:mod:`pixie.eval.scores`).

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

import math
import time
from collections.abc import Iterable, Sequence
from pathlib import Path

import numpy as np

from pixie.eval import pose_error as M
from pixie.errors import EstimateError
from pixie.eval.datasets import BopDataset, GtInstance, PoseEstimate, check_pose_values, read_results_csv
from pixie.eval.objects import ObjectData, load_object_data
from pixie.eval.scores import (
    DEFAULT_METRICS,
    Scores,
    TargetResult,
    _Acc,
    _aggregate,
    _assign,
    _curves,
    _make_accumulators,
    count_matches,
    normalize_metrics,
    valid_gt_mask,
)
from pixie.eval.shape_metrics import aps
from pixie.geometry.rotations import orthonormalize


def _checked(results: Iterable[PoseEstimate]) -> list[PoseEstimate]:
    """Estimates given as objects, held to the rules of a results file (:func:`check_pose_values`)."""
    out = list(results)
    for k, e in enumerate(out):
        where = f"estimate #{k} (scene {e.scene_id}, image {e.im_id}, object {e.obj_id})"
        T = np.asarray(e.T_cam_from_obj, np.float64) if e.T_cam_from_obj is not None else None
        if T is None or T.shape != (4, 4):
            raise EstimateError(f"{where}: T_cam_from_obj must be a 4x4 pose, got "
                                f"{None if T is None else T.shape}")
        check_pose_values(T[:3, :3], T[:3, 3], e.score, e.time, where, EstimateError)
    return out


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
        accs["mssd"].add(oid, count_matches(err["mssd"] / d, valid, accs["mssd"].thresholds))
    if "mspd" in accs:
        accs["mspd"].add(oid, count_matches(err["mspd"] * (640.0 / width), valid, accs["mspd"].thresholds))
    for m in ("add", "adds", "ad"):
        if m in err:
            accs[m + "_rel"].add(oid, count_matches(err[m] / d, valid, accs[m + "_rel"].thresholds))
            accs[m + "_abs"].add(oid, count_matches(err[m], valid, accs[m + "_abs"].thresholds))
    if vsd_err is not None:
        for k, acc in enumerate(vsd_accs):
            acc.add(oid, count_matches(vsd_err[:, :, k], valid, acc.thresholds))


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
                rec.errors["aps"] = aps(r, r, est.T_cam_from_obj, g.T_cam_from_obj, K, *size)
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
    ests = read_results_csv(results) if isinstance(results, (str, Path)) else _checked(results)
    mets = normalize_metrics(metrics)
    targets = ds.targets() if targets is None else list(targets)
    delta = vsd_delta if vsd_delta is not None else M.vsd_delta(ds.name)

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
