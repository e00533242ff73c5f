"""Seeded task sets and the evaluation harness: success rate and steps of a policy.

A task is a start ``state`` and a ``goal_state``; a task set is a TensorDict of them
(``[num_tasks]``), drawn by the env's profile (:attr:`~dorp_rl.envs.EnvProfile.draw_tasks`,
by default the env's own reset) with a fixed seed, so every method is measured on the
same tasks. :func:`evaluate_policy` runs a policy on every task with ``env.rollout``
from ``env.reset(tasks, set_state=True)`` and counts a task solved when the env says so
within the step limit (its ``success`` entry, else ``terminated``); it reports the steps
next to the lower bound of each task when the profile knows one. Any TorchRL env that
starts from a given ``state`` / ``goal_state`` on ``reset(td, set_state=True)`` can be
evaluated.

Seeding rule: with ``seed`` given, :func:`evaluate_policy` reseeds the policy before the
chunk of tasks ``[k * tasks_per_rollout, (k + 1) * tasks_per_rollout)`` with ``seed + k``
(:func:`seed_policy`), so a chunk's results depend only on its tasks and its index, not on
which chunks ran before it in the same process. :func:`~dorp_rl.eval.evaluate_parallel`
uses the same rule, which is why it gives the same per-task results on any number of
worker processes or machines.
"""

from __future__ import annotations

import hashlib
import json
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.envs import EnvBase

from dorp_rl.envs.profile import EnvProfile, profile_of, reset_tasks
from dorp_rl.progress import progress_bar
from dorp_rl.validation import MissingKeyError, check_int, check_seed, derive_seed


def seed_policy(policy: Any, seed: int) -> None:
    """Reseeds ``policy`` for one chunk of tasks: ``policy.set_seed(seed)`` when it has
    one (the planner-based policies), otherwise torch's global generator
    (``torch.manual_seed(seed)``), which ``env.rand_action`` and plain functions draw from.
    """
    seed = check_seed(seed)
    set_seed = getattr(policy, "set_seed", None)
    if callable(set_seed):
        set_seed(seed)
    else:
        torch.manual_seed(seed)


def check_env(env: Any, name: str = "env") -> EnvBase:
    """``env`` if it is a TorchRL env that tasks can be set on (it writes ``state`` and
    ``goal_state`` and starts from them on ``reset(td, set_state=True)``), else
    ``ValueError`` naming ``name`` and what is missing."""
    if not isinstance(env, EnvBase):
        raise ValueError(
            f"{name} must be a TorchRL EnvBase (dorp_rl.envs.make_env(<profile>) or your "
            f"own), got {type(env).__name__} {env!r:.60}."
        )
    keys = set(env.observation_spec.keys())
    missing = [k for k in ("state", "goal_state") if k not in keys]
    if missing:
        raise ValueError(
            f"{name} ({type(env).__name__}) has no {missing} in its observation spec: a task "
            "is a start state and a goal state the env is reset to (reset(td, set_state=True))."
        )
    if not getattr(env, "_supports_set_state", False):
        raise ValueError(
            f"{name} ({type(env).__name__}) does not declare _supports_set_state = True: "
            "tasks start from given states through env.reset(td, set_state=True)."
        )
    return env


def task_limit(env: EnvBase, max_steps: int | None = None) -> int:
    """The step limit of a task on ``env``: ``max_steps``, else the env's ``max_steps``,
    else its profile's (:meth:`~dorp_rl.envs.EnvProfile.task_limit`)."""
    if max_steps is not None:
        return check_int("max_steps", max_steps, low=1)
    limit = getattr(env, "max_steps", None)
    if limit is None:
        profile = profile_of(env)
        limit = profile.task_limit(env=env) if profile is not None else 200
    return check_int("max_steps", limit, low=1)


def _state_shape(env: EnvBase) -> tuple[int, ...]:
    spec = env.observation_spec["state"]
    return tuple(spec.shape[len(env.batch_size) :])


def check_policy(policy: Any, name: str = "policy") -> Callable[[TensorDictBase], TensorDictBase]:
    """``policy`` if it is callable (a TensorDict module or function), else ``ValueError``."""
    if not callable(policy):
        raise ValueError(
            f"{name} must be a TensorDict policy: a module or callable that takes the "
            "tensordict of a step and writes its 'action' (e.g. env.rand_action, "
            f"make_dorp_policy(...), VisualForesightPolicy(...)), got {type(policy).__name__} "
            f"{policy!r:.60}."
        )
    return policy


def check_task_set(tasks: Any, env: EnvBase | None = None, name: str = "tasks") -> TensorDictBase:
    """Checks a task set (:func:`make_task_set`) before anything runs on it; returns it.

    A task set is a TensorDict ``[num_tasks]`` (``num_tasks >= 1``) holding int64
    ``state`` and ``goal_state``; its optional ``lower_bound`` holds one finite number
    ``>= 0`` per task (steps cannot be negative, and a NaN bound would be averaged into
    ``mean_lower_bound``). With ``env``, starts and goals must be states of ``env``: its
    state shape and, when the env declares ``check_state(states, name)``, its rules.

    Raises:
        ValueError: naming ``name``, the entry and what it must be.
    """
    if not isinstance(tasks, TensorDictBase):
        raise ValueError(
            f"{name} must be a TensorDict of tasks (make_task_set), got {type(tasks).__name__}."
        )
    if tasks.batch_dims != 1:
        raise ValueError(
            f"{name} must have one batch dimension [num_tasks], got batch_size "
            f"{list(tasks.batch_size)}."
        )
    for key in ("state", "goal_state"):
        if key not in tasks.keys():
            raise ValueError(
                f"{name} must hold {key!r} (see make_task_set), got {list(tasks.keys())}."
            )
    if tasks.shape[0] == 0:
        raise ValueError(
            f"{name} is empty: an evaluation needs at least one task (make_task_set(env, n) "
            "with n >= 1)."
        )
    if "lower_bound" in tasks.keys():
        bound = tasks.get("lower_bound")
        if bound.dtype == torch.bool or bound.dtype.is_complex:
            raise ValueError(
                f"{name}['lower_bound'] must hold numbers of steps, got dtype {bound.dtype}."
            )
        if tuple(bound.shape) != (tasks.shape[0],):
            raise ValueError(
                f"{name}['lower_bound'] must have shape [{tasks.shape[0]}] (one per task), got "
                f"{list(bound.shape)}."
            )
        bad = ~torch.isfinite(bound.double()) | (bound < 0)
        if bool(bad.any()):
            first = int(bad.nonzero()[0])
            raise ValueError(
                f"{name}['lower_bound'] must hold finite step counts >= 0 (a -1 is a goal the "
                f"env cannot reach), got {bound[first].item()} at task {first}."
            )
    if env is not None:
        shape = (tasks.shape[0], *_state_shape(env))
        check_state = getattr(env, "check_state", None)
        for key in ("state", "goal_state"):
            value = tasks.get(key)
            if callable(check_state):
                value = check_state(value, f"{name}[{key!r}]")
            if tuple(value.shape) != shape:
                raise ValueError(
                    f"{name}[{key!r}] must have shape {list(shape)} ([num_tasks, "
                    f"*state_shape] of {type(env).__name__}), got {list(value.shape)}."
                )
    return tasks


def make_task_set(
    env: EnvBase, num_tasks: int, seed: int = 0, profile: EnvProfile | None = None
) -> TensorDictBase:
    """``num_tasks`` start/goal pairs of ``env`` drawn with ``seed`` by its profile.

    ``profile`` (default: the registered profile of ``env``, :func:`~dorp_rl.envs.profile_of`,
    else the generic one) draws them (:meth:`~dorp_rl.envs.EnvProfile.tasks`): the grid
    worlds from their start and goal distributions, leaving the env's generator as it was;
    by default what ``env.reset()`` draws after ``env.set_seed(seed)``. Starts equal to
    their goal are redrawn. The task set is checked (:func:`check_task_set`) before it is
    returned: a lower bound given as negative (an unreachable goal) is refused.

    Returns:
        TensorDict ``[num_tasks]`` with ``state``, ``goal_state`` (int64) and, when the
        profile knows one, ``lower_bound`` (int64 ``[num_tasks]``).

    Examples:
        >>> from dorp_rl.envs import ObjectRearrangementEnv
        >>> from dorp_rl.eval import make_task_set
        >>> tasks = make_task_set(ObjectRearrangementEnv(num_objects=2), 5, seed=0)
        >>> tasks["state"].shape, bool((tasks["lower_bound"] > 0).all())
        (torch.Size([5, 2, 2]), True)
    """
    env = check_env(env)
    num_tasks = check_int("num_tasks", num_tasks, low=1)
    seed = check_seed(seed)
    profile = profile or profile_of(env)
    tasks = (
        reset_tasks(env, num_tasks, seed)
        if profile is None
        else profile.tasks(env, num_tasks, seed)
    )
    try:
        return check_task_set(tasks, env)
    except ValueError as err:
        raise ValueError(
            f"make_task_set: the tasks drawn from {type(env).__name__} are no task set: {err}"
        ) from None


def check_rollout_batch(env: EnvBase, tasks_per_rollout: int, name: str = "env") -> None:
    """Refuses a batch-locked ``env`` whose batch is not ``(tasks_per_rollout,)``.

    Raises:
        ValueError: naming ``name``'s batch size, ``tasks_per_rollout`` and the envs that fit.
    """
    locked = env.batch_locked and env.batch_size != torch.Size([])
    if locked and env.batch_size != torch.Size([tasks_per_rollout]):
        raise ValueError(
            f"{name} has batch_size {tuple(env.batch_size)} but tasks_per_rollout is "
            f"{tasks_per_rollout}: give an env with batch_size=({tasks_per_rollout},) or "
            "batch_size=() and batch_locked=False."
        )


def evaluate_policy(
    env: EnvBase,
    policy: Callable[[TensorDictBase], TensorDictBase],
    tasks: TensorDictBase,
    *,
    max_steps: int | None = None,
    tasks_per_rollout: int = 1,
    progress: bool = False,
    report_keys: Sequence[str] = (),
    seed: int | None = None,
    resume_file: str | Path | None = None,
) -> dict[str, Any]:
    """Runs ``policy`` on every task and returns success and step figures.

    Tasks run ``tasks_per_rollout`` at a time (one batched ``env.rollout``, stopped
    when all of them are done): batching is faster with cheap policies, one at a time
    wastes no planning on tasks already solved.

    Args:
        env: the acting env; it must take ``tasks_per_rollout`` rows (an env with
            ``batch_size=(n,)`` needs ``tasks_per_rollout == n``; ``batch_size=()``
            with ``batch_locked=False`` takes any).
        policy: a TensorDict policy: a module or callable that takes a step's
            tensordict and writes its ``action`` (e.g. a planner-based policy, or
            ``env.rand_action``).
        tasks: from :func:`make_task_set`, at least one task (checked with
            :func:`check_task_set`: the starts and goals must be states of ``env``,
            lower bounds finite and ``>= 0``).
        max_steps: step limit per task (default: ``env.max_steps``).
        tasks_per_rollout: tasks per batched rollout.
        progress: show a tqdm bar over tasks.
        report_keys: keys the policy writes (e.g. ``dorp_replans``) whose value at each
            task's last step is reported per task, as a list of numbers (the first
            element of the value).
        seed: if given, the policy is reseeded with ``seed + k`` before the ``k``-th
            chunk of ``tasks_per_rollout`` tasks (:func:`seed_policy`); the rule that makes
            :func:`~dorp_rl.eval.evaluate_parallel` match this function. ``None`` (the
            default) leaves the policy's generators as they are.
        resume_file: a JSON file where the results of each finished chunk are written.
            Chunks already in it are not run again, so an evaluation stopped part way
            (a long one through a video model) resumes at its first unfinished chunk
            with the results of an uninterrupted run. Needs ``seed``; the caller keeps
            the policy the same (the file identifies the tasks, limit, chunk size, seed
            and report keys, and refuses a different evaluation). ``seconds`` then
            includes the earlier runs.

    A task whose start already is its goal is solved at step 0, whatever the policy
    does next (success is checked before the first action).

    Returns:
        ``success`` (bool list per task), ``steps`` (int list: steps until success, 0
        for a task solved at its start, or the limit), ``success_rate``, ``mean_steps``
        (over successful tasks, ``nan`` if none), ``mean_lower_bound`` (over the same
        tasks), ``num_tasks``, ``seconds``, ``records`` (one dict per task: ``task``,
        ``outcome`` -- ``"solved"``, ``"step_limit"`` or the reason the policy gave it up
        -- ``steps``, and what the policy's ``task_records`` adds; :func:`task_records`)
        and one list per entry of ``report_keys``.

    Examples:
        >>> from dorp_rl.data import UniformRandomPolicy
        >>> from dorp_rl.envs import ObjectRearrangementEnv
        >>> from dorp_rl.eval import evaluate_policy, make_task_set
        >>> env = ObjectRearrangementEnv(num_objects=1, batch_size=(), batch_locked=False, seed=0)
        >>> tasks = make_task_set(env, 4, seed=0)
        >>> policy = UniformRandomPolicy(env.num_actions, seed=0)
        >>> result = evaluate_policy(env, policy, tasks, max_steps=20, tasks_per_rollout=4)
        >>> result["num_tasks"], len(result["success"]), max(result["steps"]) <= 20
        (4, 4, True)
    """
    env = check_env(env)
    policy = check_policy(policy)
    limit = task_limit(env, max_steps)
    tasks_per_rollout = check_int("tasks_per_rollout", tasks_per_rollout, low=1)
    seed = check_seed(seed, optional=True)
    tasks = check_task_set(tasks, env)
    n = tasks.shape[0]
    check_rollout_batch(env, tasks_per_rollout)
    if resume_file is not None and seed is None:
        raise ValueError(
            "resume_file needs seed: a chunk's results then depend only on its index, "
            "so finished chunks can be skipped."
        )
    record = _ChunkFile.open(resume_file, tasks, limit, tasks_per_rollout, seed, report_keys)
    chunks: list[dict[str, list]] = []
    earlier = 0.0 if record is None else record.seconds
    # Tasks of recorded chunks count from the start, not as progress (the time left).
    done = 0 if record is None else record.finished_tasks
    bar = progress_bar(progress, total=n, initial=done, desc="tasks", unit="task")
    start = time.perf_counter()
    for first in range(0, n, tasks_per_rollout):
        index = first // tasks_per_rollout
        if record is not None and index in record.chunks:
            chunks.append(record.chunks[index])
        else:
            chunks.append(
                _run_chunk(
                    env,
                    policy,
                    tasks[first : first + tasks_per_rollout],
                    first,
                    limit,
                    tasks_per_rollout,
                    report_keys,
                    seed,
                    bar,
                )
            )
            if record is not None:
                record.add(index, chunks[-1], earlier + time.perf_counter() - start)
        if bar is not None and first + len(chunks[-1]["success"]) > bar.n:
            bar.update(first + len(chunks[-1]["success"]) - bar.n)
    if bar is not None:
        bar.close()
    seconds = earlier + time.perf_counter() - start
    return summarize_chunks(tasks, chunks, limit, seconds, report_keys)


def summarize_chunks(
    tasks: TensorDictBase,
    chunks: Sequence[dict[str, list]],
    max_steps: int,
    seconds: float,
    report_keys: Sequence[str] = (),
) -> dict[str, Any]:
    """:func:`summarize` of per-chunk results (``success``, ``steps``, ``records`` and the
    ``report_keys`` lists of each chunk, in task order). A chunk without records (kept
    by an older version) gets the outcome and steps of each task alone."""
    joined = {k: [v for c in chunks for v in c[k]] for k in ("success", "steps", *report_keys)}
    reported = {key: joined[key] for key in report_keys}
    records: list[dict[str, Any]] = []
    for chunk in chunks:
        given = chunk.get("records") or [
            {"outcome": SOLVED if ok else STEP_LIMIT, "steps": int(n)}
            for ok, n in zip(chunk["success"], chunk["steps"], strict=True)
        ]
        records += [{**r, "task": len(records) + i} for i, r in enumerate(given)]
    return summarize(
        tasks, joined["success"], joined["steps"], max_steps, seconds, reported, records
    )


def rollout_chunk(
    env: EnvBase,
    policy: Callable[[TensorDictBase], TensorDictBase],
    chunk: TensorDictBase,
    first: int = 0,
    *,
    max_steps: int | None = None,
    tasks_per_rollout: int | None = None,
    seed: int | None = None,
    bar: Any = None,
) -> tuple[TensorDictBase, torch.Tensor]:
    """The batched rollout of one chunk of tasks, as :func:`evaluate_policy` runs it.

    With the same ``env``, ``policy``, ``seed``, ``tasks_per_rollout`` and chunk (tasks
    ``first`` onwards of the set) this is the rollout the evaluation saw, so a failed
    task can be drawn as it failed (``dorp evaluate`` draws failures first).

    Args:
        env, policy: as in :func:`evaluate_policy`.
        chunk: the chunk's tasks (rows of :func:`make_task_set`).
        first: index of the chunk's first task in the set (it picks the seed).
        max_steps: step limit (default: ``env.max_steps``).
        tasks_per_rollout: the evaluation's chunk size (default: the chunk's rows); a
            batch-locked env gets a short last chunk padded with repeats of its first task.
        seed: the evaluation's seed; the policy is reseeded with ``seed + first //
            tasks_per_rollout`` (:func:`seed_policy`). ``None``: left as it is.
        bar: a progress bar moved as tasks finish (``None``: none).

    Returns:
        ``rollout`` (``[rows (+ padding), T]``) and ``at_goal`` (``[rows]`` bool: tasks
        that started at their goal).
    """
    rows = chunk.shape[0]
    limit = task_limit(env, max_steps)
    tasks_per_rollout = rows if tasks_per_rollout is None else tasks_per_rollout
    locked = env.batch_locked and env.batch_size != torch.Size([])
    if seed is not None:
        seed_policy(policy, derive_seed(seed, first // tasks_per_rollout))
    if locked and rows != tasks_per_rollout:  # pad the last chunk with repeats
        chunk = torch.cat([chunk, chunk[:1].expand(tasks_per_rollout - rows)], 0)
    given = TensorDict(
        state=chunk["state"], goal_state=chunk["goal_state"], batch_size=chunk.shape
    ).to(env.device)
    td = env.reset(given, set_state=True)
    # A task that starts at its goal is solved before any action (the first one may move
    # a block away from it).
    at_goal = _at_goal(td).reshape(-1)[:rows].cpu()

    def tick(_env: Any, step: TensorDictBase) -> None:
        # The bar moves as tasks finish, not only per chunk, so it can tell time left.
        finished = first + int(step["done"].reshape(-1)[:rows].sum())
        if finished > bar.n:
            bar.update(finished - bar.n)

    rollout = env.rollout(
        # All solved at the start: one step gives the policy's report values at step 0.
        1 if bool(at_goal.all()) else limit,
        policy,
        None if bar is None else tick,
        tensordict=td,
        auto_reset=False,
        break_when_any_done=False,
        break_when_all_done=True,
    )
    return rollout, at_goal


def succeeded(td: TensorDictBase) -> torch.Tensor:
    """Bool ``[*B, 1]``: the env's ``success`` where it writes one, else ``terminated``."""
    key = "success" if "success" in td.keys() else "terminated"
    return td.get(key).reshape(*td.batch_size, 1).bool()


def _at_goal(td: TensorDictBase) -> torch.Tensor:
    """Bool ``[*B]``: rows of a reset tensordict that start at their goal."""
    if "success" in td.keys():
        return td.get("success").reshape(td.batch_size).bool()
    state, goal = td.get("state"), td.get("goal_state")
    return (state == goal).reshape(*td.batch_size, -1).all(-1)


def _run_chunk(
    env: EnvBase,
    policy: Callable[[TensorDictBase], TensorDictBase],
    chunk: TensorDictBase,
    first: int,
    limit: int,
    tasks_per_rollout: int,
    report_keys: Sequence[str],
    seed: int | None,
    bar: Any,
) -> dict[str, list]:
    """One batched rollout of the tasks ``chunk`` (task ``first`` onwards); per-task lists."""
    rows = chunk.shape[0]
    rollout, at_goal = rollout_chunk(
        env,
        policy,
        chunk,
        first,
        max_steps=limit,
        tasks_per_rollout=tasks_per_rollout,
        seed=seed,
        bar=bar,
    )
    done = rollout["next", "done"].squeeze(-1)[:rows]  # [rows, T]
    won = succeeded(rollout["next"]).squeeze(-1)[:rows]
    t = done.shape[-1]
    first_done = torch.where(
        done.any(-1),
        done.float().argmax(-1),
        torch.full_like(done[:, 0], t - 1, dtype=torch.int64),
    )
    won_at_end = won.gather(-1, first_done[:, None]).squeeze(-1) & done.any(-1)
    won_at_end = won_at_end.cpu()
    success = [bool(at_goal[row] or won_at_end[row]) for row in range(rows)]
    steps = [
        0 if at_goal[row] else int(first_done[row]) + 1 if success[row] else limit
        for row in range(rows)
    ]
    # Reported values: at the step the task ended (the first, for a task solved at 0).
    first_done = torch.where(
        at_goal.to(first_done.device), torch.zeros_like(first_done), first_done
    )
    result: dict[str, list] = {"success": success, "steps": steps}
    result["records"] = task_records(policy, rollout, first_done, first, success, steps)
    for key in report_keys:
        if key not in rollout.keys(True, True):
            raise MissingKeyError(
                f"report key {key!r} is not in the rollout: does the policy write it?"
            )
        values = rollout.get(key)[:rows]
        result[key] = (
            values.reshape(rows, t, -1)[torch.arange(rows), first_done, 0].float().tolist()
        )
    return result


#: How a task ended, in the ``outcome`` of a task record (:func:`task_records`): solved,
#: held to the step limit, or given up by the policy for one of its reasons (the
#: DORP policy's :data:`~dorp_rl.policies.ENDINGS`: ``no_path``, ``goal_stalled``,
#: ``removal_limit``).
SOLVED, STEP_LIMIT = "solved", "step_limit"


def task_records(
    policy: Any,
    rollout: TensorDictBase,
    last_step: torch.Tensor,
    first: int,
    success: Sequence[bool],
    steps: Sequence[int],
) -> list[dict[str, Any]]:
    """One record per task of a chunk's rollout: how it ended and the policy's counts.

    Every record has ``task`` (its index in the task set), ``outcome`` (``"solved"``,
    ``"step_limit"`` or the reason the policy gave the task up) and ``steps``. A policy
    with a ``task_records(last)`` method (:meth:`~dorp_rl.policies.AbstractGoalPolicy.
    task_records`) is asked about the tensordicts of the tasks' last steps (``last``,
    ``[rows]``) and its fields are added; its ``outcome`` is used for unsolved tasks.

    Args:
        policy: the policy of the rollout.
        rollout: ``[rows (+ padding), T]`` rollout of the chunk.
        last_step: ``[rows]`` index of each task's last step in ``rollout``.
        first: index of the chunk's first task in the task set.
        success, steps: the chunk's per-task results.
    """
    rows = len(success)
    extra: list[dict[str, Any]] = [{} for _ in range(rows)]
    describe = getattr(policy, "task_records", None)
    if callable(describe):
        index = torch.arange(rows, device=last_step.device)
        last = rollout[:rows][index, last_step]
        extra = [dict(r) for r in describe(last)]
        if len(extra) != rows:
            raise ValueError(
                f"{type(policy).__name__}.task_records gave {len(extra)} records for {rows} tasks."
            )
    records = []
    for row in range(rows):
        given_up = extra[row].pop("outcome", None)
        outcome = SOLVED if success[row] else (given_up or STEP_LIMIT)
        records.append(
            {"task": first + row, "outcome": outcome, "steps": int(steps[row]), **extra[row]}
        )
    return records


class _ChunkFile:
    """The finished chunks of one evaluation, kept in a JSON file so a stopped run resumes.

    The file holds what identifies the evaluation (task set digest, step limit, chunk
    size, seed, report keys), the per-task results of every finished chunk and the
    seconds spent so far. It is rewritten whole (to a temporary file, then renamed)
    after each chunk, so a stop at any moment leaves the last finished chunk in it.
    """

    def __init__(self, path: str | Path, evaluation: dict[str, Any]) -> None:
        self.path = Path(path)
        self.evaluation = evaluation
        self.chunks: dict[int, dict[str, list]] = {}
        self.seconds = 0.0
        if not self.path.exists():
            return
        try:
            data = json.loads(self.path.read_text())
            chunks = {int(k): v for k, v in data["chunks"].items()}
            seconds = float(data["seconds"])
            stored = dict(data["evaluation"])
        except (ValueError, KeyError, TypeError, AttributeError) as err:
            raise ValueError(
                f"resume_file {self.path} is not a readable evaluation record ({err!r}): "
                "remove it to run the evaluation from the start."
            ) from err
        if stored != evaluation:
            changed = [
                f"{k} {stored.get(k)!r} -> {evaluation.get(k)!r}"
                for k in sorted(set(stored) | set(evaluation))
                if stored.get(k) != evaluation.get(k)
            ]
            raise ValueError(
                f"resume_file {self.path} was written by a different evaluation "
                f"({', '.join(changed)}): remove it, or pass another file."
            )
        per_chunk = evaluation["tasks_per_rollout"]
        for index, chunk in chunks.items():
            rows = min(per_chunk, evaluation["num_tasks"] - index * per_chunk)
            lengths = {
                k: len(chunk.get(k, ())) for k in ("success", "steps", *evaluation["report_keys"])
            }
            if rows < 1 or any(n != rows for n in lengths.values()):
                raise ValueError(
                    f"resume_file {self.path}: chunk {index} should hold {rows} results per "
                    f"key, got {lengths}: remove the file to run the evaluation from the start."
                )
        self.chunks, self.seconds = chunks, seconds

    @property
    def finished_tasks(self) -> int:
        """Tasks in the recorded chunks."""
        return sum(len(chunk["success"]) for chunk in self.chunks.values())

    @classmethod
    def open(
        cls,
        path: str | Path | None,
        tasks: TensorDictBase,
        max_steps: int,
        tasks_per_rollout: int,
        seed: int,
        report_keys: Sequence[str],
    ) -> _ChunkFile | None:
        """The record of this evaluation at ``path`` (``None``: no record kept)."""
        if path is None:
            return None
        return cls(path, cls.describe(tasks, max_steps, tasks_per_rollout, seed, report_keys))

    @staticmethod
    def describe(
        tasks: TensorDictBase,
        max_steps: int,
        tasks_per_rollout: int,
        seed: int,
        report_keys: Sequence[str],
    ) -> dict[str, Any]:
        """What identifies an evaluation (the policy is the caller's to keep the same)."""
        digest = hashlib.sha256()
        for key in ("state", "goal_state"):
            digest.update(tasks[key].to(torch.int64).cpu().contiguous().numpy().tobytes())
        return {
            "num_tasks": int(tasks.shape[0]),
            "tasks": digest.hexdigest()[:16],
            "max_steps": int(max_steps),
            "tasks_per_rollout": int(tasks_per_rollout),
            "seed": int(seed),
            "report_keys": list(report_keys),
        }

    def add(self, index: int, chunk: dict[str, list], seconds: float) -> None:
        """Records chunk ``index`` and the seconds spent so far (earlier runs included)."""
        self.chunks[index] = chunk
        self.seconds = seconds
        data = {
            "evaluation": self.evaluation,
            "seconds": seconds,
            "chunks": {str(k): v for k, v in sorted(self.chunks.items())},
        }
        self.path.parent.mkdir(parents=True, exist_ok=True)
        tmp = self.path.with_name(self.path.name + ".tmp")
        tmp.write_text(json.dumps(data) + "\n")
        tmp.replace(self.path)


def summarize(
    tasks: TensorDictBase,
    success: Sequence[bool],
    steps: Sequence[int],
    max_steps: int,
    seconds: float,
    reported: dict[str, list[float]] | None = None,
    records: Sequence[dict[str, Any]] | None = None,
) -> dict[str, Any]:
    """The result dict of :func:`evaluate_policy` from per-task ``success`` and ``steps``
    (lists in task order, one entry per row of ``tasks``) and the task ``records``
    (:func:`task_records`; default: outcome and steps alone)."""
    success, steps = list(success), list(steps)
    n = tasks.shape[0]
    if n == 0:
        raise ValueError("no tasks to summarize: an evaluation needs at least one task.")
    if len(success) != n or len(steps) != n:
        raise ValueError(
            f"expected one success and one steps entry per task ({n}), "
            f"got {len(success)} and {len(steps)}."
        )
    if records is None:
        records = [
            {"task": i, "outcome": SOLVED if won else STEP_LIMIT, "steps": int(n)}
            for i, (won, n) in enumerate(zip(success, steps, strict=True))
        ]
    if len(records) != n:
        raise ValueError(f"expected one record per task ({n}), got {len(records)}.")
    ok = torch.tensor(success, dtype=torch.bool)
    bound = tasks["lower_bound"].float() if "lower_bound" in tasks.keys() else None
    return {
        "num_tasks": n,
        "success": success,
        "steps": steps,
        "success_rate": float(ok.float().mean()),
        "mean_steps": float(torch.tensor(steps, dtype=torch.float)[ok].mean())
        if ok.any()
        else float("nan"),
        "mean_lower_bound": float(bound[ok].mean())
        if bound is not None and ok.any()
        else float("nan"),
        "max_steps": max_steps,
        "seconds": seconds,
        "records": [dict(r) for r in records],
        **(reported or {}),
    }
