"""Encoder, similarity matrices, CPC loss, representation trainer and checkpoints."""

from __future__ import annotations

import copy
import math
import pickle
import warnings
from unittest import mock

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from tensordict import TensorDict

from dorp_rl.checkpoint import load_checkpoint, save_checkpoint
from dorp_rl.envs import KeyWallEnv, ObjectRearrangementEnv
from dorp_rl.eval import code_information
from dorp_rl.modules import (
    DDDPSimilarity,
    DiscreteCodeEncoder,
    EncoderConfig,
    FullSimilarity,
    IdentitySimilarity,
)
from dorp_rl.objectives import CPCLoss
from dorp_rl.objectives.cpc import uncovered_motion
from dorp_rl.trainers import RepresentationConfig, RepresentationTrainer, load_encoder


def _pixels(n: int, seed: int = 0) -> torch.Tensor:
    env = ObjectRearrangementEnv(2, seed=seed, batch_size=(), batch_locked=False)
    return env.render_state(env.sample_states((n,)))


def _tiny_config(tmp_path, **overrides) -> RepresentationConfig:
    base = RepresentationConfig.for_env(
        "rearrangement",
        1,
        encoder={"code_sizes": (8,)},
        num_frames=512,
        num_envs=16,
        batch_size=32,
        num_steps=12,
        log_every=3,
        checkpoint_every=5,
        diagnostics_every=10**9,
        progress=False,
        out_dir=str(tmp_path / "run"),
        collapse_check_after=10**9,
        dead_check_frames=0,
    )
    return base.replace(**overrides)


# ---------------------------------------------------------------- encoder
@pytest.mark.parametrize("competition", ["sigmoid", "softmax"])
def test_encoder_shapes_and_dtypes(competition):
    encoder = DiscreteCodeEncoder(
        EncoderConfig(
            code_sizes=(16, 2), channels=8, mlp_sizes=(32, 32), map_competition=competition
        )
    )
    code, probs = encoder(_pixels(5))
    assert code.dtype == torch.int64 and code.shape == (5, 2)
    assert probs.shape == (5, 2, 16) and probs.dtype == torch.float32
    assert torch.allclose(probs.sum(-1), torch.ones(5, 2))
    # the 2-way one-hot never puts mass on codes it does not have
    assert probs[:, 1, 2:].abs().max() == 0 and (code[:, 1] < 2).all()
    assert encoder.logits(_pixels(3)).shape == (3, 2, 16)
    assert encoder.encode(_pixels(7).view(7, 1, 3, 16, 16)).shape == (7, 1, 2)


def test_encoder_as_tensordict_module():
    encoder = DiscreteCodeEncoder(EncoderConfig.small(code_sizes=(8, 8)))
    module = encoder.as_tensordict_module()
    td = module(TensorDict(pixels=_pixels(4), batch_size=[4]))
    assert td["code"].shape == (4, 2) and td["code_probs"].shape == (4, 2, 8)
    goal = encoder.as_tensordict_module("goal_pixels", ("goal_code", "goal_code_probs"))
    td = goal(TensorDict(goal_pixels=_pixels(4), batch_size=[4]))
    assert "goal_code" in td.keys()


def test_encoder_presets_differ_in_size():
    small = sum(p.numel() for p in DiscreteCodeEncoder(EncoderConfig.small((32,))).parameters())
    big = sum(p.numel() for p in DiscreteCodeEncoder(EncoderConfig.authors((32,))).parameters())
    assert small < big / 3


def _encoder_with_running_stats(competition: str = "softmax") -> DiscreteCodeEncoder:
    torch.manual_seed(0)
    encoder = DiscreteCodeEncoder(EncoderConfig.small((8, 8, 2), map_competition=competition))
    for module in encoder.modules():
        if isinstance(module, torch.nn.BatchNorm2d):
            module.running_mean.uniform_(-1, 1)
            module.running_var.uniform_(0.5, 2)
            torch.nn.init.uniform_(module.weight, 0.5, 1.5)
            torch.nn.init.uniform_(module.bias, -0.5, 0.5)
    return encoder.eval()


@pytest.mark.parametrize("competition", ["sigmoid", "softmax"])
def test_inference_extractor_computes_what_the_extractor_computes(competition):
    encoder = _encoder_with_running_stats(competition)
    pixels = _pixels(64)
    reference = encoder.logits(pixels).detach()  # gradients on: the plain extractor
    with torch.no_grad():
        fast = encoder.logits(pixels)
    finite = torch.isfinite(reference)
    assert torch.equal(finite, torch.isfinite(fast))
    assert torch.allclose(fast[finite], reference[finite], atol=1e-4, rtol=1e-4)
    with torch.no_grad():
        assert torch.equal(encoder(pixels)[0], reference.argmax(-1))
    # Folded BatchNorm is not the training-mode function: the fast path is eval-only.
    encoder.train()
    with torch.no_grad():
        assert not torch.allclose(encoder.logits(pixels)[finite], fast[finite])


def test_inference_extractor_follows_weight_changes_and_stays_out_of_the_state_dict():
    encoder = _encoder_with_running_stats()
    pixels = _pixels(16)
    keys = set(encoder.state_dict())
    with torch.no_grad():
        before = encoder.logits(pixels)
        first = encoder.inference_extractor()
        assert encoder.inference_extractor() is first  # cached while nothing changes
        encoder.extractor[0].weight.add_(0.5)  # an in-place update, as an optimiser's
        after = encoder.logits(pixels)
    assert encoder.inference_extractor() is not first
    assert not torch.allclose(before, after)
    assert torch.allclose(after, encoder.logits(pixels).detach(), atol=1e-4, rtol=1e-4)
    other = _encoder_with_running_stats()
    other.load_state_dict(encoder.state_dict())
    with torch.no_grad():
        assert torch.allclose(other.logits(pixels), after, atol=1e-5, rtol=1e-5)
    assert set(encoder.state_dict()) == keys
    clone = copy.deepcopy(encoder)
    assert "_inference_extractor" not in clone.__dict__
    assert "_inference_extractor" not in pickle.loads(pickle.dumps(encoder)).__dict__
    with torch.no_grad():
        assert torch.equal(clone(pixels)[0], encoder(pixels)[0])


@pytest.mark.parametrize(
    "pixels, match",
    [
        (torch.zeros(2, 3, 8, 8, dtype=torch.uint8), r"\[\*B, 3, 16, 16\]"),
        (torch.zeros(2, 16, 16, 3, dtype=torch.uint8), r"\[\*B, 3, 16, 16\]"),
        (torch.zeros(2, 3, 16, 16, dtype=torch.int32), "uint8"),
    ],
)
def test_encoder_rejects_bad_pixels(pixels, match):
    encoder = DiscreteCodeEncoder(EncoderConfig.small((8,)))
    with pytest.raises(ValueError, match=match):
        encoder(pixels)


def test_encoder_rejects_bad_config():
    with pytest.raises(ValueError, match="code_sizes"):
        DiscreteCodeEncoder(EncoderConfig(code_sizes=(1,)))
    with pytest.raises(ValueError, match="map_competition"):
        DiscreteCodeEncoder(EncoderConfig(code_sizes=(4,), map_competition="max"))


# ---------------------------------------------------------------- similarity
@settings(max_examples=50, deadline=None)
@given(
    dim=st.integers(2, 12),
    scale=st.floats(-4, 4),
    psi=st.floats(-10, 10),
    spread=st.floats(0, 10),
    seed=st.integers(0, 1000),
    sign=st.sampled_from(["paper", "authors"]),
)
def test_dddp_diagonally_positive_and_dominant(dim, scale, psi, spread, seed, sign):
    sim = DDDPSimilarity(dim, sign=sign)
    gen = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        sim.log_scale.fill_(scale)
        sim.psi.copy_(psi + spread * torch.randn(dim, dim, generator=gen))
    w = sim.matrix()
    diag = w.diagonal()
    off = w.masked_fill(torch.eye(dim, dtype=torch.bool), float("-inf"))
    assert (diag > 0).all()
    # each diagonal entry beats every other entry of its row and of its column
    assert (diag > off.max(dim=1).values).all() and (diag > off.max(dim=0).values).all()
    if sign == "authors":  # their variant is dominant in magnitude too (ties only where
        # float32 sigmoids saturate to exactly 0 or 1)
        assert (
            diag >= w.masked_fill(torch.eye(dim, dtype=torch.bool), 0).abs().max(1).values
        ).all()


def test_similarity_variants_and_errors():
    a, b = torch.randn(3, 6), torch.randn(5, 6)
    assert IdentitySimilarity(6)(a, b).shape == (3, 5)
    assert torch.allclose(IdentitySimilarity(6)(a, b), a @ b.T)
    assert len(list(FullSimilarity(6).parameters())) == 1
    assert len(list(IdentitySimilarity(6).parameters())) == 0
    with pytest.raises(ValueError, match=r"anchor must have shape \[B, 6\]"):
        IdentitySimilarity(6)(torch.randn(3, 4), b)
    with pytest.raises(ValueError, match="alpha"):
        DDDPSimilarity(4, alpha=0.5)
    with pytest.raises(ValueError, match="sign"):
        DDDPSimilarity(4, sign="other")


# ---------------------------------------------------------------- loss
def _loss(gumbel_side="positive", **kwargs) -> CPCLoss:
    torch.manual_seed(0)
    encoder = DiscreteCodeEncoder(EncoderConfig(code_sizes=(8, 8), channels=8, mlp_sizes=(32, 32)))
    return CPCLoss(encoder, DDDPSimilarity(16), gumbel_side=gumbel_side, **kwargs)


def _capture(loss: CPCLoss) -> dict[str, torch.Tensor]:
    """Records what the loss's encoder and similarity return on its next call."""
    seen: dict[str, torch.Tensor] = {}
    encode = loss.encoder.logits_and_maps

    def logits_and_maps(pixels):
        out = encode(pixels)
        seen["logits"], seen["maps"] = (t.detach() for t in out)
        return out

    loss.encoder.logits_and_maps = logits_and_maps
    loss.similarity.register_forward_hook(lambda m, i, o: seen.update(scores=o.detach()))
    return seen


@pytest.mark.parametrize("side", ["positive", "anchor"])
def test_gradients_reach_extractor_through_gumbel_path(side):
    loss = _loss(side)
    seen = _capture(loss)
    pixels = _pixels(8)
    out = loss(TensorDict(pixels=pixels, future_pixels=_pixels(8, seed=1), batch_size=[8]))
    out["loss_cpc"].backward()
    first_conv = loss.encoder.extractor[0].weight
    assert first_conv.grad is not None and first_conv.grad.abs().sum() > 0
    assert loss.similarity.psi.grad.abs().sum() > 0
    assert math.isclose(
        float(out["mi_lower_bound"]), math.log(8) - float(out["loss_cpc"].detach()), rel_tol=1e-5
    )
    # accuracy: share of anchors whose highest score is their own future (the diagonal);
    # codes_in_batch: distinct anchor codes per one-hot, averaged (min: the fewest).
    own = seen["scores"].argmax(1) == torch.arange(8)
    assert float(out["accuracy"]) == pytest.approx(float(own.float().mean()))
    codes = seen["logits"][:8].argmax(-1)  # the anchors' codes, [8, 2]
    used = [len(set(codes[:, c].tolist())) for c in range(2)]
    assert float(out["codes_in_batch"]) == pytest.approx(sum(used) / 2)
    assert float(out["min_codes_in_batch"]) == min(used)


def test_loss_optional_terms_and_keys():
    from dorp_rl.objectives.cpc import change_imbalance, change_overlap

    loss = _loss(usage_weight=0.1, exclusivity_weight=0.1)
    seen = _capture(loss)
    loss.set_keys(pixels="obs", future_pixels=("next", "obs"))
    td = TensorDict(
        obs=_pixels(6), next=TensorDict(obs=_pixels(6, 1), batch_size=[6]), batch_size=[6]
    )
    out = loss(td)
    assert {"loss_cpc", "loss_usage", "loss_exclusivity"} <= set(out.keys())
    # usage: weight x the mean, over one-hots, of log 8 minus the entropy of the anchors'
    # mean code distribution (0 only if every code is used equally).
    mean_probs = seen["logits"][:6].softmax(-1).mean(0)  # [2, 8]
    entropy = -(mean_probs * mean_probs.log()).sum(-1)
    usage = 0.1 * (math.log(8) - entropy).mean()
    assert float(out["loss_usage"].detach()) == pytest.approx(float(usage), rel=1e-5)
    assert float(usage) > 1e-4
    # exclusivity: weight x (overlap + imbalance) of how much each one-hot's map changes
    # from the anchor (obs) to its future (next obs).
    maps = seen["maps"]
    change = (maps[:6] - maps[6:]).abs().flatten(-2).sum(-1)  # [6, 2]
    expected = 0.1 * (change_overlap(change) + change_imbalance(change))
    assert float(out["loss_exclusivity"].detach()) == pytest.approx(float(expected), rel=1e-5)
    assert float(expected) > 1e-4


def test_usage_weight_per_one_hot_weighs_each_one_hot_on_its_own():
    """One weight per one-hot: the term is the mean over one-hots of weight x entropy
    deficit, so a 0 leaves that one-hot out (a key one-hot whose states are not equally
    frequent is not pushed to split them evenly)."""
    td = TensorDict(pixels=_pixels(6), future_pixels=_pixels(6, 1), batch_size=[6])
    loss = _loss(usage_weight=(0.3, 0.0))
    seen = _capture(loss)
    out = loss(td)
    mean_probs = seen["logits"][:6].softmax(-1).mean(0)  # [2, 8]
    deficit = math.log(8) + (mean_probs * mean_probs.log()).sum(-1)  # [2]
    assert float(deficit[1]) > 1e-4  # the second one-hot has a deficit that is not counted
    expected = (0.3 * deficit[0] + 0.0 * deficit[1]) / 2
    assert float(out["loss_usage"].detach()) == pytest.approx(float(expected), rel=1e-5)
    # one number is the same weight for every one-hot
    same = _loss(usage_weight=0.3)(td)["loss_usage"]
    both = _loss(usage_weight=(0.3, 0.3))(td)["loss_usage"]
    assert float(same.detach()) == pytest.approx(float(both.detach()), rel=1e-6)
    with pytest.raises(ValueError, match="usage_weight has 3 weights, the encoder has 2 one-hots"):
        _loss(usage_weight=(1.0, 1.0, 1.0))
    with pytest.raises(ValueError, match=r"usage_weight\[1\] must be >= 0"):
        _loss(usage_weight=(1.0, -1.0))


def test_sparsity_term_shrinks_the_object_maps():
    torch.manual_seed(0)
    loss = _loss(sparsity_weight=1.0)
    td = TensorDict(pixels=_pixels(8), future_pixels=_pixels(8, seed=3), batch_size=[8])
    out = loss(td)
    maps = loss.encoder.object_maps(torch.cat([td["pixels"], td["future_pixels"]]))
    assert float(out["loss_sparsity"].detach()) == pytest.approx(
        float(maps.detach().mean()), rel=1e-5
    )
    first_mass = float(out["map_mass"])
    opt = torch.optim.Adam(loss.encoder.extractor.parameters(), lr=1e-2)
    for _ in range(30):
        out = loss(td)
        opt.zero_grad()
        out["loss_sparsity"].backward()
        opt.step()
    assert float(out["map_mass"]) < 0.5 * first_mass


def test_uncovered_motion_counts_moving_pixels_outside_every_map():
    anchor = torch.zeros(1, 3, 16, 16, dtype=torch.uint8)
    future = anchor.clone()
    anchor[0, :, 2, 3] = 255  # the object was at (2, 3) ...
    future[0, :, 5, 6] = 255  # ... and moved to (5, 6)
    empty = torch.zeros(1, 2, 16, 16)
    assert float(uncovered_motion(anchor, future, empty, empty)) == 1.0
    at_start, at_end = empty.clone(), empty.clone()
    at_start[0, 1, 2, 3] = 1.0  # one map holds the object where it was ...
    assert float(uncovered_motion(anchor, future, at_start, empty)) == 0.5
    at_end[0, 0, 5, 6] = 1.0  # ... another where it went: all motion is covered
    assert float(uncovered_motion(anchor, future, at_start, at_end)) == 0.0
    # no moving pixel: nothing to cover
    assert float(uncovered_motion(anchor, anchor, empty, empty)) == 0.0


def test_motion_term_covers_motion_with_the_wide_onehot_only():
    torch.manual_seed(0)
    env = KeyWallEnv(batch_size=(), batch_locked=False)
    states = torch.tensor([[3, 3, 0], [10, 2, 0], [7, 12, 1], [12, 5, 1]])
    moved = env.transition(states, torch.tensor([0, 1, 2, 3]))
    td = TensorDict(
        pixels=env.render_state(states), future_pixels=env.render_state(moved), batch_size=[4]
    )
    encoder = DiscreteCodeEncoder(EncoderConfig.small(code_sizes=(16, 2)))
    loss = CPCLoss(encoder, DDDPSimilarity(32), motion_weight=2.0)
    out = loss(td)
    maps = encoder.object_maps(torch.cat([td["pixels"], td["future_pixels"]])).detach()
    agent_only = uncovered_motion(td["pixels"], td["future_pixels"], maps[:4, :1], maps[4:, :1])
    assert float(out["loss_motion"].detach()) == pytest.approx(2 * float(agent_only), rel=1e-5)
    # training on the term alone puts the agent's map on the agent
    opt = torch.optim.Adam(encoder.extractor.parameters(), lr=1e-2)
    first = float(out["loss_motion"].detach())
    for _ in range(30):
        out = loss(td)
        opt.zero_grad()
        out["loss_motion"].backward()
        opt.step()
    assert float(out["loss_motion"].detach()) < 0.5 * first


def test_loss_errors():
    loss = _loss()
    with pytest.raises(ValueError, match="sparsity_weight must be >= 0"):
        CPCLoss(loss.encoder, DDDPSimilarity(16), sparsity_weight=-1.0)
    with pytest.raises(ValueError, match="motion_weight must be >= 0"):
        CPCLoss(loss.encoder, DDDPSimilarity(16), motion_weight=-0.5)
    with pytest.raises(ValueError, match="same shape"):
        loss(TensorDict(pixels=_pixels(4), future_pixels=_pixels(5), batch_size=[]))
    with pytest.raises(ValueError, match="dim"):
        CPCLoss(loss.encoder, DDDPSimilarity(10))
    with pytest.raises(ValueError, match="gumbel_side"):
        CPCLoss(loss.encoder, DDDPSimilarity(16), gumbel_side="both")


def test_loss_falls_on_a_tiny_dataset():
    torch.manual_seed(0)
    env = ObjectRearrangementEnv(1, seed=0, batch_size=(), batch_locked=False)
    states = env.sample_states((64,))
    moved = env.transition(states, torch.randint(4, (64,)))
    td = TensorDict(
        pixels=env.render_state(states), future_pixels=env.render_state(moved), batch_size=[64]
    )
    encoder = DiscreteCodeEncoder(EncoderConfig.small(code_sizes=(16,)))
    loss = CPCLoss(encoder, DDDPSimilarity(16))
    opt = torch.optim.Adam(loss.parameters(), lr=1e-3)
    first = None
    # 250 steps: at 150 the loss fell by 1.17 with two threads but by 0.77 with one (the
    # reduction order changes the run); at 250 by 1.23 and 1.44.
    for _ in range(250):
        out = loss(td)
        first = float(out["loss_cpc"].detach()) if first is None else first
        opt.zero_grad()
        out["loss_cpc"].backward()
        opt.step()
    assert float(out["loss_cpc"].detach()) < first - 1.0


# ---------------------------------------------------------------- trainer
def test_trainer_runs_logs_and_checkpoints(tmp_path):
    trainer = RepresentationTrainer(_tiny_config(tmp_path))
    result = trainer.train()
    assert result["step"] == 12 and not result["collapsed"]
    assert trainer.checkpoint_path.exists()
    assert (tmp_path / "run" / "logs").exists()
    assert [h["step"] for h in trainer.history] == [3, 6, 9, 12]


def test_checkpoint_round_trip(tmp_path):
    trainer = RepresentationTrainer(_tiny_config(tmp_path))
    trainer.train()
    other = RepresentationTrainer(_tiny_config(tmp_path, seed=5))
    other.load(trainer.checkpoint_path)
    pixels = _pixels(16)
    assert torch.equal(trainer.encoder.encode(pixels), other.encoder.encode(pixels))
    assert other.step == trainer.step
    for a, b in zip(trainer.similarity.parameters(), other.similarity.parameters(), strict=True):
        assert torch.equal(a, b)
    encoder = load_encoder(trainer.checkpoint_path, env=trainer.env)
    assert not encoder.training
    assert torch.equal(encoder.encode(pixels), trainer.encoder.encode(pixels))


def test_resume_equals_uninterrupted_run(tmp_path):
    full = RepresentationTrainer(_tiny_config(tmp_path / "a"))
    full.train()

    interrupted = RepresentationTrainer(_tiny_config(tmp_path / "b", num_steps=5))
    interrupted.train()  # stops at step 5 with a checkpoint
    resumed = RepresentationTrainer(_tiny_config(tmp_path / "b"))
    with (
        pytest.warns(UserWarning, match=r"num_steps=12 \(checkpoint 5\)"),
        mock.patch.object(resumed, "train_step", wraps=resumed.train_step) as step,
    ):
        result = resumed.train(resume=True)
    # It went on from the checkpoint's step 5: only steps 6-12 trained here.
    assert resumed.resumed_from_step == result["resumed_from_step"] == 5
    assert step.call_count == 7 and resumed.step == 12
    for a, b in zip(
        full.encoder.state_dict().values(), resumed.encoder.state_dict().values(), strict=True
    ):
        assert torch.equal(a, b)


def test_collapse_detector_restarts_and_reports(tmp_path):
    # A learning rate of 1e-12 (lr=0 is refused) never leaves the initial near-uniform
    # codes: the loss stays at log B, so every attempt is declared collapsed.
    cfg = _tiny_config(tmp_path, lr=1e-12, collapse_check_after=4, max_restarts=2, num_steps=15)
    trainer = RepresentationTrainer(cfg)
    reason = trainer.collapse_hook.collapse_reason({"min_codes_in_batch": 1.0, "loss_cpc": 0.1}, 10)
    assert reason is not None and "only 1 code" in reason
    with pytest.warns(RuntimeWarning) as caught:
        result = trainer.train()
    said = [str(w.message) for w in caught]
    restarts = [m for m in said if "restarted at step" in m]
    assert len(restarts) == 2 and "(restart 1/2)" in restarts[0] and "(restart 2/2)" in restarts[1]
    # The last attempt collapses too: training stops at its check, not at its end.
    assert any("collapsed in all 3 attempts" in m for m in said)
    assert result["attempt"] == 2 and len(result["restarts"]) == 2
    assert result["collapsed"] is True and result["gave_up"] is not None
    assert result["step"] == result["restarts"][-1]["step"] + cfg.collapse_check_after


def test_healthy_metrics_are_not_collapse(tmp_path):
    collapse = RepresentationTrainer(_tiny_config(tmp_path)).collapse_hook
    assert collapse.collapse_reason({"min_codes_in_batch": 9.0, "loss_cpc": 2.0}, 10**6) is None
    assert collapse.collapse_reason({"min_codes_in_batch": 1.0, "loss_cpc": 2.0}, 0) is None


def test_one_noisy_batch_is_not_a_flat_loss(tmp_path):
    trainer = RepresentationTrainer(_tiny_config(tmp_path, collapse_check_after=0))
    log_b = math.log(trainer.config.batch_size)
    noisy = {"min_codes_in_batch": 9.0, "loss_cpc": log_b + 0.5}
    trainer.history = [{"step": s, "loss_cpc": 2.0} for s in range(1, 6)]
    assert trainer.collapse_hook.collapse_reason(noisy, 10**6) is None
    trainer.history = [{"step": s, "loss_cpc": log_b} for s in range(1, 6)]
    assert "flat" in trainer.collapse_hook.collapse_reason(noisy, 10**6)
    trainer.history_start = 5  # a restarted attempt does not inherit the old history
    assert "flat" in trainer.collapse_hook.collapse_reason(noisy, 10**6)
    trainer.history = [{"step": s, "loss_cpc": 2.0} for s in range(1, 6)]
    assert "flat" in trainer.collapse_hook.collapse_reason(noisy, 10**6)


def test_checkpoint_from_another_env_or_corrupted(tmp_path):
    trainer = RepresentationTrainer(_tiny_config(tmp_path))
    trainer.train()
    two = RepresentationTrainer(_tiny_config(tmp_path / "two", num_objects=2))
    with pytest.raises(ValueError, match="another environment.*num_objects"):
        two.load(trainer.checkpoint_path)
    broken = tmp_path / "broken.pt"
    broken.write_bytes(b"not a checkpoint")
    with pytest.raises(ValueError, match="corrupted"):
        load_checkpoint(broken)
    with pytest.raises(FileNotFoundError):
        load_checkpoint(tmp_path / "missing.pt")
    path = save_checkpoint(
        tmp_path / "wm.pt", kind="world_model", config={}, env_config={}, state={}, step=0
    )
    with pytest.raises(ValueError, match="expected 'representation'"):
        load_checkpoint(path, kind="representation")


def test_config_presets_and_validation():
    assert RepresentationConfig.for_env("rearrangement", 3).code_sizes == (32, 32, 32)
    assert RepresentationConfig.for_env("rearrangement", 1).code_sizes == (16,)
    assert RepresentationConfig.for_env("key-wall").code_sizes == (16, 2)
    assert RepresentationConfig.for_env("key-corridor").env == "key-corridor"
    with pytest.raises(ValueError, match="env must be an env profile name or import path"):
        RepresentationConfig(env="maze").validate()
    with pytest.raises(ValueError, match="unknown RepresentationConfig fields"):
        RepresentationConfig.from_dict({"colour": 1})
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        RepresentationConfig.for_env("key-wall").validate()


def test_change_overlap_separates_factorized_from_shared_changes():
    from dorp_rl.objectives.cpc import change_overlap

    moved = torch.tensor([0, 1, 0, 1, 1, 0, 0, 1])
    factorized = torch.nn.functional.one_hot(moved, 2).float() * torch.rand(8, 1).add(0.5)
    assert float(change_overlap(factorized)) == pytest.approx(0.0, abs=1e-6)
    shared = torch.rand(8, 1).add(0.1).expand(8, 3)  # every one-hot changes on every pair
    assert float(change_overlap(shared)) == pytest.approx(1.0, abs=1e-5)
    # scale-free: shrinking all changes does not lower it; constant maps give 0, not NaN
    assert float(change_overlap(shared * 1e-3)) == pytest.approx(1.0, abs=1e-4)
    assert float(change_overlap(torch.zeros(8, 3))) == 0.0


def test_exclusivity_gradient_reaches_the_extractor():
    loss = _loss(exclusivity_weight=1.0)
    out = loss(TensorDict(pixels=_pixels(8), future_pixels=_pixels(8, seed=3), batch_size=[8]))
    out["loss_exclusivity"].backward()
    assert loss.encoder.extractor[0].weight.grad.abs().sum() > 0
    # the term only looks at the maps: the code head gets no gradient from it
    assert loss.encoder.map_encoder[-1].weight.grad is None


def test_entanglement_check_uses_recent_map_entanglement(tmp_path):
    trainer = RepresentationTrainer(_tiny_config(tmp_path, entanglement_check_after=100))
    trainer.history = [{"step": s, "map_entanglement": 0.2} for s in range(1, 6)]
    assert trainer.entanglement_hook.entanglement_reason(50) is None  # too early in the attempt
    reason = trainer.entanglement_hook.entanglement_reason(500)
    assert reason is not None and "entangled" in reason
    trainer.history_start = 5  # a restarted attempt does not inherit the old history
    assert trainer.entanglement_hook.entanglement_reason(500) is None
    trainer.history_start = 0
    trainer.history = [{"step": s, "map_entanglement": 0.01} for s in range(1, 6)]
    assert trainer.entanglement_hook.entanglement_reason(500) is None


def test_dead_onehot_check_judges_the_attempts_end_and_names_the_onehot(tmp_path):
    cfg = _tiny_config(
        tmp_path, env="key-wall", trajectory_length=16, num_steps=40, dead_check_frames=64
    )
    trainer = RepresentationTrainer(cfg)
    assert cfg.code_sizes == (8, 2)  # an agent one-hot and a key bit
    codes = torch.stack([torch.arange(64) % 8, torch.zeros(64, dtype=torch.int64)], 1)
    hook = trainer.dead_hook
    with mock.patch.object(trainer, "play_codes", return_value=codes) as play:
        for step, due in ((10, False), (39, False), (40, True)):
            trainer.step = step
            reason = hook.reason({}, True)
            assert (reason is not None) == due, step
        assert play.call_count == 1
        assert "one-hot(s) [1]" in reason and "64 evenly spaced play frames" in reason
        trainer.step, trainer.attempt_start = 45, 5  # a restarted attempt's end
        assert hook.reason({}, True) is not None
    # The key bit takes both codes: nothing is dead.
    alive = codes.clone()
    alive[::7, 1] = 1
    with mock.patch.object(trainer, "play_codes", return_value=alive):
        assert hook.reason({}, True) is None
    trainer.config = cfg.replace(dead_check_frames=0)
    with mock.patch.object(trainer, "play_codes", return_value=codes) as play:
        assert hook.reason({}, True) is None and play.call_count == 0


def test_a_dead_onehot_restarts_the_attempt_for_a_whole_new_run(tmp_path):
    cfg = _tiny_config(tmp_path, num_steps=12, max_restarts=2, dead_check_frames=8192)
    trainer = RepresentationTrainer(cfg)
    real = trainer.play_codes

    def dead_in_the_first_attempt(count):
        codes = real(count)
        return codes * 0 if trainer.attempt == 0 else codes

    frames = real(10**6)
    assert frames.shape == (min(len(trainer.buffer), 10**6), 1)
    trainer.play_codes = dead_in_the_first_attempt
    with pytest.warns(RuntimeWarning, match=r"restarted at step 12 \(one-hot\(s\) \[0\]"):
        result = trainer.train()
    assert [r["reason"].split(" give")[0] for r in result["restarts"]] == ["one-hot(s) [0]"]
    assert result["attempt"] == 1 and result["step"] == 24  # 12 more steps after the restart
    assert trainer.hooks["dead"].restarts[0]["step"] == 12


def test_key_bit_does_not_count_as_collapse():
    torch.manual_seed(0)
    encoder = DiscreteCodeEncoder(EncoderConfig(code_sizes=(8, 2), channels=8, mlp_sizes=(32, 32)))
    loss = CPCLoss(encoder, DDDPSimilarity(16))
    anchor, future = _pixels(32), _pixels(32, 1)
    out = loss(TensorDict(pixels=anchor, future_pixels=future, batch_size=[32]))
    codes = encoder.logits(torch.cat([anchor, future]))[:32].argmax(-1)  # same batch statistics
    # the minimum is taken over the 8-code one-hot only, never the 2-way bit
    assert float(out["min_codes_in_batch"]) == float(torch.unique(codes[:, 0]).numel())


def test_a_one_by_one_extractor_sees_each_pixel_alone():
    torch.manual_seed(0)
    encoder = DiscreteCodeEncoder(EncoderConfig(code_sizes=(16, 2), kernel_size=1, channels=8))
    encoder.eval()
    pixels = _pixels(2)
    changed = pixels.clone()
    changed[:, :, 3, 5] = 255 - changed[:, :, 3, 5]
    diff = (encoder.object_maps(pixels) - encoder.object_maps(changed)).abs().sum(dim=(0, 1))
    assert diff[3, 5] > 0
    diff[3, 5] = 0
    assert diff.max() == 0  # no other pixel of any map moved
    with pytest.raises(ValueError, match="kernel_size"):
        DiscreteCodeEncoder(EncoderConfig(code_sizes=(4,), kernel_size=2))


# ---------------------------------------------------------------- screening
def test_screening_continues_the_highest_scoring_candidate(tmp_path):
    cfg = _tiny_config(
        tmp_path, num_candidates=3, candidate_steps=6, num_steps=6, log_every=1, lr=3e-3
    )
    trainer = RepresentationTrainer(cfg)
    result = trainer.train()
    candidates = result["candidates"]
    assert [c["attempt"] for c in candidates] == [0, 1, 2]
    assert len({c["score"] for c in candidates}) == 3  # three different initialisations
    # num_steps == candidate_steps: the run ends on the chosen candidate, unchanged.
    assert result["step"] == trainer.planned_steps == 18
    best = max(candidates, key=lambda c: c["score"])
    assert trainer.attempt == best["attempt"]
    assert result["chosen_candidate"] == best
    assert trainer.screening_hook.score() == pytest.approx(best["score"])
    stored = load_checkpoint(best["path"], kind="representation")["state"]["encoder"]
    for name, value in trainer.encoder.state_dict().items():
        assert torch.equal(value, stored[name]), name


def test_screening_continues_the_chosen_candidate_to_num_steps(tmp_path):
    cfg = _tiny_config(tmp_path, num_candidates=2, candidate_steps=6, num_steps=9, log_every=1)
    trainer = RepresentationTrainer(cfg)
    result = trainer.train()
    assert result["step"] == 6 + 9  # the chosen candidate's 6 steps count towards num_steps
    for candidate in result["candidates"]:
        end = candidate["step"]
        last = [h["loss_cpc"] for h in trainer.history if end - 5 < h["step"] <= end]
        assert candidate["loss"] == pytest.approx(sum(last) / len(last))


def test_resume_during_screening_equals_uninterrupted_run(tmp_path):
    overrides = dict(num_candidates=2, candidate_steps=6, num_steps=10, checkpoint_every=1)
    full = RepresentationTrainer(_tiny_config(tmp_path / "a", **overrides))
    full.train()

    interrupted = RepresentationTrainer(_tiny_config(tmp_path / "b", **overrides))
    original_step = interrupted.train_step

    def crash_in_second_candidate():
        if interrupted.step == 8:
            raise KeyboardInterrupt
        return original_step()

    interrupted.train_step = crash_in_second_candidate
    with pytest.raises(KeyboardInterrupt):
        interrupted.train()
    resumed = RepresentationTrainer(_tiny_config(tmp_path / "b", **overrides))
    with mock.patch.object(resumed, "train_step", wraps=resumed.train_step) as step:
        result = resumed.train(resume=True)
    # The crash came after step 8, checkpointed (checkpoint_every=1), in the second
    # candidate: the resume goes on from there, it does not screen the first one again.
    assert resumed.resumed_from_step == result["resumed_from_step"] == 8
    assert step.call_count == 16 - 8
    assert result["step"] == full.step == 16
    assert [c["score"] for c in result["candidates"]] == [c["score"] for c in full.candidates]
    for a, b in zip(
        full.encoder.state_dict().values(), resumed.encoder.state_dict().values(), strict=True
    ):
        assert torch.equal(a, b)


def test_screening_config_is_validated(tmp_path):
    with pytest.raises(ValueError, match="candidate_steps"):
        RepresentationTrainer(_tiny_config(tmp_path, num_candidates=2, candidate_steps=13))


def test_code_information_separates_factorized_from_redundant_codes():
    generator = torch.Generator().manual_seed(0)
    a = torch.randint(0, 4, (20000,), generator=generator)
    b = torch.randint(0, 4, (20000,), generator=generator)
    independent = code_information(torch.stack([a, b], -1))
    assert independent["entropy"][0] == pytest.approx(math.log(4), abs=0.01)
    assert independent["mutual_information"][0][1] < 0.01
    assert independent["unique_information"] == pytest.approx(2 * math.log(4), abs=0.02)
    redundant = code_information(torch.stack([a, a], -1))
    assert redundant["mutual_information"][0][1] == pytest.approx(math.log(4), abs=0.01)
    assert abs(redundant["unique_information"]) < 1e-9
    constant = code_information(torch.zeros(100, 2, dtype=torch.long))
    assert constant["unique_information"] == 0.0


@pytest.mark.parametrize(
    "codes, match",
    [
        (torch.zeros(10), "shape"),
        (torch.zeros(10, 2), "integer"),
        (-torch.ones(10, 2, dtype=torch.long), ">= 0"),
    ],
)
def test_code_information_rejects_bad_codes(codes, match):
    with pytest.raises(ValueError, match=match):
        code_information(codes)


# ---------------------------------------------------------------- one-hot widths
def test_width_order_gives_the_widest_slots_the_most_changing_onehots():
    from dorp_rl.trainers.representation import width_order

    assert width_order((16, 4), (0.016, 0.054)) == [1, 0]  # swapped: the 4-code one moves more
    assert width_order((16, 4), (0.093, 0.012)) == [0, 1]
    assert width_order((4, 16, 2), (0.5, 0.1, 0.01)) == [1, 0, 2]
    # equal sizes never move among themselves, whatever their rates
    assert width_order((8, 8, 2), (0.01, 0.3, 0.002)) == [0, 1, 2]
    assert width_order((8, 8, 2), (0.01, 0.3, 0.2)) == [1, 2, 0]
    assert width_order((8, 8, 2), (0.01, 0.002, 0.3)) == [0, 2, 1]
    with pytest.raises(ValueError, match="one change rate per one-hot"):
        width_order((8, 2), (0.1,))


def test_permuting_onehots_moves_their_maps_and_similarity_positions(tmp_path):
    cfg = _tiny_config(tmp_path, env="key-wall", trajectory_length=16, num_steps=2)
    trainer = RepresentationTrainer(cfg)
    trainer.train()
    encoder = trainer.encoder.eval()
    pixels = trainer.buffer.storage[torch.arange(8)]["pixels"]
    maps = encoder.object_maps(pixels)
    matrix = trainer.similarity.matrix().detach().clone()
    last = encoder.extractor[-1]
    assert last.weight in trainer.optimizer.state  # moments from the training steps
    trainer.permute_onehots([1, 0])
    moved = encoder.object_maps(pixels)
    assert torch.allclose(moved[:, 0], maps[:, 1]) and torch.allclose(moved[:, 1], maps[:, 0])
    z = encoder.max_codes
    blocks = matrix.reshape(2, z, 2, z)[[1, 0]][:, :, [1, 0]].reshape(2 * z, 2 * z)
    assert torch.equal(trainer.similarity.matrix().detach(), blocks)
    assert last.weight not in trainer.optimizer.state  # its moments restart
    assert encoder.code_sizes == (8, 2)  # the sizes stay with the slots
    with pytest.raises(ValueError, match="permutation of range"):
        encoder.permute_onehots_([0, 0])


def test_the_width_hook_reorders_once_per_attempt_and_resumes_with_its_record(tmp_path):
    overrides = dict(env="key-wall", trajectory_length=16, num_steps=10, order_widths_at=4)
    trainer = RepresentationTrainer(_tiny_config(tmp_path, **overrides))
    rates = [0.01, 0.3]  # the 2-code one-hot changes more: its map goes to the 8-code slot
    with (
        mock.patch.object(trainer, "play_change_rates", return_value=rates) as measure,
        mock.patch.object(trainer, "permute_onehots", wraps=trainer.permute_onehots) as permute,
    ):
        trainer.train()
    assert measure.call_count == 1 and permute.call_args.args == ([1, 0],)
    record = trainer.hooks["widths"].reorders
    assert record == [{"step": 4, "attempt": 0, "change_rate": rates, "order": [1, 0]}]
    resumed = RepresentationTrainer(_tiny_config(tmp_path, **{**overrides, "num_steps": 12}))
    resumed.train(resume=True)
    assert resumed.hooks["widths"].reorders == record  # not measured again after step 4
    # in order already: measured, recorded, nothing moved; 0 turns the hook off
    for at, expected_calls in ((4, 1), (0, 0)):
        trainer = RepresentationTrainer(
            _tiny_config(tmp_path / f"at{at}", **{**overrides, "order_widths_at": at})
        )
        with (
            mock.patch.object(trainer, "play_change_rates", return_value=[0.3, 0.01]) as measure,
            mock.patch.object(trainer, "permute_onehots") as permute,
        ):
            trainer.train()
        assert measure.call_count == expected_calls and permute.call_count == 0


def test_out_of_restarts_training_goes_on_from_the_least_entangled_attempt(tmp_path):
    cfg = _tiny_config(
        tmp_path,
        num_steps=12,
        log_every=1,
        max_restarts=2,
        entanglement_check_after=6,
        entanglement_threshold=0.0,  # every attempt counts as entangled
        num_objects=2,
        encoder={"code_sizes": (8, 8)},
        exclusivity_weight=1.0,  # map_entanglement is logged with the exclusivity term
    )
    trainer = RepresentationTrainer(cfg)
    hook = trainer.entanglement_hook
    # attempt 1 is the least entangled: 0.5, then 0.1, then 0.3 for the last attempt
    values = {0: 0.5, 1: 0.1, 2: 0.3}
    real = hook.entanglement_reason

    def staged(attempt_steps):
        reason = real(attempt_steps)
        if reason is not None:
            hook._value = values[trainer.attempt]
        return reason

    hook.entanglement_reason = staged
    with pytest.warns(RuntimeWarning, match="going on from attempt 1"):
        result = trainer.train()
    assert [a["attempt"] for a in hook.attempts] == [0, 1]
    assert hook.kept == {"attempt": 1, "entanglement": 0.1}
    saved = load_checkpoint(hook.attempts[1]["path"])["state"]["encoder"]
    assert result["attempt"] == trainer.attempt == 1
    # the kept attempt trains on from its checkpoint for the rest of its num_steps
    steps_in = hook.attempts[1]["attempt_steps"]
    assert result["step"] == 3 * steps_in + cfg.num_steps - steps_in
    kept = trainer.encoder.state_dict()
    assert any(not torch.equal(kept[k], saved[k]) for k in saved)  # it trained on
    # and a resumed run keeps the same choice
    again = RepresentationTrainer(cfg)
    again.train(resume=True)
    assert again.entanglement_hook.kept == hook.kept and again.attempt == 1
