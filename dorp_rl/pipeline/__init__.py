"""The stages of the ``dorp`` command and the run folder they work in.

:class:`Run` holds a run folder ``<root>/<name>/`` (its lock, ``stages.json``, the log)
and runs each stage once per config (:meth:`Run.stage`); ``play_stage``, ``codes_stage``,
``graph_stage``, ``world_model_stage``, ``latent_model_stage`` and ``evaluate_stage`` are
the pipeline's stages, and the command dataclasses (:class:`Collect` ... :class:`Demo`)
their options, each a composition of the option groups it needs (:class:`RunOptions`,
:class:`CodeOptions`, :class:`WorldModelOptions`, :class:`LatentModelOptions`,
:class:`EvaluationOptions`, :class:`PaperOptions`). The
``dorp`` command (:mod:`dorp_rl.cli`) parses arguments into these and runs them;
``dorp reproduce --paper`` (:mod:`dorp_rl.reproduce`) runs them once per setting.
"""

from dorp_rl.pipeline.options import (
    COMMANDS,
    DEMO_CODE_STEPS,
    DORP_VARIANTS,
    LOW_LEVEL_NAMES,
    PLAY_FIELDS,
    BuildGraph,
    CodeOptions,
    Collect,
    Demo,
    DORPOptions,
    Evaluate,
    EvaluationOptions,
    LatentModelOptions,
    PaperOptions,
    Reproduce,
    RunOptions,
    TrainEncoder,
    TrainWorldModel,
    WorldModelOptions,
    default_command,
)
from dorp_rl.pipeline.run import (
    NAME_RULE,
    RUN_HOLDER,
    RUN_LOCK,
    Run,
    UsageError,
    quiet_torchrl,
    run_folder,
)
from dorp_rl.pipeline.stages import (
    codes_stage,
    dorp_stages,
    evaluate_stage,
    graph_stage,
    latent_model_stage,
    method_policy,
    play_stage,
    say_chosen,
    task_set,
    world_model_stage,
)

__all__ = [
    "COMMANDS",
    "DEMO_CODE_STEPS",
    "DORP_VARIANTS",
    "LOW_LEVEL_NAMES",
    "NAME_RULE",
    "PLAY_FIELDS",
    "RUN_HOLDER",
    "RUN_LOCK",
    "BuildGraph",
    "CodeOptions",
    "Collect",
    "DORPOptions",
    "Demo",
    "Evaluate",
    "EvaluationOptions",
    "LatentModelOptions",
    "PaperOptions",
    "Reproduce",
    "Run",
    "RunOptions",
    "TrainEncoder",
    "TrainWorldModel",
    "UsageError",
    "WorldModelOptions",
    "codes_stage",
    "default_command",
    "dorp_stages",
    "evaluate_stage",
    "graph_stage",
    "latent_model_stage",
    "play_stage",
    "quiet_torchrl",
    "run_folder",
    "say_chosen",
    "task_set",
    "world_model_stage",
    "method_policy",
]
