"""Divergence stop: a non-finite loss, gradient or weight ends training, naming the step.

The parameters are not updated by the failing step, nothing is saved after it,
and the last good checkpoint still loads with the weights an uninterrupted run had
at its step.
"""

from __future__ import annotations

import math
from pathlib import Path
from unittest import mock

import pytest
import torch

from dorp_rl.checkpoint import load_checkpoint
from dorp_rl.trainers import (
    RepresentationTrainer,
    TrainingDivergedError,
    WorldModelTrainer,
    load_encoder,
    load_video_model,
)

pytestmark = pytest.mark.usefixtures("one_torch_thread")


def weights(module: torch.nn.Module) -> dict[str, torch.Tensor]:
    return {k: v.detach().clone() for k, v in module.state_dict().items()}


def parameters(module: torch.nn.Module) -> dict[str, torch.Tensor]:
    return {k: v.detach().clone() for k, v in module.named_parameters()}


def same(a: dict, b: dict) -> bool:
    return a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)


def logged(out_dir: str | Path, name: str = "loss_cpc") -> list[tuple[int, str]]:
    """The (step, value) rows of one scalar in a run's CSV logs, in the order written."""
    path = Path(out_dir) / "logs" / "scalars" / f"{name}.csv"
    rows = [line.split(",") for line in path.read_text().splitlines()]
    return [(int(step), value) for step, value in rows]


def model_of(trainer) -> torch.nn.Module:
    return trainer.encoder if isinstance(trainer, RepresentationTrainer) else trainer.model


def make(kind: str, representation_config, world_model_config, name: str = "run", **overrides):
    if kind == "representation":
        return RepresentationTrainer(representation_config(name, **overrides))
    return WorldModelTrainer(world_model_config(name, **overrides))


def poison_loss_at(trainer, step: int, value: float = math.nan) -> None:
    """Makes the loss non-finite at ``step`` (1-based), as a diverging run would."""
    loss_module = trainer.loss
    original = loss_module.forward

    def forward(*args, **kwargs):
        out = original(*args, **kwargs)
        if trainer.step + 1 == step:
            key = next(k for k in out.keys() if k.startswith("loss_"))
            out.set(key, out.get(key) * value)
        return out

    loss_module.forward = forward


KINDS = ["representation", "world_model"]


@pytest.mark.parametrize("kind", KINDS)
def test_a_huge_learning_rate_stops_with_the_step(kind, representation_config, world_model_config):
    trainer = make(kind, representation_config, world_model_config, lr=1e9, checkpoint_every=1)
    with pytest.raises(TrainingDivergedError, match=r"diverged at step \d+") as info:
        trainer.train()
    assert isinstance(info.value, ValueError)
    assert "lr=1000000000.0" in str(info.value)
    # The first update already makes the next step diverge; with checkpoint_every=1 the
    # step before it was saved, is named as kept, and still loads with finite weights.
    diverged = trainer.step + 1
    assert f"diverged at step {diverged}:" in str(info.value)
    assert diverged >= 2 and trainer.saved_step == trainer.step
    assert f"(step {trainer.saved_step}), is kept" in str(info.value)
    assert load_checkpoint(trainer.checkpoint_path)["step"] == trainer.saved_step
    loader = load_encoder if kind == "representation" else load_video_model
    assert all(torch.isfinite(p).all() for p in loader(trainer.checkpoint_path).parameters())


@pytest.mark.parametrize("kind", KINDS)
@pytest.mark.parametrize("value", [math.nan, math.inf])
def test_a_non_finite_loss_keeps_the_last_good_checkpoint(
    kind, value, representation_config, world_model_config
):
    reference = make(kind, representation_config, world_model_config, "ref", num_steps=6)
    while reference.step < 4:  # an uninterrupted run, looked at after step 4
        reference.train_step()
    trainer = make(kind, representation_config, world_model_config, num_steps=6, checkpoint_every=2)
    poison_loss_at(trainer, 5, value)
    with pytest.raises(TrainingDivergedError, match="step 5: the loss is") as info:
        trainer.train()
    assert "(step 4), is kept" in str(info.value)
    payload = load_checkpoint(trainer.checkpoint_path)
    assert payload["step"] == 4
    loader = load_encoder if kind == "representation" else load_video_model
    assert same(weights(loader(trainer.checkpoint_path)), weights(model_of(reference).eval()))
    # The failing step did not update the parameters either.
    assert same(parameters(model_of(trainer)), parameters(model_of(reference)))


def test_a_non_finite_gradient_stops_before_the_update(representation_config):
    trainer = RepresentationTrainer(representation_config(num_steps=6))
    parameter = next(trainer.encoder.parameters())
    before: dict[str, torch.Tensor] = {}

    def hook(grad: torch.Tensor) -> torch.Tensor:
        if trainer.step + 1 == 3:
            before.update(parameters(trainer.encoder))
            return grad * math.inf
        return grad

    parameter.register_hook(hook)
    with pytest.raises(TrainingDivergedError, match="step 3: the gradient norm is") as info:
        trainer.train()
    assert "no checkpoint had been written yet" in str(info.value)
    assert same(parameters(trainer.encoder), before)
    assert not trainer.checkpoint_path.exists()


def test_an_update_that_makes_weights_non_finite_is_caught(world_model_config):
    trainer = WorldModelTrainer(world_model_config(num_steps=6, checkpoint_every=2))
    step = trainer.optimizer.step

    def broken_step(*args, **kwargs):
        out = step(*args, **kwargs)
        if trainer.step + 1 == 3:
            with torch.no_grad():
                next(trainer.model.parameters()).fill_(math.inf)
        return out

    trainer.optimizer.step = broken_step
    with pytest.raises(TrainingDivergedError, match="step 3: the update made weights"):
        trainer.train()
    assert load_checkpoint(trainer.checkpoint_path)["step"] == 2
    assert all(
        torch.isfinite(p).all() for p in load_video_model(trainer.checkpoint_path).parameters()
    )


def test_resume_after_a_divergence_continues_from_the_good_checkpoint(representation_config):
    full = RepresentationTrainer(representation_config("full", num_steps=8, checkpoint_every=4))
    full.train()
    broken = RepresentationTrainer(representation_config("run", num_steps=8, checkpoint_every=4))
    poison_loss_at(broken, 6)
    with pytest.raises(TrainingDivergedError):
        broken.train()
    resumed = RepresentationTrainer(representation_config("run", num_steps=8, checkpoint_every=4))
    with mock.patch.object(resumed, "train_step", wraps=resumed.train_step) as step:
        result = resumed.train(resume=True)  # a transient fault (the poisoned step) is retried
    # It went on from the good checkpoint (step 4): steps 5-8 trained, 1-4 not again.
    assert resumed.resumed_from_step == result["resumed_from_step"] == 4
    assert step.call_count == 4 and resumed.step == 8
    assert same(weights(resumed.encoder), weights(full.encoder))
    # The log (log_every=2) has steps 2 and 4 from the broken run (it stopped before logging
    # step 6), then 6 and 8 from the resume: each once, with the uninterrupted run's values.
    assert logged(resumed.config.out_dir) == logged(full.config.out_dir)
    assert [step for step, _ in logged(resumed.config.out_dir)] == [2, 4, 6, 8]


def test_clipping_can_be_turned_off_with_inf(world_model_config):
    result = WorldModelTrainer(world_model_config(grad_clip=math.inf, num_steps=2)).train()
    assert result["step"] == 2 and math.isfinite(result["metrics"]["grad_norm"])
