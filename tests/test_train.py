"""Smoke tests of the synthetic data engine and the adapter fine-tuning (tiny, CPU, a few seconds)."""

from __future__ import annotations

import numpy as np
import pytest

from pixie.synth.pairs import PairConfig, make_pair
from pixie.synth.parts import FAMILIES, build_part

TINY = PairConfig(size=128, n_distractors=(1, 2))


@pytest.mark.parametrize("family", FAMILIES)
def test_parts_are_valid_meshes(family):
    m = build_part(family, 3)
    assert len(m.faces) > 4 and np.isfinite(m.vertices).all()
    assert 20.0 < m.diameter < 500.0
    assert np.allclose(m.center, 0.0, atol=1e-6)


def test_pair_is_deterministic():
    a, b = make_pair(5, TINY), make_pair(5, TINY)
    assert np.array_equal(a.query, b.query)
    for e in a.refs:
        assert np.array_equal(a.refs[e], b.refs[e])
    assert np.allclose(a.ref_T, b.ref_T) and np.allclose(a.query_K, b.query_K)
    c = make_pair(6, TINY)
    assert not np.array_equal(a.query, c.query)


def test_gt_correspondences_reproject():
    p = make_pair(2, TINY)
    ys, xs = np.nonzero(p.query_mask)
    assert len(xs) > 50
    kp = np.stack([xs, ys], 1).astype(float)
    # query XYZ reprojects onto its own pixel with the query crop's K and pose
    X = p.query_xyz[ys, xs].astype(np.float64)
    Xc = X @ p.query_T[:3, :3].T + p.query_T[:3, 3]
    uv = Xc[:, :2] / Xc[:, 2:] * [p.query_K[0, 0], p.query_K[1, 1]] + p.query_K[:2, 2]
    assert np.abs(uv - kp).max() < 0.6
    # valid correspondences land on reference pixels showing the same surface point
    r_uv, valid = p.correspond(kp)
    assert valid.mean() > 0.3
    from pixie.geometry.camera import backproject, invert_T

    ri = np.rint(r_uv[valid]).astype(int)
    z = p.ref_depth[ri[:, 1], ri[:, 0]].astype(np.float64)
    Xr = backproject(p.ref_K, ri.astype(np.float64), z)
    Ti = invert_T(p.ref_T)
    Xo = Xr @ Ti[:3, :3].T + Ti[:3, 3]
    err = np.linalg.norm(Xo - X[valid], axis=1)
    assert np.median(err) < 0.01 * p.mesh.diameter
    # and back: reference -> query -> reference lands within ~1 px
    q_uv, ok = p.correspond_ref(r_uv[valid])
    assert ok.mean() > 0.8
    assert np.median(np.linalg.norm(q_uv[ok] - kp[valid][ok], axis=1)) < 1.0


def test_finetune_steps_reduce_loss(tmp_path):
    torch = pytest.importorskip("torch")
    from pixie.errors import WeightsError
    from pixie.train.finetune import TrainConfig, build_cache, load_cache, load_checkpoint, pair_loss, train

    try:
        paths = build_cache([11, 12], tmp_path / "cache", PairConfig(size=160, n_distractors=(1, 1)), log=None)
    except WeightsError:
        pytest.skip("ALIKED weights not available")
    data = load_cache(paths)
    assert all(d["q_valid"].sum() > 0 for d in data)
    cfg = TrainConfig(steps=30, batch_pairs=2, lr=3e-3, eval_every=30, ckpt_every=15, window=48.0)
    model, hist = train(data, data, cfg, run_dir=tmp_path / "run", log=lambda *_: None)
    from pixie.matching.adapter import DescriptorAdapter

    t = torch.tensor(cfg.init_temp)
    with torch.no_grad():
        before = np.mean([float(pair_loss(DescriptorAdapter(), d, t, 48.0)) for d in data])
        after = np.mean([float(pair_loss(model, d, t, 48.0)) for d in data])
    assert after < before
    ck = load_checkpoint(tmp_path / "run" / "last.pt")
    assert ck["step"] == 30 and "optimizer" in ck
    # resuming a finished run does no more steps and returns the same weights
    model2, _ = train(data, data, cfg, run_dir=tmp_path / "run", log=lambda *_: None)
    for a, b in zip(model.state_dict().values(), model2.state_dict().values()):
        assert torch.equal(a, b)


def test_finetuned_matcher_is_registered():
    pytest.importorskip("torch")
    from pixie.errors import WeightsError
    from pixie.matching import available_matchers, get_matcher

    if "aliked-ft-nn" not in available_matchers():
        pytest.skip("shipped adapter or kornia ALIKED missing")
    try:
        m = get_matcher("aliked-ft-nn", allow_download=False, window=48.0, grid=8)
    except WeightsError:
        pytest.skip("ALIKED weights not available")
    rng = np.random.default_rng(0)
    img = (rng.random((96, 96, 3)) * 255).astype(np.uint8)
    mask = np.zeros((96, 96), bool)
    mask[20:80, 20:80] = True
    f = m.extract(img, mask)
    g = np.asarray(f.keypoints)
    assert len(f) >= 49  # the 8 px grid inside the 60x60 mask at least
    assert np.all((g >= 19.5) & (g <= 80.5))
    assert np.allclose(np.linalg.norm(f.descriptors, axis=1), 1.0, atol=1e-4)
    q = m.extract(img)
    assert len(m.match(q, f)) >= 0
