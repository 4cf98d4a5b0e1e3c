"""The `pixie` command: version, help of every command, refusing no box, `pixie weights`, outputs kept as named."""

from __future__ import annotations

import json
import os
import stat

import pytest

import pixie
from pixie.cli import main


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

    from pixie.demo import generated_part

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
