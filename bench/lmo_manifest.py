"""Write a `pixie estimate --batch` manifest (CSV) of LM-O dev photos of one object, with GT visible boxes.

Rows: image (relative to the manifest), K (fx,fy,cx,cy), bbox (x,y,w,h; BOP's bbox_visib converted to pixel
counts), scene_id, im_id, obj_id -- so the batch's results.csv scores with `pixie eval`.

Usage::

    .venv/bin/python bench/lmo_manifest.py --obj-id 5 --n 20 -o out/bench/lmo20/manifest.csv
"""

from __future__ import annotations

import argparse
import csv
import os
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "src"))

from pixie.eval.datasets import BopDataset  # noqa: E402

DEFAULT_DATASET = REPO.parent / "shared/data/lmo_dev/lmo"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--dataset", type=Path, default=DEFAULT_DATASET)
    ap.add_argument("--obj-id", type=int, default=5)
    ap.add_argument("--n", type=int, default=20, help="number of images (evenly spread over the object's targets)")
    ap.add_argument("-o", "--output", type=Path, required=True)
    args = ap.parse_args(argv)
    ds = BopDataset(args.dataset)
    targets = [t for t in ds.targets() if t.obj_id == args.obj_id]
    if not targets:
        raise SystemExit(f"no targets of object {args.obj_id} in {args.dataset}")
    step = max(1, len(targets) // args.n)
    chosen = targets[::step][: args.n]
    args.output.parent.mkdir(parents=True, exist_ok=True)
    with open(args.output, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["image", "K", "bbox", "scene_id", "im_id", "obj_id"])
        for t in chosen:
            inst = max((g for g in ds.instances(t.scene_id, t.im_id) if g.obj_id == t.obj_id),
                       key=lambda g: g.visib_fract if g.visib_fract is not None else 1.0)
            K = ds.camera(t.scene_id, t.im_id).K
            img = ds.image_path(t.scene_id, t.im_id)
            w.writerow([os.path.relpath(img, args.output.parent), f"{K[0, 0]:.9g},{K[1, 1]:.9g},{K[0, 2]:.9g},{K[1, 2]:.9g}",
                        ",".join(f"{v:g}" for v in inst.box_visib), t.scene_id, t.im_id, t.obj_id])
    print(f"{len(chosen)} rows (object {args.obj_id}) -> {args.output}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
