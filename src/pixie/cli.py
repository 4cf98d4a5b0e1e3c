"""Command line: ``pixie refs build|show``, ``pixie estimate``, ``pixie run``, ``pixie eval``.

Every command takes ``--config FILE.yaml`` and ``--set section.key=value`` (repeatable) overrides
of :class:`pixie.config.PixieConfig`. Errors pixie raises on purpose print one line and exit 2.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import time
from pathlib import Path

import numpy as np

from pixie.camera import parse_K
from pixie.config import PixieConfig
from pixie.errors import PixieError
from pixie.estimator import PoseEstimator
from pixie.eval import add_eval_arguments, main_eval, run_eval
from pixie.mesh import load_mesh
from pixie.query import load_image
from pixie.references import build_reference_set, check_output_path, load_reference_set, save_reference_set
from pixie.render import Renderer
from pixie.runner import make_matcher, run_dataset
from pixie.viz import contact_sheet, overlay_pose, save_png


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
def cmd_refs_build(args: argparse.Namespace) -> int:
    cfg = _config(args)
    if args.views is not None:
        cfg.refs.n_fibonacci = args.views - (6 if cfg.refs.canonical else 0)
        if cfg.refs.n_fibonacci < 0:
            raise PixieError(f"--views {args.views} is fewer than the 6 canonical views")
    for key in ("rotations", "size"):
        if getattr(args, key) is not None:
            setattr(cfg.refs, key, getattr(args, key))
    if args.encodings:
        cfg.refs.encodings = args.encodings.split(",")
    out = check_output_path(args.output)  # fail before minutes of rendering, not after
    mesh = load_mesh(args.mesh, units=args.units)
    if args.matcher and args.matcher != "none":
        cfg.match.matcher = args.matcher
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
    refs = load_reference_set(args.refs)
    views = None if args.views is None else [int(v) for v in args.views.split(",")]
    sheet = contact_sheet(refs, args.encodings.split(",") if args.encodings else None, views, tile=args.tile)
    save_png(args.output, sheet)
    feats = ", ".join(f"{k} ({len(refs.features_for(*k.split('/', 1))[0])} images)" for k in refs.features) or "none"
    print(f"{args.refs}: {refs.mesh.name}, {refs.n_views} views x {refs.n_rolls} rolls at {refs.size} px; "
          f"features: {feats}; sheet -> {args.output}")
    return 0


# --------------------------------------------------------------------------------------- estimate
def cmd_estimate(args: argparse.Namespace) -> int:
    cfg = _config(args)
    refs = load_reference_set(args.refs)
    image = load_image(args.image)
    K = parse_K(args.K)
    bbox = None if args.bbox is None else [float(v) for v in args.bbox.split(",")]
    mask = None
    if args.mask:
        mask = load_image(args.mask)[..., 0] > 127
    stored = sorted({k.split("/")[0] for k in refs.features})
    if stored and cfg.match.matcher not in stored and not any(o.startswith("match.matcher=") for o in args.set or []):
        cfg.match.matcher = stored[0]  # use the features the set was built with instead of re-extracting
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
    if args.output:
        Path(args.output).parent.mkdir(parents=True, exist_ok=True)
        Path(args.output).write_text(json.dumps(res.to_dict(), indent=1))
        print(f"result -> {args.output}")
    if args.overlay:
        save_png(args.overlay, overlay_pose(image, Renderer(refs.mesh), T, K))
        print(f"overlay -> {args.overlay}")
    return 1 if res.failed else 0


# ------------------------------------------------------------------------------------------- run
def cmd_run(args: argparse.Namespace) -> int:
    cfg = _config(args)
    objects = None if not args.objects else [int(o) for o in args.objects.split(",")]
    t0 = time.perf_counter()
    csv = run_dataset(args.dataset, args.output, cfg, objects=objects, max_targets=args.max_targets,
                      refs_dir=args.refs_dir)
    print(f"results -> {csv} ({time.perf_counter() - t0:.0f} s); scoring")
    run_eval(args.dataset, csv, args.output, report=not args.no_report,
             only_estimated=args.max_targets is not None or args.objects is not None)
    return 0


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
    b.add_argument("--units", default="mm", choices=["mm", "cm", "m", "auto"], help="units of the mesh file")
    b.add_argument("--encodings", help="comma-separated encodings (default shade3_edges,depth,normal)")
    b.add_argument("--matcher", help="features to store (default: config match.matcher; 'none' for none)")
    b.add_argument("--workers", type=int, default=1, help="render processes")
    _add_config_args(b)
    b.set_defaults(func=cmd_refs_build)
    s = refs.add_parser("show", help="contact sheet of a reference set's encodings")
    s.add_argument("refs")
    s.add_argument("-o", "--output", required=True, help="output .png")
    s.add_argument("--encodings")
    s.add_argument("--views", help="comma-separated view indices (default all)")
    s.add_argument("--tile", type=int, default=128)
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
    ev.set_defaults(func=main_eval)
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=logging.INFO if args.verbose else logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    try:
        return int(args.func(args) or 0)
    except PixieError as exc:
        print(f"pixie: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
