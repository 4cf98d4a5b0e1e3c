"""``pixie render`` (a photo of the part at a known pose, with K, box, mask and ground truth) and ``estimate --gt``."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from pixie.app.cli import main
from pixie.app.track import read_pose_file
from pixie.pipeline.estimator import PoseEstimator
from pixie.pipeline.query import load_image
from pixie.references.store import save_reference_set
from pixie.synth.check import check_scene, pose_error

pytestmark = pytest.mark.usefixtures("one_torch_thread")


@pytest.fixture(scope="module")
def part_files(proc_trimesh, query_e2e, tmp_path_factory):
    d = tmp_path_factory.mktemp("render")
    proc_trimesh.export(d / "part.stl")
    refs, cfg, _ = query_e2e
    return d, save_reference_set(refs, d / "part.npz"), cfg


def test_render_writes_photo_mask_box_and_ground_truth_and_estimate_scores_against_it(part_files, query_e2e, capsys):
    d, refs_path, cfg = part_files
    out = d / "scene"
    assert main(["render", "--mesh", str(d / "part.stl"), "-o", str(out), "--seed", "2", "--background", "clutter"]) == 0
    scene = json.loads((out / "scene.json").read_text())
    T_gt = read_pose_file(out / "gt_pose.json")
    img, mask = load_image(out / "photo.png"), load_image(out / "mask.png")[..., 0] > 127
    assert img.shape == (480, 640, 3) and mask.shape == (480, 640)
    ys, xs = np.nonzero(mask)  # the box is the mask's, and the mask is where the part is drawn
    assert scene["bbox_xywh"] == [int(xs.min()), int(ys.min()), int(np.ptp(xs) + 1), int(np.ptp(ys) + 1)]
    assert "next: pixie estimate" in capsys.readouterr().out
    # the estimate on the rendered photo is right (easy settings: clean render, whole part visible)
    refs, cfg_e, matcher = query_e2e
    res = PoseEstimator(refs, cfg_e, matcher=matcher).estimate(img, np.array(scene["K"]), bbox=scene["bbox_xywh"])
    e = pose_error(res.T_cam_from_obj, T_gt, refs.mesh.vertices)
    assert e["rot_deg"] < 2.5 and e["depth_pct"] < 2.5, e
    # estimate --gt prints the errors and writes them into the result JSON
    argv = ["estimate", "--refs", str(refs_path), "--image", str(out / "photo.png"), "--K", scene["K_arg"], "--bbox",
            ",".join(str(v) for v in scene["bbox_xywh"]), "--gt", str(out / "gt_pose.json"), "-o", str(d / "res.json"),
            "--set", f"match.matcher={cfg.match.matcher}", "--set", "refs.feature_rolls=first",
            "--set", "match.in_plane=query"]
    assert main(argv) == 0
    assert "error against --gt: rotation" in capsys.readouterr().out
    ge = json.loads((d / "res.json").read_text())["gt_error"]
    assert ge["rot_deg"] < 2.5 and ge["depth_pct"] < 2.5 and ge["add_mm"] < 5.0


def test_check_scene_honours_a_given_pose_and_plain_background(proc_mesh):
    from pixie.geometry.camera import make_K

    from conftest import pose_facing

    K = make_K(600.0, 600.0, 319.5, 239.5)
    T = pose_facing(proc_mesh, np.random.default_rng(5), 3.0, 0.0, K)
    sc = check_scene(proc_mesh, K, 480, 640, T=T, seed=1, colour=(200, 40, 40), background="plain")
    np.testing.assert_allclose(sc.T_cam_from_obj, T)
    assert sc.visib_fract == pytest.approx(1.0)
    far = cv2.dilate(sc.mask.astype(np.uint8), np.ones((5, 5), np.uint8)) == 0  # 2 px off the part's outline
    assert np.all(sc.rgb[far] == 128)  # plain grey around the part
    assert pose_error(T, T, proc_mesh.vertices) == {"rot_deg": 0.0, "trans_mm": 0.0, "depth_pct": 0.0, "add_mm": 0.0}


def test_render_refuses_bad_options_and_existing_outputs(part_files, capsys):
    d, _, _ = part_files
    mesh = str(d / "part.stl")
    for extra, msg in ((["--size", "640by480"], "WIDTHxHEIGHT"), (["--background", "nosuch"], "--background"),
                       (["--distance-factor", "-1"], "positive")):
        assert main(["render", "--mesh", mesh, "-o", str(d / "bad"), *extra]) == 2
        assert msg in capsys.readouterr().err
    assert main(["render", "--mesh", mesh, "-o", str(d / "twice")]) == 0
    before = (d / "twice" / "photo.png").read_bytes()
    assert main(["render", "--mesh", mesh, "-o", str(d / "twice"), "--seed", "9"]) == 2  # no --force: kept
    assert (d / "twice" / "photo.png").read_bytes() == before
    assert main(["render", "--mesh", mesh, "-o", str(d / "twice"), "--seed", "9", "--force"]) == 0
    assert (d / "twice" / "photo.png").read_bytes() != before
