"""Evaluation: task sets and the harness, results and failure records; the measures of
codes and models (:mod:`dorp_rl.metrics`) are re-exported here."""

from dorp_rl.eval.failures import (
    failure_section,
    format_failures,
    summarize_failures,
    tasks_to_draw,
    write_task_records,
)
from dorp_rl.eval.parallel import BACKENDS, EvalSpec, evaluate_parallel
from dorp_rl.eval.results import RESULT_COLUMNS, format_table, result_row, write_results
from dorp_rl.eval.settings import PAPER_SUCCESS, SETTINGS, Setting, setting_of
from dorp_rl.eval.tasks import (
    check_task_set,
    evaluate_policy,
    make_task_set,
    rollout_chunk,
    seed_policy,
)
from dorp_rl.metrics.code_information import code_dynamics, code_information, play_code_dynamics
from dorp_rl.metrics.diagnostics import (
    GROUND_TRUTH_DIAGNOSTICS,
    best_assignment,
    connected_fraction,
    encode_pixels,
    ground_truth_diagnostics,
    key_room_code_maps,
    key_room_diagnostics,
    object_diagnostics,
    play_object_diagnostics,
    rearrangement_code_maps,
    rearrangement_diagnostics,
    sample_rearrangement_states,
)
from dorp_rl.metrics.world_model import open_loop_accuracy

__all__ = [
    "BACKENDS",
    "EvalSpec",
    "evaluate_parallel",
    "seed_policy",
    "PAPER_SUCCESS",
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
    "best_assignment",
    "check_task_set",
    "GROUND_TRUTH_DIAGNOSTICS",
    "code_dynamics",
    "code_information",
    "object_diagnostics",
    "play_object_diagnostics",
    "play_code_dynamics",
    "connected_fraction",
    "encode_pixels",
    "ground_truth_diagnostics",
    "evaluate_policy",
    "key_room_code_maps",
    "key_room_diagnostics",
    "make_task_set",
    "rollout_chunk",
    "open_loop_accuracy",
    "rearrangement_code_maps",
    "rearrangement_diagnostics",
    "sample_rearrangement_states",
]
