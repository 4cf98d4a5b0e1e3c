"""The ``pixie`` command line: every sub-command on small real inputs, one-line errors (exit 2), version and help,
refusing no box, ``pixie weights``, outputs kept as named."""

from __future__ import annotations

import json
import os
import stat

import cv2
import numpy as np
import pytest

import pixie
from pixie.app.cli import main
from pixie.geometry.render import Renderer

pytestmark = pytest.mark.usefixtures("one_torch_thread")

TINY = ["--set", "refs.n_fibonacci=4", "--set", "refs.rotations=2", "--set", "match.matcher=sift-nn",
        "--set", "refine.render_iters=0"]


@pytest.fixture(scope="module")
def built(synthetic_bop, tmp_path_factory):
    root, _ = synthetic_bop
    out = tmp_path_factory.mktemp("cli")
    refs = out / "box.npz"
    assert main(["refs", "build", str(root / "models" / "obj_000001.ply"), "-o", str(refs), "--size", "64",
                 "--encodings", "shade3_edges", "--matcher", "sift-nn", *TINY]) == 0
    return root, out, refs


def test_refs_build_and_show(built, capsys):
    _, out, refs = built
    assert refs.is_file()
    assert main(["refs", "show", str(refs), "-o", str(out / "sheet.png")]) == 0
    sheet = cv2.imread(str(out / "sheet.png"))
    assert sheet is not None and sheet.shape[0] > 0
    assert "10 views x 2 rolls at 64 px" in capsys.readouterr().out


def test_estimate_writes_a_result_and_an_overlay(built, synthetic_bop):
    root, out, refs = built
    _, meta = synthetic_bop
    T = meta["scenes"][0][0][1]
    image = root / "test" / "000001" / "rgb" / "000000.png"
    mask = Renderer(meta["meshes"][1]).render(T, np.array([[500.0, 0, 160], [0, 500, 120], [0, 0, 1]]), 240, 320).mask
    ys, xs = np.nonzero(mask)
    bbox = f"{xs.min()},{ys.min()},{np.ptp(xs) + 1},{np.ptp(ys) + 1}"
    rc = main(["estimate", "--refs", str(refs), "--image", str(image), "--K", "500,500,160,120", "--bbox", bbox,
               "-o", str(out / "res.json"), "--overlay", str(out / "ov.png"), *TINY])
    res = json.loads((out / "res.json").read_text())
    assert rc == (1 if res["failed"] else 0)
    assert set(res) >= {"T_cam_from_obj", "score", "failed", "hypotheses", "timings"}
    ov = cv2.imread(str(out / "ov.png"))  # the photo under a status banner: green OK / red FAILED
    assert ov.shape[1] == 320 and 240 < ov.shape[0] <= 240 + 40
    assert tuple(ov[2, -3]) == ((30, 30, 200) if res["failed"] else (60, 150, 30))


@pytest.mark.parametrize("args, message", [
    (["estimate", "--refs", "missing.npz", "--image", "x.png", "--K", "1,1,0,0", "--bbox", "0,0,5,5"],
     "reference set not found"),
    (["refs", "build", "missing.ply", "-o", "r.npz"], "missing.ply"),
    (["refs", "build", "m.ply", "-o", "r.npz", "--set", "refs.nosuch=1"], "unknown key 'nosuch'"),
])
def test_errors_are_one_line_and_exit_2(args, message, tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    assert main(args) == 2
    err = capsys.readouterr().err
    assert err.startswith("pixie: error:") and message in err and err.count("\n") == 1


def test_run_and_eval_commands(synthetic_bop, tmp_path, capsys):
    root, _ = synthetic_bop
    out = tmp_path / "run"
    assert main(["run", str(root), "-o", str(out), "--refs-dir", str(tmp_path / "refs"), "--set", "refs.size=128",
                 "--set", "refs.encodings=[shade3_edges]", *TINY, "--set", "refs.n_fibonacci=10"]) == 0
    scores = json.loads((out / "scores.json").read_text())
    assert scores["n_targets"] == 4 and (out / "report.html").is_file() and (out / "results.csv").is_file()
    assert main(["eval", str(root), "--results", str(out / "results.csv"), "-o", str(tmp_path / "ev"),
                 "--metrics", "mssd,mspd", "--no-report"]) == 0
    assert json.loads((tmp_path / "ev" / "scores.json").read_text())["overall"]["AR_MSSD"] == scores["overall"]["AR_MSSD"]
    assert "AR" in capsys.readouterr().out


def test_version_and_help(capsys):
    with pytest.raises(SystemExit) as info:
        main(["--version"])
    assert info.value.code == 0 and capsys.readouterr().out.strip() == f"pixie {pixie.__version__}"
    for cmd in (["refs", "build"], ["refs", "show"], ["estimate"], ["run"], ["weights"], ["eval"], ["demo"]):
        with pytest.raises(SystemExit) as info:
            main([*cmd, "-h"])
        assert info.value.code == 0, cmd
    out = capsys.readouterr().out
    assert "--preset" in out and "--device" in out and "--ray" in out


def test_estimate_without_box_refuses_saying_what_to_pass(tmp_path, capsys):
    rc = main(["estimate", "--refs", str(tmp_path / "r.npz"), "--image", "x.png", "--K", "600,600,320,240"])
    err = capsys.readouterr().err
    assert rc == 2 and "no object box" in err and "--bbox x,y,w,h" in err and "--mask" in err
    assert "Traceback" not in err


def test_weights_lists_the_shipped_extractor(capsys):
    assert main(["weights", "--json"]) == 0
    data = json.loads(capsys.readouterr().out)
    by_name = {w["name"]: w for w in data["weights"]}
    assert by_name["aliked-n16"]["path"] and len(by_name["aliked-n16"]["sha256"]) == 64
    assert data["backends"]["aliked-nn"]["ready"] and data["backends"]["aliked-nn"]["weights"] == ["aliked-n16"]


def test_refs_build_keeps_the_output_name(tmp_path, capsys):
    import trimesh

    from pixie.app.demo import generated_part

    m = generated_part()
    stl = tmp_path / "bracket.stl"
    trimesh.Trimesh(m.vertices / 1000.0, m.faces, process=False).export(stl)  # a metre file
    small = ["--views", "6", "--rotations", "1", "--size", "32", "--encodings", "depth", "--matcher", "none"]
    assert main(["refs", "build", str(stl), "-o", str(tmp_path / "bracket.refs"), *small]) == 0
    out = capsys.readouterr().out
    assert "read in metres (auto-detected from its size), diameter 164.9 mm" in out
    assert (tmp_path / "bracket.refs").is_file() and not (tmp_path / "bracket.refs.npz").exists()
    before = os.stat("/dev/null")
    assert main(["refs", "build", str(stl), "-o", "/dev/null", *small]) == 0
    assert stat.S_ISCHR(os.stat("/dev/null").st_mode) and os.stat("/dev/null").st_ino == before.st_ino


def test_estimate_from_a_mesh_builds_references_once(tmp_path, monkeypatch, capsys):
    """`pixie estimate --mesh` builds the reference set into the user cache once; the JSON names its inputs."""
    import trimesh

    from pixie.app.demo import generated_part, generated_photo
    from pixie.pipeline.query import bbox_from_mask
    from pixie.viz import save_png

    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    m = generated_part()
    trimesh.Trimesh(m.vertices, m.faces, process=False).export(tmp_path / "part.stl")
    img, K, T = generated_photo(m)
    save_png(tmp_path / "photo.png", img)
    x, y, w, h = bbox_from_mask(Renderer(m).render(T, K, *img.shape[:2]).mask)
    args = ["estimate", "--mesh", str(tmp_path / "part.stl"), "--image", str(tmp_path / "photo.png"),
            "--K", f"{K[0, 0]},{K[1, 1]},{K[0, 2]},{K[1, 2]}", "--bbox", f"{x:.0f},{y:.0f},{w:.0f},{h:.0f}",
            "-o", str(tmp_path / "r.json"), "--overlay", str(tmp_path / "o.png"), *TINY]
    main(args)
    assert "building references" in capsys.readouterr().out
    sets = list((tmp_path / "cache" / "pixie" / "refs").glob("*.npz"))
    assert len(sets) == 1
    main(args)
    assert "building references" not in capsys.readouterr().out
    res = json.loads((tmp_path / "r.json").read_text())
    assert res["units"] == "mm" and res["box"]["source"] == "bbox" and res["box"]["xywh"] == [x, y, w, h]
    import hashlib

    assert res["image"]["sha256"] == hashlib.sha256((tmp_path / "photo.png").read_bytes()).hexdigest()
    assert res["mesh_sha256"] == hashlib.sha256((tmp_path / "part.stl").read_bytes()).hexdigest()
    ov = cv2.imread(str(tmp_path / "o.png"))  # the photo under its status banner
    assert ov.shape[1:] == img.shape[1:] and img.shape[0] < ov.shape[0] <= img.shape[0] + 40
