"""The HTML report (pixie.eval.report): self-contained, with the table, histograms and true overlays."""

from __future__ import annotations

import base64
import html as html_lib
import re

import cv2
import numpy as np

from pixie.eval import evaluate
from pixie.eval.datasets import BopDataset, PoseEstimate
from pixie.eval.report import overlay_target, write_report
from pixie.eval.writers import format_table


def _scores(root, meta, shift_mm: float = 0.0):
    ests = [PoseEstimate(1, im, o, 1.0, T.copy(), -1.0) for im, insts in meta["scenes"].items() for o, T in insts]
    ests[1].T_cam_from_obj[0, 3] += shift_mm  # the cylinder of image 0
    ds = BopDataset(root)
    return ds, evaluate(ds, ests, metrics=["mssd", "mspd", "ad"])


def test_report_is_self_contained_with_table_and_overlays(synthetic_bop, tmp_path):
    root, meta = synthetic_bop
    ds, scores = _scores(root, meta, shift_mm=40.0)
    path = write_report(scores, ds, tmp_path, n_overlays=2, title="t<1>")
    html = path.read_text()
    assert path == tmp_path / "report.html"
    assert "t&lt;1&gt;" in html  # titles are escaped
    srcs = re.findall(r"src='([^']*)'", html)
    assert srcs and all(s.startswith("data:image/png;base64,") for s in srcs)  # nothing outside the file
    assert html.count("<figcaption>") == 4  # 2 best + 2 worst targets
    assert html_lib.escape(format_table(scores).splitlines()[1]) in html
    # every embedded image decodes
    for s in srcs:
        img = cv2.imdecode(np.frombuffer(base64.b64decode(s.split(",", 1)[1]), np.uint8), cv2.IMREAD_COLOR)
        assert img is not None and img.size > 0
    # the worst target is the shifted cylinder
    worst = html[html.index("Worst targets"):]
    assert "obj 2" in worst[: worst.index("</figure>")]


def test_overlay_draws_gt_and_estimate_where_they_are(synthetic_bop):
    root, meta = synthetic_bop
    ds, scores = _scores(root, meta, shift_mm=60.0)
    from pixie.eval import load_object_data

    t = next(t for t in scores.targets if t.obj_id == 2)
    img = overlay_target(ds, t, load_object_data(ds, 2).renderer, pad=0)
    green = (img[..., 1] > 200) & (img[..., 0] < 80)
    red = (img[..., 0] > 200) & (img[..., 1] < 80)
    assert green.any() and red.any()
    # 60 mm at 650 mm and f = 500 px: the estimate's contour is ~46 px (before the crop's enlargement) right
    # of the GT's, and at the same height
    dx = np.nonzero(red)[1].mean() - np.nonzero(green)[1].mean()
    dy = np.nonzero(red)[0].mean() - np.nonzero(green)[0].mean()
    assert dx > 30 and abs(dy) < 0.2 * dx


def test_report_survives_a_missing_image(synthetic_bop, tmp_path):
    root, meta = synthetic_bop
    ds, scores = _scores(root, meta)
    scores.targets[0].im_id = 99  # no such image: reported in the page, not raised
    html = write_report(scores, ds, tmp_path, n_overlays=4).read_text()  # every target drawn
    assert "im 99" in html
