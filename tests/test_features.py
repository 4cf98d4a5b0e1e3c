"""The keypoint data contract (pixie.features): validation and the packed storage round trip."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from pixie.errors import ReferenceSetError
from pixie.features import Features, pack_features, unpack_features


def _random_features(rng: np.random.Generator, n: int, dim: int = 32, size: int = 128) -> Features:
    desc = rng.normal(size=(n, dim)).astype(np.float32)
    desc /= np.linalg.norm(desc, axis=1, keepdims=True)
    return Features(rng.uniform(0, size, (n, 2)), desc, rng.uniform(size=n), (size, size))


# ------------------------------------------------------------------------------------------------ records


def test_features_coerce_and_validate() -> None:
    f = Features(np.zeros((3, 2), np.float64), np.ones((3, 8), np.float16), [1, 2, 3], (10, 20))
    assert f.keypoints.dtype == np.float32 and f.descriptors.dtype == np.float32 and f.scores.dtype == np.float32
    assert len(f) == 3 and f.dim == 8 and f.image_size == (10, 20)
    with pytest.raises(ValueError):
        Features(np.zeros((3, 3)), np.ones((3, 8)), np.ones(3), (10, 20))
    with pytest.raises(ValueError):
        Features(np.zeros((3, 2)), np.ones((2, 8)), np.ones(3), (10, 20))


def test_pack_unpack_round_trip() -> None:
    rng = np.random.default_rng(0)
    feats = [_random_features(rng, n) for n in (5, 0, 17, 1)]
    packed = pack_features(feats)
    assert packed["feat_descriptors"].dtype == np.float16
    assert packed["feat_offsets"].tolist() == [0, 5, 5, 22, 23]
    back = unpack_features(packed)
    assert len(back) == len(feats)
    for a, b in zip(feats, back):
        assert np.array_equal(a.keypoints, b.keypoints)
        assert np.array_equal(a.scores, b.scores)
        assert np.array_equal(a.descriptors.astype(np.float16).astype(np.float32), b.descriptors)
        assert b.descriptors.dtype == np.float32 and a.image_size == b.image_size
    single = Features.from_arrays(feats[2].to_arrays("x_"), "x_")
    assert np.array_equal(single.keypoints, feats[2].keypoints) and single.image_size == feats[2].image_size
    assert unpack_features(pack_features([])) == []


def test_pack_round_trip_through_npz(tmp_path: Path) -> None:
    rng = np.random.default_rng(1)
    feats = [_random_features(rng, n) for n in (4, 9)]
    np.savez(tmp_path / "refs.npz", **pack_features(feats), other=np.arange(3))
    with np.load(tmp_path / "refs.npz") as data:
        back = unpack_features(data)
    assert [len(f) for f in back] == [4, 9]


def test_unpack_rejects_corrupt_arrays() -> None:
    rng = np.random.default_rng(2)
    packed = pack_features([_random_features(rng, 4), _random_features(rng, 3)])
    broken = dict(packed, feat_offsets=np.array([0, 4, 9]))
    with pytest.raises(ReferenceSetError):
        unpack_features(broken)
    del packed["feat_scores"]
    with pytest.raises(ReferenceSetError, match="feat_scores"):
        unpack_features(packed)
