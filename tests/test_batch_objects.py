"""Several objects per photo in one batch: a manifest row per (photo, object, box), one reference set per object."""

from __future__ import annotations

import csv
import json

import cv2
import numpy as np
import pytest
import trimesh
from conftest import assert_cli_error, run_cli

from pixie.app.runner import make_matcher
from pixie.config import RefsConfig
from pixie.geometry.camera import make_K, make_T, rotation_angle_deg
from pixie.geometry.mesh import from_arrays
from pixie.geometry.render import Renderer
from pixie.references.store import save_reference_set
from pixie.synth.e2e import e2e_config
from pixie.synth.photo import LightRig, Material, random_background, render_rgb

pytestmark = pytest.mark.usefixtures("one_torch_thread")

K = make_K(600.0, 600.0, 319.5, 239.5)


def ell():
    """An L-shaped bracket, 70 x 50 x 20 mm (asymmetric)."""
    a = trimesh.creation.box(extents=[70.0, 20.0, 20.0])
    b = trimesh.creation.box(extents=[20.0, 50.0, 20.0])
    b.apply_translation([-25.0, 25.0, 0.0])
    m = trimesh.util.concatenate([a, b])
    return from_arrays(np.asarray(m.vertices), np.asarray(m.faces), name="ell")


def cylinder_peg():
    """A cylinder with a side peg, 30 mm across, 70 mm long."""
    c = trimesh.creation.cylinder(radius=15.0, height=70.0, sections=32)
    p = trimesh.creation.box(extents=[20.0, 10.0, 10.0])
    p.apply_translation([20.0, 0.0, 25.0])
    m = trimesh.util.concatenate([c, p])
    return from_arrays(np.asarray(m.vertices), np.asarray(m.faces), name="peg")


@pytest.fixture(scope="module")
def scene(tmp_path_factory, proc_mesh, matcher_name, build_refs):
    d = tmp_path_factory.mktemp("objects")
    meshes = [proc_mesh, ell(), cylinder_peg()]
    rng = np.random.default_rng(7)
    poses = []
    for m, (u, v), ax in zip(meshes, [(170, 170), (460, 160), (330, 350)],
                             ([0.5, -0.3, 0.2], [1.2, 0.4, -0.5], [-0.4, 1.0, 0.8])):
        R = cv2.Rodrigues(np.array(ax))[0]
        z = 4.0 * max(x.diameter for x in meshes)
        c = np.array([(u - K[0, 2]) / K[0, 0] * z, (v - K[1, 2]) / K[1, 1] * z, z])
        poses.append(make_T(R, c - R @ m.center))
    ph = render_rgb([Renderer(m) for m in meshes], poses, K, 480, 640, [Material.random(rng) for _ in meshes], rng,
                    background=random_background(480, 640, rng, "noise"), lights=LightRig.random(rng), shadows=False)
    cv2.imwrite(str(d / "photo.png"), cv2.cvtColor(ph.rgb, cv2.COLOR_RGB2BGR))
    cfg = e2e_config(matcher_name)
    cfg.refs = RefsConfig(n_fibonacci=30, rotations=8, size=256, encodings=["shade3_edges"], feature_rolls="first")
    matcher = make_matcher(cfg)
    rows = []
    for i, (m, mv) in enumerate(zip(meshes, ph.masks_visib)):
        refs = save_reference_set(build_refs(m, cfg.refs, matcher=matcher), d / f"{m.name}.npz")
        ys, xs = np.nonzero(mv)
        (d / f"gt{i + 1}.json").write_text(json.dumps({"T_cam_from_obj": poses[i].tolist()}))
        rows.append({"image": "photo.png", "K": "600,600,319.5,239.5", "obj_id": i + 1, "refs": refs.name,
                     "bbox": f"{xs.min()},{ys.min()},{np.ptp(xs) + 1},{np.ptp(ys) + 1}", "gt_pose": f"gt{i + 1}.json"})
    with open(d / "manifest.csv", "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    sets = ["--set", f"match.matcher={matcher_name}", "--set", "refs.feature_rolls=first", "--set",
            "match.in_plane=query"]
    return d, meshes, poses, sets


def test_three_objects_in_one_photo_give_three_poses_three_rows_and_one_overlay(scene):
    d, meshes, poses, sets = scene
    code, out, err = run_cli("estimate", "--batch", str(d / "manifest.csv"), "-o", str(d / "out"), *sets)
    assert code == 0, err
    assert "3 rows, 3 objects (1 photos)" in out
    with open(d / "out" / "results.csv") as fh:
        rows = list(csv.DictReader(fh))
    assert sorted(int(r["obj_id"]) for r in rows) == [1, 2, 3]
    recs = [json.loads(x) for x in (d / "out" / "results.jsonl").read_text().splitlines()]
    assert len(recs) == 3 and len({r["photo_overlay"] for r in recs}) == 1
    assert (d / "out" / recs[0]["photo_overlay"]).is_file()
    assert recs[0]["photo_overlay"] in (d / "out" / "index.html").read_text()
    for r in recs:  # each row was estimated with its own object's set
        T = np.asarray(r["result"]["T_cam_from_obj"])
        Tg = poses[r["obj_id"] - 1]
        assert abs(T[2, 3] - Tg[2, 3]) / Tg[2, 3] < 0.05, (r["refs"], T[:3, 3], Tg[:3, 3])
        if r["obj_id"] != 3:  # the peg's cylinder is nearly symmetric about its axis: depth only
            assert rotation_angle_deg(T[:3, :3], Tg[:3, :3]) < 5.0, r["refs"]
        # the manifest's gt_pose: the same errors, in the result and on the page
        assert r["result"]["gt_error"]["rot_deg"] == pytest.approx(rotation_angle_deg(T[:3, :3], Tg[:3, :3]), abs=1e-6)
    assert "error vs the manifest's gt_pose" in (d / "out" / "index.html").read_text()


def test_a_row_without_an_object_and_no_default_is_refused(scene):
    d, *_, sets = scene
    (d / "bad.csv").write_text("image,K,bbox\nphoto.png,\"600,600,319.5,239.5\",\"10,10,50,50\"\n")
    assert_cli_error(run_cli("estimate", "--batch", str(d / "bad.csv"), "-o", str(d / "bad_out"), *sets),
                     "--refs SET.npz")
    (d / "both.csv").write_text("image,K,bbox,refs,mesh\nphoto.png,\"600,600,319.5,239.5\",\"10,10,50,50\",proc.npz,"
                                "proc.npz\n")
    assert_cli_error(run_cli("estimate", "--batch", str(d / "both.csv"), "-o", str(d / "both_out"), *sets),
                     "not both")
