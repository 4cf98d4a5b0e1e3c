"""The ``pixie eval`` command: evaluate a results CSV and write scores, per-target errors and the HTML report.

Typical use (what ``pixie eval DATASET --results results.csv -o OUT`` calls)::

    from pixie.eval import run_eval
    scores = run_eval("data/lmo", "results.csv", "out/eval")
"""

from __future__ import annotations

import argparse
import warnings
from collections.abc import Callable, Iterable
from pathlib import Path

from pixie.errors import DatasetError, UsageError
from pixie.eval.datasets import BopDataset, read_results_csv
from pixie.eval.evaluate import evaluate
from pixie.eval.objects import ObjectData
from pixie.eval.report import write_report
from pixie.eval.scores import ALL_METRICS, DEFAULT_METRICS, Scores, normalize_metrics
from pixie.eval.writers import format_table, write_per_target_csv, write_scores_json
from pixie.paths import not_an_input, output_dir

EVAL_OUTPUTS = ("scores.json", "per_target.csv", "report.html")  # written into the output folder


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
    targets: list | str | Path | None = None,
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
    only_estimated : score only the targets that have at least one row in the results; a target without a row
        is then left out, not a miss (not BOP's protocol: prefer ``targets``)
    targets : the targets to score (a list of Target, or a BOP targets JSON such as ``pixie run``'s
        ``targets.json``); by default every target of the dataset. A target without an estimate is a miss, as in BOP

    Returns
    -------
    Scores
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    ds = BopDataset(Path(dataset_root))
    objects: dict[int, ObjectData] = {}
    if isinstance(targets, (str, Path)):
        targets = BopDataset(ds.root, split=ds.split, targets_file=str(Path(targets).resolve())).targets()
    if only_estimated:
        rows = {(e.scene_id, e.im_id, e.obj_id) for e in read_results_csv(results_csv)}
        targets = [t for t in (targets or ds.targets()) if (t.scene_id, t.im_id, t.obj_id) in rows]
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
    parser.add_argument("--targets", help="BOP targets JSON to score (e.g. the targets.json of `pixie run`: its subset); "
                        "default: the dataset's. A target without an estimate counts as a miss")
    parser.add_argument("--only-estimated", action="store_true",
                        help="score only targets with a row in the results: targets without one are left out, not "
                        "counted as misses (not BOP's protocol; prefer --targets)")
    return parser


def main_eval(args: argparse.Namespace) -> int:
    """Entry point for ``pixie eval`` given parsed :func:`add_eval_arguments` arguments (checked first)."""
    check_eval_args(args)
    run_eval(
        args.dataset,
        args.results,
        args.out,
        metrics=[m for m in args.metrics.split(",") if m],
        n_points=args.n_points,
        report=not args.no_report,
        progress=args.progress,
        only_estimated=args.only_estimated,
        targets=args.targets,
    )
    return 0


def check_eval_args(args: argparse.Namespace) -> None:
    """Check ``pixie eval``'s inputs before scoring starts: metrics, the results file against the dataset, the
    output folder (:class:`DatasetError`, :class:`UsageError` naming the problem)."""
    if not [m for m in args.metrics.split(",") if m.strip()]:
        raise UsageError(f"--metrics names no metric, got {args.metrics!r}")
    normalize_metrics([m for m in args.metrics.split(",") if m])
    ds = BopDataset(args.dataset)
    rows = read_results_csv(args.results)
    if not rows:
        raise DatasetError(f"{args.results} holds no results (empty or header only): nothing to score")
    targets = ds.targets() if not args.targets else BopDataset(
        args.dataset, targets_file=str(Path(args.targets).resolve())).targets()
    objs, scenes = {t.obj_id for t in targets}, {t.scene_id for t in targets}
    bad_objs = sorted({r.obj_id for r in rows} - objs)
    if bad_objs:
        raise DatasetError(f"{args.results}: object id(s) {bad_objs} are not targets of dataset {ds.name} "
                           f"(objects {sorted(objs)}): results of another dataset?")
    bad_scenes = sorted({r.scene_id for r in rows} - scenes)
    if bad_scenes:
        raise DatasetError(f"{args.results}: scene id(s) {bad_scenes} are not in dataset {ds.name} "
                           f"(scenes {sorted(scenes)}): results of another dataset?")
    keys = {(t.scene_id, t.im_id, t.obj_id) for t in targets}
    n_off = sum((r.scene_id, r.im_id, r.obj_id) not in keys for r in rows)
    if n_off == len(rows):
        raise DatasetError(f"{args.results}: none of its {len(rows)} rows is a target (scene, image, object) of "
                           f"dataset {ds.name}: results of another dataset or split?")
    if n_off:
        warnings.warn(f"{args.results}: {n_off} of {len(rows)} rows are not targets of dataset {ds.name}; "
                      "they are ignored")
    if args.n_points is not None and args.n_points < 1:
        raise UsageError(f"--n-points must be at least 1, got {args.n_points}")
    output_dir(args.out, what="output folder")
    out = Path(args.out)
    not_an_input([out, *(out / n for n in EVAL_OUTPUTS)], [args.dataset, args.results, getattr(args, "targets", None)])
