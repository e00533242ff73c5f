"""``dorp reproduce --paper``, the pictures of a run (code maps, histogram, rollout GIFs),
the paper-table layout and the evaluation progress bar."""

from __future__ import annotations

import csv
import json
import os
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image
from tensordict import TensorDict

from dorp_rl.checkpoint import load_checkpoint
from dorp_rl.cli import main
from dorp_rl.envs import ObjectRearrangementEnv
from dorp_rl.eval import RESULT_COLUMNS, evaluate_policy, make_task_set, paper_methods
from dorp_rl.eval.results import PAPER_COLUMNS, SEED_COLUMNS, format_paper_table
from dorp_rl.viz.rollouts import rollout_gif_frames, waypoint_panel

ONE_GIF = ("--gifs", "1")


@pytest.fixture(autouse=True)
def _one_thread(one_torch_thread) -> None:
    """Every test runs with one torch thread (and restores the count)."""


def read_csv(path: Path) -> tuple[list[str], list[dict[str, str]]]:
    with path.open() as f:
        reader = csv.DictReader(f)
        return list(reader.fieldnames or []), list(reader)


def test_reproduce_paper_writes_the_table_the_timings_and_the_pictures(tmp_path, dorp) -> None:
    out = dorp(tmp_path, "reproduce", "--paper", "--settings", "1obj",
               "--low-level", "ground-truth", *dorp.CODES, *dorp.EVAL, *ONE_GIF)  # fmt: skip
    run = tmp_path / "run"
    columns, rows = read_csv(run / "results.csv")
    assert tuple(columns) == RESULT_COLUMNS + PAPER_COLUMNS
    assert [r["method"] for r in rows] == list(paper_methods("1obj"))
    assert {r["low_level"] for r in rows} == {"gt"}  # "ground-truth" is another name of it
    assert {r["setting"] for r in rows} == {"1obj"} and {r["tasks"] for r in rows} == {"2"}
    paper = {r["method"]: r["paper_success_rate"] for r in rows}
    assert float(paper["dorp-arbitrary"]) == 0.92 and float(paper["vf-rs"]) == 0.83
    table = (run / "results.md").read_text()
    assert "## As the paper's Table 1" in table and "| – identity weight |" in table
    for figure in ("success.png", "steps.png"):
        assert f"]({figure})" in table and Image.open(run / figure).format == "PNG"

    # Each ablation trained codes or built a graph of its own, in the setting's sub-run.
    columns, timings = read_csv(run / "timings.csv")
    stages = {t["stage"]: t for t in timings}
    for stage in ("play", "codes", "codes:arbitrary", "codes:identity", "graph",
                  "graph:arbitrary", "graph:identity", "graph:full", "evaluate:dorp:gt",
                  "evaluate:vf-cem:gt", "pictures"):  # fmt: skip
        assert stage in stages, stage
        assert float(stages[stage]["seconds"]) > 0 and stages[stage]["this_command"] == "ran"
    assert "codes:full" not in stages  # the full-graph ablation plans with DORP's codes
    assert (run / "1obj" / "codes-arbitrary" / "checkpoints" / "last.pt").is_file()
    timings_md = (run / "timings.md").read_text()
    assert "| all | total |" in timings_md
    # What dominates: seconds by what the stages do, largest first, adding up to the total.
    section = timings_md.split("## Where the time went")[1].splitlines()
    by_kind = [line for line in section if line.startswith("| ") and "| share |" not in line]
    spent = [float(line.split(" | ")[2]) for line in by_kind]
    assert spent == sorted(spent, reverse=True) and len(spent) == len({t["does"] for t in timings})
    assert sum(spent) == pytest.approx(
        sum(float(t["seconds"]) for t in timings), abs=0.1 * len(spent)
    )
    assert "Where the time went:" in out

    pictures = run / "1obj" / "pictures"
    for still in ("code_map.png", "factorization_histogram.png",
                  "arbitrary/code_map.png", "identity/factorization_histogram.png"):  # fmt: skip
        image = Image.open(pictures / still)
        image.verify()
        assert image.format == "PNG"
    # The one GIF (--gifs 1) draws DORP's first failed task if it failed any, as it failed.
    _, task_lines = read_csv(run / "1obj" / "tasks.csv")
    dorp_tasks = [t for t in task_lines if t["method"] == "dorp"]
    assert [t["task"] for t in dorp_tasks] == ["0", "1"]
    failed = [t["task"] for t in dorp_tasks if t["outcome"] != "solved"]
    drawn = failed[0] if failed else "0"
    gif = Image.open(pictures / f"rollout_{drawn}.gif")
    assert gif.format == "GIF" and gif.n_frames >= 2 and gif.size[0] > 3 * 128
    assert [p.name for p in pictures.glob("*.gif")] == [f"rollout_{drawn}.gif"]
    assert f"rollout GIF: {pictures / f'rollout_{drawn}.gif'}" in out
    stages_json = json.loads((run / "1obj" / "stages.json").read_text())
    summary = stages_json["pictures"]["summary"]
    assert summary["gif_tasks"] == [int(drawn)]
    assert summary["gif_solved"] == [not failed]
    # How the tasks ended, per method, in the run's results and in the table's results.
    assert "## How the tasks ended" in (run / "1obj" / "results.md").read_text()
    assert "1obj dorp: " in table and " of 2 solved" in table
    _, all_tasks = read_csv(run / "tasks.csv")
    assert len(all_tasks) == 2 * len(paper_methods("1obj"))

    # Run again (with "gt"): every stage is reused, the table and timings are the same.
    again = dorp(
        tmp_path, "reproduce", "--paper", "--settings", "1obj", *dorp.CODES, *dorp.EVAL, *ONE_GIF
    )
    assert ": running (" not in again
    _, rows_again = read_csv(run / "results.csv")
    assert rows_again == rows
    _, timings_again = read_csv(run / "timings.csv")
    assert {t["this_command"] for t in timings_again} == {"reused"}
    assert [t["seconds"] for t in timings_again] == [t["seconds"] for t in timings]


def test_settings_side_by_side_give_the_one_process_results(tmp_path, dorp) -> None:
    args = ("reproduce", "--paper", "--settings", "keywall", "keycorridor",
            *dorp.CODES, *dorp.EVAL, "--gifs", "0")  # fmt: skip
    dorp(tmp_path, *args, name="one")
    out = dorp(tmp_path, *args, "--workers", "2", name="two")
    assert "2 sub-runs side by side" in out
    # The workers' lines are relayed here, named by setting, and kept in their sub-runs.
    assert "[keycorridor] codes: running (not run yet)" in out
    assert "codes: running (not run yet)" in (tmp_path / "two" / "keywall" / "log.txt").read_text()

    # Each sub-run was locked by the process that ran it: this one with one process; a
    # worker side by side, while this one held the lock of the run above (no deadlock).
    def locker(*parts: str) -> int:
        return json.loads(tmp_path.joinpath(*parts, "run.lock").read_text())["pid"]

    assert locker("one") == locker("one", "keywall") == locker("two") == os.getpid()
    assert os.getpid() not in {locker("two", s) for s in ("keywall", "keycorridor")}
    assert not list(tmp_path.glob("*/**/running.json"))  # each removed when its lock was

    timed = {"seconds_per_task"}
    one, two = (read_csv(tmp_path / name / "results.csv")[1] for name in ("one", "two"))
    assert [r["setting"] for r in two] == ["keywall", "keycorridor"]  # --settings order
    assert [{k: v for k, v in r.items() if k not in timed} for r in two] == [
        {k: v for k, v in r.items() if k not in timed} for r in one
    ]
    for setting in ("keywall", "keycorridor"):  # bitwise the same codes
        weights = [
            load_checkpoint(tmp_path / name / setting / "codes" / "checkpoints" / "last.pt")
            for name in ("one", "two")
        ]
        first, second = (w["state"]["encoder"] for w in weights)
        assert first.keys() == second.keys()
        assert all(torch.equal(first[k], second[k]) for k in first)
    _, timings = read_csv(tmp_path / "two" / "timings.csv")
    assert [t["setting"] for t in timings][0] == "keywall"
    assert {t["setting"] for t in timings} == {"keywall", "keycorridor"}

    again = dorp(tmp_path, *args, "--workers", "2", name="two")
    assert ": running (" not in again and "[keywall] evaluate:dorp:gt: done for this" in again


def test_a_seed_sweep_runs_a_sub_run_per_seed_and_pools_them(tmp_path, dorp) -> None:
    out = dorp(tmp_path, "reproduce", "--paper", "--settings", "1obj", "--seeds", "3", "4",
               *dorp.CODES, *dorp.EVAL, "--gifs", "0", "--max-steps", "12")  # fmt: skip
    assert "1obj-seed3: dorp, dorp-arbitrary" in out
    run = tmp_path / "run"
    columns, rows = read_csv(run / "results.csv")
    assert tuple(columns) == RESULT_COLUMNS + SEED_COLUMNS + PAPER_COLUMNS
    methods = list(paper_methods("1obj"))
    assert [(r["method"], r["seed"]) for r in rows] == [
        *((m, "3") for m in methods), *((m, "4") for m in methods), *((m, "all") for m in methods)
    ]  # fmt: skip
    for method in methods:
        per_seed = [float(r["success_rate"]) for r in rows if r["method"] == method][:2]
        pooled = next(r for r in rows if r["method"] == method and r["seed"] == "all")
        assert float(pooled["success_rate"]) == pytest.approx(sum(per_seed) / 2)
        assert float(pooled["success_rate_std"]) == pytest.approx(float(np.std(per_seed, ddof=1)))
        assert pooled["tasks"] == "4"
    for seed in (3, 4):  # each sub-run trained and planned with its own seed
        config = json.loads((run / f"1obj-seed{seed}" / "config.json").read_text())
        assert config["seed"] == seed and config["codes"]["seed"] == seed
    first, second = (
        load_checkpoint(run / f"1obj-seed{k}" / "codes" / "checkpoints" / "last.pt")["state"]
        for k in (3, 4)
    )
    assert not all(torch.equal(first["encoder"][k], second["encoder"][k]) for k in first["encoder"])
    assert "pooled over the seeds [3, 4]" in (run / "results.md").read_text()
    # How each seed's tasks ended, and one line per task and seed in tasks.csv.
    assert "1obj dorp seed 3: " in (run / "results.md").read_text()
    _, task_lines = read_csv(run / "tasks.csv")
    assert [(t["method"], t["seed"], t["task"]) for t in task_lines if t["method"] == "dorp"] == [
        ("dorp", "3", "0"), ("dorp", "3", "1"), ("dorp", "4", "0"), ("dorp", "4", "1")
    ]  # fmt: skip
    _, timings = read_csv(run / "timings.csv")
    assert {t["setting"] for t in timings} == {"1obj-seed3", "1obj-seed4"}


def test_evaluate_draws_the_pictures_of_dorp_once(tmp_path, dorp) -> None:
    out = dorp(
        tmp_path, "evaluate", "--methods", "dorp", "vf-rs", *dorp.CODES, *dorp.EVAL, *ONE_GIF
    )
    pictures = tmp_path / "run" / "pictures"
    (gif,) = pictures.glob("rollout_*.gif")  # the first failed task, else task 0
    assert f"rollout GIF: {gif}" in out
    assert Image.open(gif).n_frames >= 2
    assert Image.open(pictures / "factorization_histogram.png").format == "PNG"
    written = gif.stat().st_mtime_ns
    again = dorp(
        tmp_path, "evaluate", "--methods", "dorp", "vf-rs", *dorp.CODES, *dorp.EVAL, *ONE_GIF
    )
    assert "pictures: done for this config, skipped" in again
    assert f"rollout GIF: {gif}" in again
    assert gif.stat().st_mtime_ns == written
    # Without DORP there are no codes to draw.
    dorp(tmp_path / "vf", "evaluate", "--methods", "vf-rs", *dorp.CODES, *dorp.EVAL, *ONE_GIF)
    assert not (tmp_path / "vf" / "run" / "pictures").exists()


def test_paper_methods_choose_among_table_1_and_leave_out_settings_without_them(
    tmp_path, dorp
) -> None:
    out = dorp(tmp_path, "reproduce", "--paper", "--settings", "1obj", "keywall",
               "--paper-methods", "dorp-full", "vf-rs", "--low-level", "gt",
               *dorp.CODES, *dorp.EVAL, "--gifs", "0")  # fmt: skip
    assert "keywall: left out, Table 1 has none of --paper-methods dorp-full vf-rs" in out
    assert "1obj: dorp-full, vf-rs on 2 tasks" in out  # in Table 1's order
    run = tmp_path / "run"
    assert not (run / "keywall").exists()
    _, rows = read_csv(run / "results.csv")
    assert [(r["setting"], r["method"]) for r in rows] == [("1obj", "dorp-full"), ("1obj", "vf-rs")]
    _, timings = read_csv(run / "timings.csv")
    evaluated = {t["stage"] for t in timings if t["stage"].startswith("evaluate:")}
    assert evaluated == {"evaluate:dorp-full:gt", "evaluate:vf-rs:gt"}
    assert "codes:arbitrary" not in {t["stage"] for t in timings}  # no ablation codes trained

    # Adding a method later runs only its stages; the others are reused.
    more = dorp(tmp_path, "reproduce", "--paper", "--settings", "1obj",
                "--paper-methods", "dorp-full", "vf-rs", "vf-cem", "--low-level", "gt",
                *dorp.CODES, *dorp.EVAL, "--gifs", "0")  # fmt: skip
    assert "evaluate:vf-rs:gt: done for this config, skipped" in more
    assert "evaluate:vf-cem:gt: running (not run yet)" in more
    _, rows_more = read_csv(run / "results.csv")
    assert [r["method"] for r in rows_more] == ["dorp-full", "vf-rs", "vf-cem"]
    assert rows_more[:2] == rows


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["reproduce", "--paper", "--methods", "dorp"], "--methods does not apply with --paper"),
        (["reproduce", "--paper-methods", "dorp"], "--paper-methods is an option of reproduce"),
        (
            ["reproduce", "--paper", "--settings", "keywall", "--paper-methods", "vf-rs"],
            "--paper-methods vf-rs: not in Table 1 for the settings keywall",
        ),
        (["reproduce", "--paper", "--paper-methods", "random"], "--paper-methods random: not"),
        (["demo", "--paper"], "--paper is an option of reproduce"),
        (["reproduce", "--seeds", "0", "1"], "--seeds is an option of reproduce --paper"),
        (["reproduce", "--paper", "--seeds", "1", "1"], "--seeds must be distinct"),
        (["reproduce", "--paper", "--low-level", __file__], "must be 'gt', 'world-model' or"),
        (["evaluate", "--gifs", "-1"], "--gifs must be >= 0"),
    ],
)
def test_paper_arguments_that_do_not_fit_are_refused(tmp_path, capsys, args, message) -> None:
    with pytest.raises(SystemExit) as err:
        main([*args, "--root", str(tmp_path)])
    assert err.value.code == 2
    assert message in capsys.readouterr().err
    assert not any(tmp_path.iterdir())


def test_paper_methods_follow_table_1() -> None:
    assert paper_methods("3obj") == (
        "dorp", "dorp-arbitrary", "dorp-identity", "dorp-full", "vf-rs", "vf-cem"
    )  # fmt: skip
    assert "dorp-arbitrary" not in paper_methods("5obj")  # the paper reports none there
    assert paper_methods("keywall") == paper_methods("keycorridor") == ("dorp",)


def test_the_paper_table_puts_the_papers_figures_beside_ours() -> None:
    row = {"setting": "2obj", "low_level": "gt", "mean_steps": 30.0}
    rows = [
        {**row, "method": "dorp", "success_rate": 0.5,
         "per_task": {"success": [True, True, False], "steps": [20, 40, 400]}},
        {**row, "method": "vf-cem", "success_rate": 0.0,
         "per_task": {"success": [False], "steps": [400]}},
        {**row, "setting": "keywall", "method": "dorp", "success_rate": 1.0,
         "per_task": {"success": [True], "steps": [12]}},
    ]  # fmt: skip
    lines = format_paper_table(rows).splitlines()
    assert lines[0] == "| method | 2obj SR | 2obj steps | keywall SR | keywall steps |"
    # mean 30, sample std 14 of the solved tasks; the paper's DORP: 1.00, 49 +- 22
    assert lines[2] == "| DORP | 0.50 (1.00) | 30 ± 14 (49 ± 22) | 1.00 (0.93) | 12 ± 0 (-) |"
    # nothing solved: "max"; no key-wall row for VF-CEM here or in the paper
    assert lines[3] == "| VF-CEM | 0.00 (0.60) | max (47 ± 25) | - (-) | - (-) |"


def _synthetic_rollout(steps: int) -> TensorDict:
    """A 1-object rollout of ``steps`` steps with DORP's keys (2 one-hots)."""
    env = ObjectRearrangementEnv(num_objects=1)
    states = torch.tensor([[[r, 0]] for r in range(steps + 1)])
    pixels = env.render_state(states)
    goal = pixels[-1:].expand(steps, -1, -1, -1)
    return TensorDict(
        pixels=pixels[:-1],
        goal_pixels=goal,
        code=torch.tensor([[r // 4, 0] for r in range(steps)]),
        subgoal_code=torch.tensor([[r // 4 + 1, 0] for r in range(steps)]),
        subgoal_mask=torch.tensor([[True, False]] * steps),
        dorp_mode=torch.ones(steps, 1, dtype=torch.int64),
        dorp_group=torch.zeros(steps, 1, dtype=torch.int64),
        next=TensorDict(pixels=pixels[1:], batch_size=[steps]),
        batch_size=[steps],
    )


def test_rollout_gif_frames_show_each_frame_and_the_one_reached() -> None:
    rollout = _synthetic_rollout(5)
    frames = rollout_gif_frames(rollout, scale=4)
    assert len(frames) == 6  # 5 steps and the frame after the last
    assert len({f.shape for f in frames}) == 1
    # The first panel (after its caption) is the upscaled current frame.
    first = rollout["pixels"][2].repeat_interleave(4, -2).repeat_interleave(4, -1)
    expected = first.permute(1, 2, 0).numpy()
    found = [
        (y, x)
        for y in range(frames[2].shape[0] - 63)
        for x in range(8)
        if np.array_equal(frames[2][y : y + 64, x : x + 64], expected)
    ]
    assert found
    assert len(rollout_gif_frames(rollout, max_frames=3)) == 3
    plain = rollout.exclude("code", "subgoal_code", "subgoal_mask", "dorp_mode", "dorp_group")
    assert rollout_gif_frames(plain, scale=4)[0].shape[1] < frames[0].shape[1]
    with pytest.raises(ValueError, match="goal_pixels"):
        rollout_gif_frames(rollout.exclude("goal_pixels"))


def test_waypoint_panel_borders_the_masked_one_hots_and_lights_the_waypoint_region() -> None:
    code_map = np.array([[0, 0, 1], [1, 2, 2]])
    panel = waypoint_panel([0, 3], [1, 3], [True, False], 1, 0, [[code_map], None])
    yellow = np.all(panel == (255, 210, 0), axis=-1)
    assert yellow.any()  # the masked tile's border (and its waypoint code text)
    # Mask the second one-hot instead: the yellow moves right.
    other = waypoint_panel([0, 3], [1, 3], [False, True], 1, 0, [[code_map], None])
    other_yellow = np.all(other == (255, 210, 0), axis=-1)
    assert np.argwhere(other_yellow)[:, 1].min() > np.argwhere(yellow)[:, 1].min()
    # The waypoint code's cells keep their colour, the others are faded.
    from dorp_rl.viz import code_colours

    colours = (code_colours(code_map) * 255).round().astype(np.uint8)
    flat = panel.reshape(-1, 3)
    assert (flat == colours[0, 2]).all(-1).any()  # code 1: the waypoint
    assert not (flat == colours[1, 2]).all(-1).any()  # code 2: faded
    with pytest.raises(ValueError, match="subgoal_mask"):
        waypoint_panel([0], [1, 3], [True], 1)


def test_the_evaluation_bar_moves_as_tasks_finish(monkeypatch) -> None:
    from dorp_rl import progress

    updates: list[int] = []
    for bar in (progress._LogSafeBar, progress._LineBar):  # with a terminal, and without

        def recording(self, n=1, update=bar.update):
            updates.append(int(n))
            return update(self, n)

        monkeypatch.setattr(bar, "update", recording)

    def greedy(td):  # one object straight to its goal: done after its lower bound
        diff = (td["goal_state"] - td["state"])[:, 0]
        action = torch.where(
            diff[:, 0] < 0, 0, torch.where(diff[:, 0] > 0, 1, torch.where(diff[:, 1] < 0, 2, 3))
        )
        return td.set("action", action[:, None])

    env = ObjectRearrangementEnv(num_objects=1, batch_size=(4,), seed=0)
    tasks = make_task_set(env, 4, seed=0)
    result = evaluate_policy(env, greedy, tasks, tasks_per_rollout=4, progress=True)
    assert result["success"] == [True] * 4
    assert result["steps"] == tasks["lower_bound"].tolist()
    # One update per distinct finishing step, not one for the whole chunk at its end.
    assert sum(updates) == 4
    assert len(updates) == len(set(result["steps"])) > 1
