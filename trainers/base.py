"""OfflineTrainer, TrainerConfig and TrainerHook: what every dorp-rl trainer shares.

The loop over a play buffer, logging, checkpoints, resume and hooks; the config base with
the environment, play-data and bookkeeping fields.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, ClassVar

import torch
from torchrl.envs import EnvBase
from torchrl.trainers import TrainerHookBase

from dorp_rl.checkpoint import load_checkpoint, save_checkpoint
from dorp_rl.config import (
    ConfigMixin,
    Device,
    Flag,
    Int,
    Seed,
    Text,
    checked,
    config_differences,
    format_differences,
)
from dorp_rl.envs import (
    DEFAULT_ENV,
    EnvProfile,
    env_identity,
    env_profile,
    register_env_profile,
    registered_profiles,
)
from dorp_rl.integrity import DirectoryLock, IntegrityError
from dorp_rl.progress import progress_bar

#: Upper bound of ``num_objects`` (the default colour palette).
MAX_OBJECTS = 8


def read_trained(
    path: str | Path, kind: str, config_type: Any, env: EnvBase | None, state_key: str
) -> tuple[Any, dict[str, Any], dict[str, Any]]:
    """``(config, state, payload)`` of a trainer's checkpoint of ``kind``: its config as
    ``config_type``, the state dict under ``state_key`` and the whole payload; with ``env``,
    the checkpoint must come from that environment.

    Raises:
        FileNotFoundError: no file at ``path``.
        ValueError: a damaged, incomplete or non-finite file
            (:class:`~dorp_rl.integrity.IntegrityError`), another kind of checkpoint or
            another environment.
    """
    payload = load_checkpoint(
        path,
        kind=kind,
        env_config=None if env is None else env_identity(env),
        state_keys=(state_key,),
    )
    return config_type.from_dict(payload["config"]), payload["state"][state_key], payload


@dataclass(frozen=True)
class EnvName:
    """Rule of an ``env`` field: a registered profile name or an import path
    ``"package.module:attribute"`` (:func:`~dorp_rl.envs.env_profile`)."""

    def __call__(self, name: str, value: Any) -> str:
        if isinstance(value, EnvProfile):  # kept by name: registered so that it resolves
            if value.name not in registered_profiles():
                register_env_profile(value)
            value = value.name
        if not isinstance(value, str) or not value:
            raise ValueError(f"{name} must be an env profile name or import path, got {value!r}.")
        try:
            env_profile(value)
        except ValueError as err:
            raise ValueError(f"{name} must be an env profile name or import path; {err}") from None
        return value


@dataclass
class TrainerConfig(ConfigMixin):
    """What every trainer config holds: environment, play data and bookkeeping.

    :class:`~dorp_rl.trainers.RepresentationConfig` and
    :class:`~dorp_rl.trainers.WorldModelConfig` add their model's config (a nested
    field), loss and optimisation fields. ``num_objects=None`` means
    :attr:`default_num_objects` for rearrangement and 1 for the key rooms (one agent);
    any other count with an env that does not count objects would be ignored, so it is
    refused. ``env`` is any env profile (:func:`~dorp_rl.envs.env_profile`): a registered
    name or an import path such as ``"mypkg.envs:make_env"``. Stored configs of older
    versions (whose key-room presets kept the rearrangement default) are read with
    ``num_objects=1``.
    """

    #: objects of a config that does not say, on an env that counts them
    default_num_objects: ClassVar[int] = 2

    # environment and play data
    env: str = checked(DEFAULT_ENV, EnvName())
    """environment: a registered profile (dorp_rl.envs.registered_profiles()) or an
    import path 'package.module:attribute' (an EnvProfile or a function building the env)"""
    num_objects: int | None = checked(None, Int(low=1, high=MAX_OBJECTS, optional=True))
    """objects of an env that counts them (None: the config's default; 1 for the others)"""
    num_frames: int = checked(100_000, Int(low=1))
    """play transitions to collect"""
    num_envs: int = checked(64, Int(low=1))
    """envs collecting play data side by side"""
    trajectory_length: int | None = checked(None, Int(low=1, optional=True))
    """steps per play trajectory (None: the env profile's, else chosen from its resets)"""
    data_dir: str | None = checked(None, Text(optional=True))
    """folder of the play data (None: kept in memory)"""
    # bookkeeping
    seed: int = checked(0, Seed())
    """seed of play data, initialisation and sampling"""
    device: str = checked("cpu", Device())
    """torch device"""
    out_dir: str = checked("outputs/run", Text())
    """folder of checkpoints and logs"""
    log_every: int = checked(50, Int(low=1))
    """steps between logged metrics"""
    checkpoint_every: int = checked(500, Int(low=1))
    """steps between checkpoints"""
    progress: bool = checked(True, Flag())
    """show a progress bar"""
    threads: int | None = checked(None, Int(low=1, optional=True))
    """torch threads while training (torch.set_num_threads for the run of train, then
    restored; None: leave torch's setting). On a shared CPU use 1 per job: with torch's
    default threads and other work on a 2-core machine a training step was about 100x
    slower"""

    def check_relations(self) -> None:
        """Resolves ``num_objects`` (see the class docstring); subclasses add their rules."""
        self.check_num_objects()

    def check_num_objects(self) -> None:
        profile = self.profile
        if self.num_objects is None and profile.counts_objects:
            self.num_objects = self.default_num_objects
        self.num_objects = profile.resolve_num_objects(self.num_objects)

    @classmethod
    def upgrade(cls, values: dict[str, Any]) -> dict[str, Any]:
        try:
            counts = env_profile(values.get("env", DEFAULT_ENV)).counts_objects
        except ValueError:  # an env that cannot be found: left to the checks to name
            return values
        if not counts:
            values["num_objects"] = 1  # it never had an effect there
        return values

    @classmethod
    def for_env(
        cls, env: str | EnvProfile, num_objects: int | None = None, **overrides: Any
    ) -> Any:
        """The preset of ``env`` (its profile's overrides of this config), then ``overrides``.

        Examples:
            >>> from dorp_rl.trainers import RepresentationConfig
            >>> cfg = RepresentationConfig.for_env("key-wall")
            >>> cfg.code_sizes, cfg.play_trajectory_length
            ((16, 2), 1000)
        """
        profile = env_profile(env)
        if num_objects is None and profile.counts_objects:
            num_objects = cls.default_num_objects
        base = cls(env=env, num_objects=profile.resolve_num_objects(num_objects))
        return base.replace(**cls.profile_overrides(profile, base.num_objects)).replace(**overrides)

    @classmethod
    def profile_overrides(cls, profile: EnvProfile, num_objects: int) -> dict[str, Any]:
        """The fields of this config that ``profile`` sets (subclasses pick their preset)."""
        return {}

    @property
    def profile(self) -> EnvProfile:
        """The env profile of :attr:`env`."""
        return env_profile(self.env)

    @classmethod
    def pop_flat_fields(
        cls, values: dict[str, Any], fields: Sequence[str], nested: str
    ) -> dict[str, Any]:
        """Removes the older flat ``fields`` from stored ``values`` and returns them.

        Raises:
            ValueError: ``values`` holds both flat fields and the ``nested`` config they became.
        """
        flat = {k: values.pop(k) for k in fields if k in values}
        if flat and nested in values:
            raise ValueError(
                f"a {cls.__name__} holds both {nested!r} and the older flat fields "
                f"{sorted(flat)} that it replaces; keep one."
            )
        return flat

    @property
    def play_trajectory_length(self) -> int:
        """Steps of each play trajectory: ``trajectory_length``, else the profile's, else
        chosen from the env's resets (:meth:`play_length_choice`)."""
        return self.play_length_choice()[0]

    def play_length_choice(self) -> tuple[int, str | None]:
        """``(length, why)`` of :attr:`play_trajectory_length`: ``why`` is None when the
        config or the profile gives the length, else the reason it was chosen
        (:func:`~dorp_rl.data.choose_play_length`, once per env and object count)."""
        if self.trajectory_length:
            return int(self.trajectory_length), None
        profile = self.profile
        if profile.play_trajectory_length is not None:
            return int(profile.play_trajectory_length), None
        key = (profile.name, id(profile.make_env), self.num_objects)
        if key not in _CHOSEN_PLAY_LENGTHS:
            from dorp_rl.data import RESET_PROBES, choose_play_length

            env = self.make_env(batch_size=(RESET_PROBES,), seed=0)
            _CHOSEN_PLAY_LENGTHS[key] = choose_play_length(env)
            env.close()
        return _CHOSEN_PLAY_LENGTHS[key]

    def make_env(self, **kwargs: Any) -> EnvBase:
        """The environment this config trains on (``kwargs``, such as ``batch_size``, go to
        the profile's factory, :meth:`~dorp_rl.envs.EnvProfile.build`)."""
        return self.profile.build(self.num_objects, device=self.device, **kwargs)


#: play lengths chosen from an env's resets, by (profile name, factory, object count)
_CHOSEN_PLAY_LENGTHS: dict[tuple[Any, ...], tuple[int, str]] = {}


class TrainerHook(TrainerHookBase):
    """A piece of trainer behaviour with its own state, called by the trainer loop.

    A torchrl :class:`~torchrl.trainers.TrainerHookBase` for :class:`OfflineTrainer`:
    ``hook.register(trainer)`` (torchrl's way, under :attr:`default_name`) or
    ``trainer.register_hook(name, hook)`` registers it under a name. The trainer calls
    :meth:`after_step` after every step (after logging, before evaluation and
    checkpoints), in registration order. A hook returning ``True`` has acted on the step
    (e.g. re-initialised the model); the hooks after it are not called for that step.
    Its :meth:`state_dict` is saved in every checkpoint and given back to
    :meth:`load_state_dict` on load and resume, so a resumed run continues the hook
    where it was.
    """

    #: the name :meth:`register` uses when none is given
    default_name = "hook"
    #: the trainer it is registered on (``None`` until registered)
    trainer: Any = None
    #: the name it is registered under
    name: str = ""

    def register(self, trainer: OfflineTrainer, name: str | None = None) -> None:
        """Registers this hook on ``trainer`` under ``name`` (default :attr:`default_name`)."""
        trainer.register_hook(self.default_name if name is None else name, self)

    def after_step(self, metrics: dict[str, float], logged: bool) -> bool:
        """Called after every step with its metrics; ``True``: later hooks are skipped."""
        return False

    def state_dict(self) -> dict[str, Any]:
        """JSON-like state saved with checkpoints."""
        return {}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restores :meth:`state_dict` (a checkpoint of an older version may lack it)."""


class TrainingDivergedError(ValueError):
    """Training produced a non-finite loss, gradient or weight; nothing was saved after it."""


class TrainingGaveUpError(RuntimeError):
    """Training stopped before its end because it learned nothing (e.g. every attempt of
    the codes collapsed); the message says what was seen and what to change."""


class NoCheckpointWarning(UserWarning):
    """``train(resume=True)`` found no checkpoint to continue from, so it trained from step 0."""


class OfflineTrainer:
    """Base class of :class:`RepresentationTrainer` and :class:`WorldModelTrainer`: training from a play buffer.

    Not torchrl's ``Trainer``, which is built around a data collector: these trainers
    sample batches from a fixed play buffer. A subclass sets :attr:`kind` (the checkpoint kind), builds its model, loss and
    optimiser, and implements :meth:`train_step`, :meth:`state_dict` /
    :meth:`load_state_dict` and :meth:`evaluate`. This class gives it:

    - the loop of :meth:`train`: ``train_step`` until :meth:`done`; every ``log_every``
      steps the metrics go to the logger (a torchrl ``CSVLogger`` in
      ``<out_dir>/logs`` by default) and to :attr:`history`; every
      :attr:`evaluate_every` steps :meth:`evaluate`; every ``checkpoint_every`` steps
      and at the end a checkpoint; a tqdm bar when ``config.progress``;
    - one checkpoint format (:func:`~dorp_rl.checkpoint.save_checkpoint`): config,
      env config, state dicts, step, the torch and data RNG states, and
      :meth:`extra_state`; ``train(resume=True)`` continues from the last checkpoint
      and ends exactly where an uninterrupted run with the same seed would. It reports
      where it went on from: :attr:`resumed_from_step` (also ``"resumed_from_step"`` in
      the result of :meth:`train`, and a ``resumed_from`` scalar in the logs) is the
      checkpoint's step; a resume that finds no checkpoint says so with a
      :class:`NoCheckpointWarning` and leaves it ``None`` (the run starts at step 0). A resume
      refuses a config that differs from the checkpoint's in a field that changes the
      result (the message lists them); :attr:`resume_adjustable_fields` (e.g.
      ``num_steps``) are taken with a warning, :attr:`bookkeeping_fields` silently;
    - a divergence stop: a non-finite loss or gradient raises
      :class:`TrainingDivergedError` naming the step before the weights are updated (a
      non-finite weight after an update too), and no checkpoint is written after it, so
      the last good one stays;
    - a lock on ``out_dir`` while :meth:`train` runs, so two runs never write into one
      directory (:class:`~dorp_rl.integrity.DirectoryLockedError`);
    - hooks (:class:`TrainerHook`, :meth:`register_hook`): called after every step,
      their state checkpointed with the trainer's.

    The config must have ``to_dict``, ``num_steps``, ``log_every``,
    ``checkpoint_every``, ``out_dir`` and ``progress``.
    """

    kind = "base"
    #: the metric shown in the progress bar
    progress_metric = "loss"
    #: entries of :meth:`state_dict` a checkpoint must hold
    state_keys: ClassVar[tuple[str, ...]] = ()
    #: config fields that never change the weights: a resume takes new values silently
    bookkeeping_fields: ClassVar[tuple[str, ...]] = (
        "progress",
        "out_dir",
        "data_dir",
        "checkpoint_every",
        "threads",
    )
    #: config fields a resume takes from the new config, with a warning
    resume_adjustable_fields: ClassVar[tuple[str, ...]] = ("num_steps",)

    def __init__(self, config: Any, env: EnvBase, logger: Any | None = None) -> None:
        self.config = config
        self.env = env
        self.out_dir = Path(config.out_dir)
        self.data_generator = torch.Generator()
        if logger is None:
            from torchrl.record.loggers import CSVLogger

            logger = CSVLogger(exp_name="logs", log_dir=str(self.out_dir))
        self.logger = logger
        self.step = 0
        #: step of the last checkpoint written or loaded under :attr:`checkpoint_path`
        self.saved_step: int | None = None
        #: step of the checkpoint the last ``train(resume=True)`` went on from; ``None``
        #: before any resume, after ``train()`` without resume, and after a resume that
        #: found no checkpoint (it trained from step 0, with a :class:`NoCheckpointWarning`)
        self.resumed_from_step: int | None = None
        self.history: list[dict[str, float]] = []
        #: the scalar results of every evaluation, with the step it was made at
        self.evaluations: list[dict[str, float]] = []
        self.last_evaluation: dict[str, Any] = {}
        #: registered hooks by name, in the order they are called
        self.hooks: dict[str, TrainerHook] = {}

    def register_hook(self, name: str, hook: TrainerHook) -> TrainerHook:
        """Registers ``hook`` under ``name``: called after every step, checkpointed under ``name``.

        Raises:
            ValueError: a hook is already registered under ``name``.
        """
        if name in self.hooks:
            raise ValueError(
                f"a hook is already registered as {name!r} (hooks: {sorted(self.hooks)})."
            )
        if not isinstance(hook, TrainerHook):
            raise TypeError(
                f"hooks of an OfflineTrainer are TrainerHook instances, got {type(hook).__name__}."
            )
        hook.trainer, hook.name = self, name
        self.hooks[name] = hook
        return hook

    # ------------------------------------------------------------------ subclass methods
    def train_step(self) -> dict[str, float]:
        """One gradient step; returns detached scalar metrics."""
        raise NotImplementedError

    def state_dict(self) -> dict[str, Any]:
        """State dicts of the models and optimiser."""
        raise NotImplementedError

    def load_state_dict(self, state: dict[str, Any]) -> None:
        raise NotImplementedError

    def evaluate(self) -> dict[str, Any]:
        """Evaluation run every :attr:`evaluate_every` steps and at the end."""
        return {}

    @property
    def evaluate_every(self) -> int:
        return 10**12

    @property
    def evaluate_at_end(self) -> bool:
        """Whether :meth:`train` evaluates after the last step (default: if it evaluates at all)."""
        return self.evaluate_every <= self.config.num_steps

    def done(self) -> bool:
        return self.step >= self.config.num_steps

    @property
    def planned_steps(self) -> int:
        """Steps the progress bar expects (restarts may add more)."""
        return self.config.num_steps

    def after_step(self, metrics: dict[str, float], logged: bool) -> None:
        """Called after every step (after logging): the hooks in order (see :class:`TrainerHook`)."""
        for hook in self.hooks.values():
            if hook.after_step(metrics, logged):
                break

    def extra_state(self) -> dict[str, Any]:
        """JSON-like state saved with checkpoints besides the state dicts (hooks' too)."""
        return {
            "history": self.history,
            "evaluations": self.evaluations,
            "hooks": {name: hook.state_dict() for name, hook in self.hooks.items()},
        }

    def load_extra_state(self, extra: dict[str, Any]) -> None:
        """Restores :meth:`extra_state`; a hook missing from it gets ``{}``."""
        self.history = list(extra.get("history", []))
        self.evaluations = list(extra.get("evaluations", []))
        hooks = extra.get("hooks") or {}
        for name, hook in self.hooks.items():
            hook.load_state_dict(dict(hooks.get(name) or {}))

    def check_checkpoint_config(self, stored: dict[str, Any]) -> None:
        """Raises ``ValueError`` if a stored config cannot be loaded into this trainer."""

    # ------------------------------------------------------------------ checkpoints
    @property
    def checkpoint_path(self) -> Path:
        return self.out_dir / "checkpoints" / "last.pt"

    def save(self, path: str | Path | None = None) -> Path:
        """Writes a checkpoint (default: ``<out_dir>/checkpoints/last.pt``)."""
        out = save_checkpoint(
            path or self.checkpoint_path,
            kind=self.kind,
            config=self.config.to_dict(),
            env_config=env_identity(self.env),
            state=self.state_dict(),
            step=self.step,
            rng={"torch": torch.get_rng_state(), "data": self.data_generator.get_state()},
            extra=self.extra_state(),
        )
        if Path(out) == self.checkpoint_path:
            self.saved_step = self.step
        return out

    def read_checkpoint(
        self, path: str | Path | None = None, *, resume: bool = False
    ) -> dict[str, Any]:
        """The checked payload of a checkpoint of this trainer (nothing is restored).

        With ``resume``, its config must also match this trainer's
        (:meth:`check_resume_config`).

        Raises:
            FileNotFoundError: no file.
            ValueError: a damaged or incomplete file (:class:`~dorp_rl.integrity.IntegrityError`),
                another kind of checkpoint, another environment, or a config this trainer
                cannot take.
        """
        path = path or self.checkpoint_path
        payload = load_checkpoint(
            path, kind=self.kind, env_config=env_identity(self.env), state_keys=self.state_keys
        )
        rng = payload.get("rng") or {}
        missing = [k for k in ("torch", "data") if k not in rng]
        if missing:
            raise IntegrityError(f"checkpoint {path} is incomplete: it has no RNG state {missing}.")
        if resume:
            self.check_resume_config(payload["config"], Path(path))
        self.check_checkpoint_config(payload["config"])
        return payload

    def load(self, path: str | Path | None = None) -> dict[str, Any]:
        """Restores a checkpoint of this trainer and returns its payload.

        Weights, optimiser state, step and RNG states come from the checkpoint; this
        trainer's config stays in force (e.g. its learning rate). To continue a run
        with the checkpoint's own config, use ``train(resume=True)``.

        Raises:
            ValueError: see :meth:`read_checkpoint`.
        """
        payload = self.read_checkpoint(path)
        self._restore(payload)
        if path is None or Path(path) == self.checkpoint_path:
            self.saved_step = self.step
        return payload

    def _restore(self, payload: dict[str, Any]) -> None:
        self.load_extra_state(payload["extra"])
        self.load_state_dict(payload["state"])
        self.step = int(payload["step"])
        torch.set_rng_state(payload["rng"]["torch"])
        self.data_generator.set_state(payload["rng"]["data"])

    def in_current_terms(self, config: Any) -> Any:
        """A checkpoint's config as this trainer would have resolved it (settings a subclass
        chooses from the env filled in the same way); as is by default."""
        return config

    def check_resume_config(self, stored: dict[str, Any], path: Path) -> None:
        """Refuses to resume with a config that changes the result; warns about taken changes.

        Raises:
            ValueError: listing every field (other than :attr:`bookkeeping_fields` and
                :attr:`resume_adjustable_fields`) whose value differs from the checkpoint's.
        """
        try:  # compare in this version's terms (older key-room configs stored num_objects=3)
            stored = self.in_current_terms(type(self.config).from_dict(stored)).to_dict()
        except (ValueError, TypeError) as err:
            raise ValueError(
                f"cannot resume from {path}: its config cannot be read ({err})."
            ) from err
        diff = config_differences(stored, self.config.to_dict())
        refused = {
            k: v
            for k, v in diff.items()
            if k not in self.bookkeeping_fields and k not in self.resume_adjustable_fields
        }
        if refused:
            details = format_differences(refused, "checkpoint", "now")
            raise ValueError(
                f"cannot resume from {path}: the config differs in fields that change the "
                f"result ({details}). Resume with the checkpoint's values, start a new run "
                "in another out_dir, or load the weights into a new run with "
                "trainer.load(path)."
            )
        taken = {k: v for k, v in diff.items() if k in self.resume_adjustable_fields}
        if taken:
            details = "; ".join(f"{k}={b!r} (checkpoint {a!r})" for k, (a, b) in taken.items())
            warnings.warn(
                f"resuming from {path} with {details}: the new value is used from here on.",
                UserWarning,
                stacklevel=5,
            )

    # ------------------------------------------------------------------ divergence
    def _diverged(self, reason: str) -> TrainingDivergedError:
        step = self.step + 1
        if self.saved_step is not None and self.checkpoint_path.exists():
            kept = f"the last good checkpoint, {self.checkpoint_path} (step {self.saved_step}), is kept"
        else:
            kept = "no checkpoint had been written yet"
        return TrainingDivergedError(
            f"{self.kind} training diverged at step {step}: {reason}. Nothing was saved after "
            f"it; {kept}. Lower the learning rate (lr={getattr(self.config, 'lr', '?')}) or "
            "check the data."
        )

    def check_gradients(
        self, loss: torch.Tensor, parameters: Iterable[torch.Tensor]
    ) -> torch.Tensor:
        """Total gradient norm (a 0-dim tensor) after ``backward``; raises if the loss or a gradient is not finite.

        Called before the optimiser step, so a failing step leaves the weights as they were.
        """
        grads = [p.grad for p in parameters if p.grad is not None]
        norm = torch.nn.utils.get_total_norm(grads) if grads else loss.new_zeros(())
        loss_value, norm_value = torch.stack(
            [loss.detach().float(), norm.detach().float()]
        ).tolist()
        if not math.isfinite(loss_value):
            raise self._diverged(f"the loss is {loss_value}")
        if not math.isfinite(norm_value):
            raise self._diverged(f"the gradient norm is {norm_value}")
        return norm

    def check_weights(self, *modules: torch.nn.Module) -> None:
        """Raises if the step made a weight or a floating buffer (BatchNorm statistics) non-finite."""
        tensors = [t for m in modules for t in (*m.parameters(), *m.buffers())]
        flags = [torch.isfinite(t.detach()).all() for t in tensors if t.is_floating_point()]
        if flags and not bool(torch.stack(flags).all()):
            raise self._diverged("the update made weights NaN or infinite")

    # ------------------------------------------------------------------ loop
    def log_metrics(self, metrics: dict[str, float], prefix: str = "") -> None:
        for key, value in metrics.items():
            if isinstance(value, (int, float)) and not isinstance(value, bool):
                self.logger.log_scalar(f"{prefix}{key}", float(value), step=self.step)

    def _evaluate_and_log(self) -> None:
        self.last_evaluation = self.evaluate()
        self.log_metrics(self.last_evaluation, prefix="eval/")
        scalars = {
            k: float(v) for k, v in self.last_evaluation.items() if isinstance(v, (int, float))
        }
        self.evaluations.append({"step": self.step, **scalars})

    def train(self, resume: bool = False) -> dict[str, Any]:
        """Trains until :meth:`done` and returns the last metrics and evaluation.

        The result holds ``step`` (the last step), ``resumed_from_step`` (see
        :attr:`resumed_from_step`), ``metrics`` (of the last step) and ``evaluation``.

        Args:
            resume: continue from ``<out_dir>/checkpoints/last.pt`` (its config must
                match, see :meth:`check_resume_config`); without that file training
                starts from step 0 with a :class:`NoCheckpointWarning`.

        Raises:
            TrainingDivergedError: a non-finite loss, gradient or weight (names the step).
            DirectoryLockedError: another run is training in ``out_dir``.
            ValueError: a damaged checkpoint or a differing config on resume.
        """
        lock = DirectoryLock(self.out_dir, ".train.lock", purpose=f"{self.kind} training")
        lock.acquire()
        threads = getattr(self.config, "threads", None)
        before = torch.get_num_threads()
        if threads is not None:
            torch.set_num_threads(int(threads))
        try:
            return self._train(resume)
        finally:
            torch.set_num_threads(before)
            lock.release()

    def _train(self, resume: bool) -> dict[str, Any]:
        cfg = self.config
        self.resumed_from_step = None
        if resume and self.checkpoint_path.exists():
            self._restore(self.read_checkpoint(resume=True))
            self.saved_step = self.resumed_from_step = self.step
            self.logger.log_scalar("resumed_from", float(self.step), step=self.step)
        elif resume:
            warnings.warn(
                f"train(resume=True) found no checkpoint at {self.checkpoint_path}: "
                f"{self.kind} training starts from step {self.step}, not from a checkpoint "
                "(resumed_from_step is None).",
                NoCheckpointWarning,
                stacklevel=3,
            )
        total = self.planned_steps
        bar = progress_bar(cfg.progress, total=total, initial=min(self.step, total), desc=self.kind)
        metrics: dict[str, float] = {}
        evaluated_at = -1
        try:
            while not self.done():
                metrics = self.train_step()
                logged = self.step % cfg.log_every == 0
                if logged:
                    self.log_metrics(metrics)
                    self.history.append({"step": self.step, **metrics})
                    if bar is not None and self.progress_metric in metrics:
                        bar.set_postfix(
                            {self.progress_metric: f"{metrics[self.progress_metric]:.4f}"}
                        )
                self.after_step(metrics, logged)
                if self.step % self.evaluate_every == 0:
                    self._evaluate_and_log()
                    evaluated_at = self.step
                if self.step % cfg.checkpoint_every == 0:
                    self.save()
                if bar is not None:
                    if bar.total != self.planned_steps:  # a restart added steps
                        bar.total = self.planned_steps
                    bar.update(1)
        finally:
            if bar is not None:
                bar.close()
        self.save()
        if evaluated_at != self.step and self.evaluate_at_end:
            self._evaluate_and_log()
        return {
            "step": self.step,
            "resumed_from_step": self.resumed_from_step,
            "metrics": metrics,
            "evaluation": self.last_evaluation,
        }
