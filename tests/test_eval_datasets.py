"""BOP dataset reader, symmetry sets and results CSV I/O."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from pixie.eval.datasets import (
    BopDataset,
    PoseEstimate,
    box_from_bop,
    gt_as_estimates,
    is_symmetric,
    read_results_csv,
    symmetry_transforms,
    write_results_csv,
)
from pixie.errors import DatasetError, ImageError
from pixie.pipeline.query import check_bbox

LMO = Path(__file__).resolve().parents[1].parent / "shared/data/lmo_dev/lmo"
needs_lmo = pytest.mark.skipif(
    not (LMO / "test_targets_bop19.json").is_file(),
    reason=f"LM-O dev data not found at {LMO} (see shared/data/lmo_dev/README.md)",
)


# ---------------------------------------------------------------------------- LM-O reader


@needs_lmo
def test_lmo_targets_and_images():
    ds = BopDataset(LMO)
    tg = ds.targets()
    assert len(tg) == 716
    assert {t.scene_id for t in tg} == {2}
    assert len({(t.scene_id, t.im_id) for t in tg}) == 97
    assert all(t.inst_count == 1 for t in tg)
    assert sorted({t.obj_id for t in tg}) == [1, 5, 6, 8, 9, 10, 11, 12]
    assert ds.scene_ids() == [2]


@needs_lmo
def test_lmo_instances_camera_and_images():
    ds = BopDataset(LMO)
    insts = ds.instances(2, 3)
    assert [g.obj_id for g in insts][:2] == [1, 5]
    g = insts[0]
    assert g.gt_id == 0
    np.testing.assert_allclose(g.T_cam_from_obj[:3, 3], [161.68945982, -113.74032768, 1112.83112737])
    np.testing.assert_allclose(g.T_cam_from_obj[0, :3], [0.87547542, 0.47867615, -0.06858282])
    assert g.bbox_obj == [388, 164, 34, 45] and g.bbox_visib == [401, 164, 20, 33]
    assert g.box_visib.tolist() == [401, 164, 21, 34]  # pixie boxes count pixels; BOP stores last - first
    assert g.visib_fract == pytest.approx(0.19964507542147295)
    assert g.px_count_visib == 225
    cam = ds.camera(2, 3)
    np.testing.assert_allclose(cam.K, [[572.4114, 0, 325.2611], [0, 573.57043, 242.04899], [0, 0, 1]])
    assert cam.depth_scale == 1.0
    assert ds.image_path(2, 3).name == "000003.png"
    rgb = ds.load_rgb(2, 3)
    assert rgb.shape == (480, 640, 3) and rgb.dtype == np.uint8
    assert ds.image_size(2, 3) == (480, 640)
    # LM-O dev has neither depth nor masks.
    assert ds.load_depth(2, 3) is None and not ds.has_depth()
    assert ds.load_mask_visib(2, 3, 0) is None


@needs_lmo
def test_lmo_models_and_info():
    ds = BopDataset(LMO)
    assert ds.model_path(1).parent.name == "models"
    assert ds.model_path(1, eval=True).parent.name == "models_eval"
    assert ds.model_info(8)["diameter"] == pytest.approx(261.472)
    assert is_symmetric(ds.model_info(10)) and is_symmetric(ds.model_info(11))
    assert not is_symmetric(ds.model_info(1))
    assert ds.obj_ids() == [1, 5, 6, 8, 9, 10, 11, 12]
    with pytest.raises(DatasetError, match="obj_000002.ply"):
        ds.model_path(2)
    with pytest.raises(DatasetError, match="no entry for object 2"):
        ds.model_info(2)


@needs_lmo
def test_gt_as_estimates_matches_targets():
    ds = BopDataset(LMO)
    ests = gt_as_estimates(ds)
    assert len(ests) == 716
    g = ds.instances(2, 3)[0]
    assert np.array_equal(ests[0].T_cam_from_obj, g.T_cam_from_obj)


# ---------------------------------------------------------------------------- symmetries


def test_symmetries_asymmetric_is_identity():
    S = symmetry_transforms({"diameter": 10.0})
    assert S.shape == (1, 4, 4) and np.array_equal(S[0], np.eye(4))


@needs_lmo
def test_discrete_symmetry_maps_model_onto_itself():
    """obj 10 (eggbox): the declared symmetry moves every vertex onto the surface again."""
    from scipy.spatial import cKDTree

    from pixie.geometry.mesh import load_mesh

    ds = BopDataset(LMO)
    info = ds.model_info(10, eval=True)
    S = symmetry_transforms(info)
    assert S.shape == (2, 4, 4)
    assert np.array_equal(S[0], np.eye(4))
    np.testing.assert_allclose(S[1].ravel(), info["symmetries_discrete"][0])
    v = load_mesh(ds.model_path(10, eval=True)).vertices
    moved = v @ S[1][:3, :3].T + S[1][:3, 3]
    d, _ = cKDTree(v).query(moved)
    assert d.mean() < 0.02 * info["diameter"]  # maps onto itself (up to modelling noise)
    assert np.linalg.norm(moved - v, axis=1).max() > 0.5 * info["diameter"]  # but moves a lot


def test_continuous_symmetry_discretisation():
    diameter = 100.0
    info = {"diameter": diameter, "symmetries_continuous": [{"axis": [0, 0, 1], "offset": [5.0, -3.0, 0.0]}]}
    step = 0.01
    S = symmetry_transforms(info, step)
    n = math.ceil(math.pi / step)
    assert len(S) == n == 315
    assert np.array_equal(S[0], np.eye(4))
    # Every element is a rotation about the axis through the offset: the offset is fixed.
    off = np.array([5.0, -3.0, 0.0])
    np.testing.assert_allclose(S[:, :3, :3] @ off + S[:, :3, 3], np.broadcast_to(off, (n, 3)), atol=1e-9)
    # A point at the largest possible distance from the axis (diameter / 2) moves ≤ step·diameter
    # between consecutive samples.
    p = off + np.array([diameter / 2, 0.0, 7.0])
    q = S[:, :3, :3] @ p + S[:, :3, 3]
    hops = np.linalg.norm(np.diff(np.vstack([q, q[:1]]), axis=0), axis=1)
    assert hops.max() <= step * diameter + 1e-9
    assert hops.max() > 0.9 * step * diameter  # not finer than needed
    # Combined with a discrete flip: product set, identity first.
    flip = np.diag([1.0, -1.0, -1.0, 1.0]).ravel().tolist()
    S2 = symmetry_transforms({**info, "symmetries_discrete": [flip]}, step)
    assert len(S2) == 2 * n
    np.testing.assert_allclose(S2[n], S[0] @ np.diag([1.0, -1.0, -1.0, 1.0]))


# ---------------------------------------------------------------------------- errors


def _mini_dataset(root: Path) -> Path:
    sc = root / "test" / "000001"
    (sc / "rgb").mkdir(parents=True)
    (root / "models").mkdir()
    (root / "test_targets_bop19.json").write_text(json.dumps([{"scene_id": 1, "im_id": 0, "obj_id": 1, "inst_count": 1}]))
    (root / "models" / "models_info.json").write_text(json.dumps({"1": {"diameter": 10.0}}))
    gt = {"0": [{"obj_id": 1, "cam_R_m2c": np.eye(3).ravel().tolist(), "cam_t_m2c": [0, 0, 500]}]}
    (sc / "scene_gt.json").write_text(json.dumps(gt))
    (sc / "scene_camera.json").write_text(json.dumps({"0": {"cam_K": [500, 0, 32, 0, 500, 24, 0, 0, 1], "depth_scale": 0.1}}))
    return root


def test_missing_and_malformed_files_name_the_file(tmp_path):
    with pytest.raises(DatasetError, match="dataset folder not found"):
        BopDataset(tmp_path / "nope")
    root = _mini_dataset(tmp_path / "ds")
    ds = BopDataset(root)
    assert ds.instances(1, 0)[0].visib_fract is None  # no scene_gt_info.json is fine
    assert ds.camera(1, 0).depth_scale == 0.1
    with pytest.raises(DatasetError, match="no image for scene 1 image 0"):
        ds.image_path(1, 0)
    with pytest.raises(DatasetError, match="scene folder not found"):
        ds.instances(7, 0)
    with pytest.raises(DatasetError, match="no entry for image 5"):
        ds.instances(1, 5)

    (root / "test" / "000001" / "scene_gt.json").write_text('{"0": [ {"obj_id": 1,, } ]}')
    with pytest.raises(DatasetError, match=r"malformed JSON in .*scene_gt\.json"):
        BopDataset(root).instances(1, 0)

    (root / "test" / "000001" / "scene_gt.json").write_text(json.dumps({"0": [{"obj_id": 1, "cam_R_m2c": [1, 0, 0], "cam_t_m2c": [0, 0, 1]}]}))
    with pytest.raises(DatasetError, match=r"scene_gt\.json: image 0 instance 0 cam_R_m2c has 3 values"):
        BopDataset(root).instances(1, 0)

    (root / "test_targets_bop19.json").write_text(json.dumps([{"scene_id": 1, "im_id": 0}]))
    with pytest.raises(DatasetError, match=r"test_targets_bop19\.json: target #0 is malformed"):
        BopDataset(root).targets()

    (root / "models" / "models_info.json").write_text(json.dumps({"1": {"size_x": 3}}))
    with pytest.raises(DatasetError, match=r"models_info\.json: object 1 has no diameter"):
        BopDataset(root).model_info(1)

    (root / "test" / "000001" / "scene_camera.json").unlink()
    with pytest.raises(DatasetError, match=r"missing file: .*scene_camera\.json"):
        BopDataset(root).camera(1, 0)


def test_depth_and_mask_loading(tmp_path):
    import cv2

    root = _mini_dataset(tmp_path / "ds")
    sc = root / "test" / "000001"
    (sc / "depth").mkdir()
    (sc / "mask_visib").mkdir()
    raw = np.zeros((48, 64), np.uint16)
    raw[10:20, 10:30] = 5000  # 500.0 mm at depth_scale 0.1
    cv2.imwrite(str(sc / "depth" / "000000.png"), raw)
    mask = np.zeros((48, 64), np.uint8)
    mask[10:20, 10:30] = 255
    cv2.imwrite(str(sc / "mask_visib" / "000000_000000.png"), mask)
    cv2.imwrite(str(sc / "rgb" / "000000.png"), np.zeros((48, 64, 3), np.uint8))
    ds = BopDataset(root)
    d = ds.load_depth(1, 0)
    assert d.dtype == np.float32 and d[15, 15] == pytest.approx(500.0) and d[0, 0] == 0
    assert ds.has_depth()
    m = ds.load_mask_visib(1, 0, 0)
    assert m.sum() == 200
    assert ds.image_size(1, 0) == (48, 64)


# ---------------------------------------------------------------------------- results CSV


def _row(R="1 0 0 0 1 0 0 0 1", t="1 2 3", extra=""):
    return f"2,3,1,0.9,{R},{t},0.5{extra}"


def test_results_roundtrip(tmp_path):
    rng = np.random.default_rng(1)
    from scipy.spatial.transform import Rotation

    ests = []
    for i in range(5):
        T = np.eye(4)
        T[:3, :3] = Rotation.from_rotvec(rng.normal(size=3)).as_matrix()
        T[:3, 3] = rng.normal(0, 300, 3)
        ests.append(PoseEstimate(2, i, 5, float(rng.random()), T, 0.25))
    p = write_results_csv(tmp_path / "r.csv", ests)
    assert p.read_text().splitlines()[0] == "scene_id,im_id,obj_id,score,R,t,time"
    back = read_results_csv(p)
    assert len(back) == 5
    for a, b in zip(ests, back):
        assert (a.scene_id, a.im_id, a.obj_id) == (b.scene_id, b.im_id, b.obj_id)
        assert b.score == pytest.approx(a.score) and b.time == pytest.approx(0.25)
        np.testing.assert_allclose(b.T_cam_from_obj, a.T_cam_from_obj, atol=1e-6)


@pytest.mark.parametrize(
    "line, message",
    [
        ("2,3,1,0.9,1 0 0 0 1 0 0 0 1,1 2 3", "line 2: 6 comma-separated columns, expected 7"),
        (_row(extra=",7"), "line 2: 8 comma-separated columns"),
        (_row(R="1 0 0 0 1 0 0 0"), "line 2: R has 8 values, expected 9"),
        (_row(t="1 2"), "line 2: t has 2 values, expected 3"),
        (_row(R="1 0 0 0 2 0 0 0 1"), "line 2: R is not orthonormal"),
        (_row(R="1 0 0 0 1 0 0 0 -1"), "line 2: R is a reflection"),
        (_row(t="1 nan 3"), "line 2: t has NaN/inf values"),
        ("2,3,1,nan,1 0 0 0 1 0 0 0 1,1 2 3,0.5", "line 2: score has NaN/inf"),
        ("2,x,1,0.9,1 0 0 0 1 0 0 0 1,1 2 3,0.5", "line 2: scene_id/im_id/obj_id must be integers"),
        (_row(t="1 2 abc"), "line 2: non-numeric value"),
    ],
)
def test_results_validation(tmp_path, line, message):
    p = tmp_path / "bad.csv"
    p.write_text("scene_id,im_id,obj_id,score,R,t,time\n" + line + "\n")
    with pytest.raises(DatasetError, match="bad.csv " + message.replace("(", r"\(").replace(")", r"\)")):
        read_results_csv(p)


def test_results_headerless_and_missing(tmp_path):
    p = tmp_path / "r.csv"
    p.write_text(_row() + "\n\n" + _row() + "\n")
    assert len(read_results_csv(p)) == 2
    with pytest.raises(DatasetError, match="results file not found"):
        read_results_csv(tmp_path / "none.csv")


def test_box_from_bop_counts_pixels_and_keeps_invisible_boxes_empty():
    """A 1-column BOP box (w = 0) covers one pixel; BOP's invisible-object box stays empty and is refused by name."""
    assert box_from_bop([10, 20, 0, 5]).tolist() == [10, 20, 1, 6]
    assert box_from_bop(None) is None
    empty = box_from_bop([-1, -1, -1, -1])
    assert empty.tolist() == [-1, -1, -1, -1]
    with pytest.raises(ImageError, match="empty crop"):
        check_bbox(empty, (480, 640))
    with pytest.raises(DatasetError, match=r"\[x, y, w, h\]"):
        box_from_bop([1, 2, 3])
