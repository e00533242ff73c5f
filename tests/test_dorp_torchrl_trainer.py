"""examples/dorp_in_torchrl_trainer.py: the DORP policy drives torchrl's Trainer (tiny config)."""

from __future__ import annotations

import importlib.util
import warnings
from pathlib import Path

import pytest
import torch
from torchrl.checkpoint import Checkpoint

pytestmark = pytest.mark.usefixtures("one_torch_thread")

EXAMPLE = Path(__file__).resolve().parents[1] / "examples" / "dorp_in_torchrl_trainer.py"


@pytest.fixture(scope="module")
def example():
    spec = importlib.util.spec_from_file_location("dorp_in_torchrl_trainer", EXAMPLE)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def exact_at_first_and_last_step(model, data) -> tuple[float, float]:
    """Share of windows whose open-loop frame is exact at step 1 and at the last step."""
    model.eval()
    frames = model.rollout(data[:, 0]["pixels"], data["action"])
    exact = (frames == data["next", "pixels"]).flatten(2).all(-1).double().mean(0)
    return float(exact[0]), float(exact[-1])


def test_smoke_run_fine_tunes_logs_and_checkpoints(example, tmp_path, monkeypatch):
    held_out = []
    windows_of = example.held_out_windows
    monkeypatch.setattr(
        example, "held_out_windows", lambda *a: held_out.append(windows_of(*a)) or held_out[-1]
    )
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        out = example.main(["--smoke", "--out-dir", str(tmp_path)])
    trainer, model, args = out["trainer"], out["model"], out["args"]
    assert trainer.collected_frames == args.total_frames
    assert trainer._optim_count == args.optim_steps * args.total_frames // args.frames_per_batch
    # torchrl's hooks: the losses and DORP's success rate went to the CSV logger
    scalars = tmp_path / "logs" / "scalars"
    for name in ("loss_reconstruction", "dorp_success", "grad_norm_0"):
        rows = (scalars / f"{name}.csv").read_text().splitlines()
        assert len(rows) == args.total_frames // args.frames_per_batch, name
    # training moved the weights away from their (seeded) initial values; the
    # checkpoint holds the fine-tuned ones
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        initial = example.build(example.parse_args(["--smoke", "--out-dir", str(tmp_path / "b")]))
    fresh = initial["model"]
    assert not all(
        torch.equal(a, b) for a, b in zip(fresh.parameters(), model.parameters(), strict=True)
    )
    # The accuracies printed before and after are those of the initial and the fine-tuned
    # model on the held-out windows (counted here from their rollouts).
    (data,) = held_out
    assert 0 < data.shape[0] <= args.eval_windows and data.shape[1] == args.horizon
    assert out["before"] == pytest.approx(exact_at_first_and_last_step(fresh, data))
    assert out["after"] == pytest.approx(exact_at_first_and_last_step(model, data))
    Checkpoint(model=fresh).load(tmp_path / "checkpoint", components=["model"])
    for a, b in zip(fresh.state_dict().values(), model.state_dict().values(), strict=True):
        assert torch.equal(a, b)
    # the replay buffer hands the loss windows of consecutive steps of one episode
    buffer = trainer._modules["replay_buffer"].replay_buffer
    sample = example.windows(buffer.sample(), args.horizon)
    assert sample.shape == (args.batch_size, args.horizon)
    assert torch.equal(sample["next", "pixels"][:, :-1], sample["pixels"][:, 1:])
    traj = sample["collector", "traj_ids"]
    assert (traj == traj[:, :1]).all()


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--frames-per-batch", "30", "--num-envs", "4"], "multiple of --num-envs"),
        (["--horizon", "20", "--frames-per-batch", "64", "--num-envs", "4"], "--horizon (20)"),
        (["--optim-steps", "0"], "--optim-steps must be >= 1"),
    ],
)
def test_bad_sizes_are_usage_errors(example, capsys, args, message):
    with pytest.raises(SystemExit) as info:
        example.parse_args(args)
    assert info.value.code == 2
    assert message in capsys.readouterr().err
