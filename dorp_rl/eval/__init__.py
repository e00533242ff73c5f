"""Evaluation: task sets and the harness, results and failure records; the measures of
codes and models (:mod:`dorp_rl.metrics`) are re-exported here."""

from dorp_rl import metrics as _metrics
from dorp_rl.eval.failures import (
    failure_section,
    format_failures,
    summarize_failures,
    tasks_to_draw,
    write_task_records,
)
from dorp_rl.eval.parallel import BACKENDS, EvalSpec, evaluate_parallel
from dorp_rl.eval.results import RESULT_COLUMNS, format_table, result_row, write_results
from dorp_rl.eval.settings import PAPER_SUCCESS, SETTINGS, Setting, paper_methods, setting_of
from dorp_rl.eval.tasks import (
    check_task_set,
    evaluate_policy,
    make_task_set,
    rollout_chunk,
    seed_policy,
)
from dorp_rl.metrics import *  # noqa: F403  (the measures of codes and models, re-exported)

__all__ = [
    "BACKENDS",
    "EvalSpec",
    "evaluate_parallel",
    "seed_policy",
    "PAPER_SUCCESS",
    "paper_methods",
    "RESULT_COLUMNS",
    "SETTINGS",
    "setting_of",
    "Setting",
    "failure_section",
    "format_failures",
    "format_table",
    "summarize_failures",
    "tasks_to_draw",
    "write_task_records",
    "result_row",
    "write_results",
    "check_task_set",
    "evaluate_policy",
    "make_task_set",
    "rollout_chunk",
    *_metrics.__all__,
]
