"""Shared fixtures: the LM-O development data, small procedural meshes, poses and cameras.

Fixture names are deliberately specific (``lmo_dir``, ``proc_mesh`` ...) so that test modules
defining their own ``lmo`` / ``synth`` fixtures keep theirs.
"""

from __future__ import annotations

import contextlib
from pathlib import Path

import numpy as np
import pytest

LMO_DIR = Path(__file__).resolve().parents[1].parent / "shared/data/lmo_dev/lmo"
WEIGHTS_DIR = Path(__file__).resolve().parents[1].parent / "shared/weights"

needs_lmo = pytest.mark.skipif(
    not (LMO_DIR / "models").is_dir(), reason=f"LM-O development data not found at {LMO_DIR}"
)


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
    from pixie.mesh import load_mesh

    return {o: load_mesh(lmo_dir / "models" / f"obj_{o:06d}.ply") for o in (1, 5, 8)}


def aliked_weights_present() -> bool:
    return WEIGHTS_DIR.is_dir() and any(WEIGHTS_DIR.glob("aliked-n16__*"))


@pytest.fixture(scope="session")
def matcher_name() -> str:
    """The learned matcher when its weights are in shared/weights, else the weight-free SIFT."""
    return "aliked-nn" if aliked_weights_present() else "sift-nn"


# ------------------------------------------------------------------------------------------ meshes


def _procedural_trimesh():
    """An asymmetric part, about 80 x 70 x 65 mm: a block with a cylinder, a peg and a notch.

    Boolean operations use manifold3d when installed; otherwise the parts are concatenated
    (interior faces are hidden from outside views, so rendering is the same up to the notch).
    """
    import trimesh

    box = trimesh.creation.box(extents=[80.0, 50.0, 30.0])
    cyl = trimesh.creation.cylinder(radius=12.0, height=40.0, sections=32)
    cyl.apply_translation([20.0, 5.0, 30.0])
    peg = trimesh.creation.box(extents=[10.0, 30.0, 10.0])
    peg.apply_translation([-25.0, 30.0, 0.0])
    notch = trimesh.creation.box(extents=[30.0, 30.0, 40.0])
    notch.apply_translation([-35.0, -20.0, 10.0])
    try:
        m = trimesh.boolean.union([box, cyl, peg], engine="manifold")
        m = trimesh.boolean.difference([m, notch], engine="manifold")
    except Exception:  # noqa: BLE001 - no boolean engine: a concatenation (no notch) is still asymmetric
        m = trimesh.util.concatenate([box, cyl, peg])
    return m


@pytest.fixture(scope="session")
def proc_trimesh():
    """The procedural part as a ``trimesh.Trimesh`` (mm)."""
    return _procedural_trimesh()


@pytest.fixture(scope="session")
def proc_mesh(proc_trimesh):
    """The procedural part as a pixie :class:`~pixie.mesh.Mesh` (mm)."""
    from pixie.mesh import from_arrays

    return from_arrays(np.asarray(proc_trimesh.vertices), np.asarray(proc_trimesh.faces), name="proc")


@pytest.fixture(scope="session")
def sphere_mesh():
    """An icosphere of radius 50 mm (smooth: vertex normals are the true normals)."""
    import trimesh

    from pixie.mesh import from_arrays

    s = trimesh.creation.icosphere(subdivisions=4, radius=50.0)
    return from_arrays(np.asarray(s.vertices), np.asarray(s.faces), name="sphere")


# ------------------------------------------------------------------------------------ cameras/poses


@pytest.fixture(scope="session")
def K640():
    """A VGA camera, f = 600 px, principal point slightly off-centre."""
    from pixie.camera import make_K

    return make_K(600.0, 605.0, 321.5, 238.0)


def random_rotation(rng: np.random.Generator) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    return Rotation.random(random_state=int(rng.integers(1 << 31))).as_matrix()


def pose_facing(mesh, rng: np.random.Generator, distance_factor: float = 4.0, offset_px: float = 0.0,
                K: np.ndarray | None = None) -> np.ndarray:
    """A random rotation with the mesh centre ``distance_factor`` diameters in front of the camera.

    ``offset_px`` shifts the centre sideways by about that many pixels (for f ~ 600).
    """
    from pixie.camera import make_T

    R = random_rotation(rng)
    z = distance_factor * mesh.diameter
    f = 600.0 if K is None else K[0, 0]
    shift = rng.uniform(-1, 1, 2) * offset_px * z / f
    t = np.array([shift[0], shift[1], z]) - R @ mesh.center
    return make_T(R, t)


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
    """``build_refs(mesh, refs_config, matcher=None, workers=1)``: build_reference_set with one torch thread."""
    from pixie.references import build_reference_set

    def _build(mesh, cfg, matcher=None, workers: int = 1):
        with torch_threads(1):
            return build_reference_set(mesh, cfg, matcher=matcher, workers=workers)

    return _build
