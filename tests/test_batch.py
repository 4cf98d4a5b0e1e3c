"""Batch estimation (pixie.app.batch): manifests, refusing rows without a box, resuming, config-keyed caching,
and Ray runs equal to serial ones."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np
import pytest

from pixie.app.batch import folder_items, read_manifest, run_batch
from pixie.config import PixieConfig, RefsConfig
from pixie.errors import ConfigError, ImageError
from pixie.viz import save_png

pytestmark = pytest.mark.usefixtures("one_torch_thread")


def tiny_config() -> PixieConfig:
    """The default preset on a small reference set (16 views x 4 rolls at 128 px): seconds to build."""
    cfg = PixieConfig.from_preset("default")
    cfg.refs = RefsConfig(n_fibonacci=10, rotations=4, size=128, encodings=["shade3_edges"], feature_rolls="first")
    cfg.refine.render_hypotheses = 2
    return cfg


@pytest.fixture(scope="module")
def batch_inputs(tmp_path_factory, build_refs):
    """Three generated photos of the demo part (different colours and clutter), K, boxes, and a saved reference set."""
    from pixie.app.demo import generated_part, generated_photo
    from pixie.pipeline.query import bbox_from_mask
    from pixie.references.store import save_reference_set
    from pixie.geometry.render import Renderer
    from pixie.app.runner import make_matcher

    root = tmp_path_factory.mktemp("batch")
    mesh = generated_part()
    cfg = tiny_config()
    refs_path = save_reference_set(build_refs(mesh, cfg.refs, matcher=make_matcher(cfg)), root / "refs.npz")
    rows = []
    for seed in range(3):
        img, K, T = generated_photo(mesh, seed=seed)
        mask = Renderer(mesh).render(T, K, *img.shape[:2]).mask
        save_png(root / "photos" / f"p{seed}.png", img)
        save_png(root / "masks" / f"p{seed}.png", mask.astype(np.uint8) * 255)
        rows.append((f"photos/p{seed}.png", K, bbox_from_mask(mask)))
    with open(root / "manifest.csv", "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["image", "K", "bbox", "mask", "im_id"])
        for n, (img, K, box) in enumerate(rows):
            k = f"{K[0, 0]},{K[1, 1]},{K[0, 2]},{K[1, 2]}"
            # the last row gives a mask instead of a box
            w.writerow([img, k, "" if n == 2 else ",".join(str(int(v)) for v in box), "" if n < 2 else f"masks/p{n}.png", 10 + n])
    return root, refs_path, cfg, rows


def test_manifest_csv_json_and_relative_paths(batch_inputs, tmp_path):
    root, _, _, rows = batch_inputs
    items = read_manifest(root / "manifest.csv")
    assert [it.image for it in items] == [root / r[0] for r in rows]
    assert np.allclose(items[0].K, rows[0][1]) and np.allclose(items[0].bbox, rows[0][2])
    assert items[2].bbox is None and items[2].mask == root / "masks" / "p2.png"
    assert [it.im_id for it in items] == [10, 11, 12] and items[0].obj_id == 1
    js = root / "manifest.json"
    js.write_text(json.dumps([{"image": rows[0][0], "K": rows[0][1].tolist(), "bbox": rows[0][2].tolist()}]))
    (it,) = read_manifest(js)
    assert it.image == root / rows[0][0] and np.allclose(it.K, rows[0][1]) and it.im_id == 0


def test_manifest_refuses_rows_without_box_and_missing_files(batch_inputs, tmp_path):
    root, *_ = batch_inputs
    bad = tmp_path / "m.csv"
    bad.write_text("image,K,bbox\n" + f"{root}/photos/p0.png,\"600,600,320,240\",\n")
    with pytest.raises(ConfigError, match="row 1: no bbox and no mask.*give a bbox"):
        read_manifest(bad)
    bad.write_text("image,K,bbox\nnope.png,\"600,600,320,240\",\"1,2,3,4\"\nnope2.png,\"600,600,320,240\",\"1,2,3,4\"\n")
    with pytest.raises(ImageError, match=r"(?s)2 file.*nope.png.*nope2.png") as info:
        read_manifest(bad)
    assert "row 2" in str(info.value)
    bad.write_text(f"image,K,bbox\n{root}/photos/p0.png,\"600,600\",\"1,2,3,4\"\n")
    with pytest.raises(ConfigError, match="K needs 4 values"):
        read_manifest(bad)
    with pytest.raises(ConfigError, match="no box for the images"):
        folder_items(root / "photos", "600,600,320,240")
    assert len(folder_items(root / "photos", "600,600,320,240", masks=root / "masks")) == 3


def test_photos_of_one_assembly_are_named_in_the_manifest_or_by_the_folder(batch_inputs, tmp_path, capsys):
    """An 'assembly' column groups a manifest's photos (judged together by pixie inspect --batch); a folder batch
    with --one-assembly is one assembly named after the folder; without either no photo has one."""
    from pixie.app.cli import main

    root, *_ = batch_inputs
    m = tmp_path / "m.csv"
    m.write_text("image,K,bbox,assembly\n" + "".join(f"{root}/photos/p{n}.png,\"600,600,320,240\",\"1,2,30,40\",{a}\n"
                                                        for n, a in enumerate(["unit 7", "", "unit 7"])))
    assert [it.assembly for it in read_manifest(m)] == ["unit 7", None, "unit 7"]
    assert [it.assembly for it in read_manifest(root / "manifest.csv")] == [None] * 3
    one = folder_items(root / "photos", "600,600,320,240", masks=root / "masks", one_assembly=True)
    assert {it.assembly for it in one} == {"photos"}
    assert {it.assembly for it in folder_items(root / "photos", "600,600,320,240", masks=root / "masks")} == {None}
    assert main(["inspect", "--batch", str(m), "--refs", "x.npz", "-o", str(tmp_path / "o"), "--one-assembly"]) == 2
    assert "in a manifest, name each photo's assembly in an 'assembly' column" in capsys.readouterr().err
    assert main(["estimate", "--image", str(root / "photos" / "p0.png"), "--refs", "x.npz", "--one-assembly"]) == 2
    assert "one --image has one view" in capsys.readouterr().err


def _poses(out: Path) -> list:
    return [json.loads(line)["result"]["T_cam_from_obj"] for line in (out / "results.jsonl").read_text().splitlines()]


def _csv_without_time(path: Path) -> list[list[str]]:
    return [row[:-1] for row in csv.reader(path.read_text().splitlines())]


@pytest.mark.slow
def test_batch_resumes_and_reruns_on_config_change(batch_inputs, tmp_path):
    root, refs_path, cfg, _ = batch_inputs
    items = read_manifest(root / "manifest.csv")
    out = tmp_path / "out"
    s1 = run_batch(items, out, cfg, refs_path, max_items=1, show_progress=False, echo=lambda m: None)
    assert (s1.n_cached, s1.n_run) == (0, 1)
    assert len(_poses(out)) == 1  # outputs cover what is done so far
    s2 = run_batch(items, out, cfg, refs_path, show_progress=False, echo=lambda m: None)  # resume
    assert (s2.n_cached, s2.n_run) == (1, 2)
    s3 = run_batch(items, out, cfg, refs_path, show_progress=False, echo=lambda m: None)
    assert (s3.n_cached, s3.n_run) == (3, 0)

    fresh = tmp_path / "fresh"
    run_batch(items, fresh, cfg, refs_path, show_progress=False, echo=lambda m: None)
    assert _poses(out) == _poses(fresh)  # an interrupted + resumed run equals one run
    assert _csv_without_time(out / "results.csv") == _csv_without_time(fresh / "results.csv")
    rows = _csv_without_time(out / "results.csv")
    assert rows[0][:3] == ["scene_id", "im_id", "obj_id"] and [r[1] for r in rows[1:]] == ["10", "11", "12"]
    recs = [json.loads(line) for line in (out / "results.jsonl").read_text().splitlines()]
    assert all((out / r["overlay"]).is_file() for r in recs)
    html = (out / "index.html").read_text()
    assert all(r["overlay"] in html for r in recs) and "3 of 3 images" in html
    for r, it in zip(recs, items):
        assert r["image_sha256"] != r["key"] and r["K"] == it.K.tolist()

    changed = PixieConfig.from_dict(cfg.to_dict())
    changed.pose.reprojection_px = 4.0
    s4 = run_batch(items, out, changed, refs_path, show_progress=False, echo=lambda m: None)
    assert (s4.n_cached, s4.n_run) == (0, 3)  # a changed config does not reuse results


@pytest.mark.slow
def test_ray_batch_equals_serial(batch_inputs, tmp_path):
    ray = pytest.importorskip("ray")
    root, refs_path, cfg, _ = batch_inputs
    items = read_manifest(root / "manifest.csv")
    serial, dist = tmp_path / "serial", tmp_path / "ray"
    run_batch(items, serial, cfg, refs_path, threads=1, overlays=False, show_progress=False, echo=lambda m: None)
    ray.init(num_cpus=2, include_dashboard=False)
    try:
        s = run_batch(items, dist, cfg, refs_path, threads=1, use_ray=True, overlays=False, show_progress=False,
                      echo=lambda m: None)
    finally:
        ray.shutdown()
    assert s.workers == 2 and s.n_run == 3
    assert _poses(dist) == _poses(serial)  # bit-identical poses (JSON floats round-trip exactly)
    assert _csv_without_time(dist / "results.csv") == _csv_without_time(serial / "results.csv")


def test_estimator_refuses_no_box(batch_inputs):
    from pixie.pipeline.estimator import PoseEstimator
    from pixie.pipeline.query import load_image
    from pixie.references.store import load_reference_set

    root, refs_path, cfg, rows = batch_inputs
    est = PoseEstimator(load_reference_set(refs_path), cfg)
    with pytest.raises(ImageError, match=r"no object box: pass bbox=\(x, y, w, h\).*mask="):
        est.estimate(load_image(root / rows[0][0]), rows[0][1])
