"""The ``pixie eval`` command: evaluate a results CSV and write scores, per-target errors and the HTML report.

Typical use (what ``pixie eval DATASET --results results.csv -o OUT`` calls)::

    from pixie.eval import run_eval
    scores = run_eval("data/lmo", "results.csv", "out/eval")
"""

from __future__ import annotations

import argparse
from collections.abc import Callable, Iterable
from pathlib import Path

from pixie.eval.datasets import BopDataset, read_results_csv
from pixie.eval.evaluate import evaluate
from pixie.eval.objects import ObjectData
from pixie.eval.report import write_report
from pixie.eval.scores import ALL_METRICS, DEFAULT_METRICS, Scores
from pixie.eval.writers import format_table, write_per_target_csv, write_scores_json


def run_eval(
    dataset_root: str | Path,
    results_csv: str | Path,
    out_dir: str | Path,
    metrics: Iterable[str] = DEFAULT_METRICS,
    n_points: int | None = None,
    report: bool = True,
    n_overlays: int = 4,
    progress: bool = False,
    echo: Callable[[str], None] | None = print,
    only_estimated: bool = False,
) -> Scores:
    """Evaluate a results CSV and write ``scores.json``, ``per_target.csv`` and ``report.html``.

    Parameters
    ----------
    dataset_root : BOP dataset folder
    results_csv : BOP'19 results file
    out_dir : output folder (created)
    metrics, n_points : see :func:`evaluate`
    report : write the HTML report (with ``n_overlays`` best and worst target overlays)
    echo : function printing the summary table (None = silent)
    only_estimated : score only the targets that have at least one row in the results (a subset run);
        by default every target of the dataset counts and a missing estimate is a miss, as in BOP

    Returns
    -------
    Scores
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    ds = BopDataset(Path(dataset_root))
    objects: dict[int, ObjectData] = {}
    targets = None
    if only_estimated:
        rows = {(e.scene_id, e.im_id, e.obj_id) for e in read_results_csv(results_csv)}
        targets = [t for t in ds.targets() if (t.scene_id, t.im_id, t.obj_id) in rows]
    scores = evaluate(ds, results_csv, metrics=metrics, n_points=n_points, progress=progress, objects=objects,
                      targets=targets)
    write_scores_json(scores, out / "scores.json")
    write_per_target_csv(scores, out / "per_target.csv")
    if report:
        write_report(scores, ds, out, n_overlays=n_overlays, objects=objects)
    if echo is not None:
        echo(format_table(scores))
        echo(f"wrote {out / 'scores.json'}" + (f", {out / 'report.html'}" if report else ""))
    return scores


def add_eval_arguments(parser: argparse.ArgumentParser) -> argparse.ArgumentParser:
    """Arguments of ``pixie eval`` (for the CLI owner to mount as a sub-command)."""
    parser.add_argument("dataset", help="BOP dataset folder (holding models/, test/, test_targets_bop19.json)")
    parser.add_argument("--results", required=True, help="BOP'19 results CSV")
    parser.add_argument("-o", "--out", default="out/eval", help="output folder")
    parser.add_argument(
        "--metrics", default=",".join(DEFAULT_METRICS), help=f"comma-separated, from {','.join(ALL_METRICS)}"
    )
    parser.add_argument("--n-points", type=int, default=None, help="vertices used by ADD/ADD-S (default: all)")
    parser.add_argument("--no-report", action="store_true", help="skip the HTML report")
    parser.add_argument("--progress", action="store_true")
    parser.add_argument("--only-estimated", action="store_true",
                        help="score only targets with a row in the results (subset runs); default: all targets, misses count")
    return parser


def main_eval(args: argparse.Namespace) -> int:
    """Entry point for ``pixie eval`` given parsed :func:`add_eval_arguments` arguments."""
    run_eval(
        args.dataset,
        args.results,
        args.out,
        metrics=[m for m in args.metrics.split(",") if m],
        n_points=args.n_points,
        report=not args.no_report,
        progress=args.progress,
        only_estimated=args.only_estimated,
    )
    return 0
