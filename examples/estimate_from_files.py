"""Estimate a pose from files: a CAD model, a photo, K and a box, each read from disk.

Usage: ``python examples/estimate_from_files.py FOLDER`` where FOLDER holds ``part.stl``, ``photo.png``,
``K.txt`` (``fx,fy,cx,cy``) and ``bbox.txt`` (``x,y,w,h``) -- ``make demo`` without the LM-O data (or
``pixie demo --synthetic``) writes such a folder to ``out/demo``.
"""

import json
import sys
from pathlib import Path

import numpy as np

import pixie

folder = Path(sys.argv[1] if len(sys.argv) > 1 else "out/demo")
K = (folder / "K.txt").read_text().strip()                                 # "fx,fy,cx,cy"
bbox = [float(v) for v in (folder / "bbox.txt").read_text().split(",")]    # x,y,w,h in pixels
image = pixie.load_image(folder / "photo.png")                             # RGB uint8

result = pixie.estimate_pose(folder / "part.stl", image, K, bbox=bbox)    # references built once, then cached
print("failed" if result.failed else "ok", f"confidence {result.confidence:.2f} (not calibrated)")
np.set_printoptions(precision=3, suppress=True)
print("T_cam_from_obj (mm, OpenCV camera):\n", result.T_cam_from_obj)
(folder / "example_result.json").write_text(json.dumps(result.to_dict(), indent=1))
