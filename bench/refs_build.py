"""Reference-set build cost on the LM-O models: render + encode time and file size per object.

For every model in ``<dataset>/models`` a full reference set is built and saved to a temporary folder to
measure the file size. The bar is <= 30 s per object.

With ``--preset NAME`` (e.g. ``default``) the set is built exactly as ``pixie refs build MESH --preset NAME``
does: the preset's refs config and its matcher's features. Without it: the RefsConfig() defaults (or the
flags below) and NO matcher features (render + encode cost only).

Usage::

    nice .venv/bin/python bench/refs_build.py --preset default [--threads 2] [--objects 1,5,8]
    nice .venv/bin/python bench/refs_build.py [--objects 1,5,8] [--size 512] [--workers 2]
                                              [--out out/bench/refs_build.json] [--profile]

``--profile`` runs cProfile on the first object and prints where the time goes.
"""

from __future__ import annotations

import argparse
import cProfile
import io
import json
import os
import platform
import pstats
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "src"))

from pixie.config import PixieConfig, RefsConfig, preset_names  # noqa: E402
from pixie.geometry.mesh import load_mesh  # noqa: E402
from pixie.references.set import build_reference_set
from pixie.references.store import save_reference_set  # noqa: E402

DEFAULT_DATASET = REPO.parent / "shared/data/lmo_dev/lmo"
BAR_S = 30.0


def _objects(models: Path, wanted: str | None) -> list[tuple[int, Path]]:
    found = sorted((int(p.stem.split("_")[-1]), p) for p in models.glob("obj_*.ply"))
    if wanted:
        ids = {int(x) for x in wanted.split(",") if x.strip()}
        missing = ids - {o for o, _ in found}
        if missing:
            raise SystemExit(f"objects not in {models}: {sorted(missing)}")
        found = [(o, p) for o, p in found if o in ids]
    return found


def _profile(mesh, cfg: RefsConfig, workers: int, top: int = 25) -> str:
    prof = cProfile.Profile()
    prof.enable()
    build_reference_set(mesh, cfg, workers=workers)
    prof.disable()
    buf = io.StringIO()
    st = pstats.Stats(prof, stream=buf)
    st.sort_stats("tottime").print_stats(top)
    return buf.getvalue()


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--dataset", type=Path, default=DEFAULT_DATASET)
    ap.add_argument("--preset", choices=preset_names(), help="build as `pixie refs build --preset NAME` (with features)")
    ap.add_argument("--threads", type=int, default=None, help="torch/OpenCV threads (default: torch's)")
    ap.add_argument("--keep", type=Path, help="with --preset: keep the sets in this folder under the names `pixie run` "
                    "caches them by (its --refs-dir), instead of deleting them")
    ap.add_argument("--objects", default=None, help="comma-separated object ids (default: every model)")
    ap.add_argument("--size", type=int, default=RefsConfig().size, help="reference image side, px")
    ap.add_argument("--workers", type=int, default=1, help="render/encode processes")
    ap.add_argument("--n-fibonacci", type=int, default=RefsConfig().n_fibonacci)
    ap.add_argument("--rotations", type=int, default=RefsConfig().rotations)
    ap.add_argument("--feature-rolls", choices=["all", "first"], default=RefsConfig().feature_rolls,
                    help="refs.feature_rolls; without a matcher 'first' skips rendering rolls 1.. (same saved set)")
    ap.add_argument("--out", type=Path, default=REPO / "out/bench/refs_build.json")
    ap.add_argument("--profile", action="store_true", help="cProfile the first object (single process)")
    args = ap.parse_args(argv)

    models = args.dataset / "models"
    if not models.is_dir():
        print(f"models folder not found: {models}", file=sys.stderr)
        return 2
    matcher = None
    if args.threads:
        from pixie.threads import set_threads

        set_threads(args.threads)
    if args.preset:
        from pixie.app.runner import make_matcher

        full = PixieConfig.from_preset(args.preset)
        cfg = full.refs
        matcher = make_matcher(full)
    else:
        cfg = RefsConfig(size=args.size, n_fibonacci=args.n_fibonacci, rotations=args.rotations,
                         feature_rolls=args.feature_rolls)
    n_views = cfg.n_fibonacci + (6 if cfg.canonical else 0)
    rows = []
    header = f"{'obj':>4} {'faces':>7} {'views x rolls':>13} {'size':>5} {'workers':>7} {'build s':>8} " \
             f"{'ms/image':>8} {'save s':>7} {'file MB':>8} {'<=30s':>5}"
    print(f"reference sets: {n_views} views x {cfg.rotations} rolls, size {cfg.size}, encodings {cfg.encodings}, "
          f"features: {matcher.name if matcher else 'none'} (preset {args.preset}); feature_rolls {cfg.feature_rolls}; "
          f"workers {args.workers}; {os.cpu_count()} CPUs; threads {args.threads or 'default'}; "
          f"OPENBLAS_NUM_THREADS={os.environ.get('OPENBLAS_NUM_THREADS', 'unset')}")
    print(header)
    print("-" * len(header))
    profile_text = None
    with tempfile.TemporaryDirectory(prefix="pixie-refs-bench-") as tmp:
        for obj_id, path in _objects(models, args.objects):
            mesh = load_mesh(path)
            if args.profile and profile_text is None:
                profile_text = _profile(mesh, cfg, workers=1)
            t0 = time.perf_counter()
            c0 = time.process_time()
            refs = build_reference_set(mesh, cfg, matcher=matcher, workers=args.workers)
            build_s = time.perf_counter() - t0
            cpu_main = time.process_time() - c0
            t1 = time.perf_counter()
            if args.keep and args.preset:
                from pixie.app.runner import reference_cache_path

                out = save_reference_set(refs, reference_cache_path(mesh, full, args.keep))
            else:
                out = save_reference_set(refs, Path(tmp) / f"obj_{obj_id:06d}.npz")
            save_s = time.perf_counter() - t1
            size_mb = out.stat().st_size / 1e6
            if not args.keep:
                out.unlink()
            n_img = refs.n_views * refs.n_rolls
            row = {
                "obj_id": obj_id, "faces": int(len(mesh.faces)), "views": refs.n_views, "rolls": refs.n_rolls,
                "size": cfg.size, "encodings": list(cfg.encodings), "workers": args.workers,
                "build_s": round(build_s, 3), "ms_per_image": round(1000 * build_s / n_img, 2),
                "main_process_cpu_s": round(cpu_main, 3), "save_s": round(save_s, 3),
                "file_mb": round(size_mb, 2), "meets_bar": build_s <= BAR_S,
            }
            rows.append(row)
            print(f"{obj_id:>4} {row['faces']:>7} {refs.n_views:>6} x {refs.n_rolls:<4} {cfg.size:>5} {args.workers:>7} "
                  f"{build_s:>8.1f} {row['ms_per_image']:>8.1f} {save_s:>7.1f} {size_mb:>8.1f} "
                  f"{'yes' if row['meets_bar'] else 'NO':>5}", flush=True)
    if rows:
        mean = sum(r["build_s"] for r in rows) / len(rows)
        print("-" * len(header))
        print(f"mean build {mean:.1f} s/object (bar {BAR_S:.0f} s); mean file {sum(r['file_mb'] for r in rows) / len(rows):.1f} MB")
    if profile_text:
        print("\ncProfile of the first object (workers=1), by own time:\n" + profile_text)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    report = {
        "config": {"n_views": n_views, "rotations": cfg.rotations, "size": cfg.size, "encodings": cfg.encodings,
                   "feature_rolls": cfg.feature_rolls, "workers": args.workers,
                   "matcher": matcher.name if matcher else None, "preset": args.preset, "threads": args.threads,
                   "OPENBLAS_NUM_THREADS": os.environ.get("OPENBLAS_NUM_THREADS")},
        "machine": {"cpus": os.cpu_count(), "python": platform.python_version(),
                    "loadavg_at_end": os.getloadavg() if hasattr(os, "getloadavg") else None},
        "bar_s": BAR_S, "rows": rows, "profile": profile_text,
    }
    args.out.write_text(json.dumps(report, indent=2))
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
