"""Shared fixtures: the LM-O development data, small procedural meshes, poses and cameras.

Fixture names are deliberately specific (``lmo_dir``, ``proc_mesh`` ...) so that test modules
defining their own ``lmo`` / ``synth`` fixtures keep theirs.
"""

from __future__ import annotations

import contextlib
import json
import os
from pathlib import Path

from pixie.threads import configure_env  # standard library only: before numpy, torch and OpenCV load

configure_env(1)  # one thread per test process: `make test` runs one process per core (pytest-xdist)

import cv2  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402
import trimesh  # noqa: E402

from pixie.geometry.camera import make_T, validate_pose  # noqa: E402
from pixie.geometry.mesh import from_arrays  # noqa: E402
from pixie.geometry.render import Renderer, composite  # noqa: E402

from pixie.synth.e2e import facing_pose, procedural_part  # noqa: E402
from pixie.weights import shared_root  # noqa: E402

_SHARED = shared_root() or Path("/nonexistent-shared")  # $PIXIE_SHARED, else ../shared beside the repository
LMO_DIR = _SHARED / "data/lmo_dev/lmo"
WEIGHTS_DIR = _SHARED / "weights"

needs_lmo = pytest.mark.skipif(
    not (LMO_DIR / "models").is_dir(), reason=f"LM-O development data not found at {LMO_DIR}"
)


# ------------------------------------------------------------------------------------------- scheduling

# Seconds each heavy test file took (one thread, 2-core machine, session 9): `make test` runs the files in this
# order, longest first, so that pytest-xdist's whole-file workers (``--dist loadfile``) finish together.
FILE_SECONDS = {"test_pipeline": 240, "test_crash_safety": 125, "test_bad_inputs": 90, "test_estimator": 70,
                "test_batch": 60, "test_cluster": 55, "test_batch_objects": 40, "test_cli": 40, "test_runner": 25,
                "test_edge_align": 25, "test_track": 20, "test_api": 20, "test_render_cmd": 12, "test_detect": 50,
                "test_eval_detections": 20, "test_parts": 20}


def pytest_collection_modifyitems(config, items):
    """Longest test files first (stable: the order inside a file, and of the other files, is kept)."""
    items.sort(key=lambda item: -FILE_SECONDS.get(item.path.stem, 0))


# ------------------------------------------------------------------------------------------- data


@pytest.fixture(scope="session")
def lmo_dir() -> Path:
    """``../shared/data/lmo_dev/lmo``; skips the test when it is absent."""
    if not (LMO_DIR / "models").is_dir():
        pytest.skip(f"LM-O development data not found at {LMO_DIR}")
    return LMO_DIR


@pytest.fixture(scope="session")
def lmo_dataset(lmo_dir):
    from pixie.eval.datasets import BopDataset

    return BopDataset(lmo_dir)


@pytest.fixture(scope="session")
def lmo_meshes(lmo_dir):
    """LM-O models 1, 5 and 8 as pixie meshes (mm), keyed by object id."""
    from pixie.geometry.mesh import load_mesh

    return {o: load_mesh(lmo_dir / "models" / f"obj_{o:06d}.ply") for o in (1, 5, 8)}


def aliked_weights_present() -> bool:
    """ALIKED-N16's weights resolve (they ship in the package, so also without ../shared)."""
    from pixie.errors import WeightsError
    from pixie.weights import resolve_weights

    try:
        resolve_weights("aliked-n16")
    except WeightsError:
        return False
    return True


@pytest.fixture(scope="session")
def matcher_name() -> str:
    """The learned matcher when its weights resolve (shipped in the package), else the weight-free SIFT."""
    return "aliked-nn" if aliked_weights_present() else "sift-nn"


# ------------------------------------------------------------------------------------------ meshes


_procedural_trimesh = procedural_part  # the part lives in pixie.synth.e2e (the bench uses it too)


@pytest.fixture(scope="session")
def proc_trimesh():
    """The procedural part as a ``trimesh.Trimesh`` (mm)."""
    return _procedural_trimesh()


@pytest.fixture(scope="session")
def proc_mesh(proc_trimesh):
    """The procedural part as a pixie :class:`~pixie.geometry.mesh.Mesh` (mm)."""
    from pixie.geometry.mesh import from_arrays

    return from_arrays(np.asarray(proc_trimesh.vertices), np.asarray(proc_trimesh.faces), name="proc")


@pytest.fixture(scope="session")
def sphere_mesh():
    """An icosphere of radius 50 mm (smooth: vertex normals are the true normals)."""
    import trimesh

    from pixie.geometry.mesh import from_arrays

    s = trimesh.creation.icosphere(subdivisions=4, radius=50.0)
    return from_arrays(np.asarray(s.vertices), np.asarray(s.faces), name="sphere")


# ------------------------------------------------------------------------------------ cameras/poses


@pytest.fixture(scope="session")
def K640():
    """A VGA camera, f = 600 px, principal point slightly off-centre."""
    from pixie.geometry.camera import make_K

    return make_K(600.0, 605.0, 321.5, 238.0)


pose_facing = facing_pose  # a random rotation, the mesh centre some diameters in front of the camera (pixie.synth.e2e)


@pytest.fixture(scope="session")
def make_pose():
    """Factory ``make_pose(mesh, seed, distance_factor=4, offset_px=0)`` of camera-facing poses."""

    def _make(mesh, seed: int, distance_factor: float = 4.0, offset_px: float = 0.0, K=None):
        return pose_facing(mesh, np.random.default_rng(seed), distance_factor, offset_px, K)

    return _make


# -------------------------------------------------------------------------------------------- speed


@contextlib.contextmanager
def torch_threads(n: int = 1):
    """Run torch with ``n`` intra-op threads, then restore the previous setting.

    On a small shared machine, torch's default of one thread per core spins against other processes
    (10x slower feature extraction at load ~8 on 2 cores); one thread degrades gracefully.
    """
    import torch

    before = torch.get_num_threads()
    torch.set_num_threads(n)
    try:
        yield
    finally:
        torch.set_num_threads(before)


@pytest.fixture(scope="module")
def one_torch_thread():
    """Module-wide :func:`torch_threads` (request it with ``pytestmark = pytest.mark.usefixtures``)."""
    with torch_threads(1):
        yield


@pytest.fixture(scope="session")
def build_refs():
    """``build_refs(mesh, refs_config, matcher=None, workers=1)``: build_reference_set with one torch thread, and
    the contour templates of the default ``shape.*`` settings built once per mesh and session (shared by every
    set of that mesh, so estimators with shape cues do not each render 300 templates)."""
    from pixie.config import ShapeConfig
    from pixie.references.set import build_reference_set
    from pixie.references.store import ensure_templates

    templates: dict = {}  # contour templates (default shape.* settings) per mesh, built once a session

    def _build(mesh, cfg, matcher=None, workers: int = 1):
        with torch_threads(1):
            refs = build_reference_set(mesh, cfg, matcher=matcher, workers=workers, shape=ShapeConfig(enabled=False))
            key = (mesh.source_hash, len(mesh.vertices), len(mesh.faces))
            if key not in templates:
                ensure_templates(refs, ShapeConfig(), save=False)
                templates[key] = refs.templates
            refs.templates = templates[key]
        return refs

    return _build


@pytest.fixture(scope="session")
def query_e2e(proc_mesh, matcher_name, build_refs, tmp_path_factory):
    """(refs, config, matcher) of the procedural part on the shipped default path (the demo's and the README's
    LM-O path): roll-0 reference features, the query crop rotated (``match.in_plane=query``).

    Built once per test run: under pytest-xdist the first worker to need it saves it into the run's shared
    temporary folder (a file lock in between) and every worker, the builder too, uses the saved set, so results do
    not depend on which worker built it. Without xdist it is built in this process and used as built."""
    from pixie.app.runner import make_matcher
    from pixie.references.store import load_reference_set, save_reference_set
    from pixie.synth.e2e import e2e_config

    cfg = e2e_config(matcher_name)  # the default preset: roll-0 features, the query rotated, no render refinement
    assert cfg.refs.feature_rolls == "first" and cfg.match.in_plane == "query" and cfg.refine.render_iters == 0
    matcher = make_matcher(cfg)
    if not os.environ.get("PYTEST_XDIST_WORKER"):
        return build_refs(proc_mesh, cfg.refs, matcher=matcher), cfg, matcher
    from filelock import FileLock  # torch's own dependency

    path = tmp_path_factory.getbasetemp().parent / f"query_e2e-{matcher_name}.npz"  # this run's, shared by workers
    with FileLock(str(path) + ".lock"):
        if not path.is_file():
            save_reference_set(build_refs(proc_mesh, cfg.refs, matcher=matcher), path)
    return load_reference_set(path), cfg, matcher


# ------------------------------------------------------------------------------ a tiny BOP dataset

SYN_K = np.array([[500.0, 0.0, 160.0], [0.0, 500.0, 120.0], [0.0, 0.0, 1.0]])
SYN_H, SYN_W = 240, 320


def rotvec(axis, deg):
    """Rotation matrix of ``deg`` degrees about ``axis`` (test helper: ``from conftest import rotvec``)."""
    from scipy.spatial.transform import Rotation

    return Rotation.from_rotvec(np.radians(deg) * np.asarray(axis, float) / np.linalg.norm(axis)).as_matrix()


def box_mesh(extents, center=(0.0, 0.0, 0.0)):
    """A box :class:`~pixie.geometry.mesh.Mesh` (test helper: ``from conftest import box_mesh``)."""
    b = trimesh.creation.box(extents=extents)
    b.apply_translation(center)
    return from_arrays(b.vertices, b.faces, name="box")


def build_synthetic_bop(root: Path) -> dict:
    """Write a tiny BOP dataset: obj 1 = box (asymmetric), obj 2 = cylinder (continuous
    symmetry about z). Image 0: one box + one cylinder; image 1: two boxes (inst_count 2).
    Depth is the renderer's z-buffer stored in 0.1 mm units (depth_scale 0.1)."""
    box = trimesh.creation.box(extents=[80.0, 60.0, 40.0])
    cyl = trimesh.creation.cylinder(radius=30.0, height=80.0, sections=64)
    meshes = {1: from_arrays(box.vertices, box.faces), 2: from_arrays(cyl.vertices, cyl.faces)}
    (root / "models").mkdir(parents=True)
    info = {}
    for oid, tm in ((1, box), (2, cyl)):
        tm.export(root / "models" / f"obj_{oid:06d}.ply")
        info[str(oid)] = {"diameter": meshes[oid].diameter}
    info["2"]["symmetries_continuous"] = [{"axis": [0, 0, 1], "offset": [0, 0, 0]}]
    (root / "models" / "models_info.json").write_text(json.dumps(info))
    scenes = {
        0: [(1, make_T(rotvec([1, 1, 0], 30), [-60.0, 0.0, 600.0])), (2, make_T(rotvec([1, 0, 0], 70), [70.0, 10.0, 650.0]))],
        1: [(1, make_T(rotvec([0, 1, 1], 20), [-70.0, 0.0, 620.0])), (1, make_T(rotvec([1, 0, 1], 50), [60.0, 5.0, 560.0]))],
    }
    sc = root / "test" / "000001"
    for sub in ("rgb", "depth"):
        (sc / sub).mkdir(parents=True)
    renderers = {o: Renderer(m) for o, m in meshes.items()}
    gt, cam, gt_info, targets = {}, {}, {}, []
    for im_id, insts in scenes.items():
        renders = [renderers[o].render(T, SYN_K, SYN_H, SYN_W) for o, T in insts]
        depth, owner = composite(renders)
        cv2.imwrite(str(sc / "depth" / f"{im_id:06d}.png"), np.round(depth * 10).astype(np.uint16))
        shade = np.zeros((SYN_H, SYN_W), np.float32)
        for i, r in enumerate(renders):
            shade = np.where(owner == i, 60 + 180 * np.abs(r.normals[..., 2]), shade)
        cv2.imwrite(str(sc / "rgb" / f"{im_id:06d}.png"), np.repeat(shade[..., None], 3, 2).astype(np.uint8))
        gt[str(im_id)] = [
            {"obj_id": o, "cam_R_m2c": T[:3, :3].ravel().tolist(), "cam_t_m2c": T[:3, 3].tolist()} for o, T in insts
        ]
        cam[str(im_id)] = {"cam_K": SYN_K.ravel().tolist(), "depth_scale": 0.1}
        gt_info[str(im_id)] = [
            {"visib_fract": float((owner == i).sum() / max(r.mask.sum(), 1)), "px_count_all": int(r.mask.sum()),
             "bbox_visib": _bop_box(owner == i), "bbox_obj": _bop_box(r.mask)}
            for i, r in enumerate(renders)
        ]
        counts: dict[int, int] = {}
        for o, _ in insts:
            counts[o] = counts.get(o, 0) + 1
        targets += [{"scene_id": 1, "im_id": im_id, "obj_id": o, "inst_count": c} for o, c in counts.items()]
    (sc / "scene_gt.json").write_text(json.dumps(gt))
    (sc / "scene_camera.json").write_text(json.dumps(cam))
    (sc / "scene_gt_info.json").write_text(json.dumps(gt_info))
    (root / "test_targets_bop19.json").write_text(json.dumps(targets))
    (root / "camera.json").write_text(json.dumps({"width": SYN_W, "height": SYN_H}))
    return {"meshes": meshes, "scenes": scenes}




def _bop_box(mask: np.ndarray) -> list[int]:
    """A mask's box as BOP stores it: [x, y, last - first, last - first]; [-1, -1, -1, -1] when empty."""
    ys, xs = np.nonzero(mask)
    if len(xs) == 0:
        return [-1, -1, -1, -1]
    return [int(xs.min()), int(ys.min()), int(xs.max() - xs.min()), int(ys.max() - ys.min())]


@pytest.fixture(scope="session")
def synthetic_bop(tmp_path_factory):
    """``(root, meta)`` of :func:`build_synthetic_bop` (written once per session; do not modify it)."""
    root = tmp_path_factory.mktemp("synthetic_bop") / "bop"
    return root, build_synthetic_bop(root)


def tiny_run_config():
    """SIFT (no weights) on a few small references, for runs over :func:`build_synthetic_bop`: fast (poses for 2 of
    its 4 instances) and deterministic."""
    from pixie.config import PixieConfig

    return PixieConfig().apply_overrides([
        "refs.n_fibonacci=10", "refs.rotations=4", "refs.size=128", "refs.encodings=[shade3_edges]",
        "match.matcher=sift-nn", "refine.render_iters=0",
    ])


# ------------------------------------------------------------------ shared checks (``from conftest import ...``)
TIMING_KEYS = ("extract", "match", "pnp", "total")


def check_result(res):
    assert res.T_cam_from_obj is not None, res.message
    assert np.all(np.isfinite(res.T_cam_from_obj))
    validate_pose(res.T_cam_from_obj)
    for k in TIMING_KEYS:
        assert k in res.timings and res.timings[k] > 0, f"timing {k!r} missing or not positive: {res.timings}"
    assert res.timings["total"] >= res.timings["extract"] + res.timings["match"] + res.timings["pnp"] - 1e-6
    json.dumps(res.to_dict())  # serialisable


# ------------------------------------------------------------------ a tiny part on disk (bad-input / crash tests)
def write_tiny_part(d: Path, proc_trimesh) -> dict:
    """Into folder ``d``: part.ply (the procedural part), photo.png and mask.png (it rendered at 320x240, f = 300),
    refs.npz (a 10-view, 2-roll, 64 px set with SIFT features). Returns their paths, the box [x, y, w, h] and T."""
    from pixie.config import RefsConfig
    from pixie.geometry.camera import make_K
    from pixie.geometry.mesh import load_mesh
    from pixie.matching import get_matcher
    from pixie.references.set import build_reference_set
    from pixie.references.store import save_reference_set

    proc_trimesh.export(d / "part.ply")
    mesh = load_mesh(d / "part.ply")
    T = make_T(cv2.Rodrigues(np.array([0.6, -0.4, 0.3]))[0], np.zeros(3))
    T[:3, 3] = [5.0, -3.0, 500.0] - T[:3, :3] @ mesh.center
    r = Renderer(mesh).render(T, make_K(300, 300, 159.5, 119.5), 240, 320)
    shade = np.where(r.mask, 60 + 180 * np.abs(r.normals[..., 2]), 20).astype(np.uint8)
    cv2.imwrite(str(d / "photo.png"), np.repeat(shade[..., None], 3, axis=2))
    cv2.imwrite(str(d / "mask.png"), r.mask.astype(np.uint8) * 255)
    ys, xs = np.nonzero(r.mask)
    box = [int(xs.min()), int(ys.min()), int(xs.max() - xs.min() + 1), int(ys.max() - ys.min() + 1)]
    cfg = RefsConfig(n_fibonacci=4, rotations=2, size=64, encodings=["shade3_edges"])
    refs = build_reference_set(mesh, cfg, matcher=get_matcher("sift-nn", max_keypoints=128, window=16.0))
    save_reference_set(refs, d / "refs.npz")
    return {"dir": d, "mesh": d / "part.ply", "photo": d / "photo.png", "mask": d / "mask.png",
            "refs": d / "refs.npz", "box": box, "T": T}


# ------------------------------------------------------------------ the command line in this process
def run_cli(*argv) -> tuple[int, str, str]:
    """Run ``pixie ARGV`` in this process; (exit code, stdout, stderr) (``from conftest import run_cli``)."""
    import io
    from contextlib import redirect_stderr, redirect_stdout

    from pixie.app.cli import main

    out, err = io.StringIO(), io.StringIO()
    with redirect_stdout(out), redirect_stderr(err):
        try:
            rc = main([str(a) for a in argv])
        except SystemExit as exc:  # argparse's own usage errors
            rc = exc.code
    return rc, out.getvalue(), err.getvalue()


def assert_cli_error(res: tuple[int, str, str], *needles: str, rc: int = 2) -> str:
    """The command failed with exit ``rc``, no traceback, and ONE ``pixie: error`` line containing every needle."""
    code, out, err = res
    assert "Traceback" not in err + out, err
    assert code == rc, (code, out, err)
    lines = [ln for ln in err.strip().splitlines() if ln.startswith("pixie: error")]
    assert len(lines) == 1, err
    for n in needles:
        assert n.lower() in lines[0].lower(), (n, lines[0])
    return lines[0]
