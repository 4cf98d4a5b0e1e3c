"""Convergence of the edge alignment on rendered photos: the trials of tests/test_edge_align.py, per settings variant.

Usage::

    PYTHONPATH=src .venv/bin/python bench/align_rendered.py [--trials 12] [--preset default] \
        "box_taper=1,schedule=(8.,4.,2.)" "box_taper=0" ...

Each variant is a comma-separated list of keyword=value for :func:`pixie.cues.edge_align.align`, applied on top of the
preset's ``config.align`` (:func:`pixie.cues.edge_align.align_kwargs`; the keywords of
:func:`pixie.cues.edge_align.photo_edges_kwargs`, e.g. ``sil_inset``, go to the photo's edges); ``""`` is the preset itself. Trials
(:func:`pixie.synth.e2e.align_trials`): the procedural part in a cluttered 640 x 480 photo, random colours, started
10° / 5 % / 3 px off; clean, and half covered by a plate. Prints, per variant, how many end within 1° and 1 % depth
and within 5° and 3 %, and the median errors.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from pixie.config import PixieConfig
from pixie.cues.edge_align import align_kwargs, photo_edges_kwargs
from pixie.geometry.render import Renderer
from pixie.synth.e2e import align_trials, plate_renderer, procedural_part
from pixie.geometry.mesh import from_arrays


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--trials", type=int, default=12)
    ap.add_argument("--preset", default="default")
    ap.add_argument("variants", nargs="*", default=[""])
    args = ap.parse_args(argv)
    tm = procedural_part()
    mesh = from_arrays(np.asarray(tm.vertices), np.asarray(tm.faces), name="proc")
    ren, plate = Renderer(mesh), plate_renderer()
    ac = PixieConfig.from_preset(args.preset).align
    base, photo_base = align_kwargs(ac), photo_edges_kwargs(ac)
    print(f"| variant (on preset {args.preset}) | clean: <1°&1% | <5°&3% | med rot° | half covered: <1°&1% | <5°&3% | med rot° | s/trial |")
    print("|---|---|---|---|---|---|---|---|")
    for v in args.variants:
        given = eval(f"dict({v})")  # noqa: S307  (the command line's own keywords)
        kw = dict(base, **{k: x for k, x in given.items() if k not in photo_base})
        pkw = dict(photo_base, **{k: x for k, x in given.items() if k in photo_base})
        cells = []
        t0 = time.perf_counter()
        for pl in (None, plate):
            e = align_trials(mesh, ren, kw, n=args.trials, plate=pl, photo_kw=pkw)
            cells += [f"{sum(r < 1 and d < 0.01 for r, d in e)}/{len(e)}", f"{sum(r < 5 and d < 0.03 for r, d in e)}/{len(e)}",
                      f"{np.median([r for r, _ in e]):.2f}"]
        dt = (time.perf_counter() - t0) / (2 * args.trials)
        print(f"| {v or '(preset)'} | " + " | ".join(cells) + f" | {dt:.2f} |", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
