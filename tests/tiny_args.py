"""Arguments of the ``dorp`` command, and configs, that make each stage take seconds in a test."""

from dorp_rl.trainers import RepresentationConfig

#: 1-object codes of a few steps (the play data's size left to the test).
CODES_ANY_FRAMES = (
    "--setting", "1obj",
    "--codes.num-envs", "16",
    "--codes.encoder.code-sizes", "8",
    "--codes.batch-size", "32",
    "--codes.num-steps", "5",
    "--codes.diagnostics-samples", "64",
)  # fmt: skip
#: the same on 256 play frames.
CODES = (*CODES_ANY_FRAMES, "--codes.num-frames", "256")
#: 2 tasks of at most 6 steps, small plans.
EVAL = (
    "--tasks", "2",
    "--tasks-per-rollout", "2",
    "--candidates", "20",
    "--planning-horizon", "3",
    "--max-steps", "6",
)  # fmt: skip
#: a world model of 3 training steps on 256 frames.
WORLD_MODEL = (
    "--world-model.num-steps", "3",
    "--world-model.num-frames", "256",
    "--world-model.num-envs", "16",
    "--world-model.horizon", "3",
    "--world-model.trajectory-length", "4",
    "--world-model.eval-frames", "128",
    "--world-model.eval-sequences", "8",
    "--world-model.model.channels", "16",
    "--world-model.model.dilations", "1", "2", "4",
    "--world-model.batch-size", "8",
)  # fmt: skip


def tiny_codes(env: str, tmp_path, **overrides) -> RepresentationConfig:
    """A code config of a few steps on a few hundred frames of ``env``."""
    values = {
        "num_frames": 512,
        "num_envs": 4,
        "batch_size": 16,
        "num_steps": 4,
        "diagnostics_every": 1000,
        "dead_check_frames": 0,
        "out_dir": str(tmp_path / "codes"),
        "progress": False,
        "encoder": {"channels": 4, "mlp_sizes": (16,)},
        **overrides,
    }
    return RepresentationConfig(env=env, **values)
