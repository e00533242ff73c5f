"""The pipeline's stages over a run folder: play data, codes, the code graph, the world
models and the evaluation, each run once per config (:meth:`~dorp_rl.pipeline.Run.stage`).
"""

from __future__ import annotations

import functools
import json
import math
from dataclasses import replace
from pathlib import Path
from typing import Any

import torch
from torchrl.envs import EnvBase

from dorp_rl.data import collect_play_data
from dorp_rl.envs import DiscreteActions, env_identity
from dorp_rl.eval import (
    PAPER_SUCCESS,
    EvalSpec,
    evaluate_parallel,
    failure_section,
    format_failures,
    make_task_set,
    result_row,
    setting_of,
    write_results,
    write_task_records,
)
from dorp_rl.pipeline.options import DORP_VARIANTS, PLAY_FIELDS, Evaluate, Reproduce
from dorp_rl.pipeline.run import Run, stage_config
from dorp_rl.planners import CodeGraph, coupled_groups, encode_transitions, encoder_fingerprint
from dorp_rl.policies import DORPConfig
from dorp_rl.trainers import (
    LatentWorldModelConfig,
    LatentWorldModelTrainer,
    RepresentationConfig,
    RepresentationTrainer,
    TrainingGaveUpError,
    WorldModelConfig,
    WorldModelTrainer,
    load_encoder,
)
from dorp_rl.viz import plot_results

__all__ = [
    "codes_stage",
    "dorp_stages",
    "evaluate_stage",
    "graph_stage",
    "latent_model_stage",
    "play_stage",
    "say_chosen",
    "task_set",
    "world_model_stage",
    "method_policy",
]


# --------------------------------------------------------------------------- stages
def _play_config(codes: RepresentationConfig) -> dict[str, Any]:
    values = codes.to_dict()
    return {k: values[k] for k in PLAY_FIELDS}


def play_stage(run: Run, codes: RepresentationConfig):
    """The play data the codes train on (collected into ``play/``, or loaded)."""
    directory = run.dir / "play"

    def collect(progress: bool):
        env = codes.make_env(batch_size=(codes.num_envs,))
        return collect_play_data(
            env,
            codes.num_frames,
            directory=directory,
            seed=codes.seed,
            trajectory_length=codes.play_trajectory_length,
            progress=progress,
        )

    def build():
        length, why = codes.play_length_choice()
        summary: dict[str, Any] = {}
        if why is not None:  # chosen from the env's resets
            say_chosen(run, "play", {"trajectory_length": {"value": length, "why": why}})
            summary["chosen"] = {"trajectory_length": length}
        buffer = collect(run.progress)
        return buffer, {"frames": len(buffer), **summary}

    return run.stage(
        "play", _play_config(codes), [directory], build, lambda: collect(progress=False)
    )


def say_chosen(run: Run, stage: str, chosen: dict[str, dict[str, Any]]) -> None:
    """Writes each setting a trainer chose from the env (``{field: {"value", "why"}}``) to
    the run's log, as ``<stage>: chose <field> = <value> (<why>)``."""
    for name, choice in chosen.items():
        run.say(f"{stage}: chose {name} = {choice['value']} ({choice['why']})")


def _tagged(name: str, variant: str, sep: str = ":") -> str:
    return f"{name}{sep}{variant}" if variant else name


def codes_stage(run: Run, codes: RepresentationConfig, variant: str = ""):
    """The trained encoder (trained into ``codes/``, or loaded); play data first.

    A ``variant`` (e.g. ``"arbitrary"``) is a stage of its own, ``codes:<variant>`` in
    ``codes-<variant>/``, on the same play data.
    """
    buffer = play_stage(run, codes)
    codes_dir = run.dir / _tagged("codes", variant, "-")
    cfg = replace(
        codes,
        out_dir=str(codes_dir),
        data_dir=str(run.dir / "play"),
        progress=run.progress,
    )
    checkpoint = codes_dir / "checkpoints" / "last.pt"

    def build(resume: bool = False):
        trainer = RepresentationTrainer(cfg, buffer=buffer)
        say_chosen(run, _tagged("codes", variant), trainer.chosen)
        result = trainer.train(resume=resume)
        if result["gave_up"] is not None:
            raise TrainingGaveUpError(f"{_tagged('codes', variant)}: {result['gave_up']}")
        diagnostics = trainer.evaluate()
        summary = {
            k: diagnostics[k]
            for k in ("selectivity", "purity", "codes_used")
            if k in diagnostics and isinstance(diagnostics[k], (int, float, list))
        }
        if summary:
            run.say(f"{_tagged('codes', variant)}: {json.dumps(summary)}")
        if trainer.chosen:
            summary["chosen"] = {k: c["value"] for k, c in trainer.chosen.items()}
        return trainer.encoder.eval(), summary

    def load():
        return load_encoder(checkpoint, codes.make_env())

    name = _tagged("codes", variant)
    resume = functools.partial(build, resume=True)
    encoder = run.stage(name, stage_config(cfg), [codes_dir], build, load, resume)
    return encoder, buffer


def graph_stage(
    run: Run,
    codes: RepresentationConfig,
    setting: str,
    variant: str = "",
    codes_variant: str = "",
    groups: Any = None,
):
    """The code graph over the play data (built into ``graph.pt``, or loaded); codes first.

    A ``variant`` is stage ``graph:<variant>`` in ``graph-<variant>.pt``, over the codes
    of ``codes_variant`` with ``groups`` (default: the setting's).
    """
    encoder, buffer = codes_stage(run, codes, codes_variant)
    path = run.dir / f"{_tagged('graph', variant, '-')}.pt"
    groups = setting_of(setting).groups if groups is None else groups
    env = codes.make_env()
    env_config, num_actions = env_identity(env), DiscreteActions.of(env).num_actions

    def build():
        # Graphs over one codes variant (per group, full) share one encoding of the play data.
        key = (codes_variant, encoder_fingerprint(encoder))
        if key not in run.encoded:
            run.encoded[key] = encode_transitions(buffer, encoder, progress=run.progress)
        chosen = groups
        if isinstance(groups, str) and groups == "auto":
            choice = coupled_groups(*run.encoded[key])
            chosen = choice.groups
            say_chosen(run, "graph", {"groups": {"value": list(chosen), "why": choice.why}})
        graph = setting_of(setting).make_graph(
            buffer, encoder, chosen, transitions=run.encoded[key], num_actions=num_actions
        )
        graph.save(path)
        nodes = [graph.num_nodes(g) for g in range(graph.num_groups)]
        return graph, {"nodes": nodes, "groups": [list(g) for g in graph.groups]}

    def load():
        return CodeGraph.load(path, encoder=encoder, env_config=env_config)

    # "action_counts": graphs keep their play data's actions (older graphs are rebuilt).
    config = {
        "groups": groups,
        "codes": stage_config(codes),
        "action_counts": True,
        "completed": setting_of(setting).completes_graph(groups),
    }
    return encoder, run.stage(_tagged("graph", variant), config, [path], build, load)


def dorp_stages(run: Run, cmd: Evaluate | Reproduce, method: str) -> tuple[Any, Any, str]:
    """Encoder, graph and graph stage name of DORP or one of its ablations
    (:data:`DORP_VARIANTS`), each trained or built once per run."""
    similarity, groups = DORP_VARIANTS[method]
    variant = method.removeprefix("dorp").removeprefix("-")
    codes, codes_variant = cmd.codes, ""
    if similarity is not None and similarity != codes.similarity:
        codes = replace(codes, similarity=similarity, alpha=1.0, dddp_sign="paper")
        codes_variant = variant
    encoder, graph = graph_stage(run, codes, cmd.setting, variant, codes_variant, groups)
    return encoder, graph, _tagged("graph", variant)


def _model_stage(run: Run, folder: str, trainer: Any, cfg: Any, metric: str, config: Any) -> Path:
    """A world model's checkpoint: trained by ``trainer(cfg)`` into ``<folder>/`` (its play
    data in ``<folder>_play/``) as the stage ``folder``, resumed, or found."""
    checkpoint = run.dir / folder / "checkpoints" / "last.pt"

    def build(resume: bool = False):
        model_trainer = trainer(cfg)
        chosen = getattr(model_trainer, "chosen", {})
        say_chosen(run, folder, chosen)
        result = model_trainer.train(resume=resume)
        summary = {metric: result.get("evaluation", {}).get(metric)}
        if chosen:
            summary["chosen"] = {k: c["value"] for k, c in chosen.items()}
        return checkpoint, summary

    outputs = [run.dir / folder, run.dir / f"{folder}_play"]
    resume = functools.partial(build, resume=True)
    run.stage(folder, config, outputs, build, lambda: checkpoint, resume)
    return checkpoint


def _in_run(run: Run, cfg: Any, folder: str, **more: Any) -> Any:
    """``cfg`` writing into the run folder: ``<folder>/``, its play data, the run's bars."""
    return replace(
        cfg,
        out_dir=str(run.dir / folder),
        data_dir=str(run.dir / f"{folder}_play"),
        progress=run.progress,
        **more,
    )


def world_model_stage(run: Run, world_model: WorldModelConfig) -> Path:
    """The world-model checkpoint (trained into ``world_model/``, or found)."""
    cfg = _in_run(run, world_model, "world_model")
    return _model_stage(
        run, "world_model", WorldModelTrainer, cfg, "exact_accuracy_last", stage_config(cfg)
    )


def latent_model_stage(
    run: Run, latent_model: LatentWorldModelConfig, codes: RepresentationConfig
) -> Path:
    """The latent world-model checkpoint (trained into ``latent_model/`` on the run's
    codes, trained first if needed, or found)."""
    codes_stage(run, codes)
    encoder = str(run.dir / "codes" / "checkpoints" / "last.pt")
    cfg = _in_run(run, latent_model, "latent_model", encoder_checkpoint=encoder)
    config = {"latent_model": stage_config(cfg), "codes": stage_config(codes)}
    return _model_stage(
        run, "latent_model", LatentWorldModelTrainer, cfg, "code_accuracy_last", config
    )


def method_policy(cmd: Evaluate | Reproduce, method: str, env: EnvBase, low_level: Any, dorp: Any):
    """The policy of ``method`` for ``env``, built by the same recipe as the workers'."""
    if method == "random":
        torch.manual_seed(cmd.seed)
    dorp_method = method in DORP_VARIANTS
    spec = EvalSpec(
        cmd.setting,
        "dorp" if dorp_method else method,
        encoder=dorp[0] if dorp_method else None,
        graph=dorp[1] if dorp_method else None,
        low_level="gt" if low_level is None else str(low_level),
        candidates=cmd.candidates,
        planning_horizon=cmd.planning_horizon,
        dorp=cmd.dorp.overrides(),
        seed=cmd.seed,
    )
    return spec.make_policy(env)


def task_set(cmd: Evaluate | Reproduce, env: EnvBase) -> tuple[Any, int]:
    """The seeded task set of ``cmd`` on ``env`` (drawn by the setting's env profile) and
    the step limit (``--max-steps``, else the profile's): what the evaluation runs, and
    the rollout GIFs run again."""
    setting = setting_of(cmd.setting)
    tasks = make_task_set(env, cmd.tasks, seed=cmd.task_seed, profile=setting.profile)
    return tasks, cmd.max_steps or setting.profile.task_limit(setting.num_objects, env)


def evaluate_stage(run: Run, cmd: Evaluate | Reproduce) -> list[dict[str, Any]]:
    """Every method of ``cmd`` on the seeded task set; returns the run's result rows."""
    setting = setting_of(cmd.setting)
    low_level: Path | None = None  # None: the true dynamics
    low_config: Any = "gt"
    level_name = cmd.low_level
    if cmd.low_level == "world-model":
        low_level = world_model_stage(run, cmd.world_model)
        low_config = stage_config(cmd.world_model)
    elif cmd.low_level == "latent-model":
        low_level = latent_model_stage(run, cmd.latent_model, cmd.codes)
        low_config = {"latent_model": stage_config(cmd.latent_model)}
    elif cmd.low_level != "gt":
        low_level, level_name = Path(cmd.low_level), "checkpoint"
        low_config = {"path": str(low_level.resolve()), "mtime": low_level.stat().st_mtime}
    batch = min(cmd.tasks, cmd.tasks_per_rollout)
    for method in cmd.methods:
        dorp = dorp_stages(run, cmd, method) if method in DORP_VARIANTS else None
        config: dict[str, Any] = {
            k: getattr(cmd, k) for k in ("setting", "tasks", "task_seed", "seed", "max_steps")
        }
        config["tasks_per_rollout"] = batch
        if method != "random":
            config.update(
                low_level=low_config,
                candidates=cmd.candidates,
                planning_horizon=cmd.planning_horizon,
            )
        if dorp is not None:
            config.update(
                dorp=cmd.dorp.overrides(),
                graph=run.stages[dorp[2]]["config"],
                dorp_where_suited=dict(DORPConfig.WHERE_SUITED),
            )

        key = f"evaluate:{method}" + ("" if method == "random" else f":{level_name}")
        # Finished chunks of tasks, so a stopped evaluation resumes at the next chunk.
        chunk_file = run.dir / "evaluations" / (key.replace(":", "-") + ".json")

        def build(
            resume: bool = False,
            method: str = method,
            dorp: Any = dorp,
            chunk_file: Path = chunk_file,
        ) -> tuple[None, dict[str, Any]]:
            if not resume:
                chunk_file.unlink(missing_ok=True)  # from another config, or none
            # Picklable factories: --workers/--backend rebuild env and policy per worker;
            # the policy is reseeded with seed + k per chunk k, so any --workers agrees.
            make_env = functools.partial(setting.make_env, batch_size=(batch,), seed=cmd.seed)
            tasks, limit = task_set(cmd, make_env())
            result = evaluate_parallel(
                make_env,
                functools.partial(method_policy, cmd, method, low_level=low_level, dorp=dorp),
                tasks,
                seed=cmd.seed,
                max_steps=limit,
                tasks_per_rollout=batch,
                workers=cmd.workers,
                backend=cmd.backend,
                address=cmd.address,
                progress=run.progress,
                resume_file=chunk_file,
            )
            chunk_file.unlink()  # its per-task results go into the stage's record
            level = "none" if method == "random" else level_name
            row = result_row(result, tasks, setting=cmd.setting, method=method, low_level=level)
            row["per_task"] = {  # for the steps plot and tasks.csv; not results.csv columns
                "success": result["success"],
                "steps": result["steps"],
                "lower_bound": (  # nan: the env's profile knows no bound
                    tasks["lower_bound"].tolist()
                    if "lower_bound" in tasks.keys()
                    else [math.nan] * cmd.tasks
                ),
                "records": result["records"],
            }
            run.say(
                f"{method}: success {row['success_rate']:.2f}, {row['mean_steps']:.1f} steps "
                f"(lower bound {row['mean_lower_bound']:.1f}), "
                f"{row['seconds_per_task']:.1f} s per task"
            )
            run.say(format_failures(result["records"], method))
            return None, row

        resume = functools.partial(build, resume=True)
        run.stage(key, config, [], build, lambda: None, resume)
    rows = run.result_rows()
    figures = plot_results(rows, run.dir, PAPER_SUCCESS)
    write_results(rows, run.dir, figures, sections=[failure_section(rows)])
    write_task_records(rows, run.dir / "tasks.csv")
    return rows
