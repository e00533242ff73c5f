"""Config validation: every field of every config has a rule, checked when the config is built.

Bad values are derived from each field's rule (below its lower bound, above its upper
bound, a non-integer, NaN, an unknown choice, a non-bool, an empty string), so a new
field without a rule, or a rule that stops checking, fails here. Rules between fields
and the buffers given to trainers are checked too.
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import pytest

from dorp_rl.config import (
    Choice,
    ConfigMixin,
    Device,
    Flag,
    Float,
    Floats,
    Int,
    Ints,
    Nested,
    Seed,
    Text,
    checked,
    field_rules,
)
from dorp_rl.data import collect_play_data
from dorp_rl.envs import ENV_NAMES, KeyWallEnv, ObjectRearrangementEnv
from dorp_rl.modules import EncoderConfig, VideoModelConfig
from dorp_rl.trainers import (
    RepresentationConfig,
    RepresentationTrainer,
    TrainerConfig,
    WorldModelConfig,
    WorldModelTrainer,
)
from dorp_rl.trainers.base import EnvName

pytestmark = pytest.mark.usefixtures("one_torch_thread")

CONFIGS = [TrainerConfig, RepresentationConfig, WorldModelConfig, VideoModelConfig, EncoderConfig]


def bad_values(rule) -> list:
    """Values that break ``rule``, each with the text the message must hold."""
    if isinstance(rule, Int):
        out = [(2.5, "integer"), ("3", "integer"), (True, "integer")]
        if rule.low is not None:
            out.append((rule.low - 1, f">= {rule.low}" if rule.high is None else f"[{rule.low}"))
        if rule.high is not None:
            out.append((rule.high + 1, f"{rule.high}]"))
        return out
    if isinstance(rule, Float):
        out = [(math.nan, "number"), ("0.1", "number")]
        if not rule.allow_inf:
            out.append((math.inf, "finite"))
        if rule.low is not None:
            out.append((rule.low - 1.0, f"{rule.low:g}"))
            if rule.low_open:
                out.append((rule.low, f"> {rule.low:g}"))
        if rule.high is not None:
            out.append((rule.high + 1.0, f"{rule.high:g}"))
        return out
    if isinstance(rule, Choice):
        return [("no-such-choice", str(rule.options[0]))]
    if isinstance(rule, Flag):
        return [("yes", "True or False"), (1, "True or False")]
    if isinstance(rule, Text):
        return [("", "non-empty string"), (3, "non-empty string")]
    if isinstance(rule, Seed):
        return [(-1, "[0, "), (1.5, "integer"), (2**63, "[0, ")]
    if isinstance(rule, Device):
        return [("gpu0", "torch.device")]
    if isinstance(rule, Ints):
        low = 1 if rule.low is None else rule.low
        out = [((low, low - 1), f">= {low}"), ((low, 2.5), "integer")]
        return out + ([((), "at least")] if rule.min_length > 0 else [])
    if isinstance(rule, Floats):
        low = 0.0 if rule.low is None else rule.low
        out = [((low, low - 1.0), f">= {low:g}"), ((low, math.nan), "number"), ((), "at least")]
        return out + [("0.1", "number")]
    if isinstance(rule, EnvName):
        return [
            ("no-such-env", "neither a registered profile"),
            ("no_such_module_xyz:make_env", "cannot import"),
            ("dorp_rl.envs:no_such_factory", "has no attribute"),
            (3, "profile name or import path"),
        ]
    if isinstance(rule, Nested):  # the nested config's own bad values, given as a dict
        nested = [
            ({k: v}, text) for k, r in field_rules(rule.cls).items() for v, text in bad_values(r)
        ]
        return [(3, "dict of its fields"), *nested]
    raise AssertionError(f"no bad values for {rule!r}")


def defaults(cls):
    return cls.default() if cls is VideoModelConfig else cls()


@pytest.mark.parametrize("cls", CONFIGS, ids=lambda c: c.__name__)
def test_every_field_has_a_rule(cls):
    fields = {f.name for f in dataclasses.fields(cls)}
    assert set(field_rules(cls)) == fields


def test_a_field_without_a_rule_is_a_type_error_naming_it():
    @dataclasses.dataclass
    class Partly(ConfigMixin):
        steps: int = checked(1, Int(low=1))
        width: int = 3

    with pytest.raises(TypeError, match=r"Partly has no validation rule for fields \['width'\]"):
        Partly()


def test_a_subclass_inherits_the_rules_of_its_parents_fields():
    assert field_rules(RepresentationConfig)["seed"] == field_rules(TrainerConfig)["seed"]
    # a field declared again takes its new rule: key rooms have no default trajectory length
    assert field_rules(TrainerConfig)["trajectory_length"] == Int(low=1, optional=True)
    assert field_rules(WorldModelConfig)["trajectory_length"] == Int(low=1)


def test_checked_needs_a_rule_and_makes_nested_defaults():
    with pytest.raises(TypeError, match="needs a rule"):
        checked(1)
    nested = checked(rule=Nested(EncoderConfig, default=EncoderConfig.small))
    assert nested.default_factory() == EncoderConfig.small()
    assert checked(rule=Nested(EncoderConfig)).default_factory() == EncoderConfig()
    assert checked(rule=Int()).default is dataclasses.MISSING  # a required field


CASES = [
    (cls, name, value, text)
    for cls in CONFIGS
    for name, rule in field_rules(cls).items()
    for value, text in bad_values(rule)
]


@pytest.mark.parametrize(
    ("cls", "name", "value", "text"),
    CASES,
    ids=[f"{c.__name__}.{n}={v!r}" for c, n, v, _ in CASES],
)
def test_a_bad_field_value_is_refused_naming_the_field_and_range(cls, name, value, text):
    with pytest.raises(ValueError) as info:
        dataclasses.replace(defaults(cls), **{name: value})
    message = str(info.value)
    assert message.startswith(f"{name}") or f"{name}[" in message, message
    assert text in message, message
    if isinstance(value, dict):  # a nested field is named <field>.<nested field>
        assert message.startswith(f"{name}.{next(iter(value))}"), message


@pytest.mark.parametrize("cls", CONFIGS, ids=lambda c: c.__name__)
def test_defaults_presets_and_round_trips_are_valid(cls):
    config = defaults(cls)
    assert cls.from_dict(config.to_dict()) == config
    if cls in (RepresentationConfig, WorldModelConfig):
        for env in ENV_NAMES:  # every preset of the project's envs
            preset = cls.for_env(env, 3 if env == "rearrangement" else None)
            assert cls.from_dict(preset.to_dict()) == preset


# ---------------------------------------------------------------- common mistakes
@pytest.mark.parametrize(
    ("cls", "changes", "message"),
    [
        (WorldModelConfig, {"grad_clip": 0}, "grad_clip must be > 0"),
        (RepresentationConfig, {"num_steps": 2.5}, "num_steps must be an integer >= 1"),
        (WorldModelConfig, {"num_steps": 2.5}, "num_steps must be an integer >= 1"),
        (RepresentationConfig, {"num_envs": 0}, "num_envs must be >= 1"),
        (RepresentationConfig, {"seed": -1}, "seed must be in [0, "),
        (WorldModelConfig, {"seed": -1}, "seed must be in [0, "),
        (RepresentationConfig, {"lr": math.nan}, "lr must be a finite number > 0"),
        (RepresentationConfig, {"lr": -1.0}, "lr must be > 0"),
        (WorldModelConfig, {"lr": math.nan}, "lr must be a finite number > 0"),
        (RepresentationConfig, {"max_offset": 4}, "max_offset <= the play trajectory length"),
    ],
)
def test_common_mistakes_name_the_field(cls, changes, message):
    with pytest.raises(ValueError) as info:
        dataclasses.replace(cls(), **changes)
    assert message in str(info.value)


# ---------------------------------------------------------------- bounds pinned by hand
# The sweep above reads each bound from the fields' rules, so a wrong bound there passes it.
# These are written out from what each field means: (config, field, the literal value
# just outside its range, the text the refusal holds, the literal boundary or inside
# values that must be taken).
R, W, E, V = RepresentationConfig, WorldModelConfig, EncoderConfig, VideoModelConfig
PINNED = [
    # learning: a step must change the weights, a batch hold a pair and its negatives
    (R, "lr", 0.0, "lr must be > 0", [1e-9, 1e-3]),
    (R, "batch_size", 1, "batch_size must be >= 2", [2]),  # CPC needs a negative
    (W, "batch_size", 0, "batch_size must be >= 1", [1]),
    (R, "num_steps", 0, "num_steps must be >= 1", [1]),
    (W, "num_steps", 0, "num_steps must be >= 1", [1]),
    (W, "grad_clip", 0.0, "grad_clip must be > 0", [1e-6, math.inf]),
    (W, "lr_final", -1e-9, "lr_final must be >= 0", [0.0]),
    # temperatures divide logits
    (R, "gumbel_temperature", 0.0, "gumbel_temperature must be > 0", [1e-3]),
    (R, "ce_temperature", 0.0, "ce_temperature must be > 0", [1e-3]),
    (R, "gumbel_temperature_start", 0.0, "gumbel_temperature_start must be > 0", [1e-3]),
    (R, "alpha", 0.999, "alpha must be >= 1", [1.0]),
    # weights of loss terms are not negative
    (R, "usage_weight", -1e-9, "usage_weight must be >= 0", [0.0]),
    (R, "usage_weight", (1.0, -1e-9), "usage_weight[1] must be >= 0", [(4.0, 0.0)]),
    (R, "usage_weight", "4", "usage_weight must be a number or a sequence of numbers", [4]),
    (R, "exclusivity_weight", -1e-9, "exclusivity_weight must be >= 0", [0.0]),
    (R, "sparsity_weight", -1e-9, "sparsity_weight must be >= 0", [0.0]),
    (R, "motion_weight", -1e-9, "motion_weight must be >= 0", [0.0]),
    (W, "kl_weight", -1e-9, "kl_weight must be >= 0", [0.0]),
    (W, "free_bits", -1e-9, "free_bits must be >= 0", [0.0]),
    # probabilities and shares
    (W, "event_share", -0.01, "event_share must be in [0, 1)", [0.0, 0.99]),
    (W, "event_share", 1.0, "event_share must be in [0, 1)", []),  # event windows only
    (W, "deterministic_fraction", -0.01, "deterministic_fraction must be in [0, 1]", [0.0]),
    (W, "deterministic_fraction", 1.01, "deterministic_fraction must be in [0, 1]", [1.0]),
    (W, "open_loop_ramp", -0.01, "open_loop_ramp must be in [0, 1]", [0.0]),
    (W, "open_loop_ramp", 1.01, "open_loop_ramp must be in [0, 1]", [1.0]),
    # windows, offsets and play data
    (W, "horizon", 0, "horizon must be >= 1", [1]),
    (W, "trajectory_length", 0, "trajectory_length must be >= 1", []),
    (R, "trajectory_length", 0, "trajectory_length must be >= 1", [1, None]),
    (R, "min_offset", 0, "min_offset must be >= 1", [1]),
    (R, "max_offset", 0, "max_offset must be >= 1", [1]),
    (R, "num_frames", 0, "num_frames must be >= 1", [1]),
    (R, "num_envs", 0, "num_envs must be >= 1", [1]),
    (W, "num_envs", 0, "num_envs must be >= 1", [1]),
    (W, "eval_frames", 0, "eval_frames must be >= 1", []),
    (W, "eval_sequences", 0, "eval_sequences must be >= 1", [1]),
    (R, "num_objects", 0, "num_objects must be", [1, 8]),
    (R, "num_objects", 9, "num_objects must be", []),  # the palette has 8 colours
    # bookkeeping
    (R, "seed", -1, "seed must be in [0, ", [0, 2**63 - 1]),
    (R, "seed", 2**63, "seed must be in [0, ", []),
    (W, "seed", -1, "seed must be in [0, ", [0]),
    (R, "log_every", 0, "log_every must be >= 1", [1]),
    (R, "checkpoint_every", 0, "checkpoint_every must be >= 1", [1]),
    (W, "eval_every", 0, "eval_every must be >= 1", [1]),
    (R, "diagnostics_every", 0, "diagnostics_every must be >= 1", [1]),
    (R, "max_restarts", -1, "max_restarts must be >= 0", [0]),
    (R, "num_candidates", 0, "num_candidates must be >= 1", [1]),
    # model sizes: a one-hot needs two codes to say anything
    (E, "code_sizes", (1,), "code_sizes[0] must be", [(2,)]),
    (E, "code_sizes", (8, 1), "code_sizes[1] must be", [(2, 2)]),
    (E, "channels", 0, "channels must be >= 1", [1]),
    (E, "input_scale", 0.0, "input_scale must be > 0", [1e-3]),
    (V, "channels", 0, "channels must be >= 1", [1]),
    (V, "latent_dim", -1, "latent_dim must be >= 0", [0]),
    (V, "dilations", (0,), "dilations[0] must be", [(1,)]),
]


def _config(cls, **changes):
    base = cls.default() if cls is VideoModelConfig else cls()
    return dataclasses.replace(base, **changes)


@pytest.mark.parametrize(
    ("cls", "name", "outside", "message", "inside"),
    PINNED,
    ids=[f"{c.__name__}.{n}={v!r}" for c, n, v, _, _ in PINNED],
)
def test_pinned_bounds_refuse_the_value_just_outside_and_take_the_boundary(
    cls, name, outside, message, inside
):
    extra = {"gumbel_anneal_steps": 10} if name == "gumbel_temperature_start" else {}
    with pytest.raises(ValueError) as info:
        _config(cls, **extra, **{name: outside})
    assert message in str(info.value), str(info.value)
    for value in inside:
        assert getattr(_config(cls, **extra, **{name: value}), name) == value


@pytest.mark.parametrize(
    ("changes", "message"),
    [
        ({"horizon": 17}, "horizon"),  # a window longer than the play trajectories
        ({"horizon": 1, "trajectory_length": 0}, "trajectory_length must be >= 1"),
    ],
)
def test_world_model_windows_fit_the_trajectories(changes, message):
    with pytest.raises(ValueError, match=message):
        WorldModelConfig(**changes)
    assert WorldModelConfig(horizon=16, trajectory_length=16).horizon == 16  # equal: taken
    assert WorldModelConfig(horizon=1, trajectory_length=1).trajectory_length == 1


def test_representation_offsets_fit_the_play_trajectories():
    key_wall = RepresentationConfig.for_env("key-wall", trajectory_length=4, max_offset=4)
    assert key_wall.max_offset == 4  # equal to the trajectory length: taken
    with pytest.raises(ValueError, match="max_offset <= the play trajectory length"):
        RepresentationConfig.for_env("key-wall", trajectory_length=4, max_offset=5)
    with pytest.raises(ValueError, match="min_offset <= max_offset"):
        RepresentationConfig.for_env("key-wall", min_offset=3, max_offset=2)
    assert RepresentationConfig.for_env("key-wall", min_offset=2, max_offset=2).min_offset == 2


def test_world_model_lr_must_be_positive():
    with pytest.raises(ValueError, match="lr must be > 0"):
        WorldModelConfig(lr=0.0)
    assert WorldModelConfig(lr=1e-9).lr == 1e-9


@pytest.mark.parametrize(
    ("cls", "changes", "fields"),
    [
        (RepresentationConfig, {"env": "key-wall", "num_objects": 3}, ["num_objects"]),
        (WorldModelConfig, {"env": "key-corridor", "num_objects": 2}, ["num_objects"]),
        (
            WorldModelConfig,
            {"trajectory_length": 5, "horizon": 6},
            ["trajectory_length", "horizon"],
        ),
        (RepresentationConfig, {"num_candidates": 2, "candidate_steps": 3000}, ["candidate_steps"]),
        (RepresentationConfig, {"encoder": {"kernel_size": 4}}, ["encoder.kernel_size"]),
        (RepresentationConfig, {"gumbel_temperature_start": 1.0}, ["gumbel_anneal_steps"]),
        (RepresentationConfig, {"similarity": "full", "alpha": 2.0}, ["alpha", "similarity"]),
        (RepresentationConfig, {"min_offset": 3, "max_offset": 2}, ["min_offset", "max_offset"]),
        (
            RepresentationConfig,
            {"env": "key-wall", "num_objects": 1, "trajectory_length": 3, "max_offset": 4},
            ["max_offset", "trajectory_length=3"],
        ),
    ],
)
def test_rules_between_fields_name_every_field_involved(cls, changes, fields):
    with pytest.raises(ValueError) as info:
        cls().replace(**changes)
    for field in fields:
        assert field in str(info.value)


@pytest.mark.parametrize("cls", [RepresentationConfig, WorldModelConfig])
def test_num_objects_follows_the_env_unless_given(cls):
    assert cls(env="key-wall").num_objects == 1
    assert cls(env="rearrangement").num_objects == cls.default_num_objects
    assert cls(env="rearrangement", num_objects=4).num_objects == 4
    stored = cls(env="key-corridor").to_dict() | {"num_objects": 3}  # older presets kept 3
    assert cls.from_dict(stored).num_objects == 1


def test_values_are_normalised():
    cfg = dataclasses.replace(
        RepresentationConfig(), num_steps=3.0, data_dir=Path("data"), device="cpu"
    )
    assert cfg.num_steps == 3 and isinstance(cfg.num_steps, int)
    assert cfg.data_dir == "data"
    assert cfg.trajectory_length is None  # optional fields keep None


def test_from_dict_validates():
    values = RepresentationConfig().to_dict() | {"lr": -1.0}
    with pytest.raises(ValueError, match="lr must be > 0"):
        RepresentationConfig.from_dict(values)


@pytest.mark.parametrize("trainer", [RepresentationTrainer, WorldModelTrainer])
def test_a_config_changed_after_construction_is_caught_by_the_trainer(
    trainer, representation_config, world_model_config
):
    cfg = representation_config() if trainer is RepresentationTrainer else world_model_config()
    cfg.lr = -1.0  # dataclasses are mutable: the trainer checks again
    with pytest.raises(ValueError, match="lr must be >=? 0"):
        trainer(cfg)


# ---------------------------------------------------------------- buffers given to trainers
def test_representation_trainer_refuses_play_data_of_another_env(representation_config):
    keywall = collect_play_data(KeyWallEnv(batch_size=(2,)), 256, seed=0)
    with pytest.raises(ValueError, match="another environment") as info:
        RepresentationTrainer(representation_config(), buffer=keywall)
    assert "env: buffer 'KeyWallEnv', config 'ObjectRearrangementEnv'" in str(info.value)
    two = collect_play_data(ObjectRearrangementEnv(2, batch_size=(4,)), 256, seed=0)
    with pytest.raises(ValueError, match="num_objects: buffer 2, config 1"):
        RepresentationTrainer(representation_config(), buffer=two)


def test_representation_trainer_refuses_trajectories_shorter_than_max_offset(
    representation_config,
):
    short = collect_play_data(KeyWallEnv(batch_size=(2,)), 256, seed=0, trajectory_length=2)
    cfg = representation_config(env="key-wall", max_offset=4)
    with pytest.raises(ValueError, match="trajectories of 2 step"):
        RepresentationTrainer(cfg, buffer=short)


def test_world_model_trainer_refuses_trajectories_shorter_than_horizon(world_model_config):
    one = ObjectRearrangementEnv(1, batch_size=(4,))
    short = collect_play_data(one, 256, seed=0, trajectory_length=2)
    with pytest.raises(ValueError, match="at least 3"):
        WorldModelTrainer(world_model_config(horizon=3), buffer=short)


def test_a_buffer_without_metadata_is_checked_by_its_state_shape(representation_config):
    buffer = collect_play_data(ObjectRearrangementEnv(2, batch_size=(4,)), 256, seed=0)
    buffer.metadata = None  # a buffer built by hand
    with pytest.raises(ValueError, match=r"states of shape \[2, 2\]"):
        RepresentationTrainer(representation_config(), buffer=buffer)


def test_a_matching_buffer_is_taken_with_the_configs_sampler(representation_config):
    cfg = representation_config(num_steps=2)
    buffer = collect_play_data(cfg.make_env(batch_size=(16,)), 256, seed=0)
    trainer = RepresentationTrainer(cfg, buffer=buffer)
    assert trainer.buffer is buffer and trainer.train()["step"] == 2
