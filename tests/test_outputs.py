"""Outputs land exactly at the path given (no suffix added), whole, and devices are written into, not replaced."""

from __future__ import annotations

import os
import stat
from pathlib import Path

import numpy as np
import pytest

from pixie.errors import PixieError, ReferenceSetError
from pixie.paths import write_atomic
from pixie.viz import save_png


def test_paths_are_kept_as_given(tmp_path: Path) -> None:
    p = write_atomic(tmp_path / "sub" / "result", "{}")
    assert p == tmp_path / "sub" / "result" and p.read_text() == "{}"
    png = save_png(tmp_path / "overlay.image", np.zeros((4, 5, 3), np.uint8))
    assert png.name == "overlay.image" and png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert sorted(x.name for x in tmp_path.iterdir()) == ["overlay.image", "sub"]  # no temp files left


def test_failed_write_keeps_the_old_file(tmp_path: Path) -> None:
    p = write_atomic(tmp_path / "r.json", "old")

    def boom(fh):
        fh.write(b"half")
        raise RuntimeError("killed")

    with pytest.raises(RuntimeError):
        write_atomic(p, boom)
    assert p.read_text() == "old" and [x.name for x in tmp_path.iterdir()] == ["r.json"]


def test_device_is_written_into_not_replaced() -> None:
    before = os.stat("/dev/null")
    write_atomic("/dev/null", b"x" * 100)
    after = os.stat("/dev/null")
    assert stat.S_ISCHR(after.st_mode) and after.st_ino == before.st_ino


def test_folder_is_refused(tmp_path: Path) -> None:
    with pytest.raises(PixieError, match="is a folder"):
        write_atomic(tmp_path, "x")


def test_reference_set_path_not_renamed(tmp_path: Path, proc_mesh) -> None:
    from pixie.config import RefsConfig
    from pixie.references.set import build_reference_set
    from pixie.references.store import load_reference_set, save_reference_set

    refs = build_reference_set(proc_mesh, RefsConfig(n_fibonacci=0, rotations=1, size=32, encodings=["depth"]))
    p = save_reference_set(refs, tmp_path / "part.refs")
    assert p == tmp_path / "part.refs" and not (tmp_path / "part.refs.npz").exists()
    assert load_reference_set(p).n_views == refs.n_views
    before = os.stat("/dev/null")
    assert save_reference_set(refs, "/dev/null") == Path("/dev/null")
    assert stat.S_ISCHR(os.stat("/dev/null").st_mode) and os.stat("/dev/null").st_ino == before.st_ino
    with pytest.raises(ReferenceSetError, match="folder"):
        save_reference_set(refs, tmp_path)
