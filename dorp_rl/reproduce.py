"""``dorp reproduce --paper`` (the paper's Table 1) and the pictures of a run folder.

:func:`reproduce_paper` runs the single-setting pipeline of :mod:`dorp_rl.pipeline` once per
setting, each in a sub-run ``<run>/<setting>/`` with its own stages (so a finished stage is
skipped when the command runs again), and gathers the rows into one table next to the
paper's figures and one table of stage wall-clock times. :func:`pictures_stage` draws, as
a stage of a run, the code maps and factorisation histogram (the paper's Figures 5 and
4(c)) of every code variant evaluated, and DORP rollouts as GIFs with the waypoint beside
each frame.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import multiprocessing
from collections.abc import Callable
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from concurrent.futures.process import BrokenProcessPool
from multiprocessing.managers import SyncManager
from pathlib import Path
from typing import Any

import torch

from dorp_rl.config import carry_changes
from dorp_rl.envs import EnvProfile
from dorp_rl.eval import (
    PAPER_SUCCESS,
    RESULT_COLUMNS,
    SETTINGS,
    failure_section,
    paper_methods,
    rollout_chunk,
    setting_of,
    tasks_to_draw,
    write_task_records,
)
from dorp_rl.eval.parallel import exit_with_parent
from dorp_rl.eval.results import (
    PAPER_COLUMNS,
    SEED_COLUMNS,
    add_paper_figures,
    describe_stage,
    format_paper_table,
    format_time_by_kind,
    format_timings,
    pool_seeds,
    write_results,
    write_timings,
)
from dorp_rl.eval.tasks import succeeded
from dorp_rl.pipeline import (
    DORP_VARIANTS,
    Evaluate,
    EvaluationOptions,
    PaperOptions,
    Reproduce,
    Run,
    default_command,
    dorp_stages,
    evaluate_stage,
    method_policy,
    task_set,
)
from dorp_rl.progress import BarMirror, progress_bar, relay_bars
from dorp_rl.viz import plot_results, write_diagnostic_plots
from dorp_rl.viz.rollouts import code_maps_for_waypoints, save_rollout_gif

__all__ = ["paper_methods", "pictures_stage", "reproduce_paper", "run_setting", "say_pictures"]

#: fields that a setting decides (never carried from one setting's preset to another)
_SETTING_FIELDS = ("env", "num_objects")


def _chosen_methods(cmd: PaperOptions, setting: str) -> tuple[str, ...]:
    """Table 1's methods in ``setting``, only those of ``cmd.paper_methods`` if it names any."""
    chosen = cmd.paper_methods
    return tuple(m for m in paper_methods(setting) if not chosen or m in chosen)


def _level_name(cmd: EvaluationOptions) -> str:
    named = ("gt", "world-model", "latent-model")
    return cmd.low_level if cmd.low_level in named else "checkpoint"


def _evaluation_key(cmd: EvaluationOptions, method: str) -> str:
    return f"evaluate:{method}" + ("" if method == "random" else f":{_level_name(cmd)}")


def _low_level_path(run: Run, cmd: EvaluationOptions) -> Path | None:
    """The planning model the evaluation used (``None``: the true dynamics)."""
    if cmd.low_level == "gt":
        return None
    if cmd.low_level == "world-model":
        return run.dir / "world_model" / "checkpoints" / "last.pt"
    if cmd.low_level == "latent-model":
        return run.dir / "latent_model" / "checkpoints" / "last.pt"
    return Path(cmd.low_level)


def _diagnostic_pictures(
    env: Any, profile: EnvProfile, encoder: Any, directory: Path, num_samples: int
):
    """The pictures of ``encoder``'s codes into ``directory`` when ``env``'s profile
    declares code diagnostics (:attr:`~dorp_rl.envs.EnvProfile.diagnostics`); returns the waypoint maps
    (:func:`~dorp_rl.viz.rollouts.code_maps_for_waypoints`, ``None`` without them) and
    the files."""
    encode = encoder.encode
    diagnostics = profile.diagnostics
    if diagnostics is None:  # no labels: the GIFs are drawn without waypoint maps
        return None, []
    result = diagnostics.measure(env, encode, max(num_samples, 2), 0)
    written: dict[str, Path] = {}
    if diagnostics.pictures is not None:
        written = write_diagnostic_plots(env, encode, directory, result=result, profile=profile)
    if diagnostics.waypoint_maps is None:
        return None, list(written.values())
    maps = diagnostics.waypoint_maps(env, encode, result)
    return code_maps_for_waypoints(maps, result["num_onehots"]), list(written.values())


def pictures_stage(run: Run, cmd: Evaluate | Reproduce) -> list[Path]:
    """Pictures of the DORP methods of ``cmd`` (after :func:`~dorp_rl.pipeline.evaluate_stage`).

    Writes into ``<run>/pictures/``: ``code_map.png`` and ``factorization_histogram.png``
    of DORP's codes (``arbitrary/`` and ``identity/`` for the ablations' codes), and
    ``rollout_<task>.gif`` for ``cmd.gifs`` tasks of the set, those the evaluation of the
    first DORP method of ``cmd.methods`` failed first (its chunks run again as the
    evaluation ran them), then solved ones. A stage of the run: skipped when nothing changed.

    Returns:
        The files written (none without a DORP method).
    """
    methods = [m for m in cmd.methods if m in DORP_VARIANTS]
    if not methods:
        return []
    directory = run.dir / "pictures"
    config = {
        "gifs": cmd.gifs,
        "evaluations": {m: run.stages[_evaluation_key(cmd, m)]["config"] for m in methods},
    }

    def build() -> tuple[list[Path], dict[str, Any]]:
        files: list[Path] = []
        maps: dict[str, Any] = {}
        loaded: dict[str, Any] = {}
        env = cmd.codes.make_env()
        for method in methods:
            sub = _codes_variant(method)
            if sub not in maps:
                loaded[method] = dorp_stages(run, cmd, method)
                maps[sub], written = _diagnostic_pictures(
                    env,
                    cmd.codes.profile,
                    loaded[method][0],
                    directory / sub,
                    cmd.codes.diagnostics_samples,
                )
                files += written
        gifs, solved, drawn = _rollout_gifs(
            run, cmd, methods[0], loaded[methods[0]], maps, directory
        )
        summary = {"files": [str(p) for p in files + gifs], "gif_solved": solved}
        return files + gifs, {**summary, "gif_tasks": drawn}

    def load() -> list[Path]:
        return [Path(p) for p in run.stages["pictures"]["summary"]["files"]]

    return run.stage("pictures", config, [directory], build, load)


def _codes_variant(method: str) -> str:
    """The codes a DORP method plans with: ``""`` (DORP's), ``"arbitrary"``, ``"identity"``."""
    return "" if DORP_VARIANTS[method][0] is None else method.removeprefix("dorp-")


def _rollout_gifs(
    run: Run,
    cmd: Evaluate | Reproduce,
    method: str,
    dorp: Any,
    maps: dict[str, Any],
    directory: Path,
) -> tuple[list[Path], list[bool], list[int]]:
    """``cmd.gifs`` tasks run with ``method`` (``dorp``: its encoder, graph and graph
    stage), as GIFs: the tasks the evaluation failed first, then solved ones
    (:func:`~dorp_rl.eval.tasks_to_draw`). Each task's chunk is run again as the
    evaluation ran it (:func:`~dorp_rl.eval.rollout_chunk`: same chunk, batch and seed),
    so a failure is drawn as it happened on this machine."""
    n = min(cmd.gifs, cmd.tasks)
    if n == 0:
        return [], [], []
    setting = setting_of(cmd.setting)
    batch = min(cmd.tasks, cmd.tasks_per_rollout)
    records = run.stages[_evaluation_key(cmd, method)]["summary"]["per_task"].get("records")
    chosen = tasks_to_draw(records, n) if records else list(range(n))
    env = setting.make_env(batch_size=(batch,), seed=cmd.seed)
    tasks, limit = task_set(cmd, env)
    policy = method_policy(cmd, method, env, _low_level_path(run, cmd), dorp)
    code_maps = maps.get(_codes_variant(method))
    bar = progress_bar(run.progress, total=len(chosen), desc="GIF rollouts", unit="task")
    paths: list[Path] = []
    solved: list[bool] = []
    drawn: list[int] = []
    try:
        for chunk_index in sorted({task // batch for task in chosen}):
            first = chunk_index * batch
            rollout, at_goal = rollout_chunk(
                env,
                policy,
                tasks[first : first + batch],
                first,
                max_steps=limit,
                tasks_per_rollout=batch,
                seed=cmd.seed,
            )
            done = rollout["next", "done"].reshape(rollout.shape[0], -1)
            success = succeeded(rollout["next"]).reshape(rollout.shape[0], -1)
            for task in (t for t in chosen if t // batch == chunk_index):
                i = task - first
                steps = int(done[i].float().argmax()) + 1 if bool(done[i].any()) else done.shape[1]
                drawn.append(task)
                solved.append(bool(at_goal[i]) or bool(success[i, steps - 1]))
                paths.append(
                    save_rollout_gif(
                        rollout[i, :steps], directory / f"rollout_{task}.gif", code_maps
                    )
                )
                if bar is not None:
                    bar.update(1)
    finally:
        if bar is not None:
            bar.close()
    return paths, solved, drawn


def say_pictures(run: Run, pictures: list[Path]) -> None:
    """Names the pictures of a run (GIFs one per line)."""
    if not pictures:
        return
    stills = [p for p in pictures if p.suffix != ".gif"]
    if stills:
        run.say("pictures: " + ", ".join(str(p) for p in stills))
    for gif in (p for p in pictures if p.suffix == ".gif"):
        run.say(f"rollout GIF: {gif}")


def _carry(target: Any, given: Any, default: Any) -> Any:
    """``carry_changes`` of the command line's changes into a setting's preset (its env
    and object count stay the setting's)."""
    return carry_changes(target, given, default, _SETTING_FIELDS)


def _expected_cost(sub: Reproduce) -> float:
    """A rough relative cost of a sub-run, to start the longest ones first: growing with
    the square of the objects and with the methods run, never below one setting's."""
    spec = SETTINGS[sub.setting]
    return max(spec.num_objects**2 * len(sub.methods) / 6, 1.0)


def _setting_command(
    cmd: Reproduce, base: Reproduce, setting: str, run: Run, seed: int | None = None
) -> Reproduce:
    """The single-setting command of ``setting`` in ``--paper``: its presets with the
    command line's ``--codes.*`` / ``--world-model.*`` / ``--latent-model.*`` / ``--dorp.*``
    changes,
    Table 1's methods, in the sub-run ``<setting>`` (or ``<setting>-seed<seed>``, whose
    codes, world models and planners use ``seed``)."""
    preset = default_command("reproduce", setting)
    codes = _carry(preset.codes, cmd.codes, base.codes)
    world_model = _carry(preset.world_model, cmd.world_model, base.world_model)
    latent_model = _carry(preset.latent_model, cmd.latent_model, base.latent_model)
    dorp = _carry(preset.dorp, cmd.dorp, base.dorp)
    seeds: dict[str, Any] = {}
    if seed is not None:
        codes = dataclasses.replace(codes, seed=seed)
        world_model = dataclasses.replace(world_model, seed=seed)
        latent_model = dataclasses.replace(latent_model, seed=seed)
        seeds["seed"] = seed
    return dataclasses.replace(
        cmd,
        root=str(run.dir),
        name=setting if seed is None else f"{setting}-seed{seed}",
        setting=setting,
        codes=codes,
        world_model=world_model,
        latent_model=latent_model,
        dorp=dorp,
        methods=_chosen_methods(cmd, setting),
        paper=False,
        paper_methods=(),
        seeds=(),
        **seeds,
    )


def run_setting(
    sub: Reproduce, echo: Callable[[str], None] | None = None, command_line: str | None = None
) -> dict[str, Any]:
    """One setting of ``--paper`` in its sub-run (``sub`` from :func:`_setting_command`):
    evaluations and pictures. Returns its result ``rows`` (with the planners' ``seed``),
    its stage ``timings`` (by sub-run name) and its ``pictures``; ``echo`` is where the
    sub-run's messages go (default: printed).

    The sub-run's own lock (``<sub-run>/run.lock``) is held throughout, by the process
    that runs it (a worker's, side by side); the parent holds the lock of the run
    above, a lock file of its own, so the two never wait for each other.
    ``command_line`` is recorded for a command refused on the sub-run meanwhile."""
    with Run(sub, "reproduce", echo=echo, command_line=command_line) as subrun:
        return _run_setting_stages(subrun, sub)


def _run_setting_stages(subrun: Run, sub: Reproduce) -> dict[str, Any]:
    before = {k: json.dumps(v) for k, v in subrun.stages.items()}
    evaluate_stage(subrun, sub)
    pictures = pictures_stage(subrun, sub)
    keys = {_evaluation_key(sub, m) for m in sub.methods}
    rows = [
        {**add_paper_figures(subrun.stages[_evaluation_key(sub, m)]["summary"]), "seed": sub.seed}
        for m in sub.methods
    ]
    timings = [
        {
            "setting": sub.name,
            "stage": stage,
            "does": describe_stage(stage),
            "seconds": float(record.get("seconds", 0.0)),
            "this_command": "ran" if before.get(stage) != json.dumps(record) else "reused",
        }
        for stage, record in subrun.stages.items()
        if record.get("config") is not None
        and not (stage.startswith("evaluate:") and stage not in keys)
    ]
    return {"rows": rows, "timings": timings, "pictures": pictures}


def _run_setting_in_worker(sub: Reproduce, messages: Any, command_line: str) -> dict[str, Any]:
    """:func:`run_setting` in a worker process: its messages and bars go to the parent
    through the queue ``messages`` as ``(kind, sub-run name, payload)``."""
    exit_with_parent()
    torch.set_num_threads(sub.threads)
    logging.getLogger("torchrl").setLevel(logging.WARNING)
    relay_bars(lambda event: messages.put(("bar", sub.name, event)))

    def say(message: str) -> None:
        messages.put(("say", sub.name, message))

    return run_setting(sub, echo=say, command_line=command_line)


def _sub_run_command_line(run: Run, name: str) -> str:
    """How a sub-run's lock records its command: the parent's, and which sub-run."""
    return f"{run.command_line} (sub-run {name})"


def _subruns_side_by_side(
    run: Run,
    subs: dict[str, Reproduce],
    processes: int,
    finished: Callable[[str, dict[str, Any]], None],
) -> None:
    """Runs the sub-runs of ``subs`` (by name: a setting, or a setting and seed) in
    ``processes`` worker processes (``spawn``), the longest setting first. Their messages
    are said here, named by sub-run, and their bars drawn here
    (:class:`~dorp_rl.progress.BarMirror`); ``finished(name, result)`` is called as each
    one ends. A failed sub-run stops the queued ones; the running ones finish (their
    stages are kept) before its error is raised."""
    context = multiprocessing.get_context("spawn")
    order = sorted(subs, key=lambda name: _expected_cost(subs[name]), reverse=True)
    bar = progress_bar(run.progress, total=len(order), desc="sub-runs", unit="sub-run")
    mirror = BarMirror()
    manager = SyncManager(ctx=context)
    manager.start(exit_with_parent)  # the queue's process too ends with this one
    with manager:
        messages = manager.Queue()

        def relay() -> None:
            try:
                while not messages.empty():
                    kind, name, payload = messages.get()
                    if kind == "say":
                        run.say(f"[{name}] {payload}")
                    else:
                        mirror.show(payload, prefix=f"[{name}] ")
            except (EOFError, OSError):  # the queue's process has ended (Ctrl-C reaches
                pass  # it too); every sub-run's lines are in its own log.txt as well

        pool = ProcessPoolExecutor(processes, mp_context=context)
        try:
            futures = {
                pool.submit(
                    _run_setting_in_worker, subs[s], messages, _sub_run_command_line(run, s)
                ): s
                for s in order
            }
            pending = set(futures)
            while pending:
                done, pending = wait(pending, timeout=0.5, return_when=FIRST_COMPLETED)
                relay()
                for future in done:
                    try:
                        result = future.result()
                    except BrokenProcessPool as err:
                        raise RuntimeError(
                            f"the worker process of {futures[future]} died (out of memory?); "
                            "run with --workers 1 to see the error in this process."
                        ) from err
                    finished(futures[future], result)
                    if bar is not None:
                        bar.update(1)
        finally:
            pool.shutdown(wait=True, cancel_futures=True)
            relay()
            mirror.close()
            if bar is not None:
                bar.close()


def reproduce_paper(run: Run, cmd: Reproduce) -> list[dict[str, Any]]:
    """The paper's Table 1: :func:`paper_methods` in each of ``cmd.settings`` (only those
    of ``cmd.paper_methods`` if it names any).

    Each setting is a sub-run ``<run>/<setting>/`` (its own play data, codes per
    similarity, graphs, world model, results and pictures). ``--codes.*``,
    ``--world-model.*``, ``--latent-model.*`` and ``--dorp.*`` changes from the defaults
    of ``--setting`` are applied to every setting's preset. Writes into the run folder ``results.csv`` / ``results.md``
    (:data:`~dorp_rl.eval.RESULT_COLUMNS` and the paper's figures,
    :data:`~dorp_rl.eval.results.PAPER_COLUMNS`, plus the table in Table 1's layout),
    ``success.png``, ``steps.png`` and ``timings.csv`` / ``timings.md`` (seconds per
    stage and setting).

    With ``--workers N`` (local backend) up to N settings run side by side in worker
    processes, the longest first, each spreading its evaluations over the workers left
    over (``N // settings``, at least 1); their messages and progress bars are relayed
    here. Every stage is seeded, so the results equal those of one process. With
    ``--backend ray`` the settings run one after another and each evaluation is spread
    over the cluster.

    Returns:
        The result rows, with the paper's figures.
    """
    base = default_command("reproduce", cmd.setting)
    seeds: tuple[int | None, ...] = cmd.seeds or (None,)
    settings = [s for s in cmd.settings if _chosen_methods(cmd, s)]
    for setting in cmd.settings:
        if setting not in settings:
            run.say(
                f"{setting}: left out, Table 1 has none of --paper-methods "
                f"{' '.join(cmd.paper_methods)} there (its methods: "
                f"{', '.join(paper_methods(setting))})"
            )
    jobs = len(settings) * len(seeds)
    side_by_side = min(cmd.workers, jobs) if cmd.backend == "local" else 1
    inner = max(1, cmd.workers // side_by_side)
    subs: dict[str, Reproduce] = {}  # by sub-run name, in the order of --settings, --seeds
    for setting in settings:
        for seed in seeds:
            sub = _setting_command(cmd, base, setting, run, seed)
            if side_by_side > 1:
                sub = dataclasses.replace(sub, workers=inner)
            subs[sub.name] = sub
            run.say(
                f"{sub.name}: {', '.join(sub.methods)} on {sub.tasks} tasks, low level "
                f"{sub.low_level}, in {Path(sub.root) / sub.name}"
            )
    results: dict[str, dict[str, Any]] = {}

    def finished(name: str, result: dict[str, Any]) -> None:
        run.begin_changes()
        results[name] = result
        # After every sub-run, in the order of --settings: a stopped run keeps its times.
        write_timings([t for n in subs if n in results for t in results[n]["timings"]], run.dir)

    if side_by_side > 1:
        run.say(
            f"{side_by_side} sub-runs side by side (longest first), {inner} worker(s) and "
            f"{cmd.threads} thread(s) each; each sub-run's log.txt has its own lines"
        )
        _subruns_side_by_side(run, subs, side_by_side, finished)
    else:
        for name, sub in subs.items():
            finished(name, run_setting(sub, command_line=_sub_run_command_line(run, name)))
    rows = [row for name in subs for row in results[name]["rows"]]
    timings = [t for name in subs for t in results[name]["timings"]]
    pictures = {name: results[name]["pictures"] for name in subs}
    table_rows = pool_seeds(rows) if cmd.seeds else rows
    columns = RESULT_COLUMNS + (SEED_COLUMNS if cmd.seeds else ()) + PAPER_COLUMNS
    figures = plot_results(table_rows, run.dir, PAPER_SUCCESS)
    links = [
        f"- {name}: "
        + ", ".join(
            f"[{p.relative_to(run.dir / name / 'pictures').as_posix()}]"
            f"({p.relative_to(run.dir).as_posix()})"
            for p in files
        )
        for name, files in pictures.items()
        if files
    ]
    sections = [
        "## As the paper's Table 1\n\nOurs, the paper's in brackets (SR: success rate; steps "
        "of the solved tasks, mean ± std; max: none solved within the step limit).\n\n"
        + format_paper_table(table_rows),
        "## Wall-clock per stage\n\nSee [timings.md](timings.md).",
    ]
    sections.insert(1, failure_section(rows, by_seed=bool(cmd.seeds)))
    write_task_records(rows, run.dir / "tasks.csv")
    if links:
        sections.append("## Pictures\n\n" + "\n".join(links))
    if cmd.seeds:
        sections.insert(1, f"Success rates are pooled over the seeds {list(cmd.seeds)} (± std "
                        "over seeds); results.csv has a row per seed and the pooled row "
                        "(seed 'all').")  # fmt: skip
        rows = [{"success_rate_std": "", **r} for r in rows]
        rows += [r for r in table_rows if r.get("seed") == "all"]
    write_results(rows, run.dir, figures, columns=columns, sections=sections)
    print(
        f"\n{format_paper_table(table_rows)}\n\n{format_timings(timings)}\n\n"
        f"Where the time went:\n\n{format_time_by_kind(timings)}\n"
    )
    run.say(
        f"results: {run.dir / 'results.csv'}, {run.dir / 'results.md'}; "
        f"timings: {run.dir / 'timings.csv'}, {run.dir / 'timings.md'}"
    )
    for files in pictures.values():
        say_pictures(run, files)
    return rows
