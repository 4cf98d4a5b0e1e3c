"""Run the estimator over a BOP dataset: cached reference sets, resumable per-target results, BOP CSV."""

from __future__ import annotations

import hashlib
import json
import logging
import time
from pathlib import Path
from typing import Callable

import numpy as np

from pixie.config import PixieConfig
from pixie.datasets import BopDataset, PoseEstimate, Target, write_results_csv
from pixie.errors import PixieError, ReferenceSetError
from pixie.mesh import Mesh, load_mesh
from pixie.references import ReferenceSet, build_reference_set, load_reference_set, save_reference_set

log = logging.getLogger(__name__)


def refs_key(mesh: Mesh, cfg: PixieConfig) -> str:
    """Short hash of everything a reference set depends on: mesh bytes, refs config, matcher."""
    blob = json.dumps({"mesh": mesh.source_hash, "refs": cfg.to_dict()["refs"], "matcher": cfg.match.matcher,
                       "kp": cfg.match.max_keypoints, "det": cfg.match.detection_threshold}, sort_keys=True)
    return hashlib.sha256(blob.encode()).hexdigest()[:12]


def make_matcher(cfg: PixieConfig, size: int | None = None):
    """The matcher of ``cfg.match`` for references of side ``size`` (default ``cfg.refs.size``)."""
    from pixie.matching import matcher_from_config

    return matcher_from_config(cfg.match, size or cfg.refs.size)


def reference_cache_path(mesh: Mesh, cfg: PixieConfig, cache_dir: str | Path) -> Path:
    """Where :func:`cached_reference_set` keeps the set of ``mesh`` for ``cfg``."""
    return Path(cache_dir) / f"{mesh.name}-{refs_key(mesh, cfg)}.npz"


def cached_reference_set(mesh: Mesh, cfg: PixieConfig, cache_dir: str | Path, matcher=None,
                         progress: Callable[[int, int], None] | None = None, workers: int = 1) -> ReferenceSet:
    """Load the reference set of ``mesh`` for ``cfg`` from ``cache_dir``, building (and saving) it if absent."""
    path = Path(cache_dir) / f"{mesh.name}-{refs_key(mesh, cfg)}.npz"
    if path.exists():
        try:
            return load_reference_set(path, mesh=mesh)
        except ReferenceSetError as exc:
            log.warning("rebuilding %s: %s", path, exc)
    matcher = matcher or make_matcher(cfg)
    refs = build_reference_set(mesh, cfg.refs, matcher=matcher, progress=progress, workers=workers)
    save_reference_set(refs, path)
    return refs


def run_dataset(dataset_root: str | Path, out_dir: str | Path, config: PixieConfig | None = None,
                objects: list[int] | None = None, max_targets: int | None = None,
                refs_dir: str | Path | None = None, echo: Callable[[str], None] = print,
                show_progress: bool = True, threads: int | None = None, use_ray: bool = False,
                address: str | None = None, workers: int | None = None) -> Path:
    """Estimate every target of a BOP dataset (GT ``bbox_visib`` as the crop) and write ``results.csv``.

    Per-target results are appended to ``out_dir/per_target.jsonl`` as they come, so an interrupted
    run resumes where it stopped. Returns the path of the BOP CSV.

    ``threads`` fixes torch/OpenCV threads for the run (``None``: leave them as they are). With ``use_ray`` the
    reference sets are built here first (once, into ``refs_dir``) and Ray workers (:func:`pixie.cluster.ray_map`,
    ``threads`` each, default 1) load them from there; the results equal a serial run's at the same ``threads``.
    """
    from pixie.estimator import PoseEstimator

    cfg = config or PixieConfig()
    if use_ray:
        return _run_dataset_ray(dataset_root, out_dir, cfg, objects, max_targets, refs_dir, echo, show_progress,
                                threads or 1, address, workers)
    ds = BopDataset(dataset_root)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    refs_dir = Path(refs_dir) if refs_dir else out / "refs"
    targets = [t for t in ds.targets() if objects is None or t.obj_id in objects]
    if max_targets is not None and len(targets) > max_targets:
        targets = [targets[i] for i in np.linspace(0, len(targets) - 1, max_targets).round().astype(int)]
    jsonl = out / "per_target.jsonl"
    done = _read_done(jsonl)
    todo = [t for t in targets if _tkey(t) not in done]
    echo(f"{len(targets)} targets, {len(targets) - len(todo)} cached, {len(todo)} to run -> {out}")
    (out / "config.json").write_text(json.dumps(cfg.to_dict(), indent=1))
    bar = _progress(len(todo), show_progress)
    matcher = make_matcher(cfg) if todo else None
    from pixie.cluster import set_threads

    before = set_threads(threads) if threads else None
    with open(jsonl, "a") as fh:
        for obj_id in sorted({t.obj_id for t in todo}):
            mesh = load_mesh(ds.model_path(obj_id))
            t0 = time.perf_counter()
            refs = cached_reference_set(mesh, cfg, refs_dir, matcher=matcher)
            echo(f"obj {obj_id}: reference set ready in {time.perf_counter() - t0:.1f} s")
            est = PoseEstimator(refs, cfg, matcher=matcher)
            for t in (t for t in todo if t.obj_id == obj_id):
                fh.write(json.dumps(_run_target(ds, est, t)) + "\n")
                fh.flush()
                bar.update(1)
    bar.close()
    if before is not None:
        set_threads(before)
    return _write_csv(out, targets, jsonl)


def _write_csv(out: Path, targets: list[Target], jsonl: Path) -> Path:
    done = _read_done(jsonl)
    ests = [e for t in targets for e in done.get(_tkey(t), [])]
    csv = out / "results.csv"
    write_results_csv(csv, [_estimate(e) for e in ests if e["T"] is not None])  # a missing pose counts as a miss
    return csv


def _run_dataset_ray(dataset_root, out_dir, cfg: PixieConfig, objects, max_targets, refs_dir, echo, show_progress,
                     threads: int, address: str | None, workers: int | None) -> Path:
    """:func:`run_dataset` on Ray workers: reference sets built here once, workers load them from ``refs_dir``."""
    from pixie.cluster import WorkerSpec, ray_map, set_threads

    ds = BopDataset(dataset_root)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    refs_dir = Path(refs_dir) if refs_dir else out / "refs"
    targets = [t for t in ds.targets() if objects is None or t.obj_id in objects]
    if max_targets is not None and len(targets) > max_targets:
        targets = [targets[i] for i in np.linspace(0, len(targets) - 1, max_targets).round().astype(int)]
    jsonl = out / "per_target.jsonl"
    done = _read_done(jsonl)
    todo = [t for t in targets if _tkey(t) not in done]
    echo(f"{len(targets)} targets, {len(targets) - len(todo)} cached, {len(todo)} to run -> {out} (Ray"
         f"{' at ' + address if address else ''})")
    (out / "config.json").write_text(json.dumps(cfg.to_dict(), indent=1))
    refs_paths: dict[int, str] = {}
    if todo:
        before = set_threads(threads)  # the build too: same threads as the workers, as in a serial run
        try:
            matcher = make_matcher(cfg)
            for obj_id in sorted({t.obj_id for t in todo}):
                mesh = load_mesh(ds.model_path(obj_id))
                t0 = time.perf_counter()
                cached_reference_set(mesh, cfg, refs_dir, matcher=matcher)
                refs_paths[obj_id] = str(reference_cache_path(mesh, cfg, refs_dir).resolve())
                echo(f"obj {obj_id}: reference set ready in {time.perf_counter() - t0:.1f} s")
        finally:
            set_threads(before)
    todo.sort(key=lambda t: (t.obj_id, t.scene_id, t.im_id))  # workers keep the estimator of the object at hand
    bar = _progress(len(todo), show_progress)
    spec = WorkerSpec(_setup_bop, _process_bop, {"dataset": str(Path(dataset_root).resolve()), "config": cfg.to_dict(),
                                                 "refs": refs_paths}, threads)
    with open(jsonl, "a") as fh:
        def on_result(_: int, rec: dict) -> None:
            fh.write(json.dumps(rec) + "\n")
            fh.flush()
            bar.update(1)

        try:
            n = ray_map(spec, [[t.scene_id, t.im_id, t.obj_id, t.inst_count] for t in todo], on_result, workers, address)
        finally:
            bar.close()
    if todo:
        echo(f"{len(todo)} targets on {n} Ray workers")
    return _write_csv(out, targets, jsonl)


def _setup_bop(args: dict) -> dict:
    """Ray worker state: the dataset, the config, the reference-set files, one matcher, estimators on demand."""
    cfg = PixieConfig.from_dict(args["config"])
    return {"ds": BopDataset(args["dataset"]), "cfg": cfg, "refs": {int(k): v for k, v in args["refs"].items()},
            "matcher": make_matcher(cfg), "est": {}}


def _process_bop(state: dict, item: list[int]) -> dict:
    """One target on a Ray worker; estimators are kept for the last two objects only (memory)."""
    from pixie.estimator import PoseEstimator

    scene_id, im_id, obj_id, inst_count = item
    ests = state["est"]
    if obj_id not in ests:
        ds = state["ds"]
        refs = load_reference_set(state["refs"][obj_id], mesh=load_mesh(ds.model_path(obj_id)))
        while len(ests) >= 2:
            ests.pop(next(iter(ests)))
        ests[obj_id] = PoseEstimator(refs, PixieConfig.from_dict(state["cfg"].to_dict()), matcher=state["matcher"])
    return _run_target(state["ds"], ests[obj_id], Target(scene_id, im_id, obj_id, inst_count))


def _run_target(ds: BopDataset, est, t: Target) -> dict:
    """Estimate the pose of each GT instance of the target object in one image (GT boxes as crops)."""
    img = ds.load_rgb(t.scene_id, t.im_id)
    K = ds.camera(t.scene_id, t.im_id).K
    rows = []
    insts = sorted((g for g in ds.instances(t.scene_id, t.im_id) if g.obj_id == t.obj_id),
                   key=lambda g: -(g.visib_fract if g.visib_fract is not None else 1.0))
    for inst in insts[: t.inst_count]:
        t0 = time.perf_counter()
        try:
            r = est.estimate(img, K, bbox=inst.box_visib)
            T, score, failed, timings = r.T_cam_from_obj, r.score, r.failed, r.timings
        except PixieError as exc:
            T, score, failed, timings = None, 0.0, True, {"error": str(exc)}
        rows.append({"T": None if T is None else T.tolist(), "score": score, "failed": failed,
                     "time": time.perf_counter() - t0, "timings": timings})
    return {"key": list(_tkey(t)), "estimates": rows}


def _tkey(t: Target) -> tuple[int, int, int]:
    return (t.scene_id, t.im_id, t.obj_id)


def _read_done(jsonl: Path) -> dict[tuple[int, int, int], list[dict]]:
    done: dict[tuple[int, int, int], list[dict]] = {}
    if jsonl.exists():
        for line in jsonl.read_text().splitlines():
            try:
                rec = json.loads(line)
            except ValueError:  # a line cut by a kill: run that target again
                continue
            k = tuple(rec["key"])
            done[k] = [dict(e, key=k) for e in rec["estimates"]]
    return done


def _estimate(e: dict) -> PoseEstimate:
    s, i, o = e["key"]
    T = np.asarray(e["T"]) if e["T"] is not None else None
    return PoseEstimate(s, i, o, float(e["score"]) if not e["failed"] else 0.0, T, float(e["time"]))


class _NoBar:
    def update(self, n: int) -> None:
        pass

    def close(self) -> None:
        pass


def _progress(total: int, show: bool):
    if not show or total == 0:
        return _NoBar()
    from tqdm import tqdm

    return tqdm(total=total, unit="target", dynamic_ncols=True)
