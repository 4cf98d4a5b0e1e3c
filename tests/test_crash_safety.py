"""Reliability, third round: nothing written is lost, nothing hangs, no result misleads.

* outputs never replace an input (also through a link), and a set another process wrote meanwhile is not
  overwritten without ``--force``;
* temporary files of a killed write and lock files of a killed builder are cleaned up or taken over;
* a target without an estimate counts as a miss, in ``pixie eval``, ``pixie run`` and the API;
* the command line and the API refuse or flag what cannot be right, with one message naming it.

Everything runs the real command line (in this process, or as a ``pixie`` subprocess for kills) on tiny inputs:
a 10-view, 2-roll, 64 px set of the procedural part, and the synthetic BOP dataset of ``conftest.py``.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from conftest import assert_cli_error, run_cli, write_tiny_part

SRC = Path(__file__).resolve().parents[1] / "src"
K_TEXT = "300,300,159.5,119.5"
FAST = ["--set", "refine.render_iters=0", "--set", "match.matcher=sift-nn", "--set", "match.max_keypoints=128"]
SMALL = ["--views", "8", "--rotations", "1", "--size", "32", "--matcher", "none", "--set", "refs.encodings=[depth]"]
TINY_RUN = ["--no-report", "--set", "refs.n_fibonacci=4", "--set", "refs.rotations=2", "--set", "refs.size=64",
            "--set", "refs.encodings=[shade3_edges]", "--set", "shape.views=20", "--set", "align.enabled=false", *FAST]
DEAD_PID = 2 ** 22 + 12345  # above Linux's pid_max: never a running process


@pytest.fixture(scope="module")
def part(tmp_path_factory, proc_trimesh):
    """part.ply, photo.png (the part rendered at 320x240), its box and a tiny refs.npz (conftest.write_tiny_part)."""
    return write_tiny_part(tmp_path_factory.mktemp("crash_safety"), proc_trimesh)


@pytest.fixture()
def bop(synthetic_bop, tmp_path):
    """A private copy of the synthetic BOP dataset (tests may break it)."""
    root = tmp_path / "bop"
    shutil.copytree(synthetic_bop[0], root)
    return root


def _box(b) -> str:
    return ",".join(str(v) for v in b)


def _temps(folder: Path) -> list[Path]:
    return [p for p in Path(folder).rglob(".*.tmp")]


# ------------------------------------------------------------------------------------ outputs vs inputs


def test_refs_build_refuses_its_mesh_as_output_even_with_force(part, tmp_path):
    mesh = tmp_path / "part.stl"
    shutil.copy(part["mesh"], mesh)
    before = mesh.read_bytes()
    assert_cli_error(run_cli("refs", "build", mesh, "-o", mesh, "--force", *SMALL), "also an input", "part.stl")
    os.link(mesh, tmp_path / "alias.npz")  # the same file under another name
    assert_cli_error(run_cli("refs", "build", mesh, "-o", tmp_path / "alias.npz", "--force", *SMALL), "also an input")
    assert mesh.read_bytes() == before


def test_refs_show_refuses_its_set_as_output(part, tmp_path):
    refs = tmp_path / "set.npz"
    shutil.copy(part["refs"], refs)
    before = refs.read_bytes()
    assert_cli_error(run_cli("refs", "show", refs, "-o", refs, "--force"), "also an input", "set.npz")
    assert refs.read_bytes() == before


def test_eval_and_run_refuse_outputs_over_their_inputs(bop, tmp_path):
    out = tmp_path / "ev"
    out.mkdir()
    csv = out / "per_target.csv"  # eval writes per_target.csv into its folder
    csv.write_text("scene_id,im_id,obj_id,score,R,t,time\n1,0,1,0.5,1 0 0 0 1 0 0 0 1,0 0 600,1.0\n")
    before = csv.read_bytes()
    assert_cli_error(run_cli("eval", bop, "--results", csv, "-o", out, "--no-report"), "also an input")
    assert csv.read_bytes() == before
    assert_cli_error(run_cli("run", bop, "-o", bop, *TINY_RUN), "also an input", "bop")
    assert not (bop / "results.csv").exists()


def test_batch_refuses_to_write_over_its_manifest(part, tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    manifest = out / "results.csv"  # the batch writes results.csv into its output folder
    manifest.write_text(f'image,K,bbox\n{part["photo"]},"{K_TEXT}","{_box(part["box"])}"\n')
    before = manifest.read_bytes()
    assert_cli_error(run_cli("estimate", "--refs", part["refs"], "--batch", manifest, "-o", out, *FAST),
                     "also an input", "results.csv")
    assert manifest.read_bytes() == before


def test_a_set_written_meanwhile_is_not_overwritten_without_force(part, tmp_path, monkeypatch):
    """Two `refs build -o same.npz` at once: the one that finishes second refuses (exit 2), the first one's set
    stays whole; with --force the last writer wins and the file is a complete set."""
    import pixie.app.cli as cli_mod
    from pixie.references.store import load_reference_set

    target = tmp_path / "same.npz"
    real_build = cli_mod.build_reference_set

    def build_while_another_finishes(*a, **k):
        refs = real_build(*a, **k)
        shutil.copy(part["refs"], target)  # the other process's complete set lands first
        return refs

    monkeypatch.setattr(cli_mod, "build_reference_set", build_while_another_finishes)
    msg = assert_cli_error(run_cli("refs", "build", part["mesh"], "-o", target, *SMALL), "exists", "--force")
    assert "same.npz" in msg
    assert target.read_bytes() == part["refs"].read_bytes() and not _temps(tmp_path)
    rc, out, err = run_cli("refs", "build", part["mesh"], "-o", target, "--force", *SMALL)
    assert rc == 0 and "wrote" in out, err
    assert load_reference_set(target).size == 32 and not _temps(tmp_path)  # this build's set, whole


def test_write_atomic_without_force_refuses_a_file_that_appeared(tmp_path):
    from pixie.errors import OutputError
    from pixie.paths import write_atomic

    target = tmp_path / "x.bin"

    def write(fh):
        fh.write(b"mine")
        target.write_bytes(b"theirs")  # another process, between our check and our rename

    with pytest.raises(OutputError, match="another process"):
        write_atomic(target, write, force=False)
    assert target.read_bytes() == b"theirs" and not _temps(tmp_path)
    write_atomic(target, b"mine")  # force (the default): replaced
    assert target.read_bytes() == b"mine"


def _spawn_python(code: str) -> subprocess.Popen:
    env = dict(os.environ, PYTHONPATH=str(SRC), PYTHONUNBUFFERED="1", OMP_NUM_THREADS="1")
    return subprocess.Popen([sys.executable, "-c", code], env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True, start_new_session=True)


def test_sigkill_during_a_save_leaves_a_temp_that_the_next_load_removes(part, tmp_path):
    """SIGKILL runs no clean-up: the hidden temporary file stays, named .<name>.<pid>.<random>.tmp, until the
    next save, load or run in that folder sees that its process is gone and removes it."""
    from pixie.paths import write_atomic
    from pixie.references.store import load_reference_set

    shutil.copy(part["refs"], tmp_path / "refs.npz")
    code = ("import sys, time\nfrom pixie.paths import write_atomic\n"
            f"def w(fh):\n    fh.write(b'x' * 1000)\n    print('writing', flush=True)\n    time.sleep(60)\n"
            f"write_atomic({str(tmp_path / 'new.npz')!r}, w)\n")
    proc = _spawn_python(code)
    try:
        assert proc.stdout.readline().strip() == "writing", proc.stderr.read()
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait(timeout=10)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
    left = _temps(tmp_path)
    assert len(left) == 1 and f".new.npz.{proc.pid}." in left[0].name and not (tmp_path / "new.npz").exists()
    live = tmp_path / f".other.npz.{os.getpid()}.abc.tmp"  # a live writer's temporary file is kept
    live.write_bytes(b"busy")
    load_reference_set(tmp_path / "refs.npz")
    assert _temps(tmp_path) == [live]
    (tmp_path / f".x.{DEAD_PID}.q1.tmp").write_bytes(b"")
    write_atomic(tmp_path / "y.txt", "y")  # a save removes them too
    assert _temps(tmp_path) == [live]


# ------------------------------------------------------------------------------------------------ locks


def _tiny_cfg():
    from pixie.config import PixieConfig

    cfg = PixieConfig()
    for item in ("refs.n_fibonacci=0", "refs.rotations=1", "refs.size=32", "refs.encodings=[depth]",
                 "shape.enabled=false", "match.matcher=sift-nn"):
        cfg.set(*item.split("="))
    return cfg


def test_a_lock_whose_builder_is_gone_is_taken_over(part, tmp_path):
    from pixie.app.runner import cached_reference_set, reference_cache_path
    from pixie.geometry.mesh import load_mesh

    mesh, cfg = load_mesh(part["mesh"]), _tiny_cfg()
    lock = reference_cache_path(mesh, cfg, tmp_path).with_suffix(".lock")
    lock.write_text(json.dumps({"pid": DEAD_PID, "host": socket.gethostname(), "time": 0}))
    said: list[str] = []
    t0 = time.perf_counter()
    refs = cached_reference_set(mesh, cfg, tmp_path, echo=said.append, max_wait_s=30)
    assert refs.n_views == 6 and time.perf_counter() - t0 < 20
    assert any("taking over" in s and str(DEAD_PID) in s for s in said), said
    assert not lock.exists() and not _temps(tmp_path)
    # the empty lock of an older pixie, older than a few seconds: taken over too
    reference_cache_path(mesh, cfg, tmp_path).unlink()
    lock.write_text("")
    os.utime(lock, (time.time() - 600, time.time() - 600))
    cached_reference_set(mesh, cfg, tmp_path, echo=said.append, max_wait_s=30)
    assert not lock.exists()


def test_waiting_on_a_live_lock_is_announced_and_bounded(part, tmp_path):
    from pixie.app.runner import cached_reference_set, reference_cache_path
    from pixie.errors import ReferenceSetError
    from pixie.geometry.mesh import load_mesh

    mesh, cfg = load_mesh(part["mesh"]), _tiny_cfg()
    lock = reference_cache_path(mesh, cfg, tmp_path).with_suffix(".lock")
    lock.write_text(json.dumps({"pid": os.getpid(), "host": socket.gethostname(), "time": time.time()}))
    said: list[str] = []
    with pytest.raises(ReferenceSetError, match=f"pid {os.getpid()}.*delete"):
        cached_reference_set(mesh, cfg, tmp_path, echo=said.append, poll_s=0.05, max_wait_s=0.3)
    assert len(said) == 1 and "waiting for" in said[0] and str(os.getpid()) in said[0]
    assert lock.exists()  # not ours: left alone


def test_run_after_a_killed_build_does_not_hang_on_its_lock(bop, tmp_path):
    from pixie.app.runner import reference_cache_path
    from pixie.config import PixieConfig
    from pixie.geometry.mesh import load_mesh

    refs_dir = tmp_path / "refs"
    refs_dir.mkdir()
    cfg = PixieConfig.from_preset("default").apply_overrides([a for a in TINY_RUN if "=" in a])
    lock = reference_cache_path(load_mesh(bop / "models" / "obj_000001.ply"), cfg, refs_dir).with_suffix(".lock")
    lock.write_text(json.dumps({"pid": DEAD_PID, "host": socket.gethostname(), "time": 0}))
    (refs_dir / f".{lock.stem}.npz.{DEAD_PID}.zz.tmp").write_bytes(b"half a set")
    rc, out, err = run_cli("run", bop, "-o", tmp_path / "run", "--refs-dir", refs_dir, "--objects", "1", *TINY_RUN)
    assert rc == 0, err
    assert "taking over" in out and not lock.exists() and not _temps(refs_dir)


# ------------------------------------------------------------------------------- misses count as misses


def _gt_estimates(bop, keys):
    from pixie.eval.datasets import BopDataset, PoseEstimate

    ds = BopDataset(bop)
    return [PoseEstimate(s, i, o, 1.0, g.T_cam_from_obj, 1.0) for (s, i, o) in keys
            for g in ds.instances(s, i) if g.obj_id == o]


def test_targets_without_an_estimate_are_misses(bop, tmp_path):
    """Hand-computed: 4 GT instances (image 0: box, cylinder; image 1: two boxes); exact poses for image 0 only.
    Every metric matches 2 of 4 (AR 0.5, ADD(-S)<0.1d 0.5); over the subset (image 0 box, image 1 boxes) 1 of 3."""
    from pixie.eval.datasets import write_results_csv
    from pixie.eval.evaluate import evaluate
    from pixie.eval.run import run_eval

    ests = _gt_estimates(bop, [(1, 0, 1), (1, 0, 2)])
    sc = evaluate(bop, ests, metrics=["mssd", "mspd", "add", "adds", "ad"])
    assert sc.n_targets == 4 and sc.overall["n_missing"] == 2
    assert sc.overall["AR_MSSD"] == pytest.approx(0.5) and sc.overall["AR_MSPD"] == pytest.approx(0.5)
    add_key = next(k for k in sc.overall if k.startswith("ADD(-S)") and "0.1" in k)
    assert sc.overall[add_key] == pytest.approx(0.5)
    subset = tmp_path / "targets.json"
    subset.write_text(json.dumps([{"scene_id": 1, "im_id": 0, "obj_id": 1, "inst_count": 1},
                                  {"scene_id": 1, "im_id": 1, "obj_id": 1, "inst_count": 2}]))
    csv = write_results_csv(tmp_path / "r.csv", ests[:1])
    sc = run_eval(bop, csv, tmp_path / "ev", metrics=["mssd", "mspd"], report=False, echo=None, targets=subset)
    assert sc.n_targets == 3 and sc.overall["n_missing"] == 2
    assert sc.overall["AR_MSSD"] == pytest.approx(1 / 3) and sc.overall["AR_noVSD"] == pytest.approx(1 / 3)
    rc, out, err = run_cli("eval", bop, "--results", csv, "-o", tmp_path / "ev2", "--no-report", "--targets", subset,
                           "--metrics", "mssd,mspd")
    assert rc == 0 and "3 targets" in out, err


def test_run_records_an_unreadable_image_as_a_failed_target_and_a_miss(bop, tmp_path):
    (bop / "test" / "000001" / "rgb" / "000001.png").unlink()
    out = tmp_path / "run"
    rc, text, err = run_cli("run", bop, "-o", out, "--objects", "1", *TINY_RUN)
    assert rc == 0 and "Traceback" not in err, err
    recs = {tuple(json.loads(ln)["key"]): json.loads(ln) for ln in (out / "per_target.jsonl").read_text().splitlines()}
    bad = recs[(1, 1, 1)]
    assert "no image for scene 1 image 1" in bad["error"] and all(e["failed"] and e["T"] is None for e in bad["estimates"])
    scores = json.loads((out / "scores.json").read_text())
    assert scores["n_targets"] == 3 and scores["overall"]["n_missing"] >= 2  # image 1's two boxes are misses
    assert "3 targets" in text
    rc, text, err = run_cli("run", bop, "-o", out, "--objects", "1", *TINY_RUN)  # the failed target runs again
    assert rc == 0 and "1 to run" in text and "could not be read" in text, err


# ------------------------------------------------------------------------------------- crash safety


def _cmd(*argv) -> list[str]:
    return [sys.executable, "-m", "pixie", *map(str, argv)]


def _env(cache: Path | None = None) -> dict:
    """The spawned command's environment; ``cache``: its user cache (``estimate --mesh`` builds its set there)."""
    env = dict(os.environ, PYTHONPATH=str(SRC), PYTHONUNBUFFERED="1", OMP_NUM_THREADS="1")
    if cache is not None:
        env["XDG_CACHE_HOME"] = str(cache)
    return env


def _work_seconds(argv, cache: Path | None = None) -> float:
    """Run to completion; the seconds from its first printed line (after the imports) to its exit."""
    proc = subprocess.Popen(_cmd(*argv), env=_env(cache), stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True,
                            start_new_session=True)
    try:
        assert proc.stdout.readline(), "no output"
        t0 = time.perf_counter()
        proc.communicate(timeout=180)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
    assert proc.returncode == 0, argv
    return time.perf_counter() - t0


def _kill_after(argv, delay: float, cache: Path | None = None) -> int | None:
    """Start the command, SIGKILL its process group ``delay`` s after its first line; its exit code if it ended first."""
    proc = subprocess.Popen(_cmd(*argv), env=_env(cache), stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True,
                            start_new_session=True)
    try:
        proc.stdout.readline()
        time.sleep(delay)
        rc = proc.poll()
        os.killpg(proc.pid, signal.SIGKILL)
    except ProcessLookupError:
        pass
    finally:
        proc.wait(timeout=30)
    return rc


def _poses(csv: Path) -> list[tuple]:
    """results.csv rows without the time column (which differs between runs)."""
    return sorted(tuple(r.split(",")[:6]) for r in csv.read_text().splitlines()[1:])


def _no_leftovers(*folders: Path) -> None:
    for f in folders:
        assert not _temps(f), _temps(f)
        assert not list(Path(f).rglob("*.lock")), list(Path(f).rglob("*.lock"))


def _set_arrays(path: Path) -> dict:
    with np.load(path) as z:
        return {k: z[k] for k in z.files if k != "meta" and not k.endswith("seconds")}  # build times differ


KILLS = 6  # per command (18 in all; 24 until session 35: each is a process start, ~4 s, and the suite is at 10 min)


@pytest.mark.slow
def test_seeded_sigkills_lose_nothing_and_leave_nothing(part, bop, tmp_path):
    """18 SIGKILLs at seeded random points of `refs build`, `run` and `estimate --batch`, each followed by a rerun
    (under a timeout: no hang). After them: no temporary file, no lock, and results identical to an uninterrupted run."""
    rng = np.random.default_rng(23)
    # refs build: each attempt starts over; the file, when there, is always a whole set
    build = ["refs", "build", part["mesh"], "--views", "40", "--rotations", "2", "--size", "64", "--matcher", "none",
             "--set", "refs.encodings=[depth]", "--force"]
    t_build = _work_seconds([*build, "-o", tmp_path / "ref.npz"])
    for _ in range(KILLS):
        _kill_after([*build, "-o", tmp_path / "b" / "set.npz"], rng.uniform(0.0, t_build))
        if (tmp_path / "b" / "set.npz").exists():
            _set_arrays(tmp_path / "b" / "set.npz")  # loadable: never half a file
    subprocess.run(_cmd(*build, "-o", tmp_path / "b" / "set.npz"), env=_env(), timeout=180, check=True,
                   capture_output=True)
    ref, got = _set_arrays(tmp_path / "ref.npz"), _set_arrays(tmp_path / "b" / "set.npz")
    assert ref.keys() == got.keys() and all(np.array_equal(ref[k], got[k]) for k in ref)
    _no_leftovers(tmp_path / "b")
    # pixie run: resumable; the reference sets are built under a lock that a kill leaves behind
    run = ["run", bop, "--objects", "1", *TINY_RUN]
    t_run = _work_seconds([*run, "-o", tmp_path / "run_ref"])
    for _ in range(KILLS):
        _kill_after([*run, "-o", tmp_path / "run"], rng.uniform(0.0, t_run))
    subprocess.run(_cmd(*run, "-o", tmp_path / "run"), env=_env(), timeout=180, check=True, capture_output=True)
    assert _poses(tmp_path / "run" / "results.csv") == _poses(tmp_path / "run_ref" / "results.csv")
    _no_leftovers(tmp_path / "run")
    # estimate --batch from a mesh (its set cached under a lock), three photos
    photos = tmp_path / "photos"
    photos.mkdir()
    for k in range(3):
        shutil.copy(part["photo"], photos / f"p{k}.png")
    batch = ["estimate", "--mesh", part["mesh"], "--batch", photos, "--K", K_TEXT, "--bbox", _box(part["box"]),
             *TINY_RUN[1:]]
    t_batch = _work_seconds([*batch, "-o", tmp_path / "batch_ref"], cache=tmp_path / "cache_ref")
    for _ in range(KILLS):  # in a cache of their own: the kills also hit the set's build under its lock
        _kill_after([*batch, "-o", tmp_path / "batch"], rng.uniform(0.0, t_batch), cache=tmp_path / "cache")
    subprocess.run(_cmd(*batch, "-o", tmp_path / "batch"), env=_env(tmp_path / "cache"), timeout=180, check=True,
                   capture_output=True)
    assert _poses(tmp_path / "batch" / "results.csv") == _poses(tmp_path / "batch_ref" / "results.csv")
    assert len((tmp_path / "batch" / "results.jsonl").read_text().splitlines()) == 3
    _no_leftovers(tmp_path / "batch")
    _no_leftovers(tmp_path / "cache" / "pixie" / "refs")


def test_api_result_carries_the_warnings_and_settings(part, tmp_path):
    """estimate_pose: the input warnings (EXIF orientation) are warned as usual AND kept in result.warnings, with
    the pose warnings and the effective settings."""
    from PIL import Image

    import pixie

    im = Image.open(part["photo"])
    exif = Image.Exif()
    exif[0x0112] = 6
    im.save(tmp_path / "rot.jpg", exif=exif.tobytes(), quality=95)
    cfg = pixie.PixieConfig.from_preset("default")
    for item in ("refine.render_iters=0", "match.matcher=sift-nn", "match.max_keypoints=128"):
        cfg.set(*item.split("="))
    with pytest.warns(UserWarning, match="EXIF orientation 6"):
        res = pixie.estimate_pose(part["refs"], tmp_path / "rot.jpg", K_TEXT, bbox=(0, 0, 320, 240), config=cfg)
    assert any("EXIF orientation 6" in w for w in res.warnings)
    assert any("covers 100 % of the image" in w for w in res.warnings)
    assert res.to_dict()["settings"]["refs.views"] == 10
