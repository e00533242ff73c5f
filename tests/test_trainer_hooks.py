"""Trainer hooks and nested configs: hook state in checkpoints, older flat checkpoints still load."""

from __future__ import annotations

import warnings
from typing import Any
from unittest import mock

import pytest
import torch

from dorp_rl.checkpoint import load_checkpoint, save_checkpoint
from dorp_rl.config import config_differences
from dorp_rl.modules import EncoderConfig, VideoModelConfig
from dorp_rl.trainers import (
    RepresentationConfig,
    RepresentationTrainer,
    TrainerHook,
    WorldModelConfig,
    WorldModelTrainer,
    choose_code_settings,
    load_encoder,
    load_video_model,
)

pytestmark = pytest.mark.usefixtures("one_torch_thread")


def same_weights(a: torch.nn.Module, b: torch.nn.Module) -> bool:
    return all(
        torch.equal(x, y)
        for x, y in zip(a.state_dict().values(), b.state_dict().values(), strict=True)
    )


# ---------------------------------------------------------------- checkpoints of the flat configs
def flat_representation_config(out_dir: str) -> dict[str, Any]:
    """The config dict of conftest's tiny representation run as versions with flat configs stored it."""
    return {
        "env": "rearrangement", "num_objects": 1, "num_frames": 256, "num_envs": 16,
        "trajectory_length": None, "min_offset": 1, "max_offset": 1, "data_dir": None,
        "code_size": 8, "encoder_preset": "small", "map_competition": "sigmoid",
        "extractor_kernel_size": 3, "similarity": "dddp", "dddp_sign": "paper", "alpha": 1.0,
        "gumbel_side": "positive", "gumbel_temperature": 0.1, "gumbel_temperature_start": None,
        "gumbel_anneal_steps": 0, "ce_temperature": 0.1, "usage_weight": 0.0,
        "exclusivity_weight": 0.0, "sparsity_weight": 0.0, "motion_weight": 0.0,
        "batch_size": 32, "lr": 1e-3, "similarity_lr_scale": 1.0, "num_steps": 10, "seed": 0,
        "device": "cpu", "out_dir": out_dir, "log_every": 2, "diagnostics_every": 10**9,
        "diagnostics_samples": 2048, "checkpoint_every": 5, "progress": False,
        "collapse_check_after": 10**9, "collapse_min_codes": 2, "collapse_loss_margin": 0.05,
        "entanglement_check_after": 600, "entanglement_threshold": 0.07, "max_restarts": 3,
        "num_candidates": 1, "candidate_steps": 1000, "screening_frames": 8192,
    }  # fmt: skip


def flat_world_model_config(out_dir: str) -> dict[str, Any]:
    """The config dict of conftest's tiny world-model run as versions with flat configs stored it."""
    return {
        "env": "rearrangement", "num_objects": 1, "num_frames": 256, "num_envs": 16,
        "trajectory_length": 4, "horizon": 3, "data_dir": None, "eval_frames": 128,
        "eval_sequences": 8, "model_preset": "small", "latent_dim": 4, "prior": "fixed",
        "feedback": "straight_through", "kl_weight": 1.0, "free_bits": 0.0,
        "deterministic_fraction": 0.5, "open_loop_ramp": 0.5, "batch_size": 8, "lr": 2e-3,
        "lr_final": 1e-4, "grad_clip": 1.0, "num_steps": 6, "seed": 0, "device": "cpu",
        "out_dir": out_dir, "log_every": 2, "eval_every": 10**6, "checkpoint_every": 2,
        "progress": False,
    }  # fmt: skip


def rewrite_as_flat(path, flat_config: dict[str, Any], legacy_extra: bool) -> None:
    """Rewrites a checkpoint as the flat-config versions wrote it (same weights and RNG)."""
    payload = load_checkpoint(path)
    extra = dict(payload["extra"])
    if legacy_extra:  # restarts and candidates were top-level entries, not hook states
        hooks = extra.pop("hooks")
        extra["restarts"] = hooks["collapse"]["restarts"] + hooks["entanglement"]["restarts"]
        extra["candidates"] = hooks["screening"]["candidates"]
    save_checkpoint(
        path,
        kind=payload["kind"],
        config=flat_config,
        env_config=payload["env_config"],
        state=payload["state"],
        step=payload["step"],
        rng=payload["rng"],
        extra=extra,
    )


def test_flat_configs_are_read_into_the_nested_ones(tmp_path, tiny_configs):
    rep = tiny_configs.representation(tmp_path / "rep")
    # The flat config stored what the defaults now choose for one block (independent maps,
    # no exclusivity, every pixel): equal once the open settings are chosen.
    flat = RepresentationConfig.from_dict(flat_representation_config(rep.out_dir))
    assert (flat.encoder.map_competition, flat.exclusivity_weight) == ("sigmoid", 0.0)
    assert choose_code_settings(flat, None)[0] == choose_code_settings(rep, None)[0]
    assert rep.encoder == EncoderConfig.small((8,))
    wm = tiny_configs.world_model(tmp_path / "wm")
    assert WorldModelConfig.from_dict(flat_world_model_config(wm.out_dir)) == wm
    authors = flat_representation_config("x") | {"encoder_preset": "authors", "code_size": 16}
    # ... with the independent maps they were trained with (16 x 16 frames: the stride
    # left open is 1).
    stored_then = EncoderConfig.authors((16,), map_competition="sigmoid")
    assert RepresentationConfig.from_dict(authors).encoder == stored_then
    with pytest.raises(ValueError, match="both 'encoder' and"):
        RepresentationConfig.from_dict(rep.to_dict() | {"code_size": 8})
    with pytest.raises(ValueError, match=r"WorldModelConfig holds both 'model' and .*'latent_dim'"):
        WorldModelConfig.from_dict(wm.to_dict() | {"latent_dim": 4})


def test_a_flat_representation_checkpoint_loads_and_resumes(tmp_path, tiny_configs):
    full = RepresentationTrainer(tiny_configs.representation(tmp_path / "full"))
    full.train()
    part_cfg = tiny_configs.representation(tmp_path / "part", num_steps=5)
    part = RepresentationTrainer(part_cfg)
    part.train()
    rewrite_as_flat(
        part.checkpoint_path,
        flat_representation_config(part_cfg.out_dir) | {"num_steps": 5},
        legacy_extra=True,
    )
    encoder = load_encoder(part.checkpoint_path, part_cfg.make_env())
    assert same_weights(encoder, part.encoder.eval())
    resumed = RepresentationTrainer(tiny_configs.representation(tmp_path / "part"))
    with (
        pytest.warns(UserWarning, match=r"num_steps=10 \(checkpoint 5\)"),
        mock.patch.object(resumed, "train_step", wraps=resumed.train_step) as step,
    ):
        result = resumed.train(resume=True)
    # It went on from the flat checkpoint's step 5: only steps 6-10 trained here.
    assert resumed.resumed_from_step == result["resumed_from_step"] == 5
    assert step.call_count == 5
    assert resumed.step == 10 and same_weights(resumed.encoder, full.encoder)


def test_a_flat_world_model_checkpoint_loads_and_resumes(tmp_path, tiny_configs):
    full = WorldModelTrainer(tiny_configs.world_model(tmp_path / "full"))
    full.train()
    part_cfg = tiny_configs.world_model(tmp_path / "part")
    part = WorldModelTrainer(part_cfg)
    step = part.train_step

    def stop_after_four() -> dict[str, float]:
        if part.step == 4:  # the learning-rate schedule needs the full run's num_steps
            raise KeyboardInterrupt
        return step()

    part.train_step = stop_after_four
    with pytest.raises(KeyboardInterrupt):
        part.train()
    rewrite_as_flat(part.checkpoint_path, flat_world_model_config(part_cfg.out_dir), False)
    model = load_video_model(part.checkpoint_path, part_cfg.make_env())
    assert same_weights(model, part.model.eval())
    resumed = WorldModelTrainer(tiny_configs.world_model(tmp_path / "part"))
    with mock.patch.object(resumed, "train_step", wraps=resumed.train_step) as counted:
        result = resumed.train(resume=True)
    # It went on from the flat checkpoint's step 4: only steps 5 and 6 trained here.
    assert resumed.resumed_from_step == result["resumed_from_step"] == 4
    assert counted.call_count == 2
    assert resumed.step == 6 and same_weights(resumed.model, full.model)


def test_resume_names_the_changed_nested_field(tmp_path, tiny_configs):
    WorldModelTrainer(tiny_configs.world_model(tmp_path / "wm", num_steps=2)).train()
    changed = tiny_configs.world_model(tmp_path / "wm", model={"latent_dim": 2})
    with pytest.raises(ValueError, match=r"model\.latent_dim: checkpoint 4, now 2"):
        WorldModelTrainer(changed).train(resume=True)
    stored = tiny_configs.world_model(tmp_path / "wm").to_dict()
    assert set(config_differences(stored, changed.to_dict())) == {"model.latent_dim"}


def test_replace_merges_a_dict_into_the_nested_config(tiny_configs, tmp_path):
    cfg = tiny_configs.world_model(tmp_path / "wm")
    assert cfg.model == VideoModelConfig.small()
    changed = cfg.replace(model={"latent_dim": 0}, lr=1e-4)
    assert changed.model == VideoModelConfig.small(latent_dim=0) and changed.lr == 1e-4
    assert cfg.model.latent_dim == 4  # the original is untouched
    changed.model.channels = 8
    assert cfg.model.channels == 16  # configs never share a nested config
    with pytest.raises(ValueError, match=r"^model\.channels must be >= 1"):
        cfg.replace(model={"channels": 0})
    # a dict given to the constructor changes the field's default (the small encoder)
    built = RepresentationConfig(encoder={"code_sizes": (8,)})
    assert built.encoder == EncoderConfig.small((8,))
    with pytest.raises(ValueError, match=r"^encoder: unknown EncoderConfig fields \['size'\]"):
        RepresentationConfig(encoder={"size": 8})


# ---------------------------------------------------------------- hooks
class CountingHook(TrainerHook):
    """Counts the steps it saw; can claim every ``claim_every``-th step."""

    def __init__(self, claim_every: int = 0) -> None:
        self.seen: list[int] = []
        self.claim_every = claim_every

    def after_step(self, metrics: dict[str, float], logged: bool) -> bool:
        self.seen.append(self.trainer.step)
        return bool(self.claim_every) and self.trainer.step % self.claim_every == 0

    def state_dict(self) -> dict[str, Any]:
        return {"seen": list(self.seen)}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.seen = list(state.get("seen", []))


def test_hooks_are_called_in_order_and_a_claimed_step_skips_the_rest(tmp_path, tiny_configs):
    trainer = WorldModelTrainer(tiny_configs.world_model(tmp_path / "wm"))
    first = trainer.register_hook("first", CountingHook(claim_every=2))
    second = trainer.register_hook("second", CountingHook())
    trainer.train()
    assert first.seen == [1, 2, 3, 4, 5, 6]
    assert second.seen == [1, 3, 5]
    with pytest.raises(ValueError, match="already registered as 'first'"):
        trainer.register_hook("first", CountingHook())


def test_hooks_are_torchrl_hooks_registered_the_torchrl_way(tmp_path, tiny_configs):
    from torchrl.trainers import TrainerHookBase

    trainer = WorldModelTrainer(tiny_configs.world_model(tmp_path / "wm", num_steps=2))
    hook = CountingHook()
    assert isinstance(hook, TrainerHookBase)
    hook.register(trainer)  # torchrl's entry point, under the hook's default name
    hook_named = CountingHook()
    hook_named.register(trainer, name="again")
    assert list(trainer.hooks) == ["hook", "again"] and hook.trainer is trainer
    trainer.train()
    assert hook.seen == hook_named.seen == [1, 2]
    with pytest.raises(TypeError, match="TrainerHook instances, got object"):
        trainer.register_hook("other", object())
    representation = RepresentationTrainer(tiny_configs.representation(tmp_path / "codes"))
    assert list(representation.hooks) == ["widths", "screening", "collapse", "entanglement", "dead"]
    assert all(isinstance(h, TrainerHookBase) for h in representation.hooks.values())


def test_hook_state_is_checkpointed_and_resumed(tmp_path, tiny_configs):
    trainer = WorldModelTrainer(tiny_configs.world_model(tmp_path / "wm", num_steps=3))
    trainer.register_hook("count", CountingHook())
    trainer.train()
    assert load_checkpoint(trainer.checkpoint_path)["extra"]["hooks"]["count"] == {
        "seen": [1, 2, 3]
    }
    resumed = WorldModelTrainer(tiny_configs.world_model(tmp_path / "wm", num_steps=5))
    hook = resumed.register_hook("count", CountingHook())
    with (
        warnings.catch_warnings(),
        mock.patch.object(resumed, "train_step", wraps=resumed.train_step) as step,
    ):
        warnings.simplefilter("ignore", UserWarning)  # num_steps changed on resume
        resumed.train(resume=True)
    # Steps 1-3 come from the checkpointed state, 4 and 5 from this run (a fresh run of 5
    # steps would give the same list, so the steps trained here are counted too).
    assert hook.seen == [1, 2, 3, 4, 5]
    assert resumed.resumed_from_step == 3 and step.call_count == 2


@pytest.fixture
def two_threads():
    """torch at two threads for one test, the count before restored after."""
    previous = torch.get_num_threads()
    torch.set_num_threads(2)
    yield
    torch.set_num_threads(previous)


class ThreadsHook(TrainerHook):
    """Records torch's thread count at every step."""

    def __init__(self) -> None:
        self.threads: list[int] = []

    def after_step(self, metrics: dict[str, float], logged: bool) -> bool:
        self.threads.append(torch.get_num_threads())
        return False


def test_threads_apply_while_training_and_are_restored(tmp_path, tiny_configs, two_threads):
    trainer = WorldModelTrainer(tiny_configs.world_model(tmp_path / "wm", num_steps=2, threads=1))
    hook = trainer.register_hook("threads", ThreadsHook())
    trainer.train()
    assert hook.threads == [1, 1] and torch.get_num_threads() == 2
    # Threads are bookkeeping: a resume with another count is not refused.
    more = WorldModelTrainer(tiny_configs.world_model(tmp_path / "wm", num_steps=3, threads=2))
    more_hook = more.register_hook("threads", ThreadsHook())
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)  # num_steps changed on resume
        more.train(resume=True)
    assert more_hook.threads == [2]
    with pytest.raises(ValueError, match="threads"):
        tiny_configs.world_model(tmp_path / "bad", threads=0)


def test_restart_hooks_keep_their_restarts_across_a_resume(tmp_path, tiny_configs):
    # lr 1e-12 never leaves the initial codes: every attempt is flat at log B and restarts.
    overrides = dict(lr=1e-12, collapse_check_after=3, max_restarts=2, checkpoint_every=1)
    trainer = RepresentationTrainer(tiny_configs.representation(tmp_path / "r", **overrides))
    assert list(trainer.hooks) == ["widths", "screening", "collapse", "entanglement", "dead"]
    with pytest.warns(RuntimeWarning):
        trainer.train()
    restarts = trainer.collapse_hook.restarts
    assert [r["attempt"] for r in restarts] == [1, 2] and trainer.restarts == restarts
    stored = load_checkpoint(trainer.checkpoint_path)["extra"]["hooks"]
    assert stored["collapse"]["restarts"] == restarts
    assert stored["entanglement"]["restarts"] == []
    assert stored["dead"]["restarts"] == []
    again = RepresentationTrainer(tiny_configs.representation(tmp_path / "r", **overrides))
    again.load()
    assert again.collapse_hook.restarts == restarts and again.attempt == 2
