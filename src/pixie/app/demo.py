"""``make demo``: build references for one object and estimate its pose in a photo, end to end.

With the LM-O dev data beside the repository (``../shared/data/lmo_dev``, or ``$PIXIE_SHARED/data/lmo_dev``) the photo is a real LM-O
image (by default image 17, the watering can: one the current pipeline gets right; on most LM-O
targets it does not yet, see bench/RESULTS.md, and ``--im-id`` shows others); otherwise a photo of a generated part is rendered (random colours, background clutter), so a
fresh clone (or an installed wheel, offline) always has something to run. Prints the pose, its error against
ground truth, and writes an overlay and a reference contact sheet under ``out/demo/`` (``./pixie-demo`` outside a
source checkout); the generated part's inputs (``part.stl``, ``photo.png``, ``K.txt``, ``bbox.txt``) go there too,
ready for ``pixie estimate``.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import cv2
import numpy as np

from pixie.geometry.camera import look_at, make_K, rotation_angle_deg
from pixie.config import PixieConfig
from pixie.references.encode import shade
from pixie.pipeline.estimator import PoseEstimator
from pixie.eval.datasets import BopDataset
from pixie.eval.pose_error import add
from pixie.geometry.mesh import Mesh, from_arrays, load_mesh
from pixie.pipeline.query import bbox_from_mask
from pixie.geometry.render import Renderer
from pixie.app.runner import cached_reference_set, reference_cache_path
from pixie.paths import not_an_input
from pixie.viz import contact_sheet, overlay_pose, save_png
from pixie.threads import default_threads, set_threads
from pixie.weights import cache_dir, repo_root, shared_root

REPO = Path(__file__).resolve().parents[3]


def lmo_dir() -> Path | None:
    """LM-O dev data in the shared folder (``$PIXIE_SHARED`` or ``<repo>/../shared``), if present."""
    root = shared_root()
    d = None if root is None else root / "data" / "lmo_dev" / "lmo"
    return d if d is not None and d.is_dir() else None


def default_out() -> Path:
    """``out/demo`` in a source checkout, else ``./pixie-demo``."""
    root = repo_root()
    return root / "out" / "demo" if root is not None else Path.cwd() / "pixie-demo"


def generated_part() -> Mesh:
    """An asymmetric bracket-like part (mm) built from boxes and a cylinder."""
    import trimesh

    parts = [
        trimesh.creation.box((120, 80, 20)),
        trimesh.creation.box((20, 80, 70), transform=trimesh.transformations.translation_matrix((50, 0, 35))),
        trimesh.creation.cylinder(radius=14, height=50, sections=48,
                                  transform=trimesh.transformations.translation_matrix((-30, 15, 30))),
        trimesh.creation.box((40, 16, 16), transform=trimesh.transformations.translation_matrix((-20, -30, 18))),
    ]
    m = trimesh.util.concatenate(parts)
    return from_arrays(m.vertices, m.faces, name="demo_bracket")


def generated_photo(mesh: Mesh, seed: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A 640x480 'photo' of ``mesh``: shaded, random face colours, noisy cluttered background."""
    rng = np.random.default_rng(seed)
    K = make_K(600.0, 600.0, 319.5, 239.5)
    T = look_at(mesh.center + np.array([260.0, -380.0, 300.0]), mesh.center, np.array([0.0, 0.0, 1.0]))
    T[:3, 3] += np.array([30.0, -10.0, 0.0])
    r = Renderer(mesh).render(T, K, 480, 640)
    bg = cv2.GaussianBlur(rng.uniform(0, 255, (480, 640, 3)).astype(np.float32), (0, 0), 6)
    bg = (bg - bg.min()) / (np.ptp(bg) + 1e-6) * 200 + 20
    colours = rng.uniform(60, 255, (len(mesh.faces), 3))
    s = shade(r.normals, r.mask, 3).astype(np.float32) / 255.0
    img = bg.copy()
    img[r.mask] = colours[r.tri_ids[r.mask]] * s[r.mask, None]
    img = np.clip(img + rng.normal(0, 4, img.shape), 0, 255).astype(np.uint8)
    return img, K, T


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="pixie demo", description=__doc__)
    ap.add_argument("--out", default=None, help="output folder (default out/demo in a checkout, else ./pixie-demo)")
    ap.add_argument("--synthetic", action="store_true", help="use a generated part even if LM-O is present")
    ap.add_argument("--im-id", type=int, default=17)
    ap.add_argument("--obj-id", type=int, default=5)
    ap.add_argument("--preset", default="default", help="configuration preset (fast, default, paper)")
    ap.add_argument("--device", choices=["auto", "cpu", "cuda"], help="where the matcher runs (default: the preset's, auto)")
    ap.add_argument("--threads", type=int, default=None, help=f"torch/OpenCV/BLAS threads (default {default_threads()} "
                    "here: half the CPUs, 1..4)")
    args = ap.parse_args(argv)
    if args.threads is not None and args.threads < 1:
        ap.error(f"--threads must be at least 1, got {args.threads}")
    set_threads(args.threads or default_threads())
    out = Path(args.out) if args.out else default_out()
    cfg = PixieConfig.from_preset(args.preset)
    if args.device:
        cfg.match.device = args.device
    lmo = lmo_dir()

    if lmo is not None and not args.synthetic:
        # the demo writes overlay.png, references.png and refs/ into --out: never into (a folder of) the dataset
        not_an_input([out], [lmo, Path(lmo) / "models", Path(lmo) / "test"])
        ds = BopDataset(lmo)
        mesh = load_mesh(ds.model_path(args.obj_id))
        image, K = ds.load_rgb(2, args.im_id), ds.camera(2, args.im_id).K
        inst = next(g for g in ds.instances(2, args.im_id) if g.obj_id == args.obj_id)
        T_gt, bbox = inst.T_cam_from_obj, inst.box_visib
        source = f"LM-O scene 2 image {args.im_id}, object {args.obj_id} (real photo, BOP GT box as crop)"
    else:
        mesh = generated_part()
        image, K, T_gt = generated_photo(mesh)
        bbox = bbox_from_mask(Renderer(mesh).render(T_gt, K, *image.shape[:2]).mask)
        source = ("generated part, rendered photo" + ("" if args.synthetic else " (LM-O data not found beside the repository)"))
        _write_inputs(out, mesh, image, K, bbox)
        mesh = load_mesh(out / "part.stl", units="mm")  # the written file: `estimate --mesh part.stl` finds its set
    print(f"pixie demo: {source}")
    print(f"mesh {mesh.name}: {len(mesh.faces)} triangles, diameter {mesh.diameter:.1f} mm")

    t0 = time.perf_counter()
    cache = cache_dir().parent / "refs"  # the cache `pixie estimate --mesh` and estimate_pose use: built once for all
    refs = cached_reference_set(mesh, cfg, cache, progress=_progress)
    refs_path = reference_cache_path(mesh, cfg, cache)
    print(f"reference set: {refs.n_views} views x {refs.n_rolls} rolls at {refs.size} px "
          f"({time.perf_counter() - t0:.1f} s) -> {refs_path}")
    save_png(out / "references.png", contact_sheet(refs, views=list(range(0, refs.n_views, 4)), tile=96))

    est = PoseEstimator(refs, cfg)
    res = est.estimate(image, K, bbox=bbox)
    T = res.T_cam_from_obj
    np.set_printoptions(precision=3, suppress=True)
    print(f"estimate: {'FAILED: ' + res.message if res.failed else 'ok'}; {res.n_inliers} PnP inliers, "
          f"score {res.score:.1f}, confidence {res.confidence:.2f}")
    print("timings (s): " + ", ".join(f"{k} {v:.2f}" for k, v in res.timings.items()))
    if T is not None:
        print("T_cam_from_obj =\n" + str(T))
        e_add = add(T, T_gt, mesh.vertices)
        print(f"error vs ground truth: rotation {rotation_angle_deg(T[:3, :3], T_gt[:3, :3]):.1f} deg, "
              f"translation {np.linalg.norm(T[:3, 3] - T_gt[:3, 3]):.1f} mm, ADD {e_add:.1f} mm "
              f"({e_add / mesh.diameter:.2f} of the diameter; correct if < 0.10)")
    path = save_png(out / "overlay.png", overlay_pose(image, Renderer(mesh), T, K, T_gt=T_gt))
    print(f"overlay (red: estimate, green: ground truth) -> {path}")
    print(f"reference contact sheet -> {out / 'references.png'}")
    if (out / "K.txt").is_file() and (out / "bbox.txt").is_file():  # the generated part's inputs: try it yourself
        print(f"try (the references above are reused, not rebuilt; --mesh {out}/part.stl finds them too):\n"
              f"  pixie estimate --refs {refs_path} --image {out}/photo.png --K $(cat {out}/K.txt) "
              f"--bbox $(cat {out}/bbox.txt) -o {out}/result.json --overlay {out}/estimate.png")
    return 0


def _write_inputs(out: Path, mesh: Mesh, image: np.ndarray, K: np.ndarray, bbox: np.ndarray) -> None:
    """The generated part's inputs as files, for trying ``pixie estimate`` on them."""
    import trimesh

    out.mkdir(parents=True, exist_ok=True)
    trimesh.Trimesh(mesh.vertices, mesh.faces, process=False).export(out / "part.stl")
    save_png(out / "photo.png", image)
    (out / "K.txt").write_text(f"{K[0, 0]:.6g},{K[1, 1]:.6g},{K[0, 2]:.6g},{K[1, 2]:.6g}\n")
    (out / "bbox.txt").write_text(",".join(f"{v:.0f}" for v in bbox) + "\n")
    print(f"inputs -> {out}/part.stl, photo.png, K.txt, bbox.txt")


def _progress(done: int, total: int) -> None:
    if done == total or done % 10 == 0:
        print(f"  rendering references: {done}/{total} views", flush=True)


if __name__ == "__main__":
    sys.exit(main())
