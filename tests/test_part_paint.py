"""Paint spill (pixie.cues.part_paint) on painted part maps, and its use in an assembly's verdict."""

from __future__ import annotations

import numpy as np
import pytest

from pixie.cues.part_paint import paint_spill
from pixie.cues.part_views import combine_views, mean_spill
from pixie.cues.parts import PartSupport

RED, BLUE, GREY = (200, 30, 20), (20, 80, 190), (128, 128, 128)


def _scene(seed: int, table=None):
    """A 240 x 320 part map (part 0 a 40 x 60 block, part 1 the same beside it, part 2 a grey block below) and a photo
    painted as the map says, over a background of random, weakly coloured noise (or a plain ``table`` colour)."""
    rng = np.random.default_rng(seed)
    pid = np.full((240, 320), -1, np.int32)
    pid[80:120, 100:160] = 0
    pid[80:120, 160:220] = 1
    pid[120:150, 100:220] = 2
    if table is None:
        img = np.clip(128 + rng.normal(0, 25, (240, 320, 3)), 0, 255).astype(np.uint8)
    else:
        img = np.empty((240, 320, 3), np.uint8)
        img[:] = table
    for k, c in enumerate((RED, BLUE, GREY)):
        img[pid == k] = c
    return img, pid


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_a_part_painted_as_the_model_says_spills_nothing_and_a_larger_one_does(seed):
    img, pid = _scene(seed)
    s = paint_spill(img, pid, 3)
    assert np.isnan(s[2])  # grey paint: no chroma to tell
    assert abs(s[0]) < 0.05 and abs(s[1]) < 0.05
    big = img.copy()
    big[70:120, 80:100] = RED  # the red part is larger than the CAD's: over the background on the left and top
    big[70:80, 80:160] = RED
    big[80:100, 160:190] = RED  # ... and over a corner of the blue part
    s2 = paint_spill(big, pid, 3)
    assert s2[0] > 0.3 and abs(s2[1]) < 0.05


def test_a_table_of_the_parts_own_colour_is_not_spill():
    img, pid = _scene(0, table=(205, 35, 25))  # a red table: every background pixel has the part's paint
    s = paint_spill(img, pid, 3)
    assert abs(s[0]) < 0.05  # the far background is as red as the band: no excess


def test_neighbours_of_a_like_paint_say_nothing_and_sizes_are_checked():
    img, pid = _scene(0)
    img[pid == 1] = (205, 40, 30)  # the neighbour is painted like part 0
    img[80:120, 160:190] = RED
    s = paint_spill(img, pid, 3)
    assert abs(s[0]) < 0.05  # the band over part 1 is left out; the rest (background) is clean
    tiny = np.full_like(pid, -1)
    tiny[10:14, 10:14] = 0
    assert np.isnan(paint_spill(img, tiny, 1)[0])  # too small to have a paint
    with pytest.raises(ValueError, match="differ in size"):
        paint_spill(img[:100], pid, 3)


def _rec(k: int, spill: float) -> PartSupport:
    return PartSupport(index=k, name=f"p{k}", support=0.8, relative=1.0, shifted=0.8, shift_px=0.0, visible=1.0,
                       n_points=150, exclusive=0.8, n_exclusive=120, spill=spill)


def test_an_assemblys_part_is_wrong_when_its_capped_spill_averages_above_the_threshold():
    """Part 0 spills in every photo (wrong), part 1 in one photo only (capped: not enough alone), part 2 is measured
    in one photo of three (NaN elsewhere), part 3 never; a flagged part keeps its own verdict."""
    photos = [[_rec(0, 0.35), _rec(1, 0.95), _rec(2, float("nan")), _rec(3, float("nan"))],
              [_rec(0, 0.3), _rec(1, 0.0), _rec(2, 0.4), _rec(3, float("nan"))],
              [_rec(0, 0.4), _rec(1, 0.05), _rec(2, float("nan")), _rec(3, float("nan"))]]
    judge = dict(flag_below=0.5, colour_weight=0.0, revealed_weight=0.0)
    assert mean_spill(photos, 0) == pytest.approx(0.35) and mean_spill(photos, 1) == pytest.approx(0.55 / 3)
    assert mean_spill(photos, 1, cap=1.0) == pytest.approx(1.0 / 3) and mean_spill(photos, 2) == pytest.approx(0.4)
    assert np.isnan(mean_spill(photos, 3))
    off = combine_views(photos, **judge)
    assert [p.verdict for p in off] == ["present"] * 4 and off[0].spill == pytest.approx(0.35)
    on = combine_views(photos, views_spill=0.3, **judge)
    assert [p.verdict for p in on] == ["wrong", "present", "wrong", "present"]
    assert on[0].as_dict()["paint_spill"] == 0.35 and on[3].as_dict()["paint_spill"] is None
    assert combine_views(photos, views_spill=0.3, spill_cap=1.0, **judge)[1].verdict == "wrong"
    for r in photos:
        r[0].exclusive = r[0].support = 0.0  # unsupported: missing, whatever its spill
    assert combine_views(photos, views_spill=0.3, **judge)[0].verdict == "missing"
    back = PartSupport.from_dict(photos[1][2].as_dict())
    assert back.spill == pytest.approx(0.4) and np.isnan(PartSupport.from_dict(photos[0][2].as_dict()).spill)
