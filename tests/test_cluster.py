"""`pixie run` on Ray workers (local ray.init(num_cpus=2)) gives the serial run's results, bit for bit."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import pytest

from pixie.config import PixieConfig, RefsConfig
from pixie.app.runner import run_dataset


def _rows(path: Path) -> list[list[str]]:
    return [row[:-1] for row in csv.reader(path.read_text().splitlines())]  # all but the time column


@pytest.mark.slow
def test_ray_run_equals_serial_on_lmo(lmo_dir, tmp_path):
    ray = pytest.importorskip("ray")
    cfg = PixieConfig.from_preset("default")
    cfg.refs = RefsConfig(n_fibonacci=10, rotations=4, size=128, encodings=["shade3_edges"], feature_rolls="first")
    cfg.refine.render_hypotheses = 2
    common = dict(objects=[5, 8], max_targets=4, refs_dir=tmp_path / "refs", echo=lambda m: None, show_progress=False)
    serial = run_dataset(lmo_dir, tmp_path / "serial", cfg, threads=1, **common)
    ray.init(num_cpus=2, include_dashboard=False)
    try:
        dist = run_dataset(lmo_dir, tmp_path / "ray", cfg, threads=1, use_ray=True, **common)
    finally:
        ray.shutdown()
    rows = _rows(serial)
    assert len(rows) == 5 and {r[2] for r in rows[1:]} == {"5", "8"}  # header + 4 targets of two objects
    assert _rows(dist) == rows
    # resuming the Ray run finds everything done
    lines = (tmp_path / "ray" / "per_target.jsonl").read_text().splitlines()
    assert len(lines) == 4 and all(json.loads(line)["estimates"] for line in lines)
