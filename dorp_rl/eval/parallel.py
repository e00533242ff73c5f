"""Evaluation spread over worker processes (one machine) or a Ray cluster (many machines).

:func:`evaluate_parallel` splits a task set into chunks of ``tasks_per_rollout`` tasks,
runs the chunks on ``workers`` processes and puts the per-task results back in task order.
Its results equal those of :func:`~dorp_rl.eval.evaluate_policy` with the same ``seed``
on one process, for any number of workers and either backend, because:

- every worker rebuilds the env and the policy from the same picklable factories
  (``make_env()``, ``make_policy(env)``), e.g. the methods of an :class:`EvalSpec`, so no
  policy, generator or env crosses a process boundary (under torch 2.13 ``spawn`` a
  worker handed a policy holding a ``torch.Generator`` or an env dies);
- the policy is reseeded with ``seed + k`` before chunk ``k`` (the seeding rule of
  :func:`~dorp_rl.eval.evaluate_policy`), so a chunk's results depend only on its tasks
  and its index, not on the worker that runs it or on what that worker ran before;
- every chunk is one :func:`~dorp_rl.eval.evaluate_policy` call on the same tasks (the
  last, shorter chunk padded the same way).

Each worker process runs with one torch thread (``torch.set_num_threads(1)``): workers
are the parallelism, and several multi-threaded processes on the same cores oversubscribe
them. Float results are bitwise those of a one-thread single-process run; a caller with
several threads can in principle differ in the last bits of a planning cost.

Backends:

- ``"local"``: a :class:`concurrent.futures.ProcessPoolExecutor` with the ``spawn``
  start method, each process building its env and policy once (pool initializer). It was
  chosen over torchrl's multi-process collectors and its ``Evaluator``: these collect
  frames or whole episodes from the env's own resets, while a task set needs every
  rollout to start from given start and goal states and to stop when all its tasks are
  done, with a seed per chunk; the executor gives exactly that with the plain
  :func:`~dorp_rl.eval.evaluate_policy` loop inside. As with any ``spawn`` pool, a
  script that calls it must keep its top-level code under
  ``if __name__ == "__main__":`` (each new process imports the script).
- ``"ray"``: one Ray actor per worker (one CPU each), chunks dealt out as actors become
  free. Ray is optional (``pip install dorp-rl[ray]``) and imported only here. An
  already initialised Ray (``ray.init`` by the caller) is used as it is and left running.
  Otherwise Ray is started here and shut down after: ``address=None`` starts a local
  instance, ``"auto"`` joins the cluster of this machine, ``"ray://host:port"`` a remote
  one. On a cluster, every node needs dorp-rl installed and the files an
  :class:`EvalSpec` names (checkpoints, graph) at the same paths.
"""

from __future__ import annotations

import dataclasses
import multiprocessing
import multiprocessing.connection
import os
import pickle
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.envs import EnvBase

from dorp_rl.eval.settings import setting_of
from dorp_rl.eval.tasks import (
    _ChunkFile,
    check_env,
    check_rollout_batch,
    check_task_set,
    evaluate_policy,
    summarize_chunks,
    task_limit,
)
from dorp_rl.progress import progress_bar
from dorp_rl.validation import check_choice, check_int, check_seed, derive_seed

#: DORPConfig fields that EvalSpec sets from its ``candidates`` and ``planning_horizon``
#: (the planners' shape, the same for every method)
PLANNER_SHAPE = ("num_candidates", "planning_horizon")

if TYPE_CHECKING:  # for annotations; the policies are imported where used (make_policy)
    from dorp_rl.policies import DORPConfig

#: backends of :func:`evaluate_parallel`
BACKENDS = ("local", "ray")
#: methods an :class:`EvalSpec` builds
METHODS = ("dorp", "vf-rs", "vf-cem", "random")

Policy = Callable[[TensorDictBase], TensorDictBase]


# --------------------------------------------------------------------------- spec
@dataclass(frozen=True)
class EvalSpec:
    """A picklable recipe for the acting env and a policy, rebuilt inside every worker.

    Attributes:
        setting: a :data:`~dorp_rl.eval.SETTINGS` name (environment and object count), or
            an env profile's name or import path (:func:`~dorp_rl.eval.setting_of`).
        method: ``"dorp"``, ``"vf-rs"``, ``"vf-cem"`` or ``"random"``.
        encoder: DORP only: ``"oracle"`` (:class:`~dorp_rl.envs.OracleCodeEncoder`
            with ``oracle_cell_size``), a representation checkpoint path, or an encoder.
        graph: DORP only: the path of a saved :class:`~dorp_rl.planners.CodeGraph`, or
            a graph.
        low_level: planning model: ``"gt"`` (the true dynamics) or a world-model
            checkpoint path.
        tasks_per_rollout: the env's batch size (tasks run side by side).
        candidates, planning_horizon: the planners' shape.
        dorp: DORP only: :class:`~dorp_rl.policies.DORPConfig` fields over the setting's
            (:meth:`dorp_config`), e.g. ``{"planner": "cem", "waypoint_budget": 40}``;
            ``candidates`` and ``planning_horizon`` size its planners.
        seed: the planners' construction seed (:func:`evaluate_parallel` reseeds them per
            chunk) and the env's seed.
        env_kwargs: more arguments of the env (e.g. ``{"max_steps": 100}``).
        planner_kwargs: more arguments of the planners (e.g. ``{"optim_steps": 2}``).
        oracle_cell_size: region side of the oracle codes.

    Examples:
        >>> spec = EvalSpec("1obj", "vf-rs", candidates=20, planning_horizon=4)
        >>> env = spec.make_env()
        >>> policy = spec.make_policy(env)
        >>> tuple(env.batch_size)
        (1,)
    """

    setting: str = "2obj"
    method: str = "dorp"
    encoder: Any = None
    graph: Any = None
    low_level: str = "gt"
    tasks_per_rollout: int = 1
    candidates: int = 1000
    planning_horizon: int = 14
    dorp: dict[str, Any] = field(default_factory=dict)
    seed: int = 0
    env_kwargs: dict[str, Any] = field(default_factory=dict)
    planner_kwargs: dict[str, Any] = field(default_factory=dict)
    oracle_cell_size: int = 4

    def __post_init__(self) -> None:
        setting_of(self.setting)  # a setting or an env profile, else named
        check_choice("method", self.method, METHODS)
        for name in ("tasks_per_rollout", "candidates", "planning_horizon"):
            check_int(name, getattr(self, name), low=1)
        check_seed(self.seed)
        if self.dorp:
            self.dorp_config()  # names the field that is wrong
        if self.method == "dorp" and (self.encoder is None or self.graph is None):
            raise ValueError(
                "method 'dorp' needs encoder ('oracle', a checkpoint path or an encoder) and "
                f"graph (a saved CodeGraph path or a graph); got encoder={self.encoder!r}, "
                f"graph={self.graph!r}."
            )
        if self.low_level != "gt" and not Path(self.low_level).is_file():
            raise ValueError(
                f"low_level must be 'gt' or a world-model checkpoint file, got {self.low_level!r}."
            )

    def make_env(self) -> EnvBase:
        """The acting env, ``batch_size=(tasks_per_rollout,)``."""
        return setting_of(self.setting).make_env(
            batch_size=(self.tasks_per_rollout,), seed=self.seed, **self.env_kwargs
        )

    def dorp_config(self) -> DORPConfig:
        """The :class:`~dorp_rl.policies.DORPConfig` of the setting's env profile for its
        object count (rearrangement's differ from 5 blocks on), with :attr:`dorp` over it
        and :attr:`candidates` / :attr:`planning_horizon` as its planners' shape."""
        from dorp_rl.policies import DORPConfig

        setting = setting_of(self.setting)
        shape = dict(zip(PLANNER_SHAPE, (self.candidates, self.planning_horizon), strict=True))
        unknown = sorted(set(self.dorp) - {f.name for f in dataclasses.fields(DORPConfig)})
        if unknown:
            raise ValueError(f"EvalSpec.dorp names {unknown}, which are no DORPConfig fields.")
        shaped = sorted(set(self.dorp) & set(shape))
        if shaped:
            raise ValueError(
                f"EvalSpec.dorp sets {shaped}: the planners' shape is EvalSpec's candidates "
                "and planning_horizon (the same for every method)."
            )
        return DORPConfig.for_env(
            setting.profile, num_objects=setting.num_objects, **{**self.dorp, **shape}
        )

    def make_policy(self, env: EnvBase) -> Policy:
        """The policy of :attr:`method` for ``env`` (``env.rand_action`` for random)."""
        from dorp_rl.policies import (
            VisualForesightPolicy,
            make_dorp_policy,
            make_planning_env,
        )

        if self.method == "random":
            return env.rand_action
        if self.method == "dorp":
            encoder = self.encoder
            if isinstance(encoder, str) and encoder == "oracle":
                from dorp_rl.envs import OracleCodeEncoder

                encoder = OracleCodeEncoder(env, cell_size=self.oracle_cell_size)
            return make_dorp_policy(
                env,
                encoder,
                self.graph,
                self.dorp_config(),
                **self.planner_kwargs,
                low_level=self.low_level,
                seed=self.seed,
            )
        return VisualForesightPolicy(
            make_planning_env(env, self.low_level),
            self.method.removeprefix("vf-"),
            planning_horizon=self.planning_horizon,
            num_candidates=self.candidates,
            seed=self.seed,
            **self.planner_kwargs,
        )


# --------------------------------------------------------------------------- workers
class _ChunkRunner:
    """Builds the env and policy once in a worker and runs chunks of tasks on them."""

    def __init__(
        self,
        make_env: Callable[[], EnvBase],
        make_policy: Callable[[EnvBase], Policy],
        options: dict[str, Any],
    ) -> None:
        torch.set_num_threads(1)
        self.env = make_env()
        self.policy = make_policy(self.env)
        self.options = options

    def run(self, index: int, state: list, goal_state: list) -> tuple[int, dict[str, Any]]:
        """Chunk ``index`` (start and goal states as nested lists); per-task lists."""
        tasks = TensorDict(
            state=torch.tensor(state, dtype=torch.int64),
            goal_state=torch.tensor(goal_state, dtype=torch.int64),
            batch_size=[len(state)],
        )
        opts = self.options
        result = evaluate_policy(
            self.env,
            self.policy,
            tasks,
            max_steps=opts["max_steps"],
            tasks_per_rollout=opts["tasks_per_rollout"],
            report_keys=opts["report_keys"],
            # One chunk: evaluate_policy reseeds it with (seed + index) + 0.
            seed=derive_seed(opts["seed"], index),
        )
        keys = ("success", "steps", "records", *opts["report_keys"])
        return index, {key: result[key] for key in keys}


_RUNNER: _ChunkRunner | None = None  # the runner of a local worker process


def exit_with_parent() -> None:
    """In a worker process, ends the process as soon as its parent is gone.

    A pool's worker outlives a parent that was killed outright (``SIGKILL``, the OOM
    killer, a closed session) and runs its task to the end: for a sub-run of
    ``dorp reproduce --paper --workers N`` that is hours of CPU, holding the run's
    locks so that running the command again would be refused. A daemon thread waits on
    the parent's sentinel and exits when it closes; what the worker had finished is kept
    (stage records, checkpoints, finished chunks of tasks). Does nothing in a process
    that no ``multiprocessing`` parent started.
    """
    parent = multiprocessing.parent_process()
    if parent is None:
        return

    def watch() -> None:
        multiprocessing.connection.wait([parent.sentinel])
        os._exit(1)  # no clean-up: the parent, which would receive it, is gone

    threading.Thread(target=watch, name="exit with parent", daemon=True).start()


def _init_local_worker(
    make_env: Callable[[], EnvBase],
    make_policy: Callable[[EnvBase], Policy],
    options: dict[str, Any],
) -> None:
    global _RUNNER
    exit_with_parent()
    _RUNNER = _ChunkRunner(make_env, make_policy, options)


def _run_local_chunk(index: int, state: list, goal_state: list) -> tuple[int, dict[str, Any]]:
    assert _RUNNER is not None, "worker process was not initialised"
    return _RUNNER.run(index, state, goal_state)


def _import_ray() -> Any:
    try:
        import ray
    except ImportError as err:
        raise ImportError(
            "backend='ray' needs Ray, an optional dependency: pip install dorp-rl[ray] "
            "(or pip install 'ray>=2.9')."
        ) from err
    return ray


# --------------------------------------------------------------------------- backends
def _run_local(
    jobs: list[tuple[int, list, list]],
    workers: int,
    init: tuple[Any, Any, dict[str, Any]],
) -> Iterator[tuple[int, dict[str, Any]]]:
    try:
        pickle.dumps(init[:2])
    except Exception as err:  # pickling raises many types
        raise ValueError(
            "make_env and make_policy must be picklable to reach the worker processes "
            "(module-level functions, functools.partial of them, or the methods of an "
            f"EvalSpec); pickling failed: {err}"
        ) from err
    context = multiprocessing.get_context("spawn")
    with ProcessPoolExecutor(
        max_workers=workers, mp_context=context, initializer=_init_local_worker, initargs=init
    ) as pool:
        pending = {pool.submit(_run_local_chunk, *job) for job in jobs}
        try:
            while pending:
                done, pending = wait(pending, return_when=FIRST_COMPLETED)
                for future in done:
                    yield future.result()
        except BrokenProcessPool as err:
            raise RuntimeError(
                "a worker process died (out of memory, or the env/policy factories failed "
                "in the new process); run with workers=1 to see the error in this process."
            ) from err
        finally:
            for future in pending:
                future.cancel()


def _run_ray(
    jobs: list[tuple[int, list, list]],
    workers: int,
    init: tuple[Any, Any, dict[str, Any]],
    address: str | None,
) -> Iterator[tuple[int, dict[str, Any]]]:
    ray = _import_ray()
    started = False
    if not ray.is_initialized():
        kwargs: dict[str, Any] = {"address": address}
        if address is None:
            kwargs["include_dashboard"] = False
        ray.init(**kwargs)
        started = True
    actors: list[Any] = []
    try:
        runner = ray.remote(num_cpus=1)(_ChunkRunner)
        actors = [runner.remote(*init) for _ in range(workers)]
        todo = list(jobs)
        running: dict[Any, Any] = {}  # object ref -> actor
        for actor in actors:
            if todo:
                running[actor.run.remote(*todo.pop(0))] = actor
        while running:
            ready, _ = ray.wait(list(running), num_returns=1)
            actor = running.pop(ready[0])
            if todo:
                running[actor.run.remote(*todo.pop(0))] = actor
            yield ray.get(ready[0])
    finally:
        for actor in actors:
            ray.kill(actor)
        if started:
            ray.shutdown()


# --------------------------------------------------------------------------- entry point
def evaluate_parallel(
    make_env: Callable[[], EnvBase],
    make_policy: Callable[[EnvBase], Policy],
    tasks: TensorDictBase,
    *,
    seed: int = 0,
    max_steps: int | None = None,
    tasks_per_rollout: int = 1,
    workers: int = 1,
    backend: str = "local",
    address: str | None = None,
    progress: bool = False,
    report_keys: Sequence[str] = (),
    resume_file: str | Path | None = None,
) -> dict[str, Any]:
    """Runs a policy on every task of ``tasks``, chunk by chunk over ``workers`` processes.

    The per-task results (``success``, ``steps``, the ``report_keys`` lists), in task
    order, equal those of ``evaluate_policy(env, policy, tasks, seed=seed, ...)`` in one
    process; see the module docstring for why. With ``workers=1`` and the local backend
    (or a single chunk) it is that call, in this process.

    Args:
        make_env: builds the acting env (``batch_size=(tasks_per_rollout,)``, or
            ``batch_size=()`` with ``batch_locked=False``); picklable for the local
            backend (e.g. :meth:`EvalSpec.make_env`, a module-level function or a
            ``functools.partial`` of one).
        make_policy: builds the policy for that env (e.g. :meth:`EvalSpec.make_policy`).
        tasks: from :func:`~dorp_rl.eval.make_task_set`, ``[num_tasks]`` with
            ``num_tasks >= 1`` (checked with :func:`~dorp_rl.eval.check_task_set`).
        seed: the policy is reseeded with ``seed + k`` before chunk ``k``.
        max_steps: step limit per task (default: the env's).
        tasks_per_rollout: tasks per chunk (one batched rollout); the last chunk may be
            shorter.
        workers: processes (local) or Ray actors (one CPU each); at most one per chunk
            is started.
        backend: ``"local"`` (processes on this machine) or ``"ray"``.
        address: Ray only: ``None`` (the running Ray, or a new local one), ``"auto"`` or
            ``"ray://host:port"``.
        progress: show a tqdm bar over tasks.
        report_keys: as in :func:`~dorp_rl.eval.evaluate_policy`.
        resume_file: as in :func:`~dorp_rl.eval.evaluate_policy`: finished chunks are
            written there as they come back, and chunks already in it are not run again.

    Returns:
        The dict of :func:`~dorp_rl.eval.evaluate_policy` (``seconds`` is the wall time,
        worker start-up and earlier runs of a ``resume_file`` included), plus
        ``workers`` (processes used) and ``backend``.

    Raises:
        ValueError: ``workers < 1``, an unknown backend, an ``address`` without the Ray
            backend, bad ``tasks_per_rollout``/``max_steps``/``seed``, an empty or bad
            task set, an env whose batch size does not fit ``tasks_per_rollout``, or
            factories that are not callable or do not pickle.
        ImportError: ``backend="ray"`` without Ray installed.

    Examples:
        >>> from dorp_rl.eval import EvalSpec, evaluate_parallel, make_task_set
        >>> spec = EvalSpec("1obj", "vf-rs", tasks_per_rollout=2, candidates=20,
        ...                 planning_horizon=4)
        >>> tasks = make_task_set(spec.make_env(), 4, seed=0)
        >>> result = evaluate_parallel(spec.make_env, spec.make_policy, tasks,
        ...                            tasks_per_rollout=2, max_steps=5)
        >>> len(result["steps"])
        4
    """
    workers = check_int("workers", workers, low=1)
    backend = check_choice("backend", backend, BACKENDS)
    if address is not None and backend != "ray":
        raise ValueError(
            f"address={address!r} is for the Ray backend: pass backend='ray' or drop it."
        )
    tasks_per_rollout = check_int("tasks_per_rollout", tasks_per_rollout, low=1)
    seed = check_seed(seed)
    report_keys = tuple(report_keys)
    for name, factory in (("make_env", make_env), ("make_policy", make_policy)):
        if not callable(factory):
            raise ValueError(
                f"{name} must be a callable that builds the "
                f"{'acting env' if name == 'make_env' else 'policy for an env'} (e.g. "
                f"EvalSpec(...).{name}), got {type(factory).__name__} {factory!r:.60}."
            )
    tasks = check_task_set(tasks)
    n = tasks.shape[0]
    chunks = -(-n // tasks_per_rollout)
    if backend == "local" and min(workers, chunks) == 1:
        env = make_env()
        result = evaluate_policy(
            env,
            make_policy(env),
            tasks,
            max_steps=max_steps,
            tasks_per_rollout=tasks_per_rollout,
            progress=progress,
            report_keys=report_keys,
            seed=seed,
            resume_file=resume_file,
        )
        return {**result, "workers": 1, "backend": backend}

    # Check the env here, before any worker starts, and resolve the step limit.
    env = check_env(make_env(), "the env of make_env()")
    limit = task_limit(env, max_steps)
    check_rollout_batch(env, tasks_per_rollout, name="the env of make_env()")
    check_task_set(tasks, env)
    del env
    record = _ChunkFile.open(resume_file, tasks, limit, tasks_per_rollout, seed, report_keys)
    by_chunk: dict[int, dict[str, Any]] = {} if record is None else dict(record.chunks)
    earlier = 0.0 if record is None else record.seconds
    options = {
        "max_steps": limit,
        "tasks_per_rollout": tasks_per_rollout,
        "report_keys": report_keys,
        "seed": seed,
    }
    jobs = []
    for index in range(chunks):
        if index in by_chunk:
            continue
        chunk = tasks[index * tasks_per_rollout : (index + 1) * tasks_per_rollout]
        jobs.append((index, chunk["state"].tolist(), chunk["goal_state"].tolist()))
    used = max(1, min(workers, len(jobs)))
    start = time.perf_counter()
    init = (make_env, make_policy, options)
    done = 0 if record is None else record.finished_tasks  # recorded: not progress
    bar = progress_bar(progress, total=n, initial=done, desc=f"tasks ({used} {backend} workers)")
    try:
        if jobs:
            results = (
                _run_local(jobs, used, init)
                if backend == "local"
                else _run_ray(jobs, used, init, address)
            )
            for index, chunk_result in results:
                by_chunk[index] = chunk_result
                if record is not None:
                    record.add(index, chunk_result, earlier + time.perf_counter() - start)
                if bar is not None:
                    bar.update(len(chunk_result["success"]))
    finally:
        if bar is not None:
            bar.close()
    ordered = [by_chunk[index] for index in range(chunks)]
    seconds = earlier + time.perf_counter() - start
    result = summarize_chunks(tasks, ordered, limit, seconds, report_keys)
    return {**result, "workers": used, "backend": backend}
