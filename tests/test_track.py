"""Pose priors and tracking (pixie.app.track, PoseEstimator.estimate_from_prior, ``pixie track``) on rendered sequences."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from pixie.app.cli import main
from pixie.app.track import Frame, Tracker, read_pose_file, track
from pixie.errors import ImageError, PixieError
from pixie.geometry.camera import make_K, make_T, rotation_angle_deg
from pixie.pipeline.estimator import PoseEstimator
from pixie.references.store import save_reference_set
from pixie.synth.sequence import smooth_sequence

pytestmark = pytest.mark.usefixtures("one_torch_thread")

K = make_K(600.0, 600.0, 320.0, 240.0)


@pytest.fixture(scope="module")
def est(query_e2e):
    refs, cfg, matcher = query_e2e
    return PoseEstimator(refs, cfg, matcher=matcher)


@pytest.fixture(scope="module")
def seq(proc_mesh):
    return smooth_sequence(proc_mesh, K, 480, 640, n_frames=8, seed=3, distractors=3)


def errors(T, Tg):
    return rotation_angle_deg(T[:3, :3], Tg[:3, :3]), abs(T[2, 3] - Tg[2, 3]) / Tg[2, 3]


def turned(T, centre, deg, dz=0.0):
    R = cv2.Rodrigues(np.array([0.3, -0.8, 0.52]) / np.linalg.norm([0.3, -0.8, 0.52]) * np.radians(deg))[0] @ T[:3, :3]
    c = (T[:3, :3] @ centre + T[:3, 3]) * (1.0 + dz)
    return make_T(R, c - R @ centre)


def test_a_prior_5_degrees_and_3_percent_off_is_refined_to_the_pose(est, seq, proc_mesh):
    for i in (0, 5):
        T0 = turned(seq.poses[i], proc_mesh.center, 5.0, 0.03)
        res = est.estimate_from_prior(seq.images[i], K, T0)  # no box: the prior's own, grown
        rot, dz = errors(res.T_cam_from_obj, seq.poses[i])
        assert rot < 1.5 and dz < 0.01, f"frame {i}: {rot:.2f} deg, {100 * dz:.2f} % depth"
        assert not res.failed and res.box_source == "prior" and res.timings["total"] < 5.0
        assert res.confidence > 0.4  # the aligned fit


def test_tracking_follows_the_part_without_searching_and_recovers_a_forced_loss(est, seq, proc_mesh):
    frames = [Frame(image=im, K=K, name=str(i)) for i, im in enumerate(seq.images)]
    steps = list(track(est, frames, init_pose=seq.poses[0]))
    assert [s.mode for s in steps] == ["prior"] * len(frames)
    errs = [errors(s.result.T_cam_from_obj, Tg) for s, Tg in zip(steps, seq.poses)]
    assert max(e[0] for e in errs) < 2.0 and max(e[1] for e in errs) < 0.02, errs
    # a prior 90° wrong at frame 4 is seen as lost (its fit drops), searched, and the track goes on
    tr = Tracker(est, init_pose=seq.poses[0])
    modes, errs = [], []
    for i, (fr, Tg) in enumerate(zip(frames, seq.poses)):
        if i == 4:
            tr.prior = turned(Tg, proc_mesh.center, 90.0)
        st = tr.step(fr)
        modes.append(st.mode)
        errs.append(errors(st.result.T_cam_from_obj, Tg))
    assert modes[4] == "search" and modes[:4] == ["prior"] * 4
    assert all(e[0] < 5.0 and e[1] < 0.05 for e in errs[5:]), errs


def test_a_prior_outside_the_image_is_a_clear_error(est, seq):
    T = seq.poses[0].copy()
    T[0, 3] += 5000.0
    with pytest.raises(ImageError, match="outside the image"):
        est.estimate_from_prior(seq.images[0], K, T)
    T = seq.poses[0].copy()
    T[2, 3] = -T[2, 3]
    with pytest.raises(ImageError, match="behind the camera"):
        est.estimate_from_prior(seq.images[0], K, T)


def test_pose_files_in_every_documented_form(tmp_path):
    R = cv2.Rodrigues(np.array([0.1, -0.2, 0.3]))[0]
    T = make_T(R, np.array([10.0, -5.0, 700.0]))
    forms = {"result.json": {"T_cam_from_obj": T.tolist(), "failed": False},
             "rt.json": {"R": R.tolist(), "t": T[:3, 3].tolist()},
             "bop.json": {"cam_R_m2c": R.ravel().tolist(), "cam_t_m2c": T[:3, 3].tolist()},
             "bare.json": T.tolist()}
    for name, d in forms.items():
        (tmp_path / name).write_text(json.dumps(d))
        np.testing.assert_allclose(read_pose_file(tmp_path / name), T, atol=1e-12)
    (tmp_path / "bad.json").write_text(json.dumps({"R": np.zeros((3, 3)).tolist(), "t": [0, 0, 1]}))
    with pytest.raises(PixieError, match="not a proper rotation"):
        read_pose_file(tmp_path / "bad.json")
    (tmp_path / "junk.json").write_text("{")
    with pytest.raises(PixieError, match="not readable JSON"):
        read_pose_file(tmp_path / "junk.json")
    with pytest.raises(PixieError, match="not found"):
        read_pose_file(tmp_path / "missing.json")


def test_cli_track_and_estimate_from_an_init_pose(est, seq, tmp_path, capsys):
    frames = tmp_path / "frames"
    frames.mkdir()
    for i, im in enumerate(seq.images[:4]):
        cv2.imwrite(str(frames / f"f{i:03d}.png"), cv2.cvtColor(im, cv2.COLOR_RGB2BGR))
    refs = save_reference_set(est.refs, tmp_path / "part.npz")
    (tmp_path / "init.json").write_text(json.dumps({"R": seq.poses[0][:3, :3].tolist(), "t": seq.poses[0][:3, 3].tolist()}))
    kv = ",".join(str(v) for v in (K[0, 0], K[1, 1], K[0, 2], K[1, 2]))
    common = ["--refs", str(refs), "--K", kv, "--init-pose", str(tmp_path / "init.json"), "--set",
              f"match.matcher={est.cfg.match.matcher}"]
    assert main(["track", str(frames), *common, "-o", str(tmp_path / "track.jsonl")]) == 0
    lines = [json.loads(x) for x in (tmp_path / "track.jsonl").read_text().splitlines()]
    assert [x["frame"] for x in lines] == [f"f{i:03d}.png" for i in range(4)]
    for x, Tg in zip(lines, seq.poses):
        rot, dz = errors(np.array(x["T_cam_from_obj"]), Tg)
        assert x["mode"] == "prior" and rot < 2.0 and dz < 0.02
    assert "4 frames" in capsys.readouterr().out
    # the same output again without --force is refused, and nothing is rewritten
    before = (tmp_path / "track.jsonl").read_bytes()
    assert main(["track", str(frames), *common, "-o", str(tmp_path / "track.jsonl")]) == 2
    assert (tmp_path / "track.jsonl").read_bytes() == before
    # estimate --init-pose: one photo refined from a prior, no box needed
    assert main(["estimate", "--image", str(frames / "f001.png"), *common, "-o", str(tmp_path / "one.json")]) == 0
    one = json.loads((tmp_path / "one.json").read_text())
    rot, dz = errors(np.array(one["T_cam_from_obj"]), seq.poses[1])
    assert rot < 2.0 and dz < 0.02 and one["box"]["source"] == "prior"
