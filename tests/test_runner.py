"""pixie.app.runner: the shared reference cache and the resumable loop, on a tiny synthetic BOP dataset."""

from __future__ import annotations

import json

import numpy as np
import pytest

from pixie.config import PixieConfig
from pixie.eval.datasets import read_results_csv
from pixie.geometry.mesh import load_mesh
from pixie.app.runner import Journal, cached_reference_set, reference_cache_path, run_dataset

from conftest import tiny_run_config

pytestmark = pytest.mark.usefixtures("one_torch_thread")


tiny_config = tiny_run_config  # conftest: SIFT on a few small references


def test_journal_resumes_and_skips_cut_lines(tmp_path):
    path = tmp_path / "j.jsonl"
    j = Journal(path, key=lambda r: r["k"])
    j.append({"k": 1, "v": "a"})
    j.append({"k": 2, "v": "b"})
    j.append({"k": 1, "v": "c"})  # the last record of a key wins
    with open(path, "a") as fh:
        fh.write('{"k": 3, "v"')  # a write cut by a kill
    again = Journal(path, key=lambda r: r["k"])
    assert len(again) == 2 and 1 in again and 3 not in again
    assert again.get(1)["v"] == "c" and again.get(2)["v"] == "b"
    again.append({"k": 3, "v": "d"})  # the redone work does not glue onto the cut line
    assert Journal(path, key=lambda r: r["k"]).get(3) == {"k": 3, "v": "d"}


def test_run_dataset_resumes_where_it_stopped(synthetic_bop, tmp_path):
    root, _ = synthetic_bop
    out, refs_dir = tmp_path / "run", tmp_path / "refs"
    lines: list[str] = []
    csv = run_dataset(root, out, tiny_config(), refs_dir=refs_dir, echo=lines.append, show_progress=False)
    first = csv.read_text()
    journal = out / "per_target.jsonl"
    records = journal.read_text().splitlines()
    assert len(records) == 3 and "3 to run" in lines[0]  # (im 0, box), (im 0, cylinder), (im 1, 2 boxes)
    assert sorted(p.suffix for p in refs_dir.iterdir()) == [".npz", ".npz"]  # built once per object, no lock left
    n_rows = len(read_results_csv(csv))
    assert 1 <= n_rows <= 4

    lines.clear()
    assert run_dataset(root, out, tiny_config(), refs_dir=refs_dir, echo=lines.append, show_progress=False) == csv
    assert "0 to run" in lines[0] and csv.read_text() == first and journal.read_text().splitlines() == records

    # kill during the last target: its line is cut; the rerun estimates it again, the same way
    journal.write_text("\n".join(records[:2]) + "\n" + records[2][: len(records[2]) // 2])
    lines.clear()
    run_dataset(root, out, tiny_config(), refs_dir=refs_dir, echo=lines.append, show_progress=False)
    assert "1 to run" in lines[0]
    redone = json.loads(journal.read_text().splitlines()[-1])
    for a, b in zip(json.loads(records[2])["estimates"], redone["estimates"]):
        assert (a["T"] is None) == (b["T"] is None)
        if a["T"] is not None:
            np.testing.assert_array_equal(a["T"], b["T"])
    assert csv.read_text().splitlines()[0] == first.splitlines()[0] and len(read_results_csv(csv)) == n_rows


def test_reference_cache_builds_once_and_rebuilds_a_corrupt_file(synthetic_bop, tmp_path):
    root, _ = synthetic_bop
    mesh = load_mesh(root / "models" / "obj_000001.ply")
    cfg = tiny_config()
    msgs: list[str] = []
    refs = cached_reference_set(mesh, cfg, tmp_path, echo=msgs.append)
    path = reference_cache_path(mesh, cfg, tmp_path)
    assert path.is_file() and not path.with_suffix(".lock").exists() and any("building" in m for m in msgs)
    msgs.clear()
    again = cached_reference_set(mesh, cfg, tmp_path, echo=msgs.append)
    assert not msgs and np.array_equal(again.poses, refs.poses)  # loaded, not built
    other = PixieConfig.from_dict(cfg.to_dict())
    other.match.detection_threshold = 0.01  # other features: another file
    assert reference_cache_path(mesh, other, tmp_path) != path
    path.write_bytes(b"not a zip")
    rebuilt = cached_reference_set(mesh, cfg, tmp_path)
    assert np.array_equal(rebuilt.poses, refs.poses)
