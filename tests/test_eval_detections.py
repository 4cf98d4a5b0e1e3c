"""pixie.eval.detections: BOP-format external detections (boxes, COCO RLE masks) and `pixie run --detections`."""

from __future__ import annotations

import json

import numpy as np
import pytest

from pixie.app.runner import run_dataset
from pixie.errors import DatasetError
from pixie.eval.datasets import BopDataset
from pixie.eval.detections import load_detections, rle_decode, rle_encode
from pixie.geometry.render import Renderer

from conftest import SYN_H, SYN_K, SYN_W, assert_cli_error, run_cli, tiny_run_config

pytestmark = pytest.mark.usefixtures("one_torch_thread")


def coco_string(counts: list[int]) -> str:
    """COCO's compressed counts (pycocotools ``rleToString``), written from its description, for the decoder's test:
    each count after the second as the difference to the one two before, 5 bits per character from '0', bit 0x20
    = more follows, the last group's bit 0x10 = the sign."""
    out = []
    for i, x in enumerate(counts):
        if i > 2:
            x -= counts[i - 2]
        more = True
        while more:
            c = x & 0x1F
            x >>= 5
            more = (x != -1) if (c & 0x10) else (x != 0)
            out.append(chr(c + (0x20 if more else 0) + 48))
    return "".join(out)


def test_rle_round_trips_and_hand_checked_runs():
    m = np.array([[0, 1, 1], [0, 1, 0]], bool)  # column-major: 0 0 | 1 1 | 1 0 -> runs 2 zeros, 3 ones, 1 zero
    assert rle_encode(m) == {"size": [2, 3], "counts": [2, 3, 1]}
    np.testing.assert_array_equal(rle_decode({"size": [2, 3], "counts": [2, 3, 1]}), m)
    assert rle_encode(np.ones((2, 2), bool))["counts"] == [0, 4]  # a mask starting with the object: empty 0-run
    rng = np.random.default_rng(0)
    for shape in ((7, 5), (31, 64), (1, 1)):
        mask = rng.random(shape) > 0.6
        rle = rle_encode(mask)
        np.testing.assert_array_equal(rle_decode(rle), mask)
        # COCO's compressed string gives the same mask (large counts and negative differences included)
        np.testing.assert_array_equal(rle_decode({"size": rle["size"], "counts": coco_string(rle["counts"])}), mask)
    big = np.zeros((480, 640), bool)
    big[100:300, 200:260] = True
    rle = rle_encode(big)
    np.testing.assert_array_equal(rle_decode({"size": [480, 640], "counts": coco_string(rle["counts"]).encode()}), big)


def write(tmp_path, entries, name="dets.json"):
    p = tmp_path / name
    p.write_text(json.dumps(entries))
    return p


def test_detections_sorted_by_score_per_target(tmp_path):
    e = [{"scene_id": 1, "image_id": 0, "category_id": 1, "score": s, "bbox": [10, 20, 30, 40], "time": 0.5}
         for s in (0.2, 0.9, 0.5)]
    e.append({"scene_id": 1, "image_id": 0, "category_id": 2, "score": 0.3, "bbox": [0, 0, 5, 5]})
    dets = load_detections(write(tmp_path, e))
    assert len(dets) == 4
    assert [d.score for d in dets.for_target(1, 0, 1, n=2)] == [0.9, 0.5]
    assert dets.for_target(1, 0, 3, n=1) == [] and dets.for_target(2, 0, 1, n=1) == []
    np.testing.assert_array_equal(dets.for_target(1, 0, 1)[0].box_xywh, [10, 20, 31, 41])  # BOP w = last - first


def test_a_segmentation_gives_the_mask_and_its_own_box(tmp_path):
    m = np.zeros((40, 60), bool)
    m[5:15, 20:50] = True
    e = [{"scene_id": 1, "image_id": 0, "category_id": 1, "score": 1.0, "bbox": [0, 0, 1, 1],
          "segmentation": {"size": [40, 60], "counts": coco_string(rle_encode(m)["counts"])}}]
    d = load_detections(write(tmp_path, e)).for_target(1, 0, 1)[0]
    np.testing.assert_array_equal(d.mask(), m)
    np.testing.assert_array_equal(d.box_xywh, [20, 5, 30, 10])


@pytest.mark.parametrize("entry, needle", [
    ({"scene_id": 1, "image_id": 0, "score": 1.0, "bbox": [0, 0, 1, 1]}, "missing category_id"),
    ({"scene_id": 1, "image_id": 0, "category_id": 1, "score": float("nan"), "bbox": [0, 0, 1, 1]}, "score"),
    ({"scene_id": 1, "image_id": 0, "category_id": 1.5, "score": 1.0, "bbox": [0, 0, 1, 1]}, "category_id"),
    ({"scene_id": 1, "image_id": 0, "category_id": 1, "score": 1.0, "bbox": [0, 0, 1]}, "bbox must be 4 numbers"),
    ({"scene_id": 1, "image_id": 0, "category_id": 1, "score": 1.0, "bbox": [0, 0, -3, 1]}, ">= 0"),
    ({"scene_id": 1, "image_id": 0, "category_id": 1, "score": 1.0, "bbox": [0, 0, 1, 1],
      "segmentation": {"size": [4, 4], "counts": [3, 2]}}, "cover 5 pixels"),
    ({"scene_id": 1, "image_id": 0, "category_id": 1, "score": 1.0, "bbox": [0, 0, 1, 1],
      "segmentation": {"size": [2, 2], "counts": [4]}}, "empty"),
    ({"scene_id": 1, "image_id": 0, "category_id": 1, "score": 1.0, "bbox": [0, 0, 1, 1],
      "segmentation": {"size": [2, 2], "counts": "~~"}}, "segmentation"),
    ("not a dict", "is an object"),
])
def test_malformed_entries_are_named(tmp_path, entry, needle):
    good = {"scene_id": 1, "image_id": 0, "category_id": 1, "score": 1.0, "bbox": [0, 0, 1, 1]}
    with pytest.raises(DatasetError, match="entry 1") as err:
        load_detections(write(tmp_path, [good, entry]))
    assert needle in str(err.value) and "dets.json" in str(err.value)


def test_unreadable_files_are_named(tmp_path):
    with pytest.raises(DatasetError, match="not found"):
        load_detections(tmp_path / "none.json")
    (tmp_path / "bad.json").write_text("[{")
    with pytest.raises(DatasetError, match="not JSON"):
        load_detections(tmp_path / "bad.json")
    with pytest.raises(DatasetError, match="JSON list"):
        load_detections(write(tmp_path, {"scene_id": 1}))


def test_run_with_detections_uses_them_and_counts_a_missing_one_as_a_miss(synthetic_bop, tmp_path):
    """Detections equal to the GT boxes give the GT-box run's poses; a mask detection is estimated from the mask;
    a target with fewer detections than instances gets a failed estimate naming the shortfall."""
    root, meta = synthetic_bop
    ds = BopDataset(root)
    refs_dir = tmp_path / "refs"
    gt_csv = run_dataset(root, tmp_path / "gt", tiny_run_config(), refs_dir=refs_dir, echo=lambda m: None,
                         show_progress=False)
    gt_rec = {tuple(json.loads(li)["key"]): json.loads(li) for li in (tmp_path / "gt" / "per_target.jsonl").open()}
    entries = []
    for g in ds.instances(1, 0):  # image 0: the box by its bbox, the cylinder by its mask
        e = {"scene_id": 1, "image_id": 0, "category_id": g.obj_id, "score": 0.9, "bbox": list(g.bbox_visib)}
        if g.obj_id == 2:
            T = dict(meta["scenes"][0])[2]
            full = Renderer(meta["meshes"][2]).render(T, SYN_K, SYN_H, SYN_W).mask
            e["segmentation"] = rle_encode(full)
        entries.append(e)
    g1 = max((g for g in ds.instances(1, 1) if g.obj_id == 1), key=lambda g: g.visib_fract)
    entries.append({"scene_id": 1, "image_id": 1, "category_id": 1, "score": 0.8, "bbox": list(g1.bbox_visib)})
    lines: list[str] = []
    run_dataset(root, tmp_path / "det", tiny_run_config(), refs_dir=refs_dir, echo=lines.append, show_progress=False,
                detections=write(tmp_path, entries))
    assert any("3 detections" in li for li in lines)
    rec = {tuple(json.loads(li)["key"]): json.loads(li) for li in (tmp_path / "det" / "per_target.jsonl").open()}
    box = rec[(1, 0, 1)]["estimates"][0]
    assert box["detection"]["mask"] is False and box["detection"]["score"] == 0.9
    assert box["T"] == gt_rec[(1, 0, 1)]["estimates"][0]["T"]  # the same crop, the same pose
    assert rec[(1, 0, 2)]["estimates"][0]["detection"]["mask"] is True
    two = rec[(1, 1, 1)]["estimates"]
    assert len(two) == 2 and two[0]["T"] == gt_rec[(1, 1, 1)]["estimates"][0]["T"]
    assert two[1]["T"] is None and two[1]["failed"] and "1 detection(s) of it for 2 instance(s)" in two[1]["timings"]["error"]
    assert gt_csv.read_text().splitlines()[0] == (tmp_path / "det" / "results.csv").read_text().splitlines()[0]


def test_cli_refuses_a_malformed_detections_file_before_any_work(synthetic_bop, tmp_path):
    root, _ = synthetic_bop
    bad = write(tmp_path, [{"scene_id": 1, "image_id": 0, "category_id": 1, "score": 1.0, "bbox": "0,0,1,1"}])
    res = run_cli("run", str(root), "-o", str(tmp_path / "out"), "--detections", str(bad))
    assert_cli_error(res, "entry 0", "bbox must be 4 numbers")
    assert not (tmp_path / "out" / "per_target.jsonl").exists()
