"""The one-call API: pixie.estimate_pose from files (mesh, image, K string, box), cached references, no-box refusal."""

from __future__ import annotations

import numpy as np
import pytest

import pixie
from pixie.config import PixieConfig, RefsConfig

pytestmark = pytest.mark.usefixtures("one_torch_thread")


@pytest.fixture(scope="module")
def part_files(tmp_path_factory):
    import trimesh

    from pixie.app.demo import generated_part, generated_photo
    from pixie.pipeline.query import bbox_from_mask
    from pixie.geometry.render import Renderer
    from pixie.viz import save_png

    root = tmp_path_factory.mktemp("api")
    mesh = generated_part()
    # the part written in metres: units='auto' must read it back in mm
    trimesh.Trimesh(mesh.vertices / 1000.0, mesh.faces, process=False).export(root / "part.stl")
    img, K, T = generated_photo(mesh, seed=3)
    save_png(root / "photo.png", img)
    box = bbox_from_mask(Renderer(mesh).render(T, K, *img.shape[:2]).mask)
    return root, mesh, K, T, box


def small_config() -> PixieConfig:
    cfg = PixieConfig.from_preset("default")
    cfg.refs = RefsConfig(n_fibonacci=20, rotations=8, size=128, encodings=["shade3_edges"], feature_rolls="first")
    return cfg


def test_public_names_at_the_root():
    for name in ("estimate_pose", "load_mesh", "build_reference_set", "load_reference_set", "PoseEstimator",
                 "PixieConfig", "load_image", "PixieError", "__version__"):
        assert hasattr(pixie, name), name


@pytest.mark.slow
def test_estimate_pose_from_files(part_files, tmp_path, capsys):
    root, mesh, K, T_true, box = part_files
    K_text = f"{K[0, 0]},{K[1, 1]},{K[0, 2]},{K[1, 2]}"
    res = pixie.estimate_pose(root / "part.stl", root / "photo.png", K_text, bbox=box, config=small_config(),
                              cache_dir=tmp_path / "refs")
    err = capsys.readouterr().err  # the first call says what takes its time: the units and the one-time build
    assert "read in metres" in err and "building the references of part once" in err
    assert res.T_cam_from_obj is not None and not res.failed
    # read in mm from a metre file: the translation is hundreds of mm, as in the photo
    assert abs(res.T_cam_from_obj[2, 3] - T_true[2, 3]) < 0.2 * T_true[2, 3]
    cached = list((tmp_path / "refs").glob("*.npz"))
    assert len(cached) == 1
    stamp = cached[0].stat().st_mtime_ns
    again = pixie.estimate_pose(root / "part.stl", pixie.load_image(root / "photo.png"), K, bbox=box,
                                config=small_config(), cache_dir=tmp_path / "refs")
    assert cached[0].stat().st_mtime_ns == stamp  # built once
    assert np.array_equal(again.T_cam_from_obj, res.T_cam_from_obj)
    assert "building" not in capsys.readouterr().err
    quiet = pixie.estimate_pose(root / "part.stl", root / "photo.png", K_text, bbox=box, config=small_config(),
                                cache_dir=tmp_path / "refs2", quiet=True)
    assert capsys.readouterr().err == "" and np.allclose(quiet.T_cam_from_obj, res.T_cam_from_obj, atol=1e-6)
    d = res.to_dict()
    assert d["units"] == "mm" and d["K"] == np.asarray(K).tolist() and d["mesh_sha256"]
    assert d["mesh"]["file_units"] == "m" and d["mesh"]["scale_to_mm"] == 1000.0  # read in metres, scaled x 1000
    assert d["source"] == res.hypotheses[0].source and "view" in d["view_note"]
    f = res.hypotheses[0].fit  # the pose's aligned edge fit (null when the alignment did not score it)
    assert d["fit"] == (float(f) if np.isfinite(f) else None) and "aligned edge fit" in d["fit_note"]
    # from a prior: the estimate refined again, no box needed, no search
    prior = pixie.estimate_pose(root / "part.stl", root / "photo.png", K_text, config=small_config(),
                                cache_dir=tmp_path / "refs", init_pose=res.T_cam_from_obj, quiet=True)
    assert prior.hypotheses[0].source == "prior" and "match" not in prior.timings
    assert np.linalg.norm(prior.T_cam_from_obj[:3, 3] - res.T_cam_from_obj[:3, 3]) < 0.02 * T_true[2, 3]
    # the alignment is on: the confidence is the calibrated probability (the ratio stays per hypothesis)
    assert res.confidence_calibrated and 0.0 <= d["confidence"] <= 1.0
    assert "probability" in d["confidence_note"].lower()
    assert 0.5 <= d["hypotheses"][0]["confidence"] <= 1.0


def test_estimate_pose_refuses_without_a_box(part_files):
    root, *_ = part_files
    with pytest.raises(pixie.PixieError, match=r"no object box: pass bbox=\(x, y, w, h\).*or mask="):
        pixie.estimate_pose(root / "part.stl", root / "photo.png", "600,600,320,240")
