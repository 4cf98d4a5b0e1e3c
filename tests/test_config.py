"""The one config object: defaults, --set overrides, YAML files, and the errors for bad values."""

from __future__ import annotations

import pytest

from pixie.config import PixieConfig
from pixie.errors import ConfigError


def test_overrides_parse_yaml_values_into_the_right_types():
    cfg = PixieConfig().apply_overrides([
        "refs.encodings=[shade3_edges, depth]", "refs.size=128", "match.window=null", "pose.reprojection_px=4",
        "refine.recrop=false", "match.matcher=sift-nn",
    ])
    assert cfg.refs.encodings == ["shade3_edges", "depth"]
    assert cfg.refs.size == 128 and isinstance(cfg.refs.size, int)
    assert cfg.match.window is None
    assert cfg.pose.reprojection_px == 4.0 and isinstance(cfg.pose.reprojection_px, float)
    assert cfg.refine.recrop is False
    assert cfg.match.matcher == "sift-nn"
    assert PixieConfig().refs.size == 256  # overrides never touch the defaults


def test_dict_and_yaml_round_trip(tmp_path):
    cfg = PixieConfig().apply_overrides(["refs.n_fibonacci=40", "match.in_plane=query", "pose.top_k_views=12"])
    assert PixieConfig.from_dict(cfg.to_dict()) == cfg
    path = tmp_path / "c.yaml"
    path.write_text("refs:\n  n_fibonacci: 40\nmatch:\n  in_plane: query\npose:\n  top_k_views: 12\n")
    assert PixieConfig.from_yaml(path) == cfg
    (tmp_path / "empty.yaml").write_text("")
    assert PixieConfig.from_yaml(tmp_path / "empty.yaml") == PixieConfig()


@pytest.mark.parametrize("override, message", [
    ("refs", "section.key=value"),
    ("size=3", "section.key"),
    ("nosuch.size=3", "unknown config section 'nosuch'"),
    ("refs.nosuch=3", "unknown key 'nosuch' in section 'refs'"),
    ("refine.recrop=1", "expects true/false"),
    ("refs.size=big", "expects a number"),
    ("pose.reprojection_px=true", "expects a number"),
])
def test_bad_overrides_name_the_problem(override, message):
    with pytest.raises(ConfigError, match=message):
        PixieConfig().apply_overrides([override])


def test_bad_yaml_files(tmp_path):
    with pytest.raises(ConfigError, match="cannot read config"):
        PixieConfig.from_yaml(tmp_path / "missing.yaml")
    (tmp_path / "list.yaml").write_text("- 1\n- 2\n")
    with pytest.raises(ConfigError, match="mapping of sections"):
        PixieConfig.from_yaml(tmp_path / "list.yaml")
    (tmp_path / "broken.yaml").write_text("refs: [1, 2\n")
    with pytest.raises(ConfigError, match="cannot read config"):
        PixieConfig.from_yaml(tmp_path / "broken.yaml")


@pytest.mark.parametrize("override", ["shape.views=abc", "shape.views=0", "shape.enabled=maybe", "shape.w_edge=-1",
                                      "shape.size=8", "shape.rolls=0"])
def test_shape_section_is_validated_like_every_other(override):
    from pixie.config import PixieConfig

    with pytest.raises(ConfigError, match=override.split("=")[0].replace(".", r"\.")):
        PixieConfig().apply_overrides([override])


def test_confidence_terms_and_coefficients_must_agree():
    """align.confidence holds the intercept and one coefficient per align.confidence_terms name; a mismatch or an
    unknown term is refused naming the keys, whichever order a file or the overrides set them in."""
    cfg = PixieConfig.from_preset("default")
    assert len(cfg.align.confidence) == 1 + len(cfg.align.confidence_terms)
    n = len(cfg.align.confidence)
    with pytest.raises(ConfigError, match=f"align.confidence has {n} coefficients"):
        PixieConfig.from_preset("default").apply_overrides(["align.confidence_terms=[fit,margin,size,edge]"])
    ok = PixieConfig.from_dict({"align": {"confidence": [1, 2, 3, 4], "confidence_terms": ["fit", "margin", "size"]}})
    assert ok.align.confidence_terms == ["fit", "margin", "size"]
    with pytest.raises(ConfigError, match="unknown 'depth'"):
        PixieConfig().apply_overrides(["align.confidence_terms=[fit,depth]"])
    assert PixieConfig().apply_overrides(["align.confidence=[]"]).align.confidence == []  # the uncalibrated ratio


def test_detect_acceptance_terms_and_coefficients_must_agree():
    """detect.accept holds the intercept and one coefficient per detect.accept_terms name, as align.confidence does;
    [] is the rule on the estimate's own confidence."""
    cfg = PixieConfig.from_preset("default")
    assert not cfg.detect.accept or len(cfg.detect.accept) == 1 + len(cfg.detect.accept_terms)
    with pytest.raises(ConfigError, match="detect.accept has 2 coefficients"):
        PixieConfig().apply_overrides(["detect.accept_terms=[fit,full_fit]", "detect.accept=[1,2]"])
    with pytest.raises(ConfigError, match="unknown 'depth'"):
        PixieConfig().apply_overrides(["detect.accept_terms=[fit,depth]"])
    with pytest.raises(ConfigError, match=r"detect\.proposals"):
        PixieConfig().apply_overrides(["detect.proposals=0"])
    ok = PixieConfig().apply_overrides(["detect.accept_terms=[fit,full_fit]", "detect.accept=[-3,2,4]"])
    assert ok.detect.accept == [-3.0, 2.0, 4.0] and PixieConfig().apply_overrides(["detect.accept=[]"]).detect.accept == []


def test_edge_detector_choices_are_what_photo_edges_accepts():
    """config cannot import the cues layer, so align.edge_detector's choices and photo_edges' DETECTORS live apart:
    this keeps them equal (align.search's choices each run in tests/test_edge_align.py)."""
    from pixie.config import CHOICES
    from pixie.cues.edge_photo import DETECTORS

    assert CHOICES["align.edge_detector"] == DETECTORS


def test_search_choices_are_what_align_accepts():
    """The same for align.search and align()'s SEARCHES; align() itself refuses anything else."""
    import numpy as np

    from pixie.config import CHOICES
    from pixie.cues.edge_align import SEARCHES, align

    assert CHOICES["align.search"] == SEARCHES
    with pytest.raises(ValueError, match="search must be one of"):
        align(None, None, np.eye(4), search="nearets")
