"""Run the estimator over a BOP dataset: cached reference sets, resumable per-target results, BOP CSV.

The building blocks are shared by ``pixie run``, the demo and the benchmark scripts in ``bench/``:

* :func:`make_matcher` -- the matcher of a config (one place: :func:`pixie.matching.matcher_from_config`);
* :func:`cached_reference_set` -- load-or-build a reference set in a cache folder, safe for several processes;
* :class:`Journal` -- an append-only JSON-lines record of finished work, so interrupted loops resume.

``pixie run`` reuses a cached per-target result only when it was made by the same code (:func:`code_version`),
config, dataset and object model (the reference set is a function of these: :func:`run_fingerprint`); a line
cut by a crash or otherwise corrupt is reported and its target runs again.
"""

from __future__ import annotations

import functools
import hashlib
import json
import logging
import os
import socket
import sys
import time
from pathlib import Path
from typing import Callable, Hashable

import numpy as np

from pixie._version import __version__
from pixie.app.cluster import WorkerSpec, ray_map
from pixie.app.notes import collect_warnings
from pixie.threads import set_threads
from pixie.config import PixieConfig
from pixie.errors import DatasetError, OutputError, PixieError, ReferenceSetError
from pixie.pipeline.estimator import PoseEstimator
from pixie.eval.detections import DetectionSet, load_detections
from pixie.eval.datasets import BopDataset, PoseEstimate, Target, write_results_csv
from pixie.matching import Matcher, matcher_from_config
from pixie.geometry.mesh import Mesh, load_mesh
from pixie.paths import output_dir, pid_alive, remove_stale_temps, write_atomic
from pixie.references.set import ReferenceSet, build_reference_set
from pixie.references.store import ensure_templates, load_reference_set, save_reference_set

log = logging.getLogger(__name__)

# written into pixie run's output folder (scores.json, per_target.csv and report.html by the scoring after it)
RUN_OUTPUTS = ("results.csv", "per_target.jsonl", "config.json", "targets.json", "scores.json", "per_target.csv",
               "report.html")


def refs_key(mesh: Mesh, cfg: PixieConfig) -> str:
    """Short hash of everything a reference set depends on: mesh bytes, refs config, the matcher's extraction."""
    m = cfg.match
    blob = json.dumps({"mesh": mesh.source_hash, "refs": cfg.to_dict()["refs"], "matcher": m.matcher,
                       "kp": m.max_keypoints, "det": m.detection_threshold, "weights": m.weights_dir}, sort_keys=True)
    return hashlib.sha256(blob.encode()).hexdigest()[:12]


def make_matcher(cfg: PixieConfig, size: int | None = None) -> Matcher:
    """The matcher of ``cfg.match`` for references of side ``size`` (default ``cfg.refs.size``)."""
    return matcher_from_config(cfg.match, size or cfg.refs.size)


def reference_cache_path(mesh: Mesh, cfg: PixieConfig, cache_dir: str | Path) -> Path:
    """Where :func:`cached_reference_set` keeps the set of ``mesh`` for ``cfg``."""
    return Path(cache_dir) / f"{mesh.name}-{refs_key(mesh, cfg)}.npz"


LOCK_WAIT_S = 6 * 3600.0  # the longest cached_reference_set waits for another process's build


def _lock_owner(lock: Path) -> dict | None:
    """The ``{"pid", "host", "time"}`` written into a lock file; None when it is gone, empty or unreadable."""
    try:
        rec = json.loads(lock.read_text())
    except (OSError, ValueError):
        return None
    return rec if isinstance(rec, dict) and isinstance(rec.get("pid"), int) else None


def lock_is_stale(lock: Path, unreadable_after_s: float = 30.0) -> bool:
    """A lock whose builder is gone: its pid no longer runs on this host, or (a lock of an older pixie, without
    owner) it is older than ``unreadable_after_s``. A lock of another host is never stale (we cannot ask it)."""
    owner = _lock_owner(lock)
    if owner is None:
        try:
            return time.time() - lock.stat().st_mtime > unreadable_after_s
        except OSError:
            return False  # gone meanwhile: not ours to remove
    return owner.get("host") == socket.gethostname() and not pid_alive(owner["pid"])


def _take_lock(lock: Path) -> bool:
    """Create ``lock`` holding this process's pid and host, atomically (a hard link of a finished temporary file,
    so nobody reads a half-written lock); False when it exists."""
    body = json.dumps({"pid": os.getpid(), "host": socket.gethostname(), "time": time.time()})
    try:
        write_atomic(lock, body, force=False)
        return True
    except OutputError:
        return False


def cached_reference_set(mesh: Mesh, cfg: PixieConfig, cache_dir: str | Path, matcher: Matcher | None = None,
                         progress: Callable[[int, int], None] | None = None, workers: int = 1,
                         echo: Callable[[str], None] | None = None, poll_s: float = 2.0,
                         max_wait_s: float = LOCK_WAIT_S) -> ReferenceSet:
    """Load the reference set of ``mesh`` for ``cfg`` from ``cache_dir``, building (and saving) it if absent.

    Several processes may share a cache: the first to need a set builds it under a lock file (``<set>.lock``,
    holding its pid and host) while the others wait for it, saying so once (``echo``, default stderr), polling
    every ``poll_s`` seconds for at most ``max_wait_s``. A lock whose process is gone (killed while it built) is
    taken over at once; one that outlives ``max_wait_s`` raises :class:`ReferenceSetError` naming it.
    """
    path = reference_cache_path(mesh, cfg, cache_dir)
    path.parent.mkdir(parents=True, exist_ok=True)
    remove_stale_temps(path.parent)
    say = echo or (lambda msg: print(msg, file=sys.stderr, flush=True))
    lock = path.with_suffix(".lock")
    owner = False
    t_wait, told = time.monotonic(), False
    while not path.is_file():
        if _take_lock(lock):
            owner = True
            break
        if lock_is_stale(lock):
            say(f"taking over {lock.name}: the process that held it ({_describe(lock)}) is gone")
            lock.unlink(missing_ok=True)
            continue
        waited = time.monotonic() - t_wait
        if waited > max_wait_s:
            raise ReferenceSetError(f"waited {waited:.0f} s for {path.name}, being built by {_describe(lock)}: if "
                                    f"that process is gone, delete {lock}")
        if not told:
            say(f"waiting for {path.name}, being built by {_describe(lock)} (at most {max_wait_s:.0f} s; if that "
                f"process is gone, delete {lock})")
            told = True
        time.sleep(poll_s)
    try:
        if path.is_file():
            try:
                refs = load_reference_set(path, mesh=mesh)
                ensure_templates(refs, cfg.shape)  # a set cached before templates were stored: upgraded once
                return refs
            except ReferenceSetError as exc:
                log.warning("rebuilding %s: %s", path, exc)
        matcher = matcher or make_matcher(cfg)
        t0 = time.perf_counter()
        if echo:
            echo(f"building references of {mesh.name} ({path.name}) ...")
        refs = build_reference_set(mesh, cfg.refs, matcher=matcher, progress=progress, workers=workers, shape=cfg.shape)
        save_reference_set(refs, path)
        if echo:
            echo(f"built {mesh.name} in {time.perf_counter() - t0:.0f} s")
        return refs
    finally:
        if owner:
            lock.unlink(missing_ok=True)


def _describe(lock: Path) -> str:
    o = _lock_owner(lock)
    return f"pid {o['pid']} on {o.get('host', '?')}" if o else "another process"


class Journal:
    """An append-only JSON-lines file of finished work: the resumable loop of pixie's runs and benchmarks.

    Each line is one JSON record; ``key(record)`` names the work it finishes (the last record of a key wins).
    A line cut by a kill is skipped, so that work runs again.

    >>> j = Journal(out / "targets.jsonl", key=lambda r: (r["scene_id"], r["im_id"], r["obj_id"]))
    >>> for t in targets:
    ...     if (t.scene_id, t.im_id, t.obj_id) not in j:
    ...         j.append(run(t))
    """

    def __init__(self, path: str | Path, key: Callable[[dict], Hashable]):
        self.path = Path(path)
        self.key = key
        self.records: dict[Hashable, dict] = {}
        self._cut = False  # the file ends inside a line (a killed write): the next record starts a new line
        self.bad_lines: list[int] = []  # 1-based numbers of lines that were cut or corrupt (their work reruns)
        if self.path.is_file():
            text = self.path.read_bytes().decode("utf-8", errors="replace")
            self._cut = bool(text) and not text.endswith("\n")
            for n, line in enumerate(text.splitlines(), 1):
                if not line.strip():
                    continue
                try:
                    rec = json.loads(line)
                    if not isinstance(rec, dict):
                        raise TypeError("not a record")
                    self.records[key(rec)] = rec
                except (ValueError, KeyError, TypeError, IndexError):  # a line cut by a kill: run that work again
                    self.bad_lines.append(n)

    def bad_lines_note(self, what: str = "targets") -> str:
        """The one line that reports cut or corrupt lines (whose work runs again)."""
        n = self.bad_lines
        return (f"warning: {self.path}: {len(n)} line(s) cut or corrupt (line {', '.join(map(str, n[:10]))}"
                f"{' ...' if len(n) > 10 else ''}); their {what} run again")

    def __contains__(self, key: Hashable) -> bool:
        return key in self.records

    def __len__(self) -> int:
        return len(self.records)

    def get(self, key: Hashable, default: dict | None = None) -> dict | None:
        return self.records.get(key, default)

    def append(self, record: dict) -> dict:
        """Write ``record`` as one line (flushed) and remember it."""
        self.path.parent.mkdir(parents=True, exist_ok=True)
        with open(self.path, "a") as fh:
            fh.write(("\n" if self._cut else "") + json.dumps(record) + "\n")
            fh.flush()
            os.fsync(fh.fileno())
        self._cut = False
        self.records[self.key(record)] = record
        return record


def run_dataset(dataset_root: str | Path, out_dir: str | Path, config: PixieConfig | None = None,
                objects: list[int] | None = None, max_targets: int | None = None,
                refs_dir: str | Path | None = None, echo: Callable[[str], None] = print,
                show_progress: bool = True, threads: int | None = None, use_ray: bool = False,
                address: str | None = None, workers: int | None = None,
                detections: str | Path | DetectionSet | None = None) -> Path:
    """Estimate every target of a BOP dataset (GT ``bbox_visib`` as the crop, or the top-scoring of the BOP-format
    ``detections``, :mod:`pixie.eval.detections`) and write ``results.csv``.

    Per-target results are appended to ``out_dir/per_target.jsonl`` as they come, so an interrupted
    run resumes where it stopped. Returns the path of the BOP CSV.

    ``threads`` fixes torch/OpenCV threads for the run (``None``: leave them as they are). With ``use_ray`` the
    reference sets are built here first (once, into ``refs_dir``) and Ray workers (:func:`pixie.app.cluster.ray_map`,
    ``threads`` each, default 1) load them from there; the results equal a serial run's at the same ``threads``.
    """
    cfg = config if config is not None else PixieConfig.from_preset()  # no config: the shipped 'default' preset
    ds = BopDataset(dataset_root)
    out = output_dir(out_dir)
    remove_stale_temps(out)
    refs_dir = Path(refs_dir) if refs_dir else out / "refs"
    targets = select_targets(ds, objects, max_targets)
    # the targets this run is about (scored by `pixie run`, or `pixie eval --targets`): one without a pose is a miss
    write_atomic(out / "targets.json", json.dumps([dict(scene_id=t.scene_id, im_id=t.im_id, obj_id=t.obj_id,
                                                        inst_count=t.inst_count) for t in targets]))
    journal = Journal(out / "per_target.jsonl", key=lambda rec: tuple(rec["key"]))
    dets = detections if isinstance(detections, DetectionSet) or detections is None else load_detections(detections)
    if dets is not None:
        echo(f"{len(dets)} detections from {dets.path} (the top-scoring per target, as BOP's unseen-object protocol)")
    prints = {o: run_fingerprint(cfg, ds, o, dets) for o in sorted({t.obj_id for t in targets})}
    cached = {_tkey(t) for t in targets if _valid_record(journal.get(_tkey(t)), prints[t.obj_id])}
    errors = sum(bool((journal.get(_tkey(t)) or {}).get("error")) for t in targets)
    stale = sum(_tkey(t) in journal and _tkey(t) not in cached for t in targets) - errors
    todo = [t for t in targets if _tkey(t) not in cached]
    where = f" (Ray{' at ' + address if address else ''})" if use_ray else ""
    echo(f"{len(targets)} targets, {len(cached)} cached, {len(todo)} to run -> {out}{where}")
    if journal.bad_lines:
        echo(journal.bad_lines_note("targets"))
    if errors:
        echo(f"{errors} target(s) that could not be read last time run again")
    if stale:
        echo(f"{stale} earlier result(s) in {journal.path.name} were made with another config, code version, dataset "
             "or model: they run again")
    write_atomic(out / "config.json", json.dumps(cfg.to_dict(), indent=1))
    if todo:
        before = set_threads(threads or 1) if (threads or use_ray) else None
        try:
            if use_ray:
                _run_ray(ds, cfg, todo, refs_dir, journal, echo, show_progress, threads or 1, address, workers, prints,
                         dets)
            else:
                _run_serial(ds, cfg, todo, refs_dir, journal, echo, show_progress, prints, dets)
        finally:
            if before is not None:
                set_threads(before)
    ests = [dict(e, key=_tkey(t)) for t in targets for e in journal.get(_tkey(t), {"estimates": []})["estimates"]]
    csv = out / "results.csv"
    write_results_csv(csv, [_estimate(e) for e in ests if e["T"] is not None])  # a missing pose counts as a miss
    return csv


def _run_serial(ds: BopDataset, cfg: PixieConfig, todo: list[Target], refs_dir: Path, journal: Journal,
                echo: Callable[[str], None], show_progress: bool, prints: dict[int, str],
                dets: DetectionSet | None = None) -> None:
    bar = _progress(len(todo), show_progress)
    matcher = make_matcher(cfg)
    for obj_id in sorted({t.obj_id for t in todo}):
        mesh = load_mesh(ds.model_path(obj_id))
        t0 = time.perf_counter()
        refs = cached_reference_set(mesh, cfg, refs_dir, matcher=matcher, echo=echo)
        echo(f"obj {obj_id}: reference set ready in {time.perf_counter() - t0:.1f} s")
        est = PoseEstimator(refs, cfg, matcher=matcher)
        for t in (t for t in todo if t.obj_id == obj_id):
            journal.append(dict(_run_target(ds, est, t, dets), run=prints[obj_id]))
            bar.update(1)
    bar.close()


def _run_ray(ds: BopDataset, cfg: PixieConfig, todo: list[Target], refs_dir: Path, journal: Journal,
             echo: Callable[[str], None], show_progress: bool, threads: int, address: str | None,
             workers: int | None, prints: dict[int, str], dets: DetectionSet | None = None) -> None:
    """The targets on Ray workers: reference sets built here once (at ``threads``, like a serial run), workers
    load them from ``refs_dir``; records come back here and go to the journal."""
    matcher = make_matcher(cfg)
    refs_paths: dict[int, str] = {}
    for obj_id in sorted({t.obj_id for t in todo}):
        mesh = load_mesh(ds.model_path(obj_id))
        t0 = time.perf_counter()
        cached_reference_set(mesh, cfg, refs_dir, matcher=matcher, echo=echo)
        refs_paths[obj_id] = str(reference_cache_path(mesh, cfg, refs_dir).resolve())
        echo(f"obj {obj_id}: reference set ready in {time.perf_counter() - t0:.1f} s")
    todo = sorted(todo, key=lambda t: (t.obj_id, t.scene_id, t.im_id))  # workers keep the estimator at hand
    bar = _progress(len(todo), show_progress)
    spec = WorkerSpec(_setup_bop, _process_bop, {"dataset": str(ds.root.resolve()), "config": cfg.to_dict(),
                                                 "refs": refs_paths,
                                                 "detections": None if dets is None else str(dets.path.resolve())},
                      threads)

    def on_result(_: int, rec: dict) -> None:
        journal.append(dict(rec, run=prints[rec["key"][2]]))
        bar.update(1)

    try:
        n = ray_map(spec, [[t.scene_id, t.im_id, t.obj_id, t.inst_count] for t in todo], on_result, workers, address)
    finally:
        bar.close()
    echo(f"{len(todo)} targets on {n} Ray workers")


def _setup_bop(args: dict) -> dict:
    """Ray worker state: the dataset, the config, the reference-set files, one matcher, estimators on demand."""
    cfg = PixieConfig.from_dict(args["config"])
    return {"ds": BopDataset(args["dataset"]), "cfg": cfg, "refs": {int(k): v for k, v in args["refs"].items()},
            "matcher": make_matcher(cfg), "est": {},
            "dets": load_detections(args["detections"]) if args.get("detections") else None}


def _process_bop(state: dict, item: list[int]) -> dict:
    """One target on a Ray worker; estimators are kept for the last two objects only (memory)."""
    scene_id, im_id, obj_id, inst_count = item
    ests = state["est"]
    if obj_id not in ests:
        ds = state["ds"]
        refs = load_reference_set(state["refs"][obj_id], mesh=load_mesh(ds.model_path(obj_id)))
        while len(ests) >= 2:
            ests.pop(next(iter(ests)))
        ests[obj_id] = PoseEstimator(refs, PixieConfig.from_dict(state["cfg"].to_dict()), matcher=state["matcher"])
    return _run_target(state["ds"], ests[obj_id], Target(scene_id, im_id, obj_id, inst_count), state.get("dets"))


def _crops(ds: BopDataset, t: Target, dets: DetectionSet | None) -> list[dict]:
    """What each of the target's ``inst_count`` estimates is given: a GT instance's ``bbox_visib`` (most visible
    first), or, with external detections, the top-scoring detections' masks or boxes; ``{"missing": why}`` where
    there is none (a failed estimate naming why)."""
    if dets is not None:
        found = dets.for_target(t.scene_id, t.im_id, t.obj_id, t.inst_count)
        out = [{"bbox": d.box_xywh if d.rle is None else None, "mask": d.mask(), "detection": d} for d in found]
        why = (f"scene {t.scene_id} image {t.im_id} object {t.obj_id}: {dets.path.name} has "
               f"{len(found)} detection(s) of it for {t.inst_count} instance(s)")
        return out + [{"missing": why}] * (t.inst_count - len(found))
    insts = sorted((g for g in ds.instances(t.scene_id, t.im_id) if g.obj_id == t.obj_id),
                   key=lambda g: -(g.visib_fract if g.visib_fract is not None else 1.0))
    out = []
    for g in insts[: t.inst_count]:
        if g.box_visib is None:
            out.append({"missing": f"scene {t.scene_id} image {t.im_id} object {t.obj_id}: the dataset gives no "
                                   "bbox_visib (scene_gt_info.json), and pixie needs the object's box"})
        else:
            out.append({"bbox": g.box_visib, "mask": None})
    return out


def _run_target(ds: BopDataset, est, t: Target, dets: DetectionSet | None = None) -> dict:
    """Estimate the pose of each instance of the target object in one image: GT ``bbox_visib`` crops, or the
    top-scoring external detections (``dets``) as BOP's unseen-object protocol does (a target without one is a miss).

    A target whose image or annotations cannot be read is recorded failed with the reason (``error``: it runs
    again next time) and counts as a miss; the run goes on."""
    rows = []
    try:
        img = ds.load_rgb(t.scene_id, t.im_id)
        K = ds.camera(t.scene_id, t.im_id).K
        crops = _crops(ds, t, dets)
    except (PixieError, OSError) as exc:
        why = str(exc) if f"image {t.im_id}" in str(exc) else f"scene {t.scene_id} image {t.im_id}: {exc}"
        return {"key": list(_tkey(t)), "error": why, "estimates": [
            {"T": None, "score": 0.0, "failed": True, "time": 0.0, "timings": {"error": why}}] * t.inst_count}
    for crop in crops:
        t0 = time.perf_counter()
        warns: list[str] = []
        try:
            if "missing" in crop:
                raise DatasetError(crop["missing"])
            with collect_warnings() as notes:
                r = est.estimate(img, K, bbox=crop["bbox"], mask=crop["mask"])
            T, score, failed, timings, warns = r.T_cam_from_obj, r.score, r.failed, r.timings, notes.merge(r.warnings)
        except PixieError as exc:
            T, score, failed, timings = None, 0.0, True, {"error": str(exc)}
        row = {"T": None if T is None else T.tolist(), "score": score, "failed": failed,
               "time": time.perf_counter() - t0, "timings": timings, "warnings": warns}
        if crop.get("detection") is not None:  # which external detection this estimate used
            d = crop["detection"]
            row["detection"] = {"index": d.index, "score": d.score, "box_xywh": [float(v) for v in d.box_xywh],
                                "mask": d.rle is not None, "time": d.time}
        rows.append(row)
    return {"key": list(_tkey(t)), "estimates": rows}


def select_targets(ds: BopDataset, objects: list[int] | None = None, max_targets: int | None = None) -> list[Target]:
    """The targets of a run: the dataset's (of ``objects``), ``max_targets`` of them spread evenly when given."""
    targets = [t for t in ds.targets() if objects is None or t.obj_id in objects]
    if max_targets is not None and len(targets) > max_targets:
        targets = [targets[i] for i in np.linspace(0, len(targets) - 1, max_targets).round().astype(int)]
    return targets


@functools.lru_cache(maxsize=1)
def code_version() -> str:
    """pixie's version plus a hash of its source files: any code change makes earlier results stale."""
    root = Path(__file__).resolve().parents[1]  # the pixie package
    h = hashlib.sha256(__version__.encode())
    for p in sorted(root.rglob("*.py")):
        h.update(str(p.relative_to(root)).encode() + b"\0" + p.read_bytes())
    return f"{__version__}+{h.hexdigest()[:12]}"


def run_fingerprint(cfg: PixieConfig, ds: BopDataset, obj_id: int, dets: DetectionSet | None = None) -> str:
    """What a per-target result of ``obj_id`` depends on: code version, the whole config, the dataset (folder
    and split), the object's model file (hence its reference set, a function of model, config and code) and the
    detections file when one gives the crops."""
    model = hashlib.sha256(Path(ds.model_path(obj_id)).read_bytes()).hexdigest()
    blob = json.dumps({"code": code_version(), "config": cfg.to_dict(), "dataset": str(Path(ds.root).resolve()),
                       "split": ds.split, "model": model}, sort_keys=True)
    if dets is not None:  # only then: earlier GT-box runs keep their fingerprints
        blob += "|detections:" + dets.sha256
    return hashlib.sha256(blob.encode()).hexdigest()[:16]


def _valid_record(rec: dict | None, fingerprint: str) -> bool:
    """A journal record that can be reused: made under ``fingerprint`` and well formed."""
    if rec is None or rec.get("run") != fingerprint or rec.get("error") or not isinstance(rec.get("estimates"), list):
        return False
    try:
        for e in rec["estimates"]:
            if e["T"] is not None and np.asarray(e["T"], np.float64).shape != (4, 4):
                return False
            float(e["score"]), float(e["time"]), bool(e["failed"])
    except (KeyError, TypeError, ValueError):
        return False
    return True


def _tkey(t: Target) -> tuple[int, int, int]:
    return (t.scene_id, t.im_id, t.obj_id)


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
