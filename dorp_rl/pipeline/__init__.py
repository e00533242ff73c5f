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

from dorp_rl.pipeline import options, run, stages
from dorp_rl.pipeline.options import *  # noqa: F403
from dorp_rl.pipeline.run import *  # noqa: F403
from dorp_rl.pipeline.stages import *  # noqa: F403

__all__ = [*options.__all__, *run.__all__, *stages.__all__]
