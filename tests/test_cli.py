"""The ``pixie`` command line: every sub-command on small real inputs, and one-line errors (exit 2)."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from pixie.cli import main
from pixie.render import Renderer

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
    assert cv2.imread(str(out / "ov.png")).shape == (240, 320, 3)


@pytest.mark.parametrize("args, message", [
    (["estimate", "--refs", "missing.npz", "--image", "x.png", "--K", "1,1,0,0"], "reference set not found"),
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
