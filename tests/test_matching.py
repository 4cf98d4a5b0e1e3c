"""Mutual NN matching and every matcher backend on a real photo and its homography warp."""

from __future__ import annotations

import re
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from pixie.errors import ConfigError, ImageError, WeightsError
from pixie.matching import (
    Features,
    Matches,
    RefBank,
    SuperPointNet,
    available_matchers,
    build_lightglue,
    get_matcher,
    matched_keypoints,
    mutual_nn_match_many,
    remap_lightglue_state,
)
from pixie.weights import shared_root

SHARED = shared_root() or Path("/nonexistent-shared")  # $PIXIE_SHARED or ../shared
PHOTO = SHARED / "data" / "lmo_dev" / "lmo" / "test" / "000002" / "rgb" / "000003.png"

# A mild perspective warp of a 256 px crop (largest displacement about 20 px).
HOMOGRAPHY = np.array([[0.95, 0.08, 8.0], [-0.06, 1.0, 4.0], [1e-4, -5e-5, 1.0]])
CROP = 256


def _random_features(rng: np.random.Generator, n: int, dim: int = 32, size: int = 128) -> Features:
    desc = rng.normal(size=(n, dim)).astype(np.float32)
    desc /= np.linalg.norm(desc, axis=1, keepdims=True)
    return Features(rng.uniform(0, size, (n, 2)), desc, rng.uniform(size=n), (size, size))


# ------------------------------------------------------------------------------------------------ mutual NN


def _brute_force_mnn(
    q: Features, r: Features, window: float | None, ratio: float | None, min_sim: float | None
) -> set[tuple[int, int]]:
    """Reference implementation, one pair of images at a time, in float64 numpy."""
    if len(q) == 0 or len(r) == 0:
        return set()
    sim = q.descriptors.astype(np.float64) @ r.descriptors.astype(np.float64).T
    if window is not None:
        dist = np.linalg.norm(q.keypoints[:, None, :] - r.keypoints[None, :, :], axis=2)
        sim[dist >= window] = -np.inf
    out = set()
    for i in range(len(q)):
        order = np.argsort(-sim[i])
        j = int(order[0])
        if not np.isfinite(sim[i, j]) or int(np.argmax(sim[:, j])) != i:
            continue
        if min_sim is not None and sim[i, j] < min_sim:
            continue
        if ratio is not None and len(order) > 1 and np.isfinite(sim[i, order[1]]):
            d1, d2 = np.sqrt(max(2 - 2 * sim[i, j], 0)), np.sqrt(max(2 - 2 * sim[i, order[1]], 0))
            if not d1 < ratio * d2:
                continue
        out.add((i, j))
    return out


@pytest.mark.parametrize(
    ("window", "ratio", "min_sim"),
    [(None, None, None), (30.0, None, None), (30.0, 0.98, None), (None, None, 0.2), (12.0, None, 0.1), (12.0, 0.95, None)],
)
def test_mutual_nn_equals_brute_force(window: float | None, ratio: float | None, min_sim: float | None) -> None:
    rng = np.random.default_rng(3)
    q = _random_features(rng, 60)
    refs = [_random_features(rng, n) for n in (40, 0, 75, 1, 33)]
    # small chunks force several chunks with padding
    got = mutual_nn_match_many(q, refs, window=window, ratio=ratio, min_similarity=min_sim, chunk_elems=5000)
    assert len(got) == len(refs)
    total = 0
    for r, m in zip(refs, got):
        assert isinstance(m, Matches)
        assert set(zip(m.idx_q.tolist(), m.idx_r.tolist())) == _brute_force_mnn(q, r, window, ratio, min_sim)
        if len(m):
            expect = np.sum(q.descriptors[m.idx_q] * r.descriptors[m.idx_r], axis=1)
            assert np.allclose(m.scores, expect, atol=1e-5)
        total += len(m)
    assert total > 0


@pytest.mark.parametrize(("window", "ratio"), [(32.0, None), (10.0, 0.9)])
def test_banded_window_matching_equals_the_dense_products(window: float, ratio: float | None) -> None:
    """The CPU path computes only the row bands a window can reach; it returns the dense path's matches."""
    import torch

    from pixie.matching.base import RefBank
    from pixie.matching.mnn import _mnn_banded, _mnn_dense

    rng = np.random.default_rng(5)
    q = _random_features(rng, 300, dim=64, size=256)
    bank = RefBank([_random_features(rng, n, dim=64, size=256) for n in (200, 0, 150, 1, 250, 90)], torch.device("cpu"))
    args = (torch.from_numpy(q.descriptors), torch.from_numpy(q.keypoints.astype(np.float32)), bank, window, ratio, None, 20000)
    dense, banded = _mnn_dense(*args), _mnn_banded(*args)
    assert len(dense[0]) > 20
    for a, b in zip(dense[:3], banded[:3]):  # query, reference and keypoint indices
        assert torch.equal(a, b)
    assert torch.allclose(dense[3], banded[3], rtol=0, atol=1e-6)  # similarities: smaller products, same sums


def test_window_excludes_far_pairs() -> None:
    d = np.eye(4, dtype=np.float32)
    q = Features([[10, 10], [50, 50], [90, 90], [10, 90]], d, np.ones(4), (100, 100))
    # the same descriptors, displaced by 5, 30, 5 and 60 pixels
    r = Features([[13, 14], [80, 50], [95, 90], [70, 90]], d, np.ones(4), (100, 100))
    wide = mutual_nn_match_many(q, [r])[0]
    assert sorted(wide.idx_q.tolist()) == [0, 1, 2, 3]
    narrow = mutual_nn_match_many(q, [r], window=20.0)[0]
    assert sorted(zip(narrow.idx_q.tolist(), narrow.idx_r.tolist())) == [(0, 0), (2, 2)]
    pq, pr = matched_keypoints(q, r, narrow)
    assert np.all(np.linalg.norm(pq - pr, axis=1) < 20.0)


def test_match_many_with_bank_and_empty_inputs() -> None:
    rng = np.random.default_rng(4)
    q = _random_features(rng, 30)
    refs = [_random_features(rng, 25) for _ in range(3)]
    bank = RefBank(refs, torch.device("cpu"))
    a = mutual_nn_match_many(q, bank, window=40.0)
    b = mutual_nn_match_many(q, refs, window=40.0)
    for x, y in zip(a, b):
        assert np.array_equal(x.idx_q, y.idx_q) and np.array_equal(x.idx_r, y.idx_r)
    empty_q = Features.empty(32, (128, 128))
    assert [len(m) for m in mutual_nn_match_many(empty_q, refs)] == [0, 0, 0]
    assert mutual_nn_match_many(q, []) == []
    with pytest.raises(ValueError, match="-D"):
        mutual_nn_match_many(_random_features(rng, 5, dim=16), refs)


# ------------------------------------------------------------------------------------------------ registry


def test_registry_and_options() -> None:
    names = available_matchers()
    for name in ("aliked-nn", "disk-nn", "xfeat-nn", "sift-nn", "aliked-lg", "disk-lg", "xfeat-lighterglue",
                 "minima-sp-lg"):
        assert name in names
    with pytest.raises(ConfigError, match="unknown matcher"):
        get_matcher("no-such-matcher")
    with pytest.raises(ConfigError, match="window"):
        get_matcher("sift-nn", windw=3)
    with pytest.raises(ConfigError, match="ALIKED model"):
        get_matcher("aliked-nn", model="aliked-n99")


def test_missing_weights_raise(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("PIXIE_WEIGHTS", str(tmp_path))
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    with pytest.raises(WeightsError, match="superpoint"):
        get_matcher("minima-sp-lg", allow_download=False)


# ------------------------------------------------------------------------------------------------ images


def test_image_checks() -> None:
    m = get_matcher("sift-nn")
    with pytest.raises(ImageError, match="uint8"):
        m.extract(np.zeros((32, 32, 3), np.float32))
    with pytest.raises(ImageError, match="shape"):
        m.extract(np.zeros((32, 32, 2), np.uint8))
    with pytest.raises(ImageError, match="empty"):
        m.extract(np.zeros((0, 32), np.uint8))
    with pytest.raises(ImageError, match="numpy"):
        m.extract([[1, 2], [3, 4]])  # type: ignore[arg-type]
    with pytest.raises(ImageError, match="mask"):
        m.extract(np.zeros((32, 32), np.uint8), np.ones((16, 16), bool))
    # the one image rule (pixie.geometry.rotations.check_image): an alpha channel is dropped, like the query's
    rgb = cv2.cvtColor(np.random.default_rng(0).integers(0, 255, (64, 64), np.uint8), cv2.COLOR_GRAY2RGB)
    rgba = np.dstack([rgb, np.full((64, 64), 7, np.uint8)])
    np.testing.assert_array_equal(m.extract(rgba).keypoints, m.extract(rgb).keypoints)
    flat = m.extract(np.full((32, 32), 128, np.uint8))
    assert len(flat) == 0 and flat.descriptors.shape == (0, 128)
    assert len(m.extract(np.zeros((32, 32), np.uint8), np.zeros((32, 32), bool))) == 0


@pytest.fixture(scope="module")
def photo_pair() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A 256 px crop of a real LM-O photo, its warp by HOMOGRAPHY, and the warp's valid-pixel mask."""
    if not PHOTO.is_file():
        pytest.skip("../shared (LM-O dev photos) is not present")
    img = cv2.cvtColor(cv2.imread(str(PHOTO)), cv2.COLOR_BGR2RGB)
    crop = np.ascontiguousarray(img[110 : 110 + CROP, 200 : 200 + CROP])
    warp = cv2.warpPerspective(crop, HOMOGRAPHY, (CROP, CROP), flags=cv2.INTER_LINEAR)
    valid = cv2.warpPerspective(np.ones((CROP, CROP), np.uint8), HOMOGRAPHY, (CROP, CROP),
                                flags=cv2.INTER_NEAREST) > 0
    valid = cv2.erode(valid.astype(np.uint8), np.ones((5, 5), np.uint8)) > 0
    return crop, warp, valid


_matcher_cache: dict[str, object] = {}
_feature_cache: dict[str, tuple[Features, Features]] = {}
TEST_KEYPOINTS = 400  # fewer than the default 1024 keeps the LightGlue tests fast on two CPU cores
# XFeat keypoints are integer pixels of a coarser detector: with 400 of them only ~75 % of the mutual
# neighbours land within 3 px of the true position (~87 % with 1024), as with verlab's own matcher
KEYPOINTS = {"xfeat-nn": 1024}


def _matcher(name: str, **options: object):  # noqa: ANN202 - returns a Matcher
    key = name + repr(sorted(options.items()))
    if key not in _matcher_cache:
        try:
            kp = KEYPOINTS.get(name, TEST_KEYPOINTS)
            _matcher_cache[key] = get_matcher(name, allow_download=False, max_keypoints=kp, **options)
        except WeightsError as exc:
            pytest.skip(f"weights for {name} not available here: {str(exc).splitlines()[0]}")
    return _matcher_cache[key]


def _pair_features(name: str, photo_pair: tuple[np.ndarray, np.ndarray, np.ndarray]) -> tuple[Features, Features]:
    """Features of the crop, and of its warp extracted inside the warp's valid mask (cached per backend)."""
    if name not in _feature_cache:
        crop, warp, valid = photo_pair
        m = _matcher(name)
        _feature_cache[name] = (m.extract(crop), m.extract(warp, valid))
    return _feature_cache[name]


def _reprojection_errors(fq: Features, fr: Features, matches: Matches) -> np.ndarray:
    pq, pr = matched_keypoints(fq, fr, matches)
    proj = cv2.perspectiveTransform(pq[None].astype(np.float64), HOMOGRAPHY)[0]
    return np.linalg.norm(proj - pr, axis=1)


BACKENDS = ["aliked-nn", "disk-nn", "xfeat-nn", "sift-nn", "aliked-lg", "disk-lg", "xfeat-lighterglue"]


@pytest.mark.parametrize("name", BACKENDS)
def test_backend_recovers_homography(name: str, photo_pair: tuple[np.ndarray, np.ndarray, np.ndarray]) -> None:
    valid = photo_pair[2]
    m = _matcher(name)
    fq, fr = _pair_features(name, photo_pair)
    matches = m.match(fq, fr)
    err = _reprojection_errors(fq, fr, matches)
    assert fq.keypoints.dtype == np.float32 and fq.descriptors.shape == (len(fq), m.descriptor_dim)
    assert fq.image_size == (CROP, CROP)
    assert 0 < len(fq) <= KEYPOINTS.get(name, TEST_KEYPOINTS)
    # the reference side was extracted with a mask: all its keypoints lie inside it
    ix, iy = np.rint(fr.keypoints).astype(int).T
    assert valid[iy, ix].all()
    assert len(matches) >= 50, f"{name}: only {len(matches)} matches"
    assert np.mean(err < 3.0) > 0.8, f"{name}: {np.mean(err < 3.0):.2f} of matches within 3 px"


def test_windowed_nn_on_photo(photo_pair: tuple[np.ndarray, np.ndarray, np.ndarray]) -> None:
    fq, fr = _pair_features("aliked-nn", photo_pair)
    matches = _matcher("aliked-nn", window=32.0).match(fq, fr)
    pq, pr = matched_keypoints(fq, fr, matches)
    assert np.all(np.linalg.norm(pq - pr, axis=1) < 32.0)
    err = _reprojection_errors(fq, fr, matches)
    assert len(matches) >= 50 and np.mean(err < 3.0) > 0.9
    tight = _matcher("aliked-nn", window=2.0).match(fq, fr)  # true partners are further apart than that
    assert len(tight) < len(matches) // 4


def test_lightglue_match_many_equals_single(photo_pair: tuple[np.ndarray, np.ndarray, np.ndarray]) -> None:
    m = _matcher("aliked-lg")
    fq, fr = _pair_features("aliked-lg", photo_pair)
    many = m.match_many(fq, [fr, fq])
    one = m.match(fq, fr)
    assert np.array_equal(one.idx_q, many[0].idx_q) and np.array_equal(one.idx_r, many[0].idx_r)
    assert np.allclose(one.scores, many[0].scores)
    assert len(many[1]) > 0.8 * len(fq)  # an image against itself


def test_aliked_variant_loads(photo_pair: tuple[np.ndarray, np.ndarray, np.ndarray]) -> None:
    f = _matcher("aliked-nn", model="aliked-t16").extract(photo_pair[0])
    assert f.dim == 64 and len(f) > 50


# ------------------------------------------------------------------------------------------------ MINIMA


def _to_old_layout(state: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """``transformers.N.self_attn.*`` -> ``self_attn.N.*`` (the layout of the v0.1 LightGlue files)."""
    pattern = re.compile(r"^transformers\.(\d+)\.(self_attn|cross_attn)\.")
    return {pattern.sub(lambda m: f"{m.group(2)}.{m.group(1)}.", k): v for k, v in state.items()}


def test_remap_lightglue_state() -> None:
    t = torch.zeros(1)
    state = {"state_dict": {"matcher.self_attn.3.Wqkv.weight": t, "matcher.log_assignment.0.r": t,
                            "extractor.model.net.x": t, "cross_attn.10.to_v.bias": t}}
    assert set(remap_lightglue_state(state)) == {"transformers.3.self_attn.Wqkv.weight",
                                                 "transformers.10.cross_attn.to_v.bias"}


def test_wrong_weight_files_raise(tmp_path: Path) -> None:
    torch.save(SuperPointNet().state_dict(), tmp_path / "sp.pth")
    with pytest.raises(WeightsError, match="does not fit"):
        get_matcher("xfeat-nn", allow_download=False, weights=tmp_path / "sp.pth")  # another network
    lg = build_lightglue("xfeat", None, torch.device("cpu")).state_dict()
    with pytest.raises(WeightsError, match="does not fit"):
        build_lightglue("superpoint", lg, torch.device("cpu"))  # same keys, other shapes


def test_minima_loader_round_trip(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    torch.manual_seed(0)
    sp = SuperPointNet().eval()
    lg = build_lightglue("superpoint", None, torch.device("cpu"))  # random weights, same architecture
    lg_state = {k: v for k, v in lg.state_dict().items() if k != "confidence_thresholds"}
    torch.save(sp.state_dict(), tmp_path / "superpoint_v1.pth")
    torch.save(_to_old_layout(lg_state), tmp_path / "minima_lightglue.pth")

    # found by name in $PIXIE_WEIGHTS (the file names MINIMA and magicleap publish)
    monkeypatch.setenv("PIXIE_WEIGHTS", str(tmp_path))
    by_name = get_matcher("minima-sp-lg", allow_download=False, max_keypoints=64)
    loaded_sp = by_name.extractor.net.state_dict()
    assert all(torch.equal(loaded_sp[k], v) for k, v in sp.state_dict().items())
    loaded_lg = by_name.assigner.model.state_dict()
    assert all(torch.equal(loaded_lg[k], v) for k, v in lg_state.items())
    # or given explicitly: a file under another name, a dict entry, a folder
    monkeypatch.delenv("PIXIE_WEIGHTS")
    other = tmp_path / "other"
    other.mkdir()
    (other / "sp.pth").write_bytes((tmp_path / "superpoint_v1.pth").read_bytes())
    for weights in (other / "sp.pth", {"superpoint": other / "sp.pth"}, tmp_path):
        sp_nn = get_matcher("superpoint-nn", allow_download=False, weights=weights)
        assert torch.equal(sp_nn.extractor.net.conv1a.weight, sp.conv1a.weight)

    rng = np.random.default_rng(5)
    image = (rng.uniform(size=(96, 128, 3)) * 255).astype(np.uint8)
    fq = by_name.extract(image)
    fr = by_name.extract(np.ascontiguousarray(image[:, ::-1]))
    assert fq.dim == 256 and 0 < len(fq) <= 64
    # the same network outputs as the freshly initialised modules
    x = torch.from_numpy(image).float().mean(-1)[None, None] / 255
    with torch.inference_mode():
        for a, b in zip(sp(x), by_name.extractor.net(x)):
            assert torch.equal(a, b)
        data = {
            side: {
                "keypoints": torch.from_numpy(f.keypoints)[None],
                "descriptors": torch.from_numpy(f.descriptors)[None],
                "image_size": torch.tensor([[128.0, 96.0]]),
            }
            for side, f in (("image0", fq), ("image1", fr))
        }
        want = lg(data)
        got = by_name.assigner.model(data)
    assert torch.equal(want["matching_scores0"], got["matching_scores0"])
    m = by_name.match(fq, fr)
    assert isinstance(m, Matches) and len(m) == int((want["matches0"][0] > -1).sum())
