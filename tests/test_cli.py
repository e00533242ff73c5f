"""The ``dorp`` command: every subcommand on tiny configs, stage skipping, results, usage errors."""

from __future__ import annotations

import csv
import json
import logging
import subprocess
import sys
from pathlib import Path

import pytest
import tiny_args
import torch

from dorp_rl.cli import main, quiet_torchrl
from dorp_rl.eval import RESULT_COLUMNS
from dorp_rl.planners import encoder_fingerprint

TINY_WORLD_MODEL = tiny_args.WORLD_MODEL


@pytest.fixture(autouse=True)
def _one_thread(one_torch_thread) -> None:
    """Every test runs with one torch thread (and restores the count)."""


def read_rows(run_dir: Path) -> list[dict[str, str]]:
    with (run_dir / "results.csv").open() as f:
        reader = csv.DictReader(f)
        assert tuple(reader.fieldnames) == RESULT_COLUMNS
        return list(reader)


def test_collect_train_encoder_and_build_graph_write_their_stages(tmp_path, dorp) -> None:
    run = tmp_path / "run"
    dorp(tmp_path, "collect", *dorp.CODES)
    assert (run / "play" / "play_data.json").is_file()
    assert not (run / "codes").exists()
    config = json.loads((run / "config.json").read_text())
    assert config["command"] == "collect" and config["codes"]["num_frames"] == 256
    assert config["codes"]["num_objects"] == 1  # the 1obj preset, not the 2obj default

    out = dorp(tmp_path, "train-encoder", *dorp.CODES)
    assert "play: done for this config, skipped" in out
    assert (run / "codes" / "checkpoints" / "last.pt").is_file()
    assert (run / "codes" / "logs").is_dir()

    dorp(tmp_path, "build-graph", *dorp.CODES)
    assert (run / "graph.pt").is_file()
    stages = json.loads((run / "stages.json").read_text())
    assert set(stages) == {"play", "codes", "graph"}
    assert stages["codes"]["config"]["num_steps"] == 5
    assert "out_dir" not in stages["codes"]["config"]  # paths do not decide a rerun


def test_rerunning_skips_finished_stages(tmp_path, dorp) -> None:
    dorp(tmp_path, "build-graph", *dorp.CODES)
    checkpoint = tmp_path / "run" / "codes" / "checkpoints" / "last.pt"
    written = checkpoint.stat().st_mtime_ns, (tmp_path / "run" / "graph.pt").stat().st_mtime_ns
    out = dorp(tmp_path, "build-graph", *dorp.CODES)
    for stage in ("play", "codes", "graph"):
        assert f"{stage}: done for this config, skipped" in out
    assert ": running (" not in out
    again = checkpoint.stat().st_mtime_ns, (tmp_path / "run" / "graph.pt").stat().st_mtime_ns
    assert again == written


def test_a_changed_field_reruns_its_stage_and_the_dependants(tmp_path, dorp) -> None:
    dorp(tmp_path, "build-graph", *dorp.CODES)
    graph = tmp_path / "run" / "graph.pt"
    before = graph.stat().st_mtime_ns
    out = dorp(tmp_path, "build-graph", *dorp.CODES, "--codes.num-steps", "6")
    assert "play: done for this config, skipped" in out  # num_steps does not change the data
    assert "codes: running (changed: num_steps 5 -> 6)" in out
    assert "graph: running (changed: codes.num_steps 5 -> 6)" in out
    assert graph.stat().st_mtime_ns != before
    stages = json.loads((tmp_path / "run" / "stages.json").read_text())
    assert stages["codes"]["config"]["num_steps"] == 6

    out = dorp(tmp_path, "build-graph", *dorp.CODES, "--codes.num-steps", "6",
               "--codes.num-frames", "320")  # fmt: skip
    assert "play: running (changed: num_frames 256 -> 320)" in out
    assert "codes: running (changed: num_frames 256 -> 320)" in out
    assert "graph: running (changed: codes.num_frames 256 -> 320)" in out

    out = dorp(tmp_path, "train-encoder", *dorp.CODES, "--codes.num-steps", "6",
               "--codes.num-frames", "320", "--codes.encoder.code-sizes", "4")  # fmt: skip
    assert "play: done for this config, skipped" in out  # the encoder does not change the data
    assert "codes: running (changed: encoder.code_sizes [8] -> [4])" in out


def test_a_field_the_stored_stage_config_lacks_is_named(tmp_path, dorp) -> None:
    dorp(tmp_path, "train-encoder", *dorp.CODES)
    stages_path = tmp_path / "run" / "stages.json"
    stages = json.loads(stages_path.read_text())
    del stages["codes"]["config"]["encoder"]["subtract_background"]  # a field added later
    stages_path.write_text(json.dumps(stages))
    out = dorp(tmp_path, "train-encoder", *dorp.CODES)
    assert "codes: running (changed: encoder.subtract_background (no such field) -> None)" in out


def test_stages_recorded_with_the_older_flat_configs_are_still_skipped(tmp_path, dorp) -> None:
    dorp(tmp_path, "build-graph", *dorp.CODES)
    stages_path = tmp_path / "run" / "stages.json"
    stages = json.loads(stages_path.read_text())

    def flat(config: dict) -> dict:  # what versions with flat configs stored
        encoder = config.pop("encoder")
        assert encoder["channels"] == 16 and encoder["mlp_sizes"] == [128, 128]  # "small"
        return config | {
            "code_size": encoder["code_sizes"][0],
            "encoder_preset": "small",
            "map_competition": encoder["map_competition"],
            "extractor_kernel_size": encoder["kernel_size"],
        }

    stages["codes"]["config"] = flat(stages["codes"]["config"])
    stages["graph"]["config"]["codes"] = flat(stages["graph"]["config"]["codes"])
    stages_path.write_text(json.dumps(stages))
    out = dorp(tmp_path, "build-graph", *dorp.CODES)
    for stage in ("play", "codes", "graph"):
        assert f"{stage}: done for this config, skipped" in out
    out = dorp(tmp_path, "build-graph", *dorp.CODES, "--codes.encoder.code-sizes", "4")
    assert "codes: running (changed: encoder.code_sizes [8] -> [4])" in out


def test_a_stage_that_did_not_finish_runs_again(tmp_path, dorp) -> None:
    dorp(tmp_path, "train-encoder", *dorp.CODES)
    stages_path = tmp_path / "run" / "stages.json"
    stages = json.loads(stages_path.read_text())
    stages["codes"]["config"] = None  # what a crash during training leaves
    stages_path.write_text(json.dumps(stages))
    out = dorp(tmp_path, "train-encoder", *dorp.CODES)
    assert "play: done for this config, skipped" in out
    assert "codes: running (it did not finish last time)" in out
    assert json.loads(stages_path.read_text())["codes"]["config"]["num_steps"] == 5


def test_an_interrupted_training_stage_resumes_from_its_last_checkpoint(
    tmp_path, dorp, monkeypatch
) -> None:
    from dorp_rl.checkpoint import load_checkpoint
    from dorp_rl.trainers import RepresentationTrainer

    args = ("train-encoder", *dorp.CODES, "--codes.num-steps", "10",
            "--codes.checkpoint-every", "4")  # fmt: skip
    dorp(tmp_path, *args, name="whole")
    step = RepresentationTrainer.train_step

    def stopped_at_step_7(self):
        if self.step == 7:
            raise KeyboardInterrupt  # as a user's Ctrl-C or the end of a session
        return step(self)

    monkeypatch.setattr(RepresentationTrainer, "train_step", stopped_at_step_7)
    monkeypatch.setattr("dorp_rl.cli.Run.heartbeat", 0.01)
    with pytest.raises(SystemExit) as stopped:
        dorp(tmp_path, *args, name="stopped")
    assert stopped.value.code == 130  # as a shell reports Ctrl-C
    said = dorp.capsys.readouterr().err
    assert "dorp train-encoder: stopped. Finished stages are kept: the same command goes on" in said
    record = json.loads((tmp_path / "stopped" / "stages.json").read_text())["codes"]
    assert record["config"] is None and record["started"]["num_steps"] == 10
    assert record["seconds"] > 0  # the time so far, kept by the heartbeat
    checkpoint = tmp_path / "stopped" / "codes" / "checkpoints" / "last.pt"
    assert load_checkpoint(checkpoint)["step"] == 4
    monkeypatch.setattr(RepresentationTrainer, "train_step", step)

    out = dorp(tmp_path, *args, name="stopped")
    assert "codes: running (it did not finish last time; resuming where it stopped)" in out
    resumed = json.loads((tmp_path / "stopped" / "stages.json").read_text())["codes"]
    assert resumed["seconds"] >= record["seconds"]  # both parts
    whole, again = (
        load_checkpoint(tmp_path / name / "codes" / "checkpoints" / "last.pt")
        for name in ("whole", "stopped")
    )
    assert again["step"] == whole["step"] == 10
    first, second = whole["state"]["encoder"], again["state"]["encoder"]
    assert all(torch.equal(first[k], second[k]) for k in first)  # as if never stopped
    # A changed config does not resume: it trains again from the start.
    dorp(tmp_path, *args, name="other")
    stages = tmp_path / "other" / "stages.json"
    stored = json.loads(stages.read_text())
    stored["codes"] = {"config": None, "started": {"num_steps": 3}, "seconds": 1.0}
    stages.write_text(json.dumps(stored))
    assert "codes: running (it did not finish last time)\n" in dorp(tmp_path, *args, name="other")


def test_an_interrupted_evaluation_resumes_at_its_next_chunk_of_tasks(
    tmp_path, dorp, monkeypatch
) -> None:
    import dorp_rl.eval.tasks as harness

    args = ("evaluate", *dorp.CODES, *dorp.EVAL, "--methods", "vf-rs", "--tasks", "6")
    dorp(tmp_path, *args, name="whole")
    run_chunk = harness._run_chunk
    ran: list[int] = []  # the first task of every chunk run

    def stopped_at_the_third_chunk(*chunk_args, **kwargs):
        if chunk_args[3] == 4:
            raise KeyboardInterrupt
        ran.append(chunk_args[3])
        return run_chunk(*chunk_args, **kwargs)

    monkeypatch.setattr(harness, "_run_chunk", stopped_at_the_third_chunk)
    with pytest.raises(SystemExit):
        dorp(tmp_path, *args, name="stopped")
    chunk_file = tmp_path / "stopped" / "evaluations" / "evaluate-vf-rs-gt.json"
    assert sorted(json.loads(chunk_file.read_text())["chunks"]) == ["0", "1"]
    assert ran == [0, 2]

    ran.clear()
    monkeypatch.setattr(
        harness, "_run_chunk", lambda *a, **k: ran.append(a[3]) or run_chunk(*a, **k)
    )
    out = dorp(tmp_path, *args, name="stopped")
    assert (
        "evaluate:vf-rs:gt: running (it did not finish last time; resuming where it stopped)" in out
    )
    assert ran == [4]  # only the unfinished chunk
    assert not chunk_file.exists()  # its results are in the stage's record now
    whole, resumed = (
        json.loads((tmp_path / name / "stages.json").read_text())["evaluate:vf-rs:gt"]["summary"]
        for name in ("whole", "stopped")
    )
    assert resumed["per_task"] == whole["per_task"]
    assert resumed["success_rate"] == whole["success_rate"]
    # A changed config starts over: the chunks of the old one are not used.
    dorp(tmp_path, *args, "--seed", "1", name="stopped")
    assert ran == [4, 0, 2, 4]


def test_evaluate_random_and_visual_foresight_write_the_results(tmp_path, dorp) -> None:
    run = tmp_path / "run"
    out = dorp(tmp_path, "evaluate", *dorp.CODES, *dorp.EVAL,
               "--methods", "random", "vf-rs", "vf-cem")  # fmt: skip
    assert not (run / "codes").exists()  # no DORP, no codes
    rows = read_rows(run)
    assert [(r["method"], r["low_level"]) for r in rows] == [
        ("random", "none"),
        ("vf-rs", "gt"),
        ("vf-cem", "gt"),
    ]
    for row in rows:
        assert row["setting"] == "1obj" and row["tasks"] == "2"
        assert 0.0 <= float(row["success_rate"]) <= 1.0
        assert float(row["seconds_per_task"]) > 0
    table = (run / "results.md").read_text()
    assert "| " + " | ".join(RESULT_COLUMNS) + " |" in table
    assert "| 1obj | vf-cem | gt | 2 |" in table
    assert "| setting | method |" in out  # the table is printed too
    for figure in ("success.png", "steps.png"):
        assert (run / figure).stat().st_size > 1000
        assert f"]({figure})" in table

    # Another method adds a row; the finished ones are skipped, not re-run.
    out = dorp(tmp_path, "evaluate", *dorp.CODES, *dorp.EVAL, "--methods", "random",
               "vf-rs", "--seed", "1")  # fmt: skip
    assert "evaluate:random: running (changed: seed 0 -> 1)" in out
    assert "evaluate:vf-rs:gt: running (changed: seed 0 -> 1)" in out
    rows = read_rows(run)
    assert [r["method"] for r in rows] == ["random", "vf-rs", "vf-cem"]  # rows keep their place


def test_evaluate_through_a_world_model(tmp_path, dorp) -> None:
    run = tmp_path / "run"
    dorp(tmp_path, "train-world-model", *TINY_WORLD_MODEL, "--setting", "1obj")
    checkpoint = run / "world_model" / "checkpoints" / "last.pt"
    assert checkpoint.is_file()
    out = dorp(tmp_path, "evaluate", *dorp.CODES, *TINY_WORLD_MODEL, *dorp.EVAL,
               "--methods", "vf-rs", "dorp", "--low-level", "world-model")  # fmt: skip
    assert "world_model: done for this config, skipped" in out
    assert [(r["method"], r["low_level"]) for r in read_rows(run)] == [
        ("vf-rs", "world-model"),
        ("dorp", "world-model"),
    ]
    stages = json.loads((run / "stages.json").read_text())
    assert stages["evaluate:dorp:world-model"]["config"]["low_level"]["num_steps"] == 3
    # A checkpoint path works as well, in another run.
    dorp(tmp_path, "evaluate", *dorp.CODES, *dorp.EVAL, "--methods", "vf-rs",
         "--low-level", str(checkpoint), name="other")  # fmt: skip
    assert read_rows(tmp_path / "other")[0]["low_level"] == "checkpoint"


def test_reproduce_and_demo_run_dorp_and_vf_cem(tmp_path, dorp) -> None:
    for command in ("reproduce", "demo"):
        out = dorp(tmp_path, command, *dorp.CODES, *dorp.EVAL, name=command)
        rows = read_rows(tmp_path / command)
        assert [(r["method"], r["low_level"]) for r in rows] == [("dorp", "gt"), ("vf-cem", "gt")]
        assert f"files in {tmp_path / command}" in out
        assert (tmp_path / command / "graph.pt").is_file()


def test_the_demo_defaults_are_the_2_object_preset_with_fewer_steps() -> None:
    from dorp_rl.cli import DEMO_CODE_STEPS, default_command
    from dorp_rl.trainers import RepresentationConfig

    demo = default_command("demo")
    preset = RepresentationConfig.for_env("rearrangement", 2)
    assert demo.setting == "2obj" and demo.tasks == 10
    assert default_command("reproduce").tasks == 50 and default_command("evaluate").tasks == 10
    assert set(demo.methods) == {"dorp", "vf-cem"} and demo.low_level == "gt"
    assert demo.codes.num_steps == DEMO_CODE_STEPS < preset.num_steps
    assert demo.codes.to_dict() | {"num_steps": preset.num_steps} == preset.to_dict()


def test_graphs_over_one_codes_variant_share_one_encoding(tmp_path, dorp, monkeypatch) -> None:
    from dorp_rl.pipeline import stages

    calls = []
    encode = stages.encode_transitions

    def counting(buffer, encoder, **kwargs):
        calls.append(encoder_fingerprint(encoder))
        return encode(buffer, encoder, **kwargs)

    monkeypatch.setattr(stages, "encode_transitions", counting)
    dorp(tmp_path, "evaluate", *dorp.CODES, *dorp.EVAL, "--methods", "dorp", "dorp-full")
    assert len(calls) == 1  # the per-one-hot and the full graph: one encoding
    assert (tmp_path / "run" / "graph.pt").exists()
    assert (tmp_path / "run" / "graph-full.pt").exists()


def test_threads_sets_torch_threads(tmp_path, dorp) -> None:
    previous = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        dorp(tmp_path, "collect", *dorp.CODES, "--threads", "1")
        assert torch.get_num_threads() == 1
    finally:
        torch.set_num_threads(previous)


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["evaluate", "--tasks", "many"], "many"),
        (["teleport"], "teleport"),
        (["evaluate", "--methods", "magic"], "magic"),
        (["evaluate", "--low-level", "no/such/checkpoint.pt"], "no/such/checkpoint.pt"),
        (["train-encoder", "--codes.num-steps", "0"], "num_steps must be >= 1"),
        (["evaluate", "--codes.lr", "-1"], "Error parsing codes: lr must be > 0"),
        (["evaluate", "--tasks", "x"], "see dorp evaluate --help"),
        (["collect", "--codes.env", "key-wall", "--codes.num-objects", "1"], "--setting"),
        (["evaluate", "--tasks", "0"], "--tasks must be >= 1"),
        (["evaluate", "--max-steps", "0"], "--max-steps must be >= 1"),
        (["evaluate", "--dorp.waypoint-budget", "-3"], "waypoint_budget must be >= 1"),
        (["evaluate", "--dorp.planner", "magic"], "planner must be one of"),
        (["reproduce", "--seed", "-1"], "--seed must be >= 0"),
        (["evaluate", "--task-seed", "-1"], "--task-seed must be >= 0"),
        (["collect", "--threads", "0"], "--threads must be >= 1"),
        (["train-encoder", "--codes.out-dir", "elsewhere"], "--codes.out-dir is set by the run"),
        (["evaluate", "--world-model.no-progress"], "--world-model.progress is set by the run"),
        (["train-encoder", "--codes.threads", "2"], "--codes.threads is set by the run"),
    ],
)
def test_bad_arguments_give_a_usage_error(tmp_path, capsys, args, message) -> None:
    with pytest.raises(SystemExit) as err:
        main([*args, "--root", str(tmp_path)])
    assert err.value.code == 2
    captured = capsys.readouterr()
    assert message in captured.err + captured.out
    assert "Traceback" not in captured.err and "tyro" not in captured.err + captured.out
    assert not any(tmp_path.iterdir())  # nothing was run


def test_python_m_dorp_rl_help_lists_every_field_with_its_default() -> None:
    # 100 columns: one column of options (wider terminals get several, side by side)
    env = {"OMP_NUM_THREADS": "1", "COLUMNS": "100", "PATH": ""}
    top = subprocess.run(
        [sys.executable, "-m", "dorp_rl", "--help"], capture_output=True, text=True, env=env
    )
    assert top.returncode == 0, top.stderr
    for command in ("collect", "train-encoder", "train-world-model", "build-graph", "evaluate",
                    "reproduce", "demo"):  # fmt: skip
        assert command in top.stdout
    sub = subprocess.run(
        [sys.executable, "-m", "dorp_rl", "evaluate", "--help"],
        capture_output=True,
        text=True,
        env=env,
    )
    assert sub.returncode == 0, sub.stderr
    for option in ("--threads", "--tasks", "--methods", "--low-level", "--codes.num-steps",
                   "--world-model.num-steps", "--root", "--name", "--codes.encoder.code-sizes",
                   "--world-model.model.latent-dim", "--dorp.goal-budget", "--dorp.planner",
                   "--dorp.reenter"):  # fmt: skip
        assert option in sub.stdout
    # the planners' shape is --candidates / --planning-horizon, for every method
    assert "--dorp.num-candidates" not in sub.stdout
    assert "100x slower" in sub.stdout  # why threads defaults to 1
    assert "(default: 10)" in sub.stdout and "(default: 1500)" in sub.stdout


def test_dorp_settings_default_to_the_env_profile_and_reach_every_evaluation(
    monkeypatch,
) -> None:
    from dorp_rl import pipeline
    from dorp_rl.cli import parse
    from dorp_rl.pipeline import stages
    from dorp_rl.reproduce import _setting_command

    # the profile's DORP settings are the defaults: the key rooms re-enter codes
    assert parse(["evaluate", "--setting", "keywall"])[1].dorp.reenter is True
    assert parse(["evaluate", "--setting", "2obj"])[1].dorp.reenter is False
    _, cmd = parse(["evaluate", "--setting", "keywall", "--dorp.planner", "cem",
                    "--dorp.goal-budget", "50", "--candidates", "7"])  # fmt: skip
    specs = []

    class Recorder:
        def __init__(self, *args, **kwargs) -> None:
            specs.append(kwargs)

        def make_policy(self, env):
            return None

    monkeypatch.setattr(stages, "EvalSpec", Recorder)
    pipeline.method_policy(cmd, "dorp", None, low_level=None, dorp=("enc", "graph", "graph"))
    (spec,) = specs
    assert spec["dorp"]["planner"] == "cem" and spec["dorp"]["goal_budget"] == 50
    assert spec["dorp"]["reenter"] is True and "num_candidates" not in spec["dorp"]
    monkeypatch.undo()
    kept = {k: v for k, v in spec.items() if k not in ("encoder", "graph")}
    config = stages.EvalSpec("keywall", "random", **kept).dorp_config()
    assert (config.planner, config.goal_budget, config.num_candidates) == ("cem", 50, 7)
    # --paper carries the command line's --dorp.* changes into every setting's own config
    _, paper = parse(["reproduce", "--paper", "--dorp.goal-budget", "50"])
    base = pipeline.default_command("reproduce", paper.setting)

    class FakeRun:
        dir = Path("runs/paper")

    for setting, reenter in (("keywall", True), ("2obj", False)):
        sub = _setting_command(paper, base, setting, FakeRun())
        assert sub.dorp.goal_budget == 50 and sub.dorp.reenter is reenter


def test_a_changed_default_of_the_policy_reruns_stored_dorp_evaluations(
    tmp_path, dorp, monkeypatch
) -> None:
    """A stored DORP evaluation is keyed by the config it ran with, including what the
    fields left None take (DORPConfig.WHERE_SUITED): the same command skips it, a
    changed value runs it again, naming the change."""
    from types import MappingProxyType

    from dorp_rl.policies import DORPConfig

    args = ("evaluate", *dorp.CODES, *dorp.EVAL, "--methods", "dorp", "--gifs", "0")
    dorp(tmp_path, *args)
    assert "evaluate:dorp:gt: done for this config, skipped" in dorp(tmp_path, *args)
    changed = {**DORPConfig.WHERE_SUITED, "action_prior_mix": 0.5}
    monkeypatch.setattr(DORPConfig, "WHERE_SUITED", MappingProxyType(changed))
    out = dorp(tmp_path, *args)
    assert "evaluate:dorp:gt: running (changed: dorp_where_suited.action_prior_mix" in out


def test_torchrl_info_lines_are_held_back_while_bars_are_shown() -> None:
    logger = logging.getLogger("torchrl")
    before = logger.level
    with quiet_torchrl(True):
        assert logger.getEffectiveLevel() == logging.WARNING
    assert logger.level == before
    with quiet_torchrl(False):
        assert logger.level == before


def test_result_plots_show_the_paper_and_solved_tasks_only(tmp_path) -> None:
    from matplotlib.figure import Figure

    from dorp_rl.viz import plot_results

    drawn: list[dict] = []
    original = Figure.savefig

    def record(fig, path, **kwargs):
        ax = fig.axes[0]
        drawn.append(
            {
                "bars": [p.get_height() for p in ax.patches],
                "points": [c.get_offsets().tolist() for c in ax.collections],
            }
        )
        return original(fig, path, **kwargs)

    row = {"setting": "2obj", "low_level": "gt", "success_rate": 0.5}
    rows = [
        {**row, "method": "dorp", "per_task": {"success": [True, False], "steps": [30, 400],
                                                "lower_bound": [20, 9]}},
        {**row, "method": "random", "low_level": "none"},
    ]  # fmt: skip
    Figure.savefig = record
    try:
        paths = plot_results(rows, tmp_path, {"2obj": {"dorp": 1.0}})
    finally:
        Figure.savefig = original
    assert [p.name for p in paths] == ["success.png", "steps.png"]
    assert sorted(drawn[0]["bars"]) == [0.5, 0.5, 1.0]  # two rows, one paper figure
    assert drawn[1]["points"] == [[[20.0, 30.0]]]  # the failed task is not drawn
