"""Evaluation on BOP datasets, separated as bop_toolkit separates it.

Modules (imports go down this list)::

    datasets   BOP dataset I/O: targets, GT, cameras, images, results CSV (read/write)
    errors     pose errors as pure functions: ADD, ADD-S, MSSD, MSPD, VSD, rotation/translation error
    shape      shape agreement of the paper: APS, IoU3D
    scores     BOP greedy matching, recall, AR; the TargetResult / Scores records
    objects    per-object evaluation data (built once) and pose_errors() for benchmark tables
    evaluate   orchestration: errors of every estimate, assignment, aggregation -> Scores
    writers    scores.json, per_target.csv, the plain-text table
    report     the self-contained HTML report
    run        the ``pixie eval`` command (run_eval, its arguments)

Typical use::

    from pixie.eval import run_eval
    scores = run_eval("data/lmo", "results.csv", "out/eval")
"""

from pixie.eval.datasets import BopDataset, PoseEstimate, Target, read_results_csv, write_results_csv
from pixie.eval.evaluate import evaluate
from pixie.eval.objects import ObjectData, load_object_data, pose_errors
from pixie.eval.run import add_eval_arguments, main_eval, run_eval
from pixie.eval.scores import ALL_METRICS, DEFAULT_METRICS, Scores, TargetResult, normalize_metrics
from pixie.eval.writers import format_table, write_per_target_csv, write_scores_json

__all__ = [
    "ALL_METRICS",
    "DEFAULT_METRICS",
    "BopDataset",
    "ObjectData",
    "PoseEstimate",
    "Scores",
    "Target",
    "TargetResult",
    "add_eval_arguments",
    "evaluate",
    "format_table",
    "load_object_data",
    "main_eval",
    "normalize_metrics",
    "pose_errors",
    "read_results_csv",
    "run_eval",
    "write_per_target_csv",
    "write_results_csv",
    "write_scores_json",
]
