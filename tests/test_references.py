"""Reference sets: building (with and without matcher features), exact lifting, save/load, bad files, atomicity."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import textwrap
import time
import zipfile
from pathlib import Path

import numpy as np
import pytest
import trimesh

from pixie.geometry.camera import backproject_depth, invert_T, transform_points
from pixie.config import RefsConfig
from pixie.errors import ReferenceSetError
from pixie.geometry.mesh import from_arrays
from pixie.references.set import add_features, build_reference_set, encoding_images, keypoint_xyz_from_depth
from pixie.references.store import FORMAT_VERSION, load_reference_set, save_reference_set
from pixie.geometry.render import Renderer
from pixie.references.views import roll, square_crop_K

pytestmark = pytest.mark.usefixtures("one_torch_thread")

SMALL = dict(n_fibonacci=10, rotations=2, size=96, encodings=["shade3_edges"])
V, R, S = 16, 2, 96


@pytest.fixture(scope="session")
def small_cfg():
    return RefsConfig(**SMALL)


@pytest.fixture(scope="session")
def refs_plain(proc_mesh, small_cfg):
    return build_reference_set(proc_mesh, small_cfg)


@pytest.fixture(scope="session")
def sift():
    from pixie.matching import get_matcher

    return get_matcher("sift-nn", allow_download=False)


@pytest.fixture(scope="session")
def refs_sift(proc_mesh, small_cfg, sift, build_refs):
    return build_refs(proc_mesh, small_cfg, matcher=sift)


@pytest.fixture(scope="session")
def refs_aliked(proc_mesh, small_cfg, matcher_name, build_refs):
    if matcher_name != "aliked-nn":
        pytest.skip("ALIKED weights not in shared/weights")
    from pixie.matching import get_matcher

    return build_refs(proc_mesh, small_cfg, matcher=get_matcher("aliked-nn", allow_download=False))


@pytest.fixture(scope="session")
def saved_sift(refs_sift, tmp_path_factory):
    return save_reference_set(refs_sift, tmp_path_factory.mktemp("refs") / "proc.npz")


# ------------------------------------------------------------------------------------------- building


def test_structure(refs_plain, proc_mesh):
    refs = refs_plain
    assert (refs.n_views, refs.n_rolls, refs.size) == (V, R, S)
    assert refs.poses.shape == (V, R, 4, 4) and refs.Ks.shape == (V, R, 3, 3)
    assert refs.depth.shape == (V, S, S) and refs.depth.dtype == np.float32
    assert refs.normals.shape == (V, S, S, 3)
    assert refs.canonical.tolist() == [True] * 6 + [False] * 10
    assert refs.encodings["shade3_edges"].shape == (V, S, S)
    assert refs.features == {}
    assert refs.build_seconds > 0
    for i in range(V):
        m = refs.masks[i]
        assert m.sum() > 0.2 * S * S, f"view {i}: object too small"
        # the object fits the crop (pad 1.2): nothing touches the border
        assert not (m[0].any() or m[-1].any() or m[:, 0].any() or m[:, -1].any())
        # roll j is the roll-0 camera rolled by 2*pi*j/R, and K is the object-centred crop of that pose
        np.testing.assert_allclose(refs.poses[i, 1], roll(refs.poses[i, 0], np.pi), atol=1e-12)
        for j in range(R):
            K, _ = square_crop_K(refs.K_start, refs.poses[i, j], proc_mesh.vertices, S, refs.config.crop_pad)
            np.testing.assert_allclose(refs.Ks[i, j], K)


def test_depth_and_normals_are_true_renders(refs_plain, proc_mesh):
    r_ = Renderer(proc_mesh, smooth_normals=refs_plain.config.smooth_normals)
    for i in (0, 5, 11):
        r = r_.render(refs_plain.poses[i, 0], refs_plain.Ks[i, 0], S, S)
        np.testing.assert_array_equal(refs_plain.masks[i], r.mask)
        np.testing.assert_allclose(refs_plain.depth[i], r.depth, atol=1e-4)
        np.testing.assert_allclose(refs_plain.normals[i], r.normals, atol=1e-5)


def test_xyz_is_the_backprojection(refs_plain, proc_mesh):
    refs = refs_plain
    r_ = Renderer(proc_mesh, smooth_normals=refs.config.smooth_normals)
    for i in range(V):
        Xc = backproject_depth(refs.Ks[i, 0], refs.depth[i].astype(np.float64))
        X = transform_points(invert_T(refs.poses[i, 0]), Xc)
        m = refs.masks[i]
        np.testing.assert_allclose(refs.xyz[i][m], X[m], atol=1e-3)
        assert not refs.xyz[i][~m].any()
        if i % 5 == 0:  # and that equals the renderer's own XYZ
            r = r_.render(refs.poses[i, 0], refs.Ks[i, 0], S, S)
            assert np.abs(refs.xyz[i][m] - r.xyz[m]).max() < 1e-3


def test_workers_give_the_same_set(refs_plain, proc_mesh, small_cfg):
    par = build_reference_set(proc_mesh, small_cfg, workers=2)
    np.testing.assert_array_equal(par.poses, refs_plain.poses)
    np.testing.assert_array_equal(par.depth, refs_plain.depth)
    np.testing.assert_array_equal(par.encodings["shade3_edges"], refs_plain.encodings["shade3_edges"])


@pytest.fixture
def render_count(monkeypatch) -> dict[str, int]:
    """Counts the renders of reference builds (the renderer they use counts its calls)."""
    count = {"renders": 0}

    class CountingRenderer(Renderer):
        def render(self, *args, **kwargs):
            count["renders"] += 1
            return super().render(*args, **kwargs)

    monkeypatch.setattr("pixie.references.set.Renderer", CountingRenderer)
    return count


@pytest.mark.parametrize(
    "feature_rolls, store_rotated, renders",
    [("all", False, V), ("first", False, V), ("all", True, V * R), ("first", True, V * R)],
)
def test_build_without_matcher_renders_only_what_it_keeps(proc_mesh, render_count, feature_rolls,
                                                           store_rotated, renders):
    """Without a matcher, rolls 1..R-1 are rendered only when their encodings are stored."""
    cfg = RefsConfig(**SMALL, feature_rolls=feature_rolls, store_rotated_encodings=store_rotated)
    build_reference_set(proc_mesh, cfg)
    assert render_count["renders"] == renders


def test_build_with_matcher_renders_the_rolls_it_extracts(proc_mesh, sift, render_count):
    build_reference_set(proc_mesh, RefsConfig(**SMALL, feature_rolls="first"), matcher=sift)
    assert render_count["renders"] == V
    refs = build_reference_set(proc_mesh, RefsConfig(**SMALL, feature_rolls="all"))
    render_count["renders"] = 0
    add_features(refs, sift)
    assert render_count["renders"] == V * R


def test_build_without_matcher_stores_what_a_full_render_stores(refs_plain, proc_mesh, small_cfg):
    """Rendering roll 0 only changes nothing stored: compare with a build that renders every roll."""
    full = build_reference_set(proc_mesh, RefsConfig(**{**small_cfg.__dict__, "store_rotated_encodings": True}))
    assert full.encodings["shade3_edges"].shape == (V, R, S, S)
    for name in ("poses", "Ks", "K_start", "canonical", "depth", "normals"):
        np.testing.assert_array_equal(getattr(refs_plain, name), getattr(full, name), err_msg=name)
    np.testing.assert_array_equal(refs_plain.encodings["shade3_edges"], full.encodings["shade3_edges"][:, 0])


def test_lifting_is_exact(refs_plain, proc_mesh):
    """keypoint_xyz_from_depth returns the rendered XYZ of the keypoint's nearest pixel."""
    rng = np.random.default_rng(0)
    r_ = Renderer(proc_mesh)
    for i in (1, 7, 13):
        T, K = refs_plain.poses[i, 1], refs_plain.Ks[i, 1]  # a rolled view
        r = r_.render(T, K, S, S)
        v, u = np.nonzero(r.mask)
        kp = np.stack([u, v], 1).astype(np.float64)
        X = keypoint_xyz_from_depth(r.depth, K, T, kp)
        assert np.abs(X - r.xyz[v, u]).max() < 1e-3
        # sub-pixel keypoints take their nearest pixel
        jitter = kp + rng.uniform(-0.49, 0.49, kp.shape)
        np.testing.assert_array_equal(keypoint_xyz_from_depth(r.depth, K, T, jitter), X)
        # background keypoints lift to NaN
        vb, ub = np.nonzero(~r.mask)
        Xb = keypoint_xyz_from_depth(r.depth, K, T, np.stack([ub, vb], 1)[:50].astype(float))
        assert np.isnan(Xb).all()
    assert keypoint_xyz_from_depth(r.depth, K, T, np.zeros((0, 2))).shape == (0, 3)


def _surface_distance(tm: trimesh.Trimesh, pts: np.ndarray) -> np.ndarray:
    """Exact distance of each point to a small mesh (brute force over its triangles, no rtree needed)."""
    tri = tm.triangles
    out = np.empty(len(pts))
    for a in range(0, len(pts), 256):
        p = pts[a : a + 256]
        cp = trimesh.triangles.closest_point(np.tile(tri, (len(p), 1, 1)), np.repeat(p, len(tri), axis=0))
        out[a : a + 256] = np.linalg.norm(cp - np.repeat(p, len(tri), axis=0), axis=1).reshape(len(p), -1).min(1)
    return out


def _check_feature_xyz(refs, matcher_name, proc_trimesh):
    feats, xyz_per_image = refs.features_for(matcher_name, "shade3_edges")
    assert len(feats) == V * R == len(xyz_per_image)
    assert refs.feature_rolls(matcher_name, "shade3_edges") == R
    n = [len(f) for f in feats]
    assert [len(x) for x in xyz_per_image] == n and min(n) > 0
    xyz = np.concatenate(xyz_per_image)
    assert np.isfinite(xyz).all(), "features are extracted inside the mask: no keypoint may lift to NaN"
    # every keypoint's point lies on the mesh surface ...
    dist = _surface_distance(proc_trimesh, xyz.astype(np.float64))
    assert dist.max() < 1e-3, f"keypoint XYZ off the surface by {dist.max():.2e} mm"
    # ... and is the one rendered under it (checked for a rolled view)
    offs = np.concatenate([[0], np.cumsum(n)])
    k = 5 * R + 1
    r = Renderer(refs.mesh).render(refs.poses[5, 1], refs.Ks[5, 1], S, S)
    kp = feats[k].keypoints
    c, rr = np.rint(kp[:, 0]).astype(int), np.rint(kp[:, 1]).astype(int)
    assert np.abs(xyz[offs[k] : offs[k + 1]] - r.xyz[rr, c]).max() < 1e-3
    np.testing.assert_array_equal(xyz_per_image[k], xyz[offs[k] : offs[k + 1]])
    with pytest.raises(ReferenceSetError, match="no superpoint-nn features"):
        refs.features_for("superpoint-nn", "shade3_edges")
    return feats


def test_features_sift(refs_sift, proc_trimesh):
    feats = _check_feature_xyz(refs_sift, "sift-nn", proc_trimesh)
    assert all(f.dim == 128 and f.image_size == (S, S) for f in feats)


def test_features_aliked(refs_aliked, proc_trimesh):
    _check_feature_xyz(refs_aliked, "aliked-nn", proc_trimesh)


def test_add_features_equals_build_with_matcher(refs_plain, refs_sift, sift, proc_mesh, small_cfg):
    late = build_reference_set(proc_mesh, small_cfg)  # a fresh copy: refs_plain is shared
    add_features(late, sift)
    a, b = late.features["sift-nn/shade3_edges"], refs_sift.features["sift-nn/shade3_edges"]
    assert set(a) == set(b)
    for k in a:
        np.testing.assert_array_equal(a[k], b[k], err_msg=k)
    add_features(late, sift)  # idempotent: nothing missing, nothing done
    assert late.features["sift-nn/shade3_edges"]["xyz"] is a["xyz"]


# ------------------------------------------------------------------------------------------ save/load


def test_save_load_roundtrip(refs_sift, saved_sift, proc_mesh):
    assert saved_sift.suffix == ".npz" and saved_sift.is_file()
    assert not [p for p in saved_sift.parent.iterdir() if p.name.endswith(".tmp")], "temp file left behind"
    back = load_reference_set(saved_sift, mesh=proc_mesh)
    np.testing.assert_array_equal(back.poses, refs_sift.poses)
    np.testing.assert_array_equal(back.Ks, refs_sift.Ks)
    np.testing.assert_array_equal(back.K_start, refs_sift.K_start)
    np.testing.assert_array_equal(back.canonical, refs_sift.canonical)
    np.testing.assert_array_equal(back.masks, refs_sift.masks)
    assert np.abs(back.depth - refs_sift.depth).max() < 0.01  # mm, uint16 quantisation
    assert np.abs(back.normals - refs_sift.normals).max() < 0.01
    np.testing.assert_allclose(np.linalg.norm(back.normals[back.masks], axis=-1), 1.0, atol=1e-5)
    assert np.abs(back.xyz - refs_sift.xyz).max() < 0.01
    assert back.config == refs_sift.config
    assert back.mesh.source_hash == proc_mesh.source_hash
    assert back.build_seconds == pytest.approx(refs_sift.build_seconds)
    assert set(back.features) == set(refs_sift.features)
    for key, packed in refs_sift.features.items():
        assert set(back.features[key]) == set(packed)
        for k, v in packed.items():
            np.testing.assert_array_equal(back.features[key][k], v, err_msg=f"{key}/{k}")
    # roll-0 encodings are re-derived from the stored depth and normals
    enc = encoding_images(back, "shade3_edges")
    diff = np.abs(enc.astype(int) - refs_sift.encodings["shade3_edges"].astype(int))
    assert diff.mean() < 0.5 and np.mean(diff > 8) < 0.01


def test_depth_and_normals_are_read_from_the_file_on_first_use(saved_sift, refs_plain, tmp_path):
    """A load leaves depth and normals in the file; saving the loaded set writes them back bit for bit; reading
    them after the file was replaced by another set is an error naming the file, not the other set's arrays."""
    import shutil

    path = tmp_path / "a.npz"
    shutil.copy(saved_sift, path)
    back = load_reference_set(path)
    again = save_reference_set(back, tmp_path / "b.npz")
    with np.load(path) as za, np.load(again) as zb:
        for k in ("depth_q", "depth_lo", "depth_step", "normals_q"):
            np.testing.assert_array_equal(za[k], zb[k], err_msg=k)
    late = load_reference_set(path)
    save_reference_set(refs_plain, path, force=True)  # another set replaces the file
    with pytest.raises(ReferenceSetError, match="changed on disk"):
        late.normals


def test_load_without_mesh_uses_the_stored_one(saved_sift, proc_mesh):
    back = load_reference_set(saved_sift)
    np.testing.assert_allclose(back.mesh.vertices, proc_mesh.vertices)
    np.testing.assert_array_equal(back.mesh.faces, proc_mesh.faces)
    assert back.mesh.source_hash == proc_mesh.source_hash


def test_stored_mesh_caches_equal_what_the_mesh_computes(saved_sift, proc_mesh):
    """The set stores the hull and the renderer's float32 corner normals; both equal a fresh computation, so a
    loaded set renders exactly like the mesh it was built from."""
    back = load_reference_set(saved_sift)
    assert back.mesh._corner_normals is not None and back.mesh._hull_vertices is not None
    np.testing.assert_array_equal(back.mesh.corner_normals(), proc_mesh.corner_normals().astype(np.float32))
    np.testing.assert_array_equal(back.mesh.hull_vertices, proc_mesh.hull_vertices)
    assert back.mesh.diameter == proc_mesh.diameter


def test_save_keeps_the_exact_name_and_creates_folders(refs_plain, tmp_path):
    """The set is written at exactly the path given (issue 17: outputs are never renamed), folders created."""
    p = save_reference_set(refs_plain, tmp_path / "a" / "b" / "plain")
    assert p == tmp_path / "a" / "b" / "plain" and p.is_file()
    assert not (tmp_path / "a" / "b" / "plain.npz").exists()
    assert load_reference_set(p).features == {}


def test_save_aliked_roundtrip(refs_aliked, tmp_path):
    p = save_reference_set(refs_aliked, tmp_path / "aliked.npz")
    back = load_reference_set(p, mesh=refs_aliked.mesh)
    for key, packed in refs_aliked.features.items():
        for k, v in packed.items():
            np.testing.assert_array_equal(back.features[key][k], v)


def _rewrite_npz(src: Path, dst: Path, edit) -> None:
    with np.load(src) as z:
        data = {k: z[k] for k in z.files}
    edit(data)
    with open(dst, "wb") as fh:
        np.savez_compressed(fh, **data)


def test_bad_files_are_reference_set_errors(saved_sift, tmp_path, proc_trimesh):
    raw = saved_sift.read_bytes()
    with pytest.raises(ReferenceSetError, match="not found"):
        load_reference_set(tmp_path / "nope.npz")
    (tmp_path / "trunc.npz").write_bytes(raw[: len(raw) // 2])
    with pytest.raises(ReferenceSetError, match="corrupt"):
        load_reference_set(tmp_path / "trunc.npz")
    (tmp_path / "garbage.npz").write_bytes(np.random.default_rng(0).bytes(5000))
    with pytest.raises(ReferenceSetError):
        load_reference_set(tmp_path / "garbage.npz")
    (tmp_path / "empty.npz").write_bytes(b"")
    with pytest.raises(ReferenceSetError):
        load_reference_set(tmp_path / "empty.npz")

    def bump_version(d):
        meta = json.loads(d["meta"].tobytes().decode())
        meta["format_version"] = FORMAT_VERSION + 1
        d["meta"] = np.frombuffer(json.dumps(meta).encode(), np.uint8)

    _rewrite_npz(saved_sift, tmp_path / "future.npz", bump_version)
    with pytest.raises(ReferenceSetError, match="format version"):
        load_reference_set(tmp_path / "future.npz")
    _rewrite_npz(saved_sift, tmp_path / "nometa.npz", lambda d: d.pop("meta"))
    with pytest.raises(ReferenceSetError, match="metadata"):
        load_reference_set(tmp_path / "nometa.npz")
    _rewrite_npz(saved_sift, tmp_path / "nodepth.npz", lambda d: d.pop("depth_q"))
    with pytest.raises(ReferenceSetError, match="missing"):
        load_reference_set(tmp_path / "nodepth.npz")
    # another mesh: a slightly moved copy of the part
    moved = proc_trimesh.copy()
    moved.apply_translation([0.5, 0.0, 0.0])
    other = from_arrays(moved.vertices, moved.faces, name="proc")
    with pytest.raises(ReferenceSetError, match="another mesh"):
        load_reference_set(saved_sift, mesh=other)


def test_corrupt_payload_is_a_reference_set_error(saved_sift, tmp_path):
    """Bytes flipped inside a compressed member (the zip directory intact)."""
    raw = bytearray(saved_sift.read_bytes())
    with zipfile.ZipFile(saved_sift) as zf:
        info = zf.getinfo("depth_q.npy")
    start = info.header_offset + 30 + len(info.filename) + len(info.extra) + 64
    for k in range(start, start + 256):
        raw[k] ^= 0x5A
    p = tmp_path / "flipped.npz"
    p.write_bytes(bytes(raw))
    with pytest.raises(ReferenceSetError):
        load_reference_set(p)


def test_unwritable_output_is_a_reference_set_error(refs_plain, tmp_path):
    blocker = tmp_path / "file"
    blocker.write_text("not a folder")
    with pytest.raises(ReferenceSetError, match="cannot create output folder"):
        save_reference_set(refs_plain, blocker / "refs.npz")
    if os.geteuid() != 0:  # root writes anywhere
        ro = tmp_path / "ro"
        ro.mkdir()
        ro.chmod(0o555)
        try:
            with pytest.raises(ReferenceSetError, match="not writable"):
                save_reference_set(refs_plain, ro / "refs.npz")
        finally:
            ro.chmod(0o755)


# ----------------------------------------------------------------------------------- atomic writing

_WRITER = textwrap.dedent(
    """
    import sys
    import numpy as np
    from pixie.config import RefsConfig
    from pixie.geometry.mesh import from_arrays
    from pixie.references.set import ReferenceSet
    from pixie.references.store import save_reference_set

    # a big set of incompressible arrays: each save takes seconds
    rng = np.random.default_rng(0)
    V, S = 24, 512
    mesh = from_arrays(np.array([[0, 0, 0], [50, 0, 0], [0, 50, 0], [0, 0, 50]], float),
                       np.array([[0, 1, 2], [0, 1, 3], [0, 2, 3], [1, 2, 3]]), name="big")
    n = rng.normal(size=(V, S, S, 3)).astype(np.float32)
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    refs = ReferenceSet(mesh=mesh, config=RefsConfig(), poses=np.tile(np.eye(4), (V, 1, 1, 1)),
                        Ks=np.tile(np.eye(3), (V, 1, 1, 1)), K_start=np.eye(3), canonical=np.zeros(V, bool),
                        depth=rng.uniform(100, 200, (V, S, S)).astype(np.float32), normals=n)
    print("saving", flush=True)
    while True:
        save_reference_set(refs, sys.argv[1])
    """
)


def _kill_mid_write(target: Path) -> bool:
    """Start a process that saves to ``target`` in a loop; SIGKILL it while its first temp file grows.

    Returns False when, on a busy machine, a whole save slipped through before the kill (the caller
    retries); True when the kill hit the first write.
    """
    env = dict(os.environ, OMP_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1")
    proc = subprocess.Popen([sys.executable, "-c", _WRITER, str(target)], stdout=subprocess.PIPE, env=env)
    try:
        assert proc.stdout.readline().strip() == b"saving"
        mtime0 = target.stat().st_mtime_ns if target.exists() else None
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline:
            tmps = [p for p in target.parent.iterdir() if p.name.endswith(".tmp")]
            if tmps and tmps[0].stat().st_size > 1_000_000:
                break
            time.sleep(0.005)
        else:
            pytest.fail("the writer never started writing")
        proc.send_signal(signal.SIGKILL)
        proc.wait(30)
        assert proc.returncode == -signal.SIGKILL
        return (target.stat().st_mtime_ns if target.exists() else None) == mtime0
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


def _leftovers(folder: Path, target: Path) -> list[Path]:
    """Files other than the target and hidden temp files."""
    return [p for p in folder.iterdir() if p != target and not (p.name.startswith(".") and p.name.endswith(".tmp"))]


def test_killed_save_leaves_no_partial_set(tmp_path):
    for attempt in range(3):
        target = tmp_path / f"new{attempt}" / "refs.npz"
        target.parent.mkdir()
        if _kill_mid_write(target):
            break
    else:
        pytest.fail("could not kill the writer during a write")
    assert not target.exists(), "a killed write left a file at the target path"
    assert _leftovers(target.parent, target) == []
    assert not list(target.parent.glob("*.npz"))
    tmps = list(target.parent.glob(".*.tmp"))
    assert tmps, "the kill should have hit a write in progress"
    with pytest.raises(ReferenceSetError):
        load_reference_set(tmps[0])  # the leftover temp really is partial


def test_killed_save_keeps_the_previous_set(refs_plain, tmp_path):
    target = save_reference_set(refs_plain, tmp_path / "refs.npz")
    before = target.read_bytes()
    for _attempt in range(3):
        if _kill_mid_write(target):
            break
        # a complete save slipped through: the new set is whole; put the old one back and retry
        load_reference_set(target)
        save_reference_set(refs_plain, target)
        before = target.read_bytes()
    else:
        pytest.fail("could not kill the writer during a write")
    assert target.read_bytes() == before
    back = load_reference_set(target, mesh=refs_plain.mesh)
    np.testing.assert_array_equal(back.poses, refs_plain.poses)
    assert _leftovers(tmp_path, target) == []


def test_templates_are_stored_loaded_and_an_old_set_upgraded_once(proc_mesh, tmp_path, caplog):
    """The set owns its contour templates: built with it, saved, loaded; a set without them (an older file) gets
    them once, saved back atomically, with one INFO message, and the next load needs no rebuild."""
    import logging

    from pixie.config import ShapeConfig
    from pixie.references.store import TEMPLATES_VERSION, ensure_templates, templates_fit

    shape = ShapeConfig(views=12, size=32, points=16)
    cfg = RefsConfig(n_fibonacci=4, rotations=1, size=32, encodings=["depth"])
    refs = build_reference_set(proc_mesh, cfg, shape=shape)
    assert templates_fit(refs, shape) and not templates_fit(refs, ShapeConfig())
    loaded = load_reference_set(save_reference_set(refs, tmp_path / "new.npz"))
    assert json.loads(np.load(tmp_path / "new.npz")["meta"].tobytes())["templates_version"] == TEMPLATES_VERSION
    assert templates_fit(loaded, shape) and not ensure_templates(loaded, shape)
    assert build_reference_set(proc_mesh, cfg).templates is None  # a RefsConfig alone: no shape cues asked for
    refs.templates = None
    old = tmp_path / "old.npz"
    save_reference_set(refs, old)
    before = load_reference_set(old)
    assert before.templates is None
    with caplog.at_level(logging.INFO, logger="pixie.references.store"):
        assert ensure_templates(before, shape)
    assert "upgraded once" in caplog.text
    again = load_reference_set(old)
    assert templates_fit(again, shape) and not ensure_templates(again, shape)
    for k, v in loaded.templates.items():
        if k != "build_seconds":  # the same templates, built again
            np.testing.assert_array_equal(again.templates[k], v)
    np.testing.assert_array_equal(again.depth, loaded.depth)  # depth and normals saved back bit for bit
    np.testing.assert_array_equal(again.normals, loaded.normals)
