"""RepresentationTrainer: learns DORP's discrete codes from play data with CPCLoss."""

from __future__ import annotations

import json
import math
import warnings
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
from tensordict import TensorDict
from torchrl.data import TensorDictReplayBuffer
from torchrl.envs import EnvBase

from dorp_rl.checkpoint import load_checkpoint, load_module_state
from dorp_rl.config import Choice, Float, Floats, Int, Nested, Text, checked
from dorp_rl.data import (
    FrameScan,
    FuturePairSampler,
    check_play_buffer,
    collect_play_data,
    future_pairs,
    scan_frames,
)
from dorp_rl.envs import DEFAULT_ENV, EnvProfile, env_identity, env_profile, profile_of
from dorp_rl.frames import frame_shape_of
from dorp_rl.metrics.code_information import (
    code_dynamics,
    code_information,
    play_code_dynamics,
)
from dorp_rl.metrics.diagnostics import play_object_diagnostics
from dorp_rl.modules import DiscreteCodeEncoder, EncoderConfig, choose_map_stride, make_similarity
from dorp_rl.modules.encoder import competing_maps, eval_mode
from dorp_rl.modules.similarity import SIMILARITIES
from dorp_rl.objectives import CPCLoss
from dorp_rl.planners.play_codes import encode_transitions
from dorp_rl.trainers.base import OfflineTrainer, TrainerConfig, TrainerHook, read_trained
from dorp_rl.validation import check_device, derive_seed

#: Flat fields of older representation configs that now live in ``encoder``.
_FLAT_ENCODER_FIELDS = ("code_size", "encoder_preset", "map_competition", "extractor_kernel_size")


def _default_encoder() -> EncoderConfig:
    return EncoderConfig.small((32,))


def _counted_then(values: dict[str, Any]) -> bool:
    """Whether stored ``values`` would have their one-hots counted today: one code size
    on an env without a layout (stored configs then meant one one-hot)."""
    encoder = values.get("encoder")
    sizes = encoder.get("code_sizes", (32,)) if isinstance(encoder, dict) else (32,)
    if len(tuple(sizes)) != 1:
        return False
    try:
        return env_profile(values.get("env", DEFAULT_ENV)).code_layout is None
    except ValueError:
        return True


@dataclass
class RepresentationConfig(TrainerConfig):
    """Everything that defines a representation run: env and play data, encoder, CPC loss.

    Use the presets :meth:`rearrangement`, :meth:`key_wall` and :meth:`key_corridor`, then
    override fields with :meth:`replace` (``cfg.replace(encoder={"code_sizes": (16,)})``
    changes one encoder field). ``encoder.code_sizes`` may be one number, the size of
    every object one-hot: rearrangement gets one such one-hot per object, a key room an
    agent one-hot plus a 2-way key bit (:attr:`code_sizes` gives the full sizes).
    Configs stored by older versions, with flat ``code_size``, ``encoder_preset``,
    ``map_competition`` and ``extractor_kernel_size`` fields, are read into ``encoder``.
    """

    out_dir: str = checked("outputs/representation", Text())
    """folder of checkpoints and logs"""
    # training pairs
    min_offset: int = checked(1, Int(low=1))
    """smallest offset k of the (o_t, o_t+k) training pairs"""
    max_offset: int = checked(1, Int(low=1))
    """largest offset k of the training pairs"""
    # encoder
    encoder: EncoderConfig = checked(rule=Nested(EncoderConfig, default=_default_encoder))
    """the encoder; its code_sizes may be one number, the size of every object one-hot"""
    num_onehots: int | None = checked(None, Int(low=1, optional=True))
    """one-hots of a one-number code_sizes where the env lays out none (None: one per
    piece that moves in the play frames, counted by dorp_rl.data.scan_frames)"""
    # loss
    similarity: str = checked("dddp", Choice(tuple(SIMILARITIES)))
    """code similarity of the CPC loss: dddp, full or identity"""
    dddp_sign: str = checked("paper", Choice(("paper", "authors")))
    """sign convention of DDDP: paper or authors"""
    alpha: float = checked(1.0, Float(low=1.0))
    """DDDP's alpha (dddp only)"""
    gumbel_side: str = checked("positive", Choice(("positive", "anchor")))
    """which side of a pair gets hard Gumbel codes: positive or anchor"""
    gumbel_temperature: float = checked(0.1, Float(low=0.0, low_open=True))
    """Gumbel-softmax temperature"""
    gumbel_temperature_start: float | None = checked(
        None, Float(low=0.0, low_open=True, optional=True)
    )
    """start of a Gumbel temperature annealing (None: no annealing)"""
    gumbel_anneal_steps: int = checked(0, Int(low=0))
    """steps of the Gumbel temperature annealing"""
    ce_temperature: float = checked(0.1, Float(low=0.0, low_open=True))
    """temperature of the contrastive cross-entropy"""
    usage_weight: float | tuple[float, ...] = checked(0.0, Floats(low=0.0, allow_scalar=True))
    """weight of the code-usage term: one number, or one per one-hot in the encoder's
    code_sizes order (0 leaves that one-hot's code usage to the contrastive loss alone)"""
    exclusivity_weight: float | None = checked(None, Float(low=0.0, optional=True))
    """weight of the map-exclusivity term (objects on separate maps); None: chosen by
    the trainer, 3.0 where several one-hots' maps compete (softmax), else 0"""
    sparsity_weight: float = checked(0.0, Float(low=0.0))
    """weight of the map-sparsity term"""
    motion_weight: float = checked(0.0, Float(low=0.0))
    """weight of the motion-coverage term (key rooms: the agent map on the agent)"""
    # optimisation
    batch_size: int = checked(128, Int(low=2))
    """pairs per step"""
    lr: float = checked(1e-3, Float(low=0.0, low_open=True, hint="(0 would never change a weight)"))
    """Adam learning rate"""
    similarity_lr_scale: float = checked(1.0, Float(low=0.0))
    """learning rate of the similarity, as a multiple of lr"""
    num_steps: int = checked(2000, Int(low=1))
    """training steps (of the last attempt)"""
    # diagnostics
    diagnostics_every: int = checked(500, Int(low=1))
    """steps between ground-truth diagnostics"""
    diagnostics_samples: int = checked(2048, Int(low=1))
    """states drawn for the diagnostics"""
    # collapse and entanglement restarts
    collapse_check_after: int = checked(300, Int(low=0))
    """steps of an attempt before the collapse check"""
    collapse_min_codes: int = checked(2, Int(low=0))
    """a one-hot using at most this many codes counts as collapsed"""
    collapse_loss_margin: float = checked(0.05, Float())
    """a loss within this margin of log(batch) counts as collapsed"""
    entanglement_check_after: int = checked(600, Int(low=0))
    """steps of an attempt before the entanglement check"""
    entanglement_threshold: float = checked(0.07, Float(low=0.0))
    """map entanglement above this restarts the attempt"""
    dead_check_frames: int = checked(8192, Int(low=0))
    """evenly spaced play frames the dead one-hot check at an attempt's end encodes (0: no
    check)"""
    max_restarts: int = checked(3, Int(low=0))
    """restarts after a collapse, entanglement or dead one-hot"""
    # one-hot widths
    order_widths_at: int = checked(0, Int(low=0))
    """steps into each attempt after which the object maps are given to the one-hots by
    how often their codes change along play, the most changing to the widest (0: never)"""
    # initialisation screening
    num_candidates: int = checked(1, Int(low=1))
    """initialisations screened before training (1: no screening)"""
    candidate_steps: int = checked(1000, Int(low=1))
    """steps per screened initialisation"""
    screening_frames: int = checked(8192, Int(low=1))
    """play frames scoring each screened initialisation"""

    @classmethod
    def profile_overrides(cls, profile: Any, num_objects: int) -> dict[str, Any]:
        """The env profile's code preset (:attr:`~dorp_rl.envs.EnvProfile.codes`)."""
        return profile.code_overrides(num_objects)

    @classmethod
    def upgrade(cls, values: dict[str, Any]) -> dict[str, Any]:
        """Older flat configs: ``code_size``, ``encoder_preset``, ``map_competition`` and
        ``extractor_kernel_size`` become the ``encoder`` field; configs without
        ``dead_check_frames`` (stored before that check) get 0."""
        values = super().upgrade(values)
        # Configs stored before the dead one-hot check existed resume as they ran.
        values.setdefault("dead_check_frames", 0)
        flat = cls.pop_flat_fields(values, _FLAT_ENCODER_FIELDS, "encoder")
        if flat:
            preset = flat.get("encoder_preset", "small")
            if preset not in ("small", "authors"):
                raise ValueError(f"encoder_preset must be 'small' or 'authors', got {preset!r}.")
            make = EncoderConfig.small if preset == "small" else EncoderConfig.authors
            encoder = make(
                (flat.get("code_size", 32),),
                map_competition=flat.get("map_competition", "sigmoid"),
                kernel_size=flat.get("extractor_kernel_size", 3),
            )
            values["encoder"] = encoder.to_dict()
        # ... and before the one-hots were counted: one number meant one one-hot.
        if "num_onehots" not in values and _counted_then(values):
            values["num_onehots"] = 1
        if isinstance(values.get("encoder"), dict):
            values["encoder"] = EncoderConfig.upgrade(dict(values["encoder"]))
        return values

    def encoder_config(self) -> EncoderConfig:
        """The encoder this config trains: ``encoder`` with the full :attr:`code_sizes`."""
        return self.encoder.replace(code_sizes=self.code_sizes)

    @property
    def code_sizes(self) -> tuple[int, ...]:
        """Codes of each one-hot: ``encoder.code_sizes``, one number laid out by the env
        profile's :attr:`~dorp_rl.envs.EnvProfile.code_layout`, else repeated for
        :attr:`num_onehots` one-hots (one while that is still to be chosen)."""
        sizes = tuple(self.encoder.code_sizes)
        if len(sizes) == 1 and self.profile.code_layout is None and self.num_onehots:
            return sizes * self.num_onehots
        return self.profile.code_sizes(sizes, self.num_objects)

    def counts_onehots(self) -> bool:
        """Whether the number of one-hots is still to be counted in the play frames."""
        return (
            self.num_onehots is None
            and len(self.encoder.code_sizes) == 1
            and self.profile.code_layout is None
        )

    def check_relations(self) -> None:
        """Rules between fields; each message names the fields and what they allow."""
        super().check_relations()
        sizes = tuple(self.encoder.code_sizes)
        layout = self.profile.code_layout
        if len(sizes) > 1 and layout is not None:
            expected = tuple(layout(sizes[0], self.num_objects))
            # Entries the layout gives whatever the number (a key bit's 2) are fixed.
            bigger = layout(sizes[0] + 1, self.num_objects)
            fixed = [a == b for a, b in zip(expected, bigger, strict=True)]
            fits = len(sizes) == len(expected) and all(
                s == e for s, e, f in zip(sizes, expected, fixed, strict=True) if f
            )
            if not fits:
                raise ValueError(
                    f"encoder.code_sizes {sizes} does not fit env={self.env!r} with "
                    f"num_objects={self.num_objects}: its layout is like {expected} (for one "
                    f"number {sizes[0]}); give sizes of that form, or one number."
                )
        # (a length chosen from the env is looked up only when an offset could exceed it)
        if not self.min_offset <= self.max_offset or (
            self.max_offset > 1 and self.max_offset > self.play_trajectory_length
        ):
            raise ValueError(
                "offsets must satisfy 1 <= min_offset <= max_offset <= the play trajectory "
                f"length ({self.play_trajectory_length} for env={self.env!r}, "
                f"trajectory_length={self.trajectory_length}): got min_offset="
                f"{self.min_offset}, max_offset={self.max_offset}. Longer offsets would never "
                "be drawn."
            )
        if self.num_candidates > 1 and self.candidate_steps > self.num_steps:
            raise ValueError(
                "need num_candidates >= 1 and, to screen, 1 <= candidate_steps <= num_steps; got "
                f"num_candidates={self.num_candidates}, candidate_steps={self.candidate_steps}, "
                f"num_steps={self.num_steps}."
            )
        if self.gumbel_temperature_start is not None and self.gumbel_anneal_steps < 1:
            raise ValueError(
                "gumbel_temperature_start needs gumbel_anneal_steps >= 1 (it is the start of "
                f"the annealing), got gumbel_anneal_steps={self.gumbel_anneal_steps}."
            )
        if self.similarity != "dddp" and (self.alpha != 1.0 or self.dddp_sign != "paper"):
            raise ValueError(
                f"alpha and dddp_sign apply to similarity='dddp' only; similarity="
                f"{self.similarity!r} would ignore alpha={self.alpha}, dddp_sign={self.dddp_sign!r}."
            )


def choose_code_settings(
    config: RepresentationConfig, scan: FrameScan | None
) -> tuple[RepresentationConfig, dict[str, dict[str, Any]]]:
    """The settings of ``config`` left to the library, chosen from the env's play frames.

    Chosen where the config leaves them open (``None``, ``"auto"``, one code size on an
    env without a layout): the number of one-hots (one per moving piece the
    :func:`~dorp_rl.data.scan_frames` scan counts), the map competition (softmax where
    several one-hots of more than 2 codes share the pixels), the exclusivity weight
    (3.0 with competing maps)
    the object maps' stride (:func:`~dorp_rl.modules.choose_map_stride`: maps at
    least 16 cells a side, a cell no wider than the smallest piece) and whether the static
    background is subtracted from the frames (where it is not black).

    Returns:
        the config with every open setting filled in, and per chosen field its
        ``value`` and ``why``.

    Examples:
        >>> from dorp_rl.trainers import RepresentationConfig
        >>> from dorp_rl.trainers.representation import choose_code_settings
        >>> cfg, chosen = choose_code_settings(RepresentationConfig.for_env("key-wall"), None)
        >>> cfg.encoder.map_competition, cfg.exclusivity_weight, sorted(chosen)
        ('sigmoid', 0.0, ['encoder.map_competition', 'encoder.map_stride', 'exclusivity_weight'])
    """
    chosen: dict[str, dict[str, Any]] = {}

    def choose(field: str, value: Any, why: str) -> None:
        chosen[field] = {"value": value, "why": why}

    if config.counts_onehots():
        if scan is None:
            raise ValueError(
                "choose_code_settings needs a scan of the play frames to count the one-hots "
                "(or set num_onehots, or give encoder.code_sizes one size per one-hot)."
            )
        config = config.replace(num_onehots=scan.pieces)
        choose(
            "num_onehots",
            scan.pieces,
            f"{scan.pieces} pieces move in a play frame ({scan.frames} frames scanned, "
            f"median {scan.pieces_median:g}): one one-hot each",
        )
    # Objects are one-hots of more than 2 codes (a 2-code one-hot is a flag, a key held).
    objects = sum(size > 2 for size in config.code_sizes)
    several = competing_maps(config.code_sizes)
    if config.encoder.map_competition == "auto":
        competition = "softmax" if several else "sigmoid"
        config = config.replace(encoder={"map_competition": competition})
        choose(
            "encoder.map_competition",
            competition,
            f"{objects} one-hot(s) of more than 2 codes: "
            + ("their maps compete for each pixel" if several else "no objects to share pixels"),
        )
    if config.exclusivity_weight is None:
        weight = 3.0 if config.encoder.map_competition == "softmax" and several else 0.0
        config = config.replace(exclusivity_weight=weight)
        choose(
            "exclusivity_weight",
            weight,
            "competing maps are kept on separate objects"
            if weight
            else "no competing maps to keep apart",
        )
    if config.encoder.subtract_background is None and scan is not None:
        subtract = not scan.plain_background
        config = config.replace(encoder={"subtract_background": subtract})
        choose(
            "encoder.subtract_background",
            subtract,
            "the play frames' static background is not black: only what moves is left"
            if subtract
            else "the play frames' background is black: nothing to subtract",
        )
    if config.encoder.map_stride is None:
        frame_shape = tuple(config.encoder.frame_shape)
        smallest = scan.smallest_piece if scan is not None and scan.smallest_piece else None
        step = scan.motion_step if scan is not None else None
        shapes_only = scan is not None and scan.pieces_share_colours
        stride = choose_map_stride(frame_shape, smallest, step, shapes_only)
        config = config.replace(encoder={"map_stride": stride})
        choose(
            "encoder.map_stride",
            stride,
            f"frames {frame_shape[1]} x {frame_shape[2]}"
            + (f", smallest piece {smallest} pixels" if smallest else "")
            + (f", pieces moving on a grid of {step} pixels" if step and step > 1 else "")
            + (", pieces of one colour told apart by shape" if shapes_only else "")
            + f": maps of {-(-frame_shape[1] // stride)} x {-(-frame_shape[2] // stride)} cells",
        )
    return config, chosen


def diagnose(
    env: EnvBase,
    encoder: DiscreteCodeEncoder,
    num_samples: int = 2048,
    seed: int = 0,
    profile: EnvProfile | None = None,
) -> dict:
    """The diagnostics of an encoder's codes that ``env``'s profile declares
    (:attr:`~dorp_rl.envs.EnvProfile.diagnostics`; ``profile`` default: the registered
    profile of the env's class).

    Raises:
        ValueError: the profile declares none.
    """
    profile = profile_of(env) if profile is None else profile
    if profile is None or profile.diagnostics is None:
        raise ValueError(
            f"{type(env).__name__}'s profile declares no code diagnostics "
            "(EnvProfile.diagnostics); the label-free dorp_rl.eval.play_code_dynamics needs none."
        )
    return dict(profile.diagnostics.measure(env, encoder.encode, num_samples, seed))


class RestartHook(TrainerHook):
    """Re-initialises the encoder when :meth:`reason` finds the attempt failed (a base class).

    Restarts of every restart hook share the trainer's ``max_restarts`` budget. The
    state is this hook's restarts (step, attempt, reason).
    """

    def __init__(self) -> None:
        self.restarts: list[dict[str, Any]] = []

    def reason(self, metrics: dict[str, float], logged: bool) -> str | None:
        """Why the current attempt failed (``None``: it did not, or it is too early)."""
        raise NotImplementedError

    def after_step(self, metrics: dict[str, float], logged: bool) -> bool:
        trainer = self.trainer
        if trainer.screening:
            return False
        reason = self.reason(metrics, logged)
        if reason is None:
            return False
        if len(trainer.restarts) >= trainer.config.max_restarts:
            self.out_of_restarts(reason)
            return False
        self.before_restart(reason)
        trainer.new_init()
        self.restarts.append({"step": trainer.step, "attempt": trainer.attempt, "reason": reason})
        count = len(trainer.restarts)
        warnings.warn(
            f"representation restarted at step {trainer.step} ({reason}); re-initialising "
            f"encoder and similarity (restart {count}/{trainer.config.max_restarts}).",
            RuntimeWarning,
            stacklevel=5,
        )
        trainer.logger.log_scalar("restart", float(count), step=trainer.step)
        return True

    def before_restart(self, reason: str) -> None:
        """The attempt failed and is about to be replaced by a new one (default: nothing)."""

    def out_of_restarts(self, reason: str) -> None:
        """The attempt failed with no restart left (default: it trains on)."""

    def state_dict(self) -> dict[str, Any]:
        return {"restarts": list(self.restarts)}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.restarts = list(state.get("restarts", []))


class CollapseRestart(RestartHook):
    """Restarts an attempt whose codes collapsed (few codes in a batch, or a flat loss).

    After ``collapse_check_after`` steps of an attempt: a one-hot using at most
    ``collapse_min_codes`` codes on a batch, or a loss still within
    ``collapse_loss_margin`` of ``log B`` (nothing learned). When the number of one-hots
    was counted from the play frames (:attr:`RepresentationTrainer.surplus_may_die`) a
    one-hot the count gave too many may settle on few codes: such an attempt is still
    restarted while restarts are left (another initialisation often codes every piece),
    but once they run out training goes on; only every one-hot that narrow, or a flat
    loss, gives training up.
    """

    default_name = "collapse"

    def out_of_restarts(self, reason: str) -> None:
        """Stops training: every attempt collapsed, and more steps would not change that
        (goes on when only a one-hot of a counted set is narrow)."""
        trainer = self.trainer
        if self.partial(reason):
            return
        if trainer.gave_up is None:
            trainer.gave_up = trainer.collapse_advice(reason)

    def partial(self, reason: str | None) -> bool:
        """Whether ``reason`` is one narrow one-hot of a counted set (no collapse of the
        whole code)."""
        return (
            reason is not None and self.trainer.surplus_may_die and reason.startswith(self.NARROW)
        )

    #: how a reason of one narrow one-hot starts
    NARROW = "a one-hot uses only"

    def reason(self, metrics: dict[str, float], logged: bool = True) -> str | None:
        trainer = self.trainer
        return self.collapse_reason(metrics, trainer.step - trainer.attempt_start)

    def collapse_reason(self, metrics: dict[str, float], attempt_steps: int) -> str | None:
        """Why an attempt of ``attempt_steps`` steps looks collapsed (``None`` if it does not)."""
        cfg = self.trainer.config
        if attempt_steps < cfg.collapse_check_after:
            return None
        if metrics["min_codes_in_batch"] <= cfg.collapse_min_codes:
            most = metrics.get("max_codes_in_batch", metrics["min_codes_in_batch"])
            if self.trainer.surplus_may_die and most <= cfg.collapse_min_codes:
                return (
                    f"every one-hot uses at most {int(most)} code(s) in a batch of {cfg.batch_size}"
                )
            return (
                f"{self.NARROW} {int(metrics['min_codes_in_batch'])} code(s) in a batch "
                f"of {cfg.batch_size}"
            )
        loss = self.trainer.recent_loss(metrics)
        if loss > math.log(cfg.batch_size) - cfg.collapse_loss_margin:
            return (
                f"the loss is flat at log B = {math.log(cfg.batch_size):.3f} (mean of the "
                f"last logged steps {loss:.3f})"
            )
        return None


class EntanglementRestart(RestartHook):
    """Restarts an attempt whose object maps stay entangled (checked on logged steps).

    After ``entanglement_check_after`` steps of an attempt, if the mean
    ``map_entanglement`` of its last five logged steps is above
    ``entanglement_threshold``: some object map follows several objects or none.

    Each restarted attempt is saved (``<out_dir>/checkpoints/attempt<i>.pt``) with its
    entanglement. When the last attempt is entangled too, training goes on from the least
    entangled of them all (the restarts then act as a screening of initialisations):
    with four or more objects every attempt can stay above the threshold at the check,
    and the last one is not the best more often than any other. The state is the
    restarts, the saved attempts and the attempt kept.
    """

    default_name = "entanglement"

    def __init__(self) -> None:
        super().__init__()
        #: restarted attempts: attempt, entanglement, steps into it, checkpoint path
        self.attempts: list[dict[str, Any]] = []
        #: the attempt training went on from once restarts ran out (None: not yet)
        self.kept: dict[str, Any] | None = None
        self._value = math.nan

    def reason(self, metrics: dict[str, float], logged: bool) -> str | None:
        if not logged:
            return None
        trainer = self.trainer
        return self.entanglement_reason(trainer.step - trainer.attempt_start)

    def before_restart(self, reason: str) -> None:
        trainer = self.trainer
        path = trainer.checkpoint_path.with_name(f"attempt{trainer.attempt}.pt")
        trainer.save(path)
        self.attempts.append(
            {
                "attempt": trainer.attempt,
                "entanglement": self._value,
                "attempt_steps": trainer.step - trainer.attempt_start,
                "path": str(path),
            }
        )

    def out_of_restarts(self, reason: str) -> None:
        """Goes on from the least entangled attempt, once (this one where it is the least)."""
        trainer = self.trainer
        if self.kept is not None:
            return
        current = {"attempt": trainer.attempt, "entanglement": self._value}
        best = min([*self.attempts, current], key=lambda a: a["entanglement"])
        self.kept = {"attempt": best["attempt"], "entanglement": best["entanglement"]}
        if best is current:
            return
        warnings.warn(
            f"representation: every attempt stayed entangled; going on from attempt "
            f"{best['attempt']} (map_entanglement {best['entanglement']:.3f}, the least; "
            f"this attempt's {self._value:.3f}).",
            RuntimeWarning,
            stacklevel=6,
        )
        trainer.continue_attempt(best["attempt"], best["path"], best["attempt_steps"])
        trainer.logger.log_scalar("kept_attempt", float(best["attempt"]), step=trainer.step)

    def state_dict(self) -> dict[str, Any]:
        return {**super().state_dict(), "attempts": list(self.attempts), "kept": self.kept}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        super().load_state_dict(state)
        self.attempts = list(state.get("attempts", []))
        self.kept = state.get("kept")

    def entanglement_reason(self, attempt_steps: int) -> str | None:
        """Why the object maps look entangled (``None`` if they do not or it is too early)."""
        trainer = self.trainer
        cfg = trainer.config
        recent = [
            h["map_entanglement"]
            for h in trainer.history[-5:]
            if h["step"] > trainer.history_start and "map_entanglement" in h
        ]
        if attempt_steps < cfg.entanglement_check_after or len(recent) < 5:
            return None
        value = self._value = sum(recent) / len(recent)
        if value > cfg.entanglement_threshold:
            return (
                f"the object maps are still entangled (map_entanglement {value:.3f} > "
                f"{cfg.entanglement_threshold}): some map follows several objects or none"
            )
        return None


class DeadOneHotRestart(RestartHook):
    """Restarts an attempt that ends with a one-hot coding every play frame alike (dead)
    (every one-hot, when their number was counted from the play frames).

    At the attempt's last step the encoder codes ``dead_check_frames`` evenly spaced
    stored play frames; a one-hot giving all of them one code carries nothing about play
    (no ground truth needed), and a new attempt of ``num_steps`` starts. Two-code
    one-hots such as a key bit are judged too, which the collapse check cannot do from a
    batch: a collapsed key-room run hid its key in a wide one-hot together with a coarse
    agent place and left the key bit at one code. Only the end is judged: a key bit may
    stay at one code for a while before the key is learned.
    """

    default_name = "dead"

    def reason(self, metrics: dict[str, float], logged: bool = True) -> str | None:
        trainer = self.trainer
        cfg = trainer.config
        at_end = trainer.step - trainer.attempt_start >= cfg.num_steps
        if cfg.dead_check_frames <= 0 or not at_end:
            return None
        codes = trainer.play_codes(cfg.dead_check_frames)  # [n, C]
        if codes.shape[0] < 2:
            return None
        dead = [i for i in range(codes.shape[1]) if bool((codes[:, i] == codes[0, i]).all())]
        if not dead or (trainer.surplus_may_die and len(dead) < codes.shape[1]):
            return None
        return (
            f"one-hot(s) {dead} give every one of {codes.shape[0]} evenly spaced play "
            "frames the same code (dead)"
        )


class WidthOrder(TrainerHook):
    """Gives the widest one-hots the object maps whose codes change most often along play.

    Which object a map takes is settled early, by the initialisation. With one-hots of
    different sizes (a 16-code one for an agent, a 4-code one for a key and door) a map
    can take the object meant for another size: a rarely changing key then holds 16
    codes and the agent 4. Once per attempt, ``order_widths_at`` steps in, this hook
    encodes ``screening_frames`` stored play transitions, ranks the one-hots by the
    share of transitions that change their code (no labels), and permutes the maps
    (:meth:`~dorp_rl.modules.DiscreteCodeEncoder.permute_onehots_`) and the
    similarity's code positions so that the ranks follow the code sizes; the moved
    parameters' optimiser moments restart. One-hots of equal size are never moved. It
    assumes what the sizes say: an object with more states changes its code more often.
    The state is the reorderings made (step, attempt, change rates, order).
    """

    default_name = "widths"

    def __init__(self) -> None:
        self.reorders: list[dict[str, Any]] = []

    def after_step(self, metrics: dict[str, float], logged: bool) -> bool:
        trainer = self.trainer
        at = trainer.config.order_widths_at
        if at <= 0 or trainer.step - trainer.attempt_start != at:
            return False
        sizes = trainer.encoder.code_sizes
        if len(set(sizes)) < 2:
            return False
        rates = trainer.play_change_rates(trainer.config.screening_frames)
        order = width_order(sizes, rates)
        if order != list(range(len(sizes))):
            trainer.permute_onehots(order)
        self.reorders.append(
            {"step": trainer.step, "attempt": trainer.attempt, "change_rate": rates, "order": order}
        )
        return False

    def state_dict(self) -> dict[str, Any]:
        return {"reorders": list(self.reorders)}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.reorders = list(state.get("reorders", []))


def width_order(code_sizes: Sequence[int], change_rates: Sequence[float]) -> list[int]:
    """Which one-hot each slot should take so that wider slots hold more often changing codes.

    ``order[i]`` is the one-hot whose map slot ``i`` (of size ``code_sizes[i]``) takes;
    ties keep their order, so equal sizes and equal rates never move.

    Examples:
        >>> width_order((16, 4), (0.016, 0.054))
        [1, 0]
        >>> width_order((16, 4), (0.09, 0.01))
        [0, 1]
    """
    if len(code_sizes) != len(change_rates):
        raise ValueError(
            f"need one change rate per one-hot: {len(code_sizes)} sizes, {len(change_rates)} rates."
        )
    slots = sorted(range(len(code_sizes)), key=lambda i: -code_sizes[i])
    ranked = sorted(range(len(change_rates)), key=lambda i: -change_rates[i])
    order = [0] * len(code_sizes)
    for slot, onehot in zip(slots, ranked, strict=True):
        order[slot] = onehot
    # within a group of equal sizes keep the one-hots' own order
    for size in set(code_sizes):
        group = [i for i in range(len(code_sizes)) if code_sizes[i] == size]
        for slot, onehot in zip(group, sorted(order[i] for i in group), strict=True):
            order[slot] = onehot
    return order


class CandidateScreening(TrainerHook):
    """Trains ``num_candidates`` initialisations for ``candidate_steps`` each, then continues the best.

    Each candidate is scored by :meth:`score` (label-free, see the
    :class:`RepresentationTrainer` docstring) and saved to
    ``<out_dir>/checkpoints/candidate<i>.pt``. The state is the scored candidates.
    While screening it acts on every step, so the restart hooks after it wait.
    """

    default_name = "screening"

    def __init__(self) -> None:
        self.candidates: list[dict[str, Any]] = []

    @property
    def active(self) -> bool:
        """Whether candidates are still being trained."""
        n = self.trainer.config.num_candidates
        return n > 1 and len(self.candidates) < n

    @property
    def chosen(self) -> dict[str, Any] | None:
        """The highest-scoring candidate once screening has ended (else ``None``)."""
        if self.active or not self.candidates:
            return None
        return max(self.candidates, key=lambda c: c["score"])

    def score(self) -> float:
        """Label-free ``unique_information`` (nats) of the codes of evenly spaced stored play frames."""
        codes = self.trainer.play_codes(self.trainer.config.screening_frames)
        return float(code_information(codes)["unique_information"])

    def after_step(self, metrics: dict[str, float], logged: bool) -> bool:
        trainer = self.trainer
        if not self.active:
            return False
        if trainer.step - trainer.attempt_start >= trainer.config.candidate_steps:
            self._end_candidate(metrics)
        return True

    def _end_candidate(self, metrics: dict[str, float]) -> None:
        """Scores the current candidate; starts the next one or continues the best."""
        trainer = self.trainer
        score = self.score()
        path = trainer.checkpoint_path.with_name(f"candidate{len(self.candidates)}.pt")
        trainer.save(path)
        self.candidates.append(
            {
                "attempt": trainer.attempt,
                "step": trainer.step,
                "score": score,
                "loss": trainer.recent_loss(metrics),
                "path": str(path),
            }
        )
        trainer.logger.log_scalar("candidate_score", score, step=trainer.step)
        if self.active:
            trainer.new_init()
            return
        best = self.chosen
        trainer.continue_attempt(best["attempt"], best["path"], trainer.config.candidate_steps)

    def state_dict(self) -> dict[str, Any]:
        return {"candidates": list(self.candidates)}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.candidates = list(state.get("candidates", []))


class RepresentationTrainer(OfflineTrainer):
    """Trains a :class:`~dorp_rl.modules.DiscreteCodeEncoder` with :class:`~dorp_rl.objectives.CPCLoss`.

    Data come from a play buffer (collected, or loaded from ``config.data_dir``) through a
    :class:`~dorp_rl.data.FuturePairSampler` of the config's offsets. A ``buffer`` given
    instead must hold play data of the config's environment, with trajectories of at
    least ``max_offset`` steps (:func:`~dorp_rl.data.check_play_buffer`); it gets this
    trainer's sampler and generator. Logging, checkpoints and resume follow
    :class:`~dorp_rl.trainers.OfflineTrainer`: a torchrl CSV logger, a tqdm bar,
    ground-truth diagnostics every ``diagnostics_every`` steps, a checkpoint (config,
    weights, optimiser, step, RNG states, hook states) every ``checkpoint_every`` steps
    and at the end; ``train(resume=True)`` ends exactly where an uninterrupted run would.

    Five hooks (:attr:`~dorp_rl.trainers.OfflineTrainer.hooks`), called in this order
    after every step, each with its own checkpointed state:

    - ``"widths"`` (:class:`WidthOrder`, ``order_widths_at > 0``): once per attempt,
      gives the widest one-hots the object maps whose codes change most often along play.
    - ``"screening"`` (:class:`CandidateScreening`, ``num_candidates > 1``): some
      initialisations end in a poor local optimum that longer training does not leave,
      with no higher contrastive loss to show it. The trainer first trains
      ``num_candidates`` initialisations for ``candidate_steps`` steps each, scores each
      by :func:`~dorp_rl.metrics.code_information`'s ``unique_information`` of its codes on
      ``screening_frames`` evenly spaced stored play frames (the one-hots' entropies
      minus what pairs of them share; no ground truth), and continues only the highest.
      The chosen candidate's steps count towards ``num_steps``; the others add
      ``(num_candidates - 1) * candidate_steps`` steps. The score is a proxy, not a
      guarantee; no preset turns screening on.
    - ``"collapse"`` (:class:`CollapseRestart`): after ``collapse_check_after`` steps of
      an attempt, if the anchor codes of a batch use at most ``collapse_min_codes`` codes
      on some one-hot, or the loss is still within ``collapse_loss_margin`` of ``log B``,
      a warning names the cause, the encoder and similarity are re-initialised from a
      new seed and training restarts. If the last attempt collapses too, ``train``
      still returns, with ``collapsed=True`` and a ``RuntimeWarning``: a dead encoder is
      never returned silently.
    - ``"entanglement"`` (:class:`EntanglementRestart`): after
      ``entanglement_check_after`` steps of an attempt, if the mean ``map_entanglement``
      of the last five logged steps is above ``entanglement_threshold``, the attempt is
      restarted the same way; when the last attempt is entangled too, training goes on
      from the least entangled attempt.
    - ``"dead"`` (:class:`DeadOneHotRestart`): at an attempt's last step, if a one-hot
      (a two-code key bit included) gives all of ``dead_check_frames`` evenly spaced
      play frames one code, a new attempt of ``num_steps`` starts the same way.

    Restarts of every kind share ``max_restarts``; ``num_steps`` counts the steps of the
    last attempt, so restarts add steps rather than eat the budget. The result of
    :meth:`train` lists ``restarts``, ``candidates`` and ``chosen_candidate``.

    Examples:
        >>> from dorp_rl.trainers import RepresentationConfig, RepresentationTrainer
        >>> cfg = RepresentationConfig.for_env("rearrangement", 1, num_steps=20, num_frames=2000,
        ...     progress=False, out_dir="/tmp/dorp_doc_repr", diagnostics_every=10**9)
        >>> result = RepresentationTrainer(cfg).train()
        >>> result["step"], list(RepresentationTrainer.hook_names)
        (20, ['widths', 'screening', 'collapse', 'entanglement', 'dead'])
    """

    kind = "representation"
    progress_metric = "loss_cpc"
    state_keys = ("encoder", "similarity", "optimizer")
    hook_names = ("widths", "screening", "collapse", "entanglement", "dead")

    def __init__(
        self,
        config: RepresentationConfig,
        buffer: TensorDictReplayBuffer | None = None,
        logger: Any | None = None,
    ) -> None:
        config.validate()
        env = config.make_env(batch_size=(config.num_envs,))
        frame_shape = frame_shape_of(env)
        if tuple(config.encoder.frame_shape) != frame_shape:
            # The encoder is sized by the env's frames; the checkpoint's config says so.
            config = config.replace(encoder={"frame_shape": frame_shape})
        super().__init__(config, env, logger)
        self.device = torch.device(config.device)
        self.sampler = FuturePairSampler(config.min_offset, config.max_offset)
        if buffer is not None:
            check_play_buffer(buffer, self.env, min_trajectory_length=config.max_offset)
            buffer.set_sampler(self.sampler)
        else:
            buffer = collect_play_data(
                self.env,
                config.num_frames,
                directory=config.data_dir,
                seed=config.seed,
                trajectory_length=config.play_trajectory_length,
                sampler=self.sampler,
                batch_size=config.batch_size,
                progress=config.progress,
            )
        self.buffer = buffer
        self.buffer.set_rng(self.data_generator)
        #: what a first pass over the play frames saw (None when nothing was left open)
        open_settings = (
            self.config.counts_onehots()
            or self.config.encoder.map_stride is None
            or self.config.encoder.subtract_background is not False
        )
        self.scan = self.scan_play_frames() if open_settings else None
        #: the settings chosen from the env: field -> {"value", "why"}
        self.config, self.chosen = choose_code_settings(self.config, self.scan)
        if self.chosen:
            self.logger.log_hparams(
                {f"chosen.{k}": f"{c['value']} ({c['why']})" for k, c in self.chosen.items()}
            )
            self.out_dir.mkdir(parents=True, exist_ok=True)
            record = {"chosen": self.chosen, "scan": self.scan.to_dict() if self.scan else None}
            (self.out_dir / "chosen.json").write_text(json.dumps(record, indent=2) + "\n")
        self.attempt = 0
        self.inits = 1
        #: why training stopped before its end (every attempt collapsed), else None
        self.gave_up: str | None = None
        self.attempt_start = 0
        self.history_start = 0
        self.widths_hook = WidthOrder()
        self.screening_hook = CandidateScreening()
        self.collapse_hook = CollapseRestart()
        self.entanglement_hook = EntanglementRestart()
        self.dead_hook = DeadOneHotRestart()
        hooks = (
            self.widths_hook,
            self.screening_hook,
            self.collapse_hook,
            self.entanglement_hook,
            self.dead_hook,
        )
        for hook in hooks:
            hook.register(self)  # in this order: screening claims its steps before restarts
        self._build(seed=config.seed)

    # ------------------------------------------------------------------ #
    def _build(self, seed: int) -> None:
        """(Re-)creates encoder, similarity, loss and optimiser from ``seed``."""
        cfg = self.config
        torch.manual_seed(seed)
        self.encoder = DiscreteCodeEncoder(cfg.encoder_config()).to(self.device)
        self.encoder.env_config = env_identity(self.env)
        if cfg.encoder.subtract_background:
            self.encoder.set_background(self.scan.background)
        sim_kwargs: dict[str, Any] = {}
        if cfg.similarity == "dddp":
            sim_kwargs = {"alpha": cfg.alpha, "sign": cfg.dddp_sign}
        dim = self.encoder.num_onehots * self.encoder.max_codes
        self.similarity = make_similarity(cfg.similarity, dim, **sim_kwargs).to(self.device)
        self.loss = CPCLoss(
            self.encoder,
            self.similarity,
            gumbel_side=cfg.gumbel_side,
            gumbel_temperature=cfg.gumbel_temperature_start or cfg.gumbel_temperature,
            ce_temperature=cfg.ce_temperature,
            usage_weight=cfg.usage_weight,
            exclusivity_weight=cfg.exclusivity_weight,
            sparsity_weight=cfg.sparsity_weight,
            motion_weight=cfg.motion_weight,
        )
        groups = [{"params": list(self.encoder.parameters()), "lr": cfg.lr}]
        sim_params = list(self.similarity.parameters())
        if sim_params:
            groups.append({"params": sim_params, "lr": cfg.lr * cfg.similarity_lr_scale})
        self.optimizer = torch.optim.Adam(groups)
        self.data_generator.manual_seed(derive_seed(seed, 1))

    def _apply_learning_rates(self) -> None:
        """The config's learning rates on the optimiser's groups (after loading its state)."""
        lrs = [self.config.lr, self.config.lr * self.config.similarity_lr_scale]
        for group, lr in zip(self.optimizer.param_groups, lrs, strict=False):
            group["lr"] = lr

    def gumbel_temperature_at(self, step: int) -> float:
        """Exponential annealing from ``gumbel_temperature_start`` to ``gumbel_temperature``."""
        cfg = self.config
        if not cfg.gumbel_temperature_start or cfg.gumbel_anneal_steps <= 0:
            return cfg.gumbel_temperature
        frac = min(1.0, step / cfg.gumbel_anneal_steps)
        start, floor = cfg.gumbel_temperature_start, cfg.gumbel_temperature
        return float(start * (floor / start) ** frac)

    # ------------------------------------------------------------------ checkpoints
    def state_dict(self) -> dict[str, Any]:
        return {
            "encoder": self.encoder.state_dict(),
            "similarity": self.similarity.state_dict(),
            "optimizer": self.optimizer.state_dict(),
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        path = self.checkpoint_path
        load_module_state(self.encoder, state["encoder"], path, "encoder")
        load_module_state(self.similarity, state["similarity"], path, "similarity")
        try:
            self.optimizer.load_state_dict(state["optimizer"])
        except (ValueError, KeyError) as err:
            raise ValueError(
                f"checkpoint {path}: its optimizer state does not fit ({err})."
            ) from err
        self._apply_learning_rates()

    def extra_state(self) -> dict[str, Any]:
        return {
            **super().extra_state(),
            "attempt": self.attempt,
            "inits": self.inits,
            "attempt_start": self.attempt_start,
            "history_start": self.history_start,
            "gave_up": self.gave_up,
        }

    def load_extra_state(self, extra: dict[str, Any]) -> None:
        if "hooks" not in extra:  # older checkpoints kept restarts and candidates here
            restarts = list(extra.get("restarts", []))
            entangled = [r for r in restarts if "entangled" in str(r.get("reason", ""))]
            extra = {
                **extra,
                "hooks": {
                    "screening": {"candidates": list(extra.get("candidates", []))},
                    "collapse": {"restarts": [r for r in restarts if r not in entangled]},
                    "entanglement": {"restarts": entangled},
                },
            }
        super().load_extra_state(extra)
        self.attempt = int(extra.get("attempt", 0))
        self.inits = int(extra.get("inits", self.attempt + 1))
        restarts = self.restarts
        fallback = restarts[-1]["step"] if restarts else 0
        self.attempt_start = int(extra.get("attempt_start", fallback))
        self.history_start = int(extra.get("history_start", fallback))
        self.gave_up = extra.get("gave_up")
        if self.attempt:  # the weights to load belong to the restarted attempt's modules
            self._build(seed=self._attempt_seed(self.attempt))

    def in_current_terms(self, config: RepresentationConfig) -> RepresentationConfig:
        """A stored config with what it left open chosen as this trainer chose it (flat
        configs of the first versions, 16 x 16 frames only, left the stride open)."""
        return choose_code_settings(config, self.scan)[0]

    def check_checkpoint_config(self, stored: dict[str, Any]) -> None:
        stored_sizes = RepresentationConfig.from_dict(stored).code_sizes
        if stored_sizes != self.config.code_sizes:
            raise ValueError(
                f"checkpoint has code sizes {stored_sizes}, this trainer {self.config.code_sizes}."
            )

    def _attempt_seed(self, attempt: int) -> int:
        return derive_seed(self.config.seed, 7919 * attempt)

    # ------------------------------------------------------------------ attempts
    @property
    def restarts(self) -> list[dict[str, Any]]:
        """Every restart (collapse, entanglement and dead one-hot hooks), in step order."""
        hooks = (self.collapse_hook, self.entanglement_hook, self.dead_hook)
        return sorted((r for h in hooks for r in h.restarts), key=lambda r: r["step"])

    @property
    def candidates(self) -> list[dict[str, Any]]:
        """The screened candidates so far (see :class:`CandidateScreening`)."""
        return self.screening_hook.candidates

    @property
    def screening(self) -> bool:
        """Whether candidates are still being trained."""
        return self.screening_hook.active

    @property
    def chosen_candidate(self) -> dict[str, Any] | None:
        """The highest-scoring candidate once screening has ended (else ``None``)."""
        return self.screening_hook.chosen

    def scan_play_frames(self, count: int = 2048) -> FrameScan:
        """:func:`~dorp_rl.data.scan_frames` of ``count`` evenly spaced stored play frames."""
        stored = len(self.buffer)
        index = torch.linspace(0, stored - 1, min(stored, count)).round().long()
        pixels = self.buffer.storage[index]["pixels"]
        return scan_frames(pixels.reshape(-1, *pixels.shape[-3:]), max_frames=count)

    def play_codes(self, count: int) -> torch.Tensor:
        """Codes int64 ``[n, C]`` of ``n = min(count, stored)`` evenly spaced stored play
        frames (the screening score and the dead one-hot check read them)."""
        stored = len(self.buffer)
        count = min(stored, count)
        index = torch.linspace(0, stored - 1, count).round().long()
        pixels = self.buffer.storage[index]["pixels"]
        return self.encoder.encode(pixels.reshape(-1, *pixels.shape[-3:]))

    def play_change_rates(self, count: int) -> list[float]:
        """Per one-hot, the share of the first ``count`` stored play transitions that
        change its code (:func:`~dorp_rl.metrics.code_information.code_dynamics`)."""
        codes, next_codes = self.encode_play_transitions(count)[1]
        return [float(r) for r in code_dynamics(codes, next_codes)["change_rate"]]

    def encode_play_transitions(self, count: int) -> tuple[Any, tuple[torch.Tensor, torch.Tensor]]:
        """The first ``count`` stored play transitions and their codes (both frames, in
        eval mode; the encoder's mode is restored)."""
        sample = self.buffer[: min(len(self.buffer), count)]
        with eval_mode(self.encoder):
            transitions = encode_transitions(sample, self.encoder)
        return sample, transitions

    def permute_onehots(self, order: Sequence[int]) -> None:
        """One-hot ``i`` takes the object map (and the similarity's code positions) that
        ``order[i]`` had; the optimiser moments of the moved parameters restart."""
        encoder = self.encoder
        encoder.permute_onehots_(order)
        z = encoder.max_codes
        index = torch.tensor([o * z + k for o in order for k in range(z)])
        self.similarity.permute_(index)
        last = encoder.extractor[-1]
        for parameter in (last.weight, last.bias, *self.similarity.parameters()):
            self.optimizer.state.pop(parameter, None)

    def recent_loss(self, metrics: dict[str, float], window: int = 5) -> float:
        """Mean ``loss_cpc`` of this attempt's last ``window`` logged steps (else this step's).

        One batch can score above ``log B`` in a healthy run, more often at a low CE
        temperature, so the flat-loss check looks at a few logged steps, not one.
        """
        recent = [
            h["loss_cpc"]
            for h in self.history[-window:]
            if h["step"] > self.history_start and "loss_cpc" in h
        ]
        return sum(recent) / len(recent) if recent else float(metrics["loss_cpc"])

    def new_init(self) -> None:
        """Starts a new attempt: encoder, similarity and optimiser from the next attempt seed."""
        self.attempt = self.inits
        self.inits += 1
        self._build(seed=self._attempt_seed(self.attempt))
        self.attempt_start = self.history_start = self.step

    def continue_attempt(self, attempt: int, path: str, attempt_steps: int) -> None:
        """Goes on from an earlier ``attempt`` saved at ``path`` ``attempt_steps`` steps into
        it (its weights and optimiser; the step count runs on): its remaining steps end
        training."""
        if attempt != self.attempt:
            self.attempt = attempt
            self._build(seed=self._attempt_seed(attempt))
            payload = load_checkpoint(
                path, kind=self.kind, env_config=env_identity(self.env), state_keys=self.state_keys
            )
            self.load_state_dict(payload["state"])
        self.attempt_start = self.step - attempt_steps
        self.history_start = self.step

    @property
    def planned_steps(self) -> int:
        """Screening and the last attempt; a restart moves the end to its step + num_steps."""
        cfg = self.config
        screened = (cfg.num_candidates - 1) * cfg.candidate_steps if cfg.num_candidates > 1 else 0
        if self.gave_up is not None:
            return self.step
        return max(cfg.num_steps + screened, self.attempt_start + cfg.num_steps)

    def done(self) -> bool:
        if self.gave_up is not None:
            return True
        return not self.screening and self.step - self.attempt_start >= self.config.num_steps

    @property
    def surplus_may_die(self) -> bool:
        """Whether the number of one-hots was counted from the play frames (a count of
        pieces that move, which can exceed the objects a plan needs): a one-hot too many
        may then code nothing without the training having collapsed."""
        return "num_onehots" in self.chosen

    def collapse_advice(self, reason: str) -> str:
        """Why training stops after every attempt collapsed, what was seen and what to change."""
        cfg = self.config
        seen = f"the play frames ({cfg.encoder.frame_shape[1]} x {cfg.encoder.frame_shape[2]}) " + (
            f"show {self.scan.pieces} moving piece(s), the smallest {self.scan.smallest_piece} "
            f"pixel(s) across, on {self.scan.foreground_share:.1%} of the pixels"
            if self.scan is not None
            else "were not scanned"
        )
        return (
            f"the codes collapsed in all {len(self.restarts) + 1} attempts (the last at step "
            f"{self.step}: {reason}); training stops here instead of running to step "
            f"{self.attempt_start + cfg.num_steps}. Seen: {seen}. The codes learn what changes "
            "between play frames a few steps apart; to change: more play data (num_frames) or "
            "longer offsets (max_offset) where a step changes few pixels, frames rendered larger "
            "where objects are a pixel or two, fewer codes per one-hot (encoder.code_sizes) "
            "where objects take few places, or a set number of one-hots (num_onehots)."
        )

    # ------------------------------------------------------------------ steps
    def _batch(self) -> TensorDict:
        anchor, future, _ = future_pairs(self.buffer.sample(self.config.batch_size))
        return TensorDict(
            pixels=anchor.to(self.device),
            future_pixels=future.to(self.device),
            batch_size=[anchor.shape[0]],
        )

    def train_step(self) -> dict[str, float]:
        """One gradient step; returns the detached metrics."""
        self.loss.gumbel_temperature = self.gumbel_temperature_at(self.step)
        out = self.loss(self._batch())
        total = sum(v for k, v in out.items() if k.startswith("loss_"))
        self.optimizer.zero_grad(set_to_none=True)
        total.backward()
        parameters = [*self.encoder.parameters(), *self.similarity.parameters()]
        self.check_gradients(total, parameters)
        self.optimizer.step()
        self.check_weights(self.encoder, self.similarity)
        self.step += 1
        return {k: float(v.detach()) for k, v in out.items()}

    def train(self, resume: bool = False) -> dict[str, Any]:
        """Runs ``config.num_steps`` steps of the last attempt; returns metrics and diagnostics.

        The result also holds ``attempt``, ``restarts`` and ``collapsed`` (the last
        attempt still looks collapsed; a ``RuntimeWarning`` says so too), and, as for every
        :class:`~dorp_rl.trainers.OfflineTrainer`, ``resumed_from_step`` (the checkpoint's
        step a resume went on from, ``None`` for a fresh run).
        """
        result = super().train(resume=resume)
        dead = (result.get("evaluation") or {}).get("dead_onehots") or []
        if dead:
            warnings.warn(
                f"one-hot(s) {dead} never change along the play data: they code nothing "
                "about play (dead); two-code one-hots such as a key bit are counted too.",
                RuntimeWarning,
                stacklevel=2,
            )
        metrics = result["metrics"]
        final_reason = self.collapse_hook.reason(metrics) if metrics else None
        if self.collapse_hook.partial(final_reason):
            final_reason = None  # a surplus one-hot of a counted set: listed as dead above
        if self.gave_up is not None:
            warnings.warn(self.gave_up, RuntimeWarning, stacklevel=2)
        elif final_reason is not None:
            warnings.warn(
                f"representation still collapsed after {len(self.restarts)} restart(s): "
                f"{final_reason}.",
                RuntimeWarning,
                stacklevel=2,
            )
        return {
            **result,
            "attempt": self.attempt,
            "restarts": self.restarts,
            "candidates": self.candidates,
            "chosen_candidate": self.chosen_candidate,
            "collapsed": final_reason is not None,
            "gave_up": self.gave_up,
            "chosen": self.chosen,
            "diagnostics": result["evaluation"],
        }

    @property
    def evaluate_every(self) -> int:
        return self.config.diagnostics_every

    def evaluate(self) -> dict[str, Any]:
        """Diagnostics of the current encoder: always the label-free code dynamics of
        ``diagnostics_samples`` play transitions (``code_dynamics``: codes used, change
        and undo rates and ``dead`` one-hots per one-hot, two-code ones included,
        :func:`~dorp_rl.eval.code_dynamics`), and the ground-truth diagnostics when the
        env's profile declares them (:func:`diagnose`) or maps states to object
        positions (``objects``: :func:`~dorp_rl.eval.object_diagnostics` on the play
        data's own states; never computed on another env's states)."""
        env = self.config.make_env()
        result: dict[str, Any] = {}
        if self.config.profile.diagnostics is not None:
            result = diagnose(
                env,
                self.encoder,
                num_samples=self.config.diagnostics_samples,
                seed=self.config.seed,
                profile=self.config.profile,
            )
        # encoded once, for both
        sample, transitions = self.encode_play_transitions(self.config.diagnostics_samples)
        dynamics = play_code_dynamics(sample, self.encoder, transitions=transitions)
        result["code_dynamics"] = dynamics
        result["dead_onehots"] = [i for i, dead in enumerate(dynamics["dead"]) if dead]
        objects = self.config.profile.objects
        if objects is not None:  # labels from this env's own play states
            labelled = play_object_diagnostics(
                sample, self.encoder, objects, transitions=transitions
            )
            result["objects"] = labelled
            for key in ("selectivity", "purity", "min_purity"):
                result.setdefault(key, labelled[key])
        return result

    diagnose = evaluate


def load_encoder(
    path: str | Path, env: EnvBase | None = None, device: str | torch.device = "cpu"
) -> DiscreteCodeEncoder:
    """The trained encoder of a representation checkpoint, in eval mode.

    Args:
        path: a checkpoint written by :class:`RepresentationTrainer`.
        env: if given, the checkpoint must come from this environment.
        device: where to put the encoder.

    Raises:
        FileNotFoundError: no file at ``path``.
        ValueError: a damaged, incomplete or non-finite file
            (:class:`~dorp_rl.integrity.IntegrityError`), another kind of checkpoint or
            another environment.
    """
    device = check_device(device)
    kind = RepresentationTrainer.kind
    cfg, state, payload = read_trained(path, kind, RepresentationConfig, env, "encoder")
    encoder = DiscreteCodeEncoder(cfg.encoder_config())
    load_module_state(encoder, state, path, "encoder")
    encoder.env_config = dict(payload.get("env_config") or {}) or None
    return encoder.to(device).eval()
