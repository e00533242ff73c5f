"""evaluate_parallel: the same per-task results on one process, two worker processes and
Ray; the seeding rule it rests on; bad arguments; and ``dorp evaluate --workers 2``."""

from __future__ import annotations

import json
import os
import signal
import sys
import time

import pytest
import torch

from dorp_rl.cli import main
from dorp_rl.data import collect_play_data
from dorp_rl.envs import ObjectRearrangementEnv, OracleCodeEncoder
from dorp_rl.eval import EvalSpec, evaluate_parallel, evaluate_policy, make_task_set
from dorp_rl.planners import CodeGraph

# 5 tasks in chunks of 2: three chunks, the last one short (padded in the batch-locked env).
RUN = {"tasks_per_rollout": 2, "max_steps": 60, "report_keys": ("dorp_replans",)}


@pytest.fixture(autouse=True)
def _one_thread(one_torch_thread) -> None:
    """Every test runs with one torch thread, as the workers do (and restores the count)."""


@pytest.fixture(scope="module")
def dorp_spec(tmp_path_factory) -> tuple[EvalSpec, object]:
    """DORP on one object: oracle codes, a code graph over 2000 play frames, small planners."""
    env = ObjectRearrangementEnv(num_objects=1, batch_size=(16,), seed=0)
    oracle = OracleCodeEncoder(env, cell_size=4)
    graph = CodeGraph.from_play_data(collect_play_data(env, 2000, seed=0), oracle)
    path = graph.save(tmp_path_factory.mktemp("graph") / "graph.pt")
    spec = EvalSpec(
        "1obj",
        "dorp",
        encoder="oracle",
        graph=str(path),
        tasks_per_rollout=2,
        candidates=30,
        planning_horizon=6,
    )
    return spec, make_task_set(spec.make_env(), 5, seed=0)


@pytest.fixture(scope="module")
def one_process(dorp_spec) -> dict:
    spec, tasks = dorp_spec
    previous = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        return evaluate_parallel(spec.make_env, spec.make_policy, tasks, seed=0, **RUN)
    finally:
        torch.set_num_threads(previous)


def per_task(result: dict) -> tuple[list, list, list]:
    return result["success"], result["steps"], result["dorp_replans"]


def test_one_worker_is_evaluate_policy_with_the_chunk_seeding_rule(dorp_spec, one_process):
    spec, tasks = dorp_spec
    assert one_process["workers"] == 1 and one_process["num_tasks"] == 5
    assert any(one_process["success"])  # a meaningful run: DORP solves tasks
    env = spec.make_env()
    policy = spec.make_policy(env)
    assert per_task(evaluate_policy(env, policy, tasks, seed=0, **RUN)) == per_task(one_process)
    # The rule: chunk k sees seed + k whatever ran before it. Run the chunks backwards on
    # one policy, each reseeded by hand, and get the same per-task results.
    backwards = {}
    for k in (2, 1, 0):
        chunk = tasks[2 * k : 2 * k + 2]
        backwards[k] = per_task(evaluate_policy(env, policy, chunk, seed=k, **RUN))
    joined = tuple(sum((list(backwards[k][i]) for k in range(3)), []) for i in range(3))
    assert joined == per_task(one_process)
    # ... and the seed matters, so agreeing runs are no accident of a seed-blind policy.
    other = evaluate_policy(env, policy, tasks, seed=1, **RUN)
    assert other["steps"] != one_process["steps"]


def test_a_policy_without_set_seed_draws_from_the_reseeded_global_generator(dorp_spec):
    spec, tasks = dorp_spec
    env = spec.make_env()
    run = {"tasks_per_rollout": 2, "max_steps": 30, "report_keys": ("action",)}
    forwards = evaluate_policy(env, env.rand_action, tasks, seed=3, **run)
    torch.manual_seed(123)  # whatever the generator held before, each chunk is reseeded
    backwards = {
        k: evaluate_policy(env, env.rand_action, tasks[2 * k : 2 * k + 2], seed=3 + k, **run)
        for k in (2, 1, 0)
    }
    for key in ("steps", "action"):
        assert sum((backwards[k][key] for k in range(3)), []) == forwards[key]
    assert (
        evaluate_policy(env, env.rand_action, tasks, seed=4, **run)["action"] != forwards["action"]
    )


def test_two_worker_processes_give_the_one_process_results(dorp_spec, one_process):
    spec, tasks = dorp_spec
    result = evaluate_parallel(spec.make_env, spec.make_policy, tasks, seed=0, workers=2, **RUN)
    assert result["workers"] == 2 and result["backend"] == "local"
    assert per_task(result) == per_task(one_process)
    for key in ("success_rate", "mean_steps", "mean_lower_bound", "max_steps"):
        assert result[key] == one_process[key]


def test_a_stopped_evaluation_resumes_at_its_first_unfinished_chunk(
    dorp_spec, one_process, tmp_path, monkeypatch
):
    import dorp_rl.eval.tasks as harness

    spec, tasks = dorp_spec
    env = spec.make_env()
    policy = spec.make_policy(env)
    run_chunk = harness._run_chunk
    ran: list[int] = []  # the first task of every chunk run
    stop = True

    def stopped_at_the_third_chunk(*args, **kwargs):
        first = args[3]
        if first == 4 and stop:
            raise KeyboardInterrupt  # a user's Ctrl-C, or the end of a session
        ran.append(first)
        return run_chunk(*args, **kwargs)

    monkeypatch.setattr(harness, "_run_chunk", stopped_at_the_third_chunk)
    path = tmp_path / "eval.json"
    with pytest.raises(KeyboardInterrupt):
        evaluate_policy(env, policy, tasks, seed=0, resume_file=path, **RUN)
    stored = json.loads(path.read_text())
    assert sorted(stored["chunks"]) == ["0", "1"] and stored["seconds"] > 0
    two_chunks = path.read_text()

    ran.clear()
    stop = False
    result = evaluate_policy(env, policy, tasks, seed=0, resume_file=path, **RUN)
    assert ran == [4]  # chunks 0 and 1 came from the file
    assert per_task(result) == per_task(one_process)  # as if never stopped
    assert result["seconds"] > stored["seconds"]  # both parts
    assert sorted(json.loads(path.read_text())["chunks"]) == ["0", "1", "2"]

    # Two worker processes resume the same file; what is in it is not run again.
    marked = json.loads(two_chunks)
    marked["chunks"]["0"]["steps"] = [999, 999]
    path.write_text(json.dumps(marked))
    result = evaluate_parallel(
        spec.make_env, spec.make_policy, tasks, seed=0, workers=2, resume_file=path, **RUN
    )
    assert result["steps"][:2] == [999, 999]  # taken from the file
    assert per_task(result)[0] == per_task(one_process)[0]
    assert result["steps"][2:] == one_process["steps"][2:]

    # An evaluation the file was not written for, a damaged file, no seed: clear errors.
    with pytest.raises(ValueError, match="different evaluation.*max_steps 60 -> 50"):
        evaluate_policy(env, policy, tasks, seed=0, resume_file=path,
                        **{**RUN, "max_steps": 50})  # fmt: skip
    with pytest.raises(ValueError, match="different evaluation.*seed 0 -> 1"):
        evaluate_parallel(spec.make_env, spec.make_policy, tasks, seed=1, workers=2,
                          resume_file=path, **RUN)  # fmt: skip
    marked["chunks"]["1"]["steps"] = [3]
    path.write_text(json.dumps(marked))
    with pytest.raises(ValueError, match="chunk 1 should hold 2 results per key"):
        evaluate_policy(env, policy, tasks, seed=0, resume_file=path, **RUN)
    path.write_text(two_chunks[: len(two_chunks) // 2])  # cut short
    with pytest.raises(ValueError, match="not a readable evaluation record.*remove it"):
        evaluate_policy(env, policy, tasks, seed=0, resume_file=path, **RUN)
    with pytest.raises(ValueError, match="resume_file needs seed"):
        evaluate_policy(env, policy, tasks, resume_file=tmp_path / "new.json", **RUN)


PARENT_SCRIPT = """
import multiprocessing, os, sys, time
from concurrent.futures import ProcessPoolExecutor
from dorp_rl.eval.parallel import exit_with_parent

def task():
    print(os.getpid(), flush=True)
    time.sleep(120)

if __name__ == "__main__":
    watch = sys.argv[1] == "watch"
    pool = ProcessPoolExecutor(1, multiprocessing.get_context("spawn"),
                               initializer=exit_with_parent if watch else None)
    pool.submit(task)
    time.sleep(120)
"""


def _ended(pid: int) -> bool:
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().rsplit(")", 1)[1].split()[0] in ("Z", "X")  # a zombie has ended
    except FileNotFoundError:
        return True


@pytest.mark.skipif(not os.path.isdir("/proc/self"), reason="reads /proc")
def test_workers_end_when_their_parent_is_killed(tmp_path):
    import subprocess

    script = tmp_path / "parent.py"
    script.write_text(PARENT_SCRIPT)
    ended = {}
    for mode in ("watch", "no-watch"):
        errors = tmp_path / f"{mode}.err"  # the killed parent's leaked-semaphore warnings
        with errors.open("w") as err:
            parent = subprocess.Popen([sys.executable, str(script), mode],
                                      stdout=subprocess.PIPE, stderr=err, text=True)  # fmt: skip
        line = parent.stdout.readline()
        assert line.strip().isdigit(), errors.read_text()
        worker = int(line)
        parent.kill()  # SIGKILL: no clean-up in the parent
        parent.wait()
        deadline = time.monotonic() + 10
        while not _ended(worker) and time.monotonic() < deadline:
            time.sleep(0.1)
        ended[mode] = _ended(worker)
        if not ended[mode]:
            os.kill(worker, signal.SIGKILL)
    # Without the watch the worker runs on (what a pool does); with it, it ends.
    assert ended == {"watch": True, "no-watch": False}


def test_the_ray_backend_gives_the_one_process_results(dorp_spec, one_process):
    ray = pytest.importorskip("ray", reason="Ray is an optional dependency (dorp-rl[ray])")
    spec, tasks = dorp_spec
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
    try:
        result = evaluate_parallel(
            spec.make_env, spec.make_policy, tasks, seed=0, workers=2, backend="ray", **RUN
        )
        assert ray.is_initialized()  # a Ray the caller started stays up
    finally:
        ray.shutdown()
    assert result["workers"] == 2 and result["backend"] == "ray"
    assert per_task(result) == per_task(one_process)


def test_bad_arguments_get_clear_errors(dorp_spec, monkeypatch):
    spec, tasks = dorp_spec
    run = {"tasks_per_rollout": 2, "max_steps": 5}
    with pytest.raises(ValueError, match="workers must be >= 1"):
        evaluate_parallel(spec.make_env, spec.make_policy, tasks, workers=0, **run)
    with pytest.raises(ValueError, match=r"backend must be one of \('local', 'ray'\)"):
        evaluate_parallel(spec.make_env, spec.make_policy, tasks, backend="dask", **run)
    with pytest.raises(ValueError, match="address='auto' is for the Ray backend"):
        evaluate_parallel(spec.make_env, spec.make_policy, tasks, address="auto", **run)
    with pytest.raises(ValueError, match="tasks_per_rollout"):
        evaluate_parallel(spec.make_env, spec.make_policy, tasks, tasks_per_rollout=0)
    # A chunk size the env's batch does not take is refused before any worker starts.
    with pytest.raises(ValueError, match=r"batch_size \(2,\) but tasks_per_rollout is 3"):
        evaluate_parallel(
            spec.make_env, spec.make_policy, tasks, tasks_per_rollout=3, workers=2, max_steps=5
        )
    with pytest.raises(ValueError, match="must be picklable"):
        evaluate_parallel(lambda: spec.make_env(), spec.make_policy, tasks, workers=2, **run)
    with pytest.raises(ValueError, match="must hold 'goal_state'"):
        evaluate_parallel(spec.make_env, spec.make_policy, tasks.exclude("goal_state"), **run)
    monkeypatch.setitem(sys.modules, "ray", None)  # as if Ray were not installed
    with pytest.raises(ImportError, match=r"pip install dorp-rl\[ray\]"):
        evaluate_parallel(spec.make_env, spec.make_policy, tasks, backend="ray", workers=2, **run)
    with pytest.raises(ValueError, match="method must be one of"):
        EvalSpec("1obj", "magic")
    with pytest.raises(ValueError, match="setting .9obj. is none of"):
        EvalSpec("9obj", "random")
    with pytest.raises(ValueError, match="'dorp' needs encoder"):
        EvalSpec("1obj", "dorp", encoder="oracle")
    with pytest.raises(ValueError, match="low_level must be 'gt' or a world-model checkpoint"):
        EvalSpec("1obj", "vf-rs", low_level="no/such/model.pt")
    with pytest.raises(ValueError, match=r"names \['speed'\], which are no DORPConfig"):
        EvalSpec("1obj", "random", dorp={"speed": 2})
    with pytest.raises(ValueError, match=r"sets \['num_candidates'\]: the planners' shape"):
        EvalSpec("1obj", "random", dorp={"num_candidates": 5})
    with pytest.raises(ValueError, match="waypoint_budget must be >= 1"):
        EvalSpec("1obj", "random", dorp={"waypoint_budget": 0})


def test_cli_workers_give_the_one_process_results(tmp_path, capsys):
    args = [
        "evaluate", "--root", str(tmp_path), "--no-progress", "--setting", "1obj",
        "--methods", "vf-rs", "--tasks", "4", "--tasks-per-rollout", "2",
        "--candidates", "8", "--planning-horizon", "3", "--max-steps", "40",
    ]  # fmt: skip
    main([*args, "--name", "one"])
    main([*args, "--name", "two", "--workers", "2"])
    capsys.readouterr()
    runs = {}
    for name in ("one", "two"):
        stages = json.loads((tmp_path / name / "stages.json").read_text())
        runs[name] = {
            k: v["summary"]["per_task"] for k, v in stages.items() if k.startswith("evaluate:")
        }
    assert set(runs["one"]) == {"evaluate:vf-rs:gt"}
    assert runs["two"] == runs["one"]
    assert any(runs["one"]["evaluate:vf-rs:gt"]["success"])  # not all at the step limit
    # --workers is not part of a stage's config: a finished stage is not re-run for it.
    main([*args, "--name", "one", "--workers", "2"])
    assert "evaluate:vf-rs:gt: done for this config, skipped" in capsys.readouterr().out


def test_cli_ray_backend_gives_the_one_process_results(tmp_path, capsys):
    ray = pytest.importorskip("ray", reason="Ray is an optional dependency (dorp-rl[ray])")
    args = [
        "evaluate", "--root", str(tmp_path), "--no-progress", "--setting", "1obj",
        "--methods", "vf-rs", "random", "--tasks", "4", "--tasks-per-rollout", "2",
        "--candidates", "8", "--planning-horizon", "3", "--max-steps", "40",
    ]  # fmt: skip
    main([*args, "--name", "one"])
    # No Ray running: the command starts a local instance and shuts it down after.
    main([*args, "--name", "ray", "--workers", "2", "--backend", "ray"])
    assert not ray.is_initialized()
    capsys.readouterr()
    rows = {}
    for name in ("one", "ray"):
        stages = json.loads((tmp_path / name / "stages.json").read_text())
        rows[name] = {k: v["summary"] for k, v in stages.items() if k.startswith("evaluate:")}
    assert set(rows["ray"]) == {"evaluate:vf-rs:gt", "evaluate:random"}
    for key, row in rows["one"].items():
        assert rows["ray"][key]["per_task"] == row["per_task"], key
        assert rows["ray"][key]["success_rate"] == row["success_rate"], key


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--workers", "0"], "--workers must be >= 1"),
        (["--address", "auto"], "--address is for --backend ray"),
        (["--backend", "dask"], "dask"),
    ],
)
def test_cli_bad_worker_arguments_give_a_usage_error(tmp_path, capsys, args, message):
    with pytest.raises(SystemExit) as err:
        main(["evaluate", "--root", str(tmp_path), *args])
    assert err.value.code == 2
    captured = capsys.readouterr()
    assert message in captured.err + captured.out
    assert not any(tmp_path.iterdir())  # nothing was run
