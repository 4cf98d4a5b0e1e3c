"""Many photos, of one object or several: ``pixie estimate --batch FOLDER|MANIFEST -o OUT``.

Inputs are a folder of images (one ``--K`` for all; one ``--bbox`` for all or a folder of masks with the
images' names) or a manifest, CSV or JSON, one row per image::

    image,K,bbox,mask
    photos/a.png,"600,600,320,240","250,180,120,110",
    photos/b.png,"600,600,320,240",,masks/b.png

``K`` is ``fx,fy,cx,cy`` (or 9 values), ``bbox`` ``x,y,w,h`` in pixels (``w``, ``h`` counting pixels), ``mask``
an image (white = object); every row needs a bbox or a mask. Optional columns ``scene_id``, ``im_id``,
``obj_id`` go to the BOP CSV (defaults 0, the row number, 1); ``gt_pose`` (a pose file) adds the estimate's
error against it to the result and the page. Paths are relative to the manifest.
JSON manifests are a list of objects with the same keys (``K`` and ``bbox`` may be lists).

**One assembly in several photos** (``pixie inspect --batch``): rows with the same ``assembly`` column (any name)
show one physical assembly from different viewpoints; its part report is judged over all of them
(:func:`pixie.cues.part_views.combine_views`: each part's score averaged over the photos that see it), which tells a
defect, present in every photo, from one photo's noise. A folder batch with ``--one-assembly`` is one assembly.

**Several objects per photo:** a row per (photo, object, box or mask), with the object named per row by a ``refs``
(a reference set) or ``mesh`` (a CAD file: its set is built once into the user cache, as for ``estimate --mesh``)
column; rows without one use
``--refs`` / ``--mesh``. Rows of one photo share one overlay with every object drawn (``overlays/*_all.png``).

One estimator per reference set serves its images (loaded or built once). Outputs in ``OUT``:

* ``results.csv`` -- BOP'19 results (scene_id, im_id, obj_id, score, R, t, time); failed rows keep their
  best guess with score 0, rows without any pose are left out;
* ``results.jsonl`` -- one full result per image, in input order (inputs, hashes, config, pose, hypotheses);
* ``index.html`` + ``overlays/*.png`` -- one overlay per image;
* ``assemblies.json`` -- with ``assembly`` groups of a mesh with parts: per assembly its photos and each part's
  verdict over them (the page lists assemblies with suspect parts first, above the photos);
* ``journal.jsonl`` -- the cache that makes runs resumable: a record is reused when the image's bytes, its
  K, box and mask, the configuration and the reference set are all the same (a changed config re-runs).
"""

from __future__ import annotations

import copy
import csv
import hashlib
import html
import json
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import cv2
import numpy as np

from pixie.geometry.camera import parse_box, parse_K
from pixie.app.assemblies import ASSEMBLY_NOTE, assembly_html, assembly_reports
from pixie.app.cluster import WorkerSpec, ray_map, serial_map
from pixie.app.notes import Notes, annotate, collect_warnings
from pixie.app.runner import Journal
from pixie.app.track import read_pose_file
from pixie.config import PixieConfig
from pixie.errors import ConfigError, ImageError, PixieError, UsageError
from pixie.pipeline.estimator import PoseEstimator
from pixie.eval.datasets import PoseEstimate, write_results_csv
from pixie.paths import remove_stale_temps, write_atomic
from pixie.pipeline.query import bbox_from_mask, check_bbox, load_image
from pixie.pose.results import NO_BOX_WHY, SUSPECT_VERDICTS
from pixie.references.store import ensure_templates, load_reference_set
from pixie.geometry.render import Renderer
from pixie.viz import draw_parts, encode_png, overlay_result, pose_detail, status_view
from pixie.synth.check import pose_error
from pixie.weights import sha256_file

__all__ = ["BatchItem", "read_manifest", "folder_items", "run_batch", "IMAGE_SUFFIXES", "BATCH_OUTPUTS"]

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff")
BATCH_OUTPUTS = ("results.csv", "results.jsonl", "index.html", "journal.jsonl", "assemblies.json")  # into the output folder


@dataclass
class BatchItem:
    """One photo to estimate: where it is, its intrinsics, and its box or mask."""

    image: Path
    K: np.ndarray
    bbox: np.ndarray | None = None  # (x, y, w, h), w/h counting pixels
    mask: Path | None = None
    scene_id: int = 0
    im_id: int = 0
    obj_id: int = 1
    refs: Path | None = None  # this row's reference set (several objects per photo); None: the batch's
    gt_pose: Path | None = None  # a pose file with this row's true pose: its errors go into the result and the page
    mesh: Path | None = None  # or its CAD file (the CLI builds the set once and fills ``refs``)
    assembly: str | None = None  # photos with the same name show one physical assembly (judged together)

    @property
    def name(self) -> str:
        return self.image.name


NO_BOX_HELP = f"give a bbox x,y,w,h or a mask image for every photo: {NO_BOX_WHY}"


def read_manifest(path: str | Path) -> list[BatchItem]:
    """Rows of a CSV or JSON manifest (see the module doc); paths are taken relative to the manifest.

    Raises
    ------
    ConfigError
        Unreadable manifest, missing columns, a row without K or without box and mask, bad numbers.
    ImageError
        Images or masks that do not exist (all of them are named).
    """
    path = Path(path)
    if not path.is_file():
        raise ConfigError(f"manifest not found: {path}")
    try:
        if path.suffix.lower() == ".json":
            data = json.loads(path.read_text())
            rows = data.get("rows") if isinstance(data, dict) else data
            if not isinstance(rows, list) or not all(isinstance(r, dict) for r in rows):
                raise ConfigError(f"manifest {path}: JSON must be a list of objects (or {{'rows': [...]}})")
        else:
            with open(path, newline="") as fh:
                rows = list(csv.DictReader(fh))
    except (OSError, ValueError, csv.Error) as exc:
        raise ConfigError(f"cannot read manifest {path}: {exc}") from exc
    if not rows:
        raise ConfigError(f"manifest {path} has no rows")
    base = path.parent
    items: list[BatchItem] = []
    missing: list[str] = []
    for n, row in enumerate(rows):
        row = {str(k).strip().lower(): v for k, v in row.items() if k is not None}
        where = f"manifest {path.name} row {n + 1}"
        if not row.get("image"):
            raise ConfigError(f"{where}: no 'image' (columns: image, K, bbox, mask)")
        if row.get("k") in (None, ""):
            raise ConfigError(f"{where}: no 'K' (fx,fy,cx,cy)")
        has_box = row.get("bbox") not in (None, "")
        has_mask = row.get("mask") not in (None, "")
        if not has_box and not has_mask:
            raise ConfigError(f"{where}: no bbox and no mask; {NO_BOX_HELP}")
        image = base / str(row["image"])
        mask = base / str(row["mask"]) if has_mask else None
        obj = {k: base / str(row[k]) for k in ("refs", "mesh") if row.get(k) not in (None, "")}
        gt = {"gt_pose": base / str(row["gt_pose"])} if row.get("gt_pose") not in (None, "") else {}
        if len(obj) == 2:
            raise ConfigError(f"{where}: give the object as 'refs' or as 'mesh', not both")
        for p in (image, mask, *obj.values(), *gt.values()):
            if p is not None and not p.is_file():
                missing.append(f"{where}: {p}")
        ids = {}
        for key, default in (("scene_id", 0), ("im_id", n), ("obj_id", 1)):
            try:
                ids[key] = int(row[key]) if row.get(key) not in (None, "") else default
            except (TypeError, ValueError) as exc:
                raise ConfigError(f"{where}: {key} must be an integer, got {row[key]!r}") from exc
        box = parse_box(row["bbox"], "bbox", where, ConfigError) if has_box else None
        asm = str(row["assembly"]).strip() if row.get("assembly") not in (None, "") else None
        items.append(BatchItem(image, parse_K(row["k"], "K", where, ConfigError), box, mask, **ids, **obj, **gt,
                               assembly=asm))
    if missing:
        raise ImageError(f"{len(missing)} file(s) of the manifest do not exist:\n  " + "\n  ".join(missing[:20]))
    return items


def folder_items(folder: str | Path, K: str | np.ndarray | None, bbox: str | None = None,
                 masks: str | Path | None = None, one_assembly: bool = False) -> list[BatchItem]:
    """Every image of ``folder`` (sorted by name) with one ``K``, and one ``bbox`` for all or a mask per image
    (``masks/<same name>`` with any image suffix). ``one_assembly``: the images show one physical assembly (its
    part report judged over all of them), named after the folder."""
    folder = Path(folder)
    images = sorted(p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES)
    if not images:
        raise ImageError(f"no images ({', '.join(IMAGE_SUFFIXES)}) in {folder}")
    if K is None:
        raise ConfigError("a folder of images needs --K fx,fy,cx,cy (or use a manifest with a K per image)")
    Km = parse_K(K, "--K", error=ConfigError) if not isinstance(K, np.ndarray) else K
    if bbox is None and masks is None:
        raise ConfigError(f"no box for the images in {folder}: {NO_BOX_HELP}. Pass --bbox x,y,w,h (one box for "
                          "every image), --masks DIR (one mask per image, same file name), or a manifest")
    items = []
    for n, img in enumerate(images):
        mask = None
        if masks is not None:
            cands = [Path(masks) / (img.stem + s) for s in IMAGE_SUFFIXES]
            mask = next((c for c in cands if c.is_file()), None)
            if mask is None:
                raise ImageError(f"no mask for {img.name} in {masks} (looked for {img.stem}.png etc.)")
        items.append(BatchItem(img, Km, None if bbox is None else parse_box(bbox, "--bbox", error=ConfigError), mask, 0, n, 1,
                               assembly=folder.resolve().name if one_assembly else None))
    return items


def load_mask(path: str | Path) -> np.ndarray:
    """A mask image as booleans (pixel values > 127 in the first channel are the object)."""

    return load_image(path)[..., 0] > 127


def sha256_bytes(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def item_key(item: BatchItem, image_sha: str, mask_sha: str | None, config_digest: str, refs_sha: str) -> str:
    """Cache key of one result: which item it is (image path, BOP ids: two photos of identical bytes are two
    results), image and mask bytes, K, box, configuration and reference set."""
    blob = json.dumps({"item": [str(item.image.resolve()), item.scene_id, item.im_id, item.obj_id],
                       "image": image_sha, "mask": mask_sha, "K": np.round(item.K, 9).tolist(),
                       "bbox": None if item.bbox is None else np.round(item.bbox, 6).tolist(),
                       "config": config_digest, "refs": refs_sha,
                       **({"gt": [str(item.gt_pose), sha256_file(item.gt_pose)]} if item.gt_pose else {})},
                      sort_keys=True)
    return hashlib.sha256(blob.encode()).hexdigest()[:20]


# ----------------------------------------------------------------------------------------- workers
def _setup(args: dict) -> dict:
    """Worker state: the configuration; an estimator and a renderer per reference set, made on first use."""

    cfg = PixieConfig.from_dict(args["config"])
    cfg.preset = args.get("preset")
    return {"est": {}, "renderer": {}, "overlays": args["overlays"], "cfg": cfg, "notes": [],
            "stage": args.get("stage")}  # serial runs: shows the running stage on the progress bar


def _estimator(state: dict, refs_path: str) -> PoseEstimator:
    """The worker's estimator of the reference set at ``refs_path`` (loaded once per worker)."""
    if refs_path not in state["est"]:
        refs = load_reference_set(refs_path)
        with collect_warnings() as notes:  # CUDA asked for but absent ...: into every result's warnings
            state["est"][refs_path] = PoseEstimator(refs, state["cfg"])
        state["renderer"][refs_path] = Renderer(refs.mesh)
        state["notes"] = list(dict.fromkeys(state["notes"] + notes.items))
    return state["est"][refs_path]


def _process(state: dict, job: dict) -> dict:
    """Estimate one photo; a bad input gives a failed record, never an exception."""

    t0 = time.perf_counter()
    rec = {k: job.get(k) for k in ("key", "row", "name", "image", "image_sha256", "K", "bbox", "mask",
                                   "scene_id", "im_id", "obj_id", "refs", "gt_pose")}
    try:
        est = _estimator(state, job["refs"])
        notes = Notes().extend(state.get("notes"))
        with collect_warnings() as seen:  # EXIF orientation, unusual K ...
            image = load_image(job["image"])
            mask = load_mask(job["mask"]) if job["mask"] else None
            K = np.asarray(job["K"], np.float64)
            res = est.estimate(image, K, bbox=job["bbox"], mask=mask, progress=state.get("stage"))
        rec["result"] = annotate(res, est, state["cfg"], notes.extend(seen.items)).to_dict()
        if job.get("gt_pose") and res.T_cam_from_obj is not None:
            rec["result"]["gt_error"] = pose_error(res.T_cam_from_obj, read_pose_file(job["gt_pose"]), est.refs.mesh.vertices)
        if state["overlays"]:

            bbox = job["bbox"] if job["bbox"] is not None else bbox_from_mask(mask)
            box = check_bbox(bbox, image.shape[:2])
            label = f"conf {res.confidence:.2f}"
            ov = overlay_result(image, state["renderer"][job["refs"]], res.T_cam_from_obj, K, box, label)
            if res.part_support:
                ov = draw_parts(ov, res.part_support)
            rec["overlay_png"] = encode_png(status_view(ov, box, res.failed, res.message, pose_detail(res)))
    except PixieError as exc:
        rec["result"] = {"T_cam_from_obj": None, "failed": True, "message": f"{type(exc).__name__}: {exc}",
                         "score": 0.0, "confidence": 0.0, "warnings": list(state.get("notes") or [])}
    rec["time_s"] = time.perf_counter() - t0
    return rec


# ------------------------------------------------------------------------------------------ driver
@dataclass
class BatchSummary:
    n_items: int
    n_cached: int
    n_run: int
    n_failed: int
    seconds: float
    results_csv: Path
    results_jsonl: Path
    html: Path
    workers: int = 1
    assemblies: list[dict] | None = None  # assembly_reports of the batch (photos judged together), when any


def with_assembly_evidence(config: PixieConfig, items: list[BatchItem], echo: Callable[[str], None] = print
                           ) -> PixieConfig:
    """``config`` with ``parts.evidence`` on when some items name an assembly and the assembly's verdict can use the
    3D-move / resize evidence (``parts.views_move_gain`` / ``views_resize_gain`` at most 1) that the config does not
    compute yet; else ``config`` itself. A photo's own verdict does not change (pixie.cues.parts.report_kwargs)."""
    pc = config.parts
    # one photo's resizes (parts.resizes) are not the assembly's (views_resize_factors, on every part): asked for anyway
    wanted = (pc.views_move_gain <= 1 and not pc.moves) or pc.views_resize_gain <= 1
    if not any(it.assembly for it in items) or not pc.enabled or pc.evidence or not wanted:
        return config
    config = copy.deepcopy(config)
    config.set("parts.evidence", True)
    echo("assemblies in the batch: every photo's parts are also tried moved (and resized, with "
         "parts.views_resize_gain) for the assemblies' verdicts (parts.evidence; a few seconds more per photo)")
    return config


def run_batch(items: list[BatchItem], out_dir: str | Path, config: PixieConfig, refs_path: str | Path | None,
              *, threads: int = 1, use_ray: bool = False, address: str | None = None, workers: int | None = None,
              overlays: bool = True, echo: Callable[[str], None] = print, show_progress: bool = True,
              max_items: int | None = None) -> BatchSummary:
    """Estimate every item with one reference set; resumable; writes the outputs listed in the module doc.

    ``max_items`` stops after that many newly run items (the outputs then cover what is done so far). An item with
    its own ``refs`` uses that set; the others use ``refs_path`` (None only when every item names its own).
    """

    t_start = time.perf_counter()
    config = with_assembly_evidence(config, items, echo)
    out = Path(out_dir)
    (out / "overlays").mkdir(parents=True, exist_ok=True)
    refs_of = {}  # every reference set used -> (its sha256, its mesh's sha256)
    for it in items:
        p = it.refs or refs_path
        if p is None:
            raise UsageError(f"{it.name}: no object: give --refs / --mesh, or a refs or mesh column in the manifest")
        p = Path(p).resolve()
        if p not in refs_of:
            refs = load_reference_set(p)  # fail early on a bad set; workers load it again from the file
            ensure_templates(refs, config.shape)  # an older set: templates built once here and saved
            refs_of[p] = (sha256_file(p), refs.mesh.source_hash)
            del refs
    digest = config.digest()
    if max_items is not None and (isinstance(max_items, bool) or not isinstance(max_items, int) or max_items < 1):
        raise UsageError(f"--max-items must be a whole number of at least 1, got {max_items!r}")
    remove_stale_temps(out)
    remove_stale_temps(out / "overlays")
    jobs = []
    for n, it in enumerate(items):
        img_sha = sha256_file(it.image) if it.image.is_file() else "missing"
        mask_sha = sha256_file(it.mask) if it.mask is not None and it.mask.is_file() else None
        rp = Path(it.refs or refs_path).resolve()
        jobs.append({"key": item_key(it, img_sha, mask_sha, digest, refs_of[rp][0]), "row": n, "name": it.name,
                     "refs": str(rp),
                     "image": str(it.image), "image_sha256": img_sha, "K": it.K.tolist(),
                     "bbox": None if it.bbox is None else it.bbox.tolist(),
                     "mask": None if it.mask is None else str(it.mask),
                     "scene_id": it.scene_id, "im_id": it.im_id, "obj_id": it.obj_id,
                     "gt_pose": None if it.gt_pose is None else str(it.gt_pose), "assembly": it.assembly})
    journal = Journal(out / "journal.jsonl", key=lambda rec: rec["key"])  # the reader pixie run uses too
    done = journal.records
    todo = [j for j in jobs if j["key"] not in done]
    n_cached = len(jobs) - len(todo)
    if max_items is not None:
        todo = todo[:max_items]
    echo(f"{len(jobs)} images, {n_cached} cached, {len(todo)} to run -> {out}" + (f" (Ray{' at ' + address if address else ''})" if use_ray else ""))
    if journal.bad_lines:
        echo(journal.bad_lines_note("images"))
    bar = None
    if show_progress and todo:
        from tqdm import tqdm

        bar = tqdm(total=len(todo), unit="image", dynamic_ncols=True)
    n_workers = 1
    def on_result(_: int, rec: dict) -> None:
        png = rec.pop("overlay_png", None)
        rec["overlay"] = None
        if png is not None:
            name = f"overlays/{rec['row']:05d}_{Path(rec['name']).stem}.png"
            write_atomic(out / name, png)
            rec["overlay"] = name
        rp = Path(rec["refs"])
        rec.update(config_digest=digest, preset=config.preset, refs_sha256=refs_of[rp][0], mesh_sha256=refs_of[rp][1])
        journal.append(rec)  # one flushed line; a line cut by a kill is reported and its image runs again
        if bar is not None:
            bar.update(1)

    args = {"config": config.to_dict(), "preset": config.preset, "overlays": overlays}
    if bar is not None and not use_ray:  # in this process: the bar says which stage of which image is running
        args["stage"] = lambda stage: bar.set_postfix_str(stage, refresh=True)
    spec = WorkerSpec(_setup, _process, args, threads)
    try:
        if use_ray:
            n_workers = ray_map(spec, todo, on_result, workers=workers, address=address)
        elif todo:
            serial_map(spec, todo, on_result)
    finally:
        if bar is not None:
            bar.close()
    records = [done[j["key"]] for j in jobs if j["key"] in done]
    ests = []
    for r in records:
        res = r["result"]
        if res.get("T_cam_from_obj") is not None:
            ests.append(PoseEstimate(r["scene_id"], r["im_id"], r["obj_id"], 0.0 if res["failed"] else float(res["score"]),
                                     np.asarray(res["T_cam_from_obj"]), float(r["time_s"])))
    if overlays:
        _photo_overlays(records, out)
    write_results_csv(out / "results.csv", ests)  # atomic (pixie.paths.write_atomic)
    write_atomic(out / "results.jsonl", "".join(json.dumps(r) + "\n" for r in records))
    # the group of each record as given now (a cached record keeps the assembly it was run under otherwise)
    group_of = {j["key"]: j["assembly"] for j in jobs}
    assemblies = assembly_reports([{**r, "assembly": group_of.get(r["key"])} for r in records], config)
    if assemblies:
        write_atomic(out / "assemblies.json", json.dumps({"note": ASSEMBLY_NOTE, "assemblies": assemblies}, indent=1))
    elif (out / "assemblies.json").is_file():
        (out / "assemblies.json").unlink()  # a previous run's groups no longer apply
    write_atomic(out / "index.html", _html(records, len(jobs), config, assemblies))
    n_failed = sum(1 for r in records if r["result"].get("failed"))
    return BatchSummary(len(jobs), n_cached, len(todo), n_failed, time.perf_counter() - t_start,
                        out / "results.csv", out / "results.jsonl", out / "index.html", n_workers, assemblies)


def _photo_overlays(records: list[dict], out: Path) -> None:
    """One overlay per photo with several objects: every object's estimate drawn into it (``*_all.png``); each
    record of that photo then points to it as ``photo_overlay``."""
    by_image: dict[str, list[dict]] = {}
    for r in records:
        by_image.setdefault(r["image"], []).append(r)
    renderers: dict[str, Renderer] = {}
    for path, group in by_image.items():
        if len(group) < 2:
            continue
        try:
            img = load_image(path)
        except PixieError:
            continue
        for r in group:
            res = r["result"]
            if r["refs"] not in renderers:
                renderers[r["refs"]] = Renderer(load_reference_set(r["refs"]).mesh)
            T = None if res.get("T_cam_from_obj") is None else np.asarray(res["T_cam_from_obj"])
            box = None
            if r["bbox"] is not None:
                x, y, w, h = r["bbox"]
                box = np.array([x, y, x + w, y + h], np.float64)
            label = f"{Path(r['refs']).stem}: {'FAILED' if res.get('failed') else 'ok'}"
            img = overlay_result(img, renderers[r["refs"]], T, np.asarray(r["K"]), box, label, shade_alpha=0.2)
        name = f"overlays/{group[0]['row']:05d}_{Path(path).stem}_all.png"
        write_atomic(out / name, encode_png(img))
        for r in group:
            r["photo_overlay"] = name


def suspect_first(records: list[dict]) -> list[dict]:
    """Records ordered for an inspector: photos with suspect parts first (most first), then the rest, each group in
    batch order."""
    def n_suspect(r: dict) -> int:
        return sum(p.get("verdict") in SUSPECT_VERDICTS for p in r["result"].get("parts") or [])

    return sorted(records, key=lambda r: (-n_suspect(r), r["row"]))


def _html(records: list[dict], n_total: int, config: PixieConfig, assemblies: list[dict] | None = None) -> str:
    rows = []
    with_parts = any(r["result"].get("parts") for r in records)
    if with_parts:
        records = suspect_first(records)
    for r in records:
        res = r["result"]
        T = res.get("T_cam_from_obj")
        t = "" if T is None else ", ".join(f"{v:.1f}" for v in np.asarray(T)[:3, 3])
        rv = "" if T is None else ", ".join(f"{v:.1f}" for v in np.degrees(cv2.Rodrigues(np.asarray(T)[:3, :3])[0].ravel()))
        ge = res.get("gt_error")
        err = "" if not ge else f"{ge['rot_deg']:.2f}&deg;, {ge['trans_mm']:.1f} mm (ADD {ge['add_mm']:.1f} mm)"
        status = "FAILED: " + html.escape(str(res.get("message", ""))) if res.get("failed") else "ok"
        shown = r.get("photo_overlay") or r.get("overlay")  # every object of the photo, when it has several
        img = (f'<a href="{html.escape(shown)}"><img src="{html.escape(shown)}" width="480"></a>'
               if shown else "")
        if with_parts:
            sus = [p for p in res.get("parts") or [] if p.get("verdict") in SUSPECT_VERDICTS]
            status += "<br>" + ("<b>suspect parts:</b> " + ", ".join(
                f"{html.escape(p['name'])} ({p['verdict']}, support {p['support']:.2f}"
                + (", at the flipped runner-up pose" if p.get("judged_at") == "runner-up" else "") + ")" for p in sus)
                if sus else "parts: none suspect")
        rows.append(f"<tr><td>{r['row']}</td><td>{html.escape(r['name'])}</td><td>{img}</td><td>{status}</td>"
                    f"<td>{res.get('score', 0):.2f}</td><td>{res.get('confidence', 0):.2f}</td><td>{rv}</td><td>{t}</td><td>{err}</td>"
                    f"<td>{r['time_s']:.1f}</td></tr>")
    return f"""<!doctype html><html><head><meta charset="utf-8"><title>pixie batch</title>
<style>body{{font-family:sans-serif}} td{{padding:4px;vertical-align:top;border-bottom:1px solid #ddd}}</style></head>
<body><h1>pixie batch: {len(records)} of {n_total} images done</h1>
{assembly_html(assemblies or [])}
{"<p>Part report: photos with suspect (missing, displaced or wrong) parts come first; on the overlays parts are green (present), red (missing), orange (displaced), magenta (wrong), grey (not visible).</p>" if with_parts else ""}
<p>preset {html.escape(str(config.preset))}, config digest {config.digest()}. Overlay: model contour at the estimate (red),
object axes at its origin (x red, y green, z blue), the given box (yellow). Confidence = best score / (best + second
distinct hypothesis's score) without the alignment; with it (presets default, fast) the calibrated probability that the
pose is right (README, "Results you can use"). Translation t in mm, camera frame
(OpenCV: x right, y down, z forward).</p>
<table><tr><th>#</th><th>image</th><th>overlay</th><th>status</th><th>score</th><th>confidence</th>
<th>R as a rotation vector (deg)</th><th>t (mm)</th><th>error vs the manifest's gt_pose</th>
<th>s</th></tr>
{chr(10).join(rows)}
</table></body></html>
"""
