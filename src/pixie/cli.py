"""Command line: ``pixie refs build|show``, ``pixie estimate``, ``pixie run``, ``pixie eval``.

Every command takes ``--config FILE.yaml`` and ``--set section.key=value`` (repeatable) overrides
of :class:`pixie.config.PixieConfig`. Inputs and output paths are checked before any work starts.

Exit codes: 0 done (``estimate``: pose ok); 1 ``estimate`` ran but the pose is flagged failed; 2 bad input
(one ``pixie: error: ...`` line naming the problem, or argparse's usage message); 3 an unexpected internal
error (one line; ``-v`` shows the traceback); 130 interrupted (Ctrl-C). Warnings print as ``pixie: warning: ...``.
"""

from __future__ import annotations

import argparse
import json
import logging
import re
import signal
import sys
import threading
import time
import warnings
from pathlib import Path

import numpy as np

from pixie.camera import check_image_K, parse_K
from pixie.config import MatchConfig, PixieConfig
from pixie.encode import check_encodings
from pixie.errors import DatasetError, OutputError, PixieError, ReferenceSetError, UsageError
from pixie.estimator import PoseEstimator
from pixie.eval import (BopDataset, add_eval_arguments, main_eval, normalize_metrics, read_results_csv,
                        run_eval)
from pixie.mesh import load_mesh
from pixie.paths import output_dir, output_file, write_atomic
from pixie.query import bbox_from_mask, check_bbox, check_query_mask, load_image
from pixie.references import build_reference_set, check_output_path, load_reference_set, save_reference_set
from pixie.render import Renderer
from pixie.runner import make_matcher, run_dataset
from pixie.viz import contact_sheet, overlay_pose, save_png


def _numbers(text: str | None, option: str, count: int | None = None, kind: type = float) -> list:
    """Comma-separated numbers of a command-line option, with an error naming the option."""
    items = re.split(r"[,\s]+", (text or "").strip())
    try:
        vals = [kind(v) for v in items if v != ""]
    except ValueError:
        raise UsageError(f"{option} expects comma-separated {'whole ' if kind is int else ''}numbers, got {text!r}") from None
    if not all(np.isfinite(vals)):
        raise UsageError(f"{option} expects finite numbers, got {text!r}")
    if not vals or (count is not None and len(vals) != count):
        raise UsageError(f"{option} expects {count or 'some'} comma-separated numbers, got {text!r}")
    return vals


def _config(args: argparse.Namespace) -> PixieConfig:
    cfg = PixieConfig.from_yaml(args.config) if getattr(args, "config", None) else PixieConfig()
    return cfg.apply_overrides(getattr(args, "set", None))


def _add_config_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--config", help="YAML file with config sections (refs, query, match, pose, refine)")
    p.add_argument("--set", action="append", metavar="SECTION.KEY=VALUE", help="override one config value (repeatable)")


def _tqdm_progress(total_label: str):
    from tqdm import tqdm

    bar = {"b": None}

    def cb(done: int, total: int) -> None:
        if bar["b"] is None:
            bar["b"] = tqdm(total=total, unit=total_label, dynamic_ncols=True)
        bar["b"].update(done - bar["b"].n)
        if done >= total:
            bar["b"].close()

    return cb


# ------------------------------------------------------------------------------------------- refs
def _load_mesh(path: str, units: str | None):
    """The mesh for a command: with ``--units`` omitted, millimetres, and an implausible size is an error."""
    return load_mesh(path, units=units or "mm", implausible="warn" if units else "error")


def cmd_refs_build(args: argparse.Namespace) -> int:
    cfg = _config(args)
    if args.workers < 1:
        raise UsageError(f"--workers must be at least 1, got {args.workers}")
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
    mesh = _load_mesh(args.mesh, args.units)
    matcher = None if args.matcher == "none" else make_matcher(cfg)
    n_views = cfg.refs.n_fibonacci + (6 if cfg.refs.canonical else 0)
    print(f"{mesh.name}: {len(mesh.vertices)} vertices, diameter {mesh.diameter:.1f} mm; "
          f"{n_views} views x {cfg.refs.rotations} rolls at {cfg.refs.size} px, encodings {cfg.refs.encodings}, "
          f"features: {matcher.name if matcher else 'none'}")
    refs = build_reference_set(mesh, cfg.refs, matcher=matcher, progress=_tqdm_progress("view"), workers=args.workers)
    path = save_reference_set(refs, out)
    print(f"wrote {path} ({path.stat().st_size / 1e6:.1f} MB) in {refs.build_seconds:.1f} s")
    return 0


def cmd_refs_show(args: argparse.Namespace) -> int:
    out = output_file(args.output, suffix=".png", force=args.force, what="contact sheet")
    if not 8 <= args.tile <= 1024:
        raise UsageError(f"--tile must be 8..1024 px, got {args.tile}")
    refs = load_reference_set(args.refs)
    views = None if args.views is None else _numbers(args.views, "--views", kind=int)
    bad = [v for v in views or [] if not 0 <= v < refs.n_views]
    if bad:
        raise UsageError(f"--views {bad} not in the set, which has views 0..{refs.n_views - 1}")
    encs = check_encodings(args.encodings.split(",")) if args.encodings else None
    sheet = contact_sheet(refs, encs, views, tile=args.tile)
    save_png(out, sheet)
    feats = ", ".join(f"{k} ({len(refs.features_for(*k.split('/', 1))[0])} images)" for k in refs.features) or "none"
    print(f"{args.refs}: {refs.mesh.name}, {refs.n_views} views x {refs.n_rolls} rolls at {refs.size} px; "
          f"features: {feats}; sheet -> {out}")
    return 0


# --------------------------------------------------------------------------------------- estimate
def _matcher_for(refs, cfg: PixieConfig, args: argparse.Namespace) -> None:
    """Use the features stored in the set; refuse a matcher the user asked for that the set has none of."""
    stored = sorted({k.split("/")[0] for k in refs.features})
    if not stored or cfg.match.matcher in stored:
        return
    asked = cfg.match.matcher != MatchConfig().matcher or any(
        o.split("=", 1)[0].strip() == "match.matcher" for o in args.set or [])
    if asked:
        raise ReferenceSetError(
            f"{args.refs} holds features of {', '.join(stored)}, not of match.matcher={cfg.match.matcher}: rebuild it "
            f"with `pixie refs build MESH --matcher {cfg.match.matcher}` or use match.matcher={stored[0]}")
    cfg.match.matcher = stored[0]  # use the features the set was built with instead of re-extracting


def _not_an_input(outputs: list, inputs: list) -> None:
    """Refuse an output path that is one of the command's inputs (``--force`` would overwrite the photo)."""
    ins = {Path(p).resolve() for p in inputs if p}
    for o in outputs:
        if o is not None and Path(o).resolve() in ins:
            raise OutputError(f"output {o} is also an input of this command")


def cmd_estimate(args: argparse.Namespace) -> int:
    cfg = _config(args)
    out_json = output_file(args.output, force=args.force, what="result") if args.output else None
    out_png = output_file(args.overlay, suffix=".png", force=args.force, what="overlay") if args.overlay else None
    _not_an_input([out_json, out_png], [args.refs, args.image, args.mask])
    K = parse_K(args.K)
    bbox = None if args.bbox is None else _numbers(args.bbox, "--bbox", 4)
    refs = load_reference_set(args.refs)
    image = load_image(args.image)
    K = check_image_K(K, image.shape[:2])
    mask = None
    if args.mask:
        mask = check_query_mask(load_image(args.mask)[..., 0] > 127, image.shape[:2])
    box = check_bbox(bbox if bbox is not None else bbox_from_mask(mask) if mask is not None
                     else [0, 0, image.shape[1], image.shape[0]], image.shape[:2])
    if mask is not None:
        check_query_mask(mask, image.shape[:2], box)
    _matcher_for(refs, cfg, args)
    est = PoseEstimator(refs, cfg)
    res = est.estimate(image, K, bbox=bbox, mask=mask)
    T = res.T_cam_from_obj
    status = "FAILED (" + res.message + ")" if res.failed else "ok"
    print(f"pose {status}: score {res.score:.1f}, {res.n_inliers} inliers, view {res.view} roll {res.roll}, "
          f"confidence {res.confidence:.2f}")
    if T is not None:
        np.set_printoptions(precision=4, suppress=True)
        print("T_cam_from_obj (mm) =\n" + str(T))
    print("timings (s): " + ", ".join(f"{k} {v:.2f}" for k, v in res.timings.items()))
    if out_json:
        write_atomic(out_json, json.dumps(res.to_dict(), indent=1))
        print(f"result -> {out_json}")
    if out_png:
        save_png(out_png, overlay_pose(image, Renderer(refs.mesh), T, K))
        print(f"overlay -> {out_png}")
    return 1 if res.failed else 0


# ------------------------------------------------------------------------------------------- run
def cmd_run(args: argparse.Namespace) -> int:
    cfg = _config(args)
    objects = None if not args.objects else _numbers(args.objects, "--objects", kind=int)
    if args.max_targets is not None and args.max_targets < 1:
        raise UsageError(f"--max-targets must be at least 1, got {args.max_targets}")
    output_dir(args.output, what="output folder")
    if args.refs_dir:
        output_dir(args.refs_dir, what="reference-set folder")
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
                      refs_dir=args.refs_dir)
    print(f"results -> {csv} ({time.perf_counter() - t0:.0f} s); scoring")
    run_eval(args.dataset, csv, args.output, report=not args.no_report,
             only_estimated=args.max_targets is not None or args.objects is not None)
    return 0


def cmd_eval(args: argparse.Namespace) -> int:
    """``pixie eval``: the results file and the output folder are checked before scoring starts."""
    if not [m for m in args.metrics.split(",") if m.strip()]:
        raise UsageError(f"--metrics names no metric, got {args.metrics!r}")
    normalize_metrics([m for m in args.metrics.split(",") if m])
    ds = BopDataset(args.dataset)
    rows = read_results_csv(args.results)
    if not rows:
        raise DatasetError(f"{args.results} holds no results (empty or header only): nothing to score")
    targets = ds.targets()
    objs, scenes = {t.obj_id for t in targets}, {t.scene_id for t in targets}
    bad_objs = sorted({r.obj_id for r in rows} - objs)
    if bad_objs:
        raise DatasetError(f"{args.results}: object id(s) {bad_objs} are not targets of dataset {ds.name} "
                           f"(objects {sorted(objs)}): results of another dataset?")
    bad_scenes = sorted({r.scene_id for r in rows} - scenes)
    if bad_scenes:
        raise DatasetError(f"{args.results}: scene id(s) {bad_scenes} are not in dataset {ds.name} "
                           f"(scenes {sorted(scenes)}): results of another dataset?")
    keys = {(t.scene_id, t.im_id, t.obj_id) for t in targets}
    n_off = sum((r.scene_id, r.im_id, r.obj_id) not in keys for r in rows)
    if n_off == len(rows):
        raise DatasetError(f"{args.results}: none of its {len(rows)} rows is a target (scene, image, object) of "
                           f"dataset {ds.name}: results of another dataset or split?")
    if n_off:
        warnings.warn(f"{args.results}: {n_off} of {len(rows)} rows are not targets of dataset {ds.name}; "
                      "they are ignored")
    if args.n_points is not None and args.n_points < 1:
        raise UsageError(f"--n-points must be at least 1, got {args.n_points}")
    output_dir(args.out, what="output folder")
    return main_eval(args)


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="pixie", description="6D object pose from one RGB photo and an untextured CAD model")
    p.add_argument("-v", "--verbose", action="store_true")
    sub = p.add_subparsers(dest="command", required=True)

    refs = sub.add_parser("refs", help="build or look at reference sets").add_subparsers(dest="refs_cmd", required=True)
    b = refs.add_parser("build", help="render, encode and extract features of the reference views of a mesh")
    b.add_argument("mesh")
    b.add_argument("-o", "--output", required=True, help="output .npz")
    b.add_argument("--views", type=int, help="total views: 6 canonical + Fibonacci (default 121)")
    b.add_argument("--rotations", type=int, help="in-plane rolls per view (default 8)")
    b.add_argument("--size", type=int, help="reference image side in px (default 256)")
    b.add_argument("--units", choices=["mm", "cm", "m", "auto"],
                   help="units of the mesh file (default mm, and a size implausible in mm is an error)")
    b.add_argument("--encodings", help="comma-separated encodings (default shade3_edges,depth,normal)")
    b.add_argument("--matcher", help="features to store (default: config match.matcher; 'none' for none)")
    b.add_argument("--workers", type=int, default=1, help="render processes")
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
    s.set_defaults(func=cmd_refs_show)

    e = sub.add_parser("estimate", help="estimate the pose of the object in one photo")
    e.add_argument("--refs", required=True, help="reference set (.npz) from `pixie refs build`")
    e.add_argument("--image", required=True)
    e.add_argument("--K", required=True, help="intrinsics fx,fy,cx,cy (OpenCV, pixels)")
    e.add_argument("--bbox", help="object box x,y,w,h in pixels, w and h counting pixels (BOP files store one less: "
                   "add 1); default: the mask's box, else the whole image")
    e.add_argument("--mask", help="object mask image (white = object)")
    e.add_argument("-o", "--output", help="result JSON")
    e.add_argument("--overlay", help="PNG with the model drawn at the estimate")
    e.add_argument("--force", action="store_true", help="replace existing output files")
    _add_config_args(e)
    e.set_defaults(func=cmd_estimate)

    r = sub.add_parser("run", help="run the estimator over a BOP dataset (resumable) and score it")
    r.add_argument("dataset", help="BOP dataset folder (with test/, models/, test_targets_bop19.json)")
    r.add_argument("-o", "--output", required=True)
    r.add_argument("--objects", help="comma-separated object ids")
    r.add_argument("--max-targets", type=int)
    r.add_argument("--refs-dir", help="cache of reference sets (default OUT/refs)")
    r.add_argument("--no-report", action="store_true")
    _add_config_args(r)
    r.set_defaults(func=cmd_run)

    ev = sub.add_parser("eval", help="score BOP results (CSV) against a BOP dataset")
    add_eval_arguments(ev)
    ev.set_defaults(func=cmd_eval)
    return p


def _show_warning(message, category, filename, lineno, file=None, line=None) -> None:
    print(f"pixie: warning: {message}", file=sys.stderr)


class _Terminated(BaseException):
    """SIGTERM, turned into an exception so that temporary files are removed and workers stopped."""


def _on_sigterm(signum, frame) -> None:
    raise _Terminated()


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    in_main = threading.current_thread() is threading.main_thread()
    previous = signal.signal(signal.SIGTERM, _on_sigterm) if in_main else None
    try:
        return _main(args)
    except _Terminated:
        print("pixie: terminated", file=sys.stderr)
        return 143
    finally:
        if in_main and previous is not None:
            signal.signal(signal.SIGTERM, previous)


def _main(args: argparse.Namespace) -> int:
    logging.basicConfig(level=logging.INFO if args.verbose else logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    with warnings.catch_warnings():
        warnings.simplefilter("default")
        warnings.showwarning = _show_warning  # one line each, without the source line
        try:
            return int(args.func(args) or 0)
        except PixieError as exc:
            print(f"pixie: error: {exc}", file=sys.stderr)
            return 2
        except KeyboardInterrupt:
            if sys.stderr.isatty():
                sys.stderr.write("\n")  # below a progress bar
            print("pixie: interrupted", file=sys.stderr)
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
