"""RepresentationTrainer: learns DORP's discrete codes from play data with CPCLoss."""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import torch
from tensordict import TensorDict
from torchrl.data import TensorDictReplayBuffer

from dorp_rl.checkpoint import load_checkpoint, load_module_state
from dorp_rl.data import FuturePairSampler, check_play_buffer, collect_play_data, future_pairs
from dorp_rl.envs import ENV_NAMES, GridWorldEnv, KeyRoomEnv, env_class, make_env
from dorp_rl.eval.code_information import code_information
from dorp_rl.modules import DiscreteCodeEncoder, EncoderConfig, make_similarity
from dorp_rl.modules.similarity import SIMILARITIES
from dorp_rl.objectives import CPCLoss
from dorp_rl.trainers.base import EnvConfigMixin, Trainer
from dorp_rl.validation import Choice, Device, Flag, Float, Int, Seed, Text, derive_seed

#: Upper bound of ``num_objects`` (the default colour palette).
_MAX_OBJECTS = 8

# What the key-room presets share (docs/RESULTS.md, "key-wall"): the motion-coverage
# term, which puts the agent's object map on the agent, the map-sparsity and code-usage
# terms, and a restart when the agent one-hot is left with a few codes (without the usage
# term, runs that used 3-5 codes of 16 at step 300-500 stayed there).
KEY_ROOM_RECIPE: dict[str, Any] = {
    "max_offset": 4,
    "motion_weight": 1.0,
    "sparsity_weight": 5.0,
    "usage_weight": 1.0,
    "num_steps": 3000,
    "collapse_check_after": 500,
    "collapse_min_codes": 4,
}


@dataclass
class RepresentationConfig(EnvConfigMixin):
    """Everything that defines a representation run (a CleanRL-style flat dataclass).

    Use the presets :meth:`rearrangement`, :meth:`key_wall` and :meth:`key_corridor`, then
    override fields with :func:`dataclasses.replace`.
    """

    FIELD_RULES = {
        "env": Choice(ENV_NAMES),
        "num_objects": Int(low=1, high=_MAX_OBJECTS, optional=True),
        "num_frames": Int(low=1),
        "num_envs": Int(low=1),
        "trajectory_length": Int(low=1, optional=True),
        "min_offset": Int(low=1),
        "max_offset": Int(low=1),
        "data_dir": Text(optional=True),
        "code_size": Int(low=2),
        "encoder_preset": Choice(("small", "authors")),
        "map_competition": Choice(("sigmoid", "softmax")),
        "extractor_kernel_size": Int(low=1),
        "similarity": Choice(tuple(SIMILARITIES)),
        "dddp_sign": Choice(("paper", "authors")),
        "alpha": Float(low=1.0),
        "gumbel_side": Choice(("positive", "anchor")),
        "gumbel_temperature": Float(low=0.0, low_open=True),
        "gumbel_temperature_start": Float(low=0.0, low_open=True, optional=True),
        "gumbel_anneal_steps": Int(low=0),
        "ce_temperature": Float(low=0.0, low_open=True),
        "usage_weight": Float(low=0.0),
        "exclusivity_weight": Float(low=0.0),
        "sparsity_weight": Float(low=0.0),
        "motion_weight": Float(low=0.0),
        "batch_size": Int(low=2),
        "lr": Float(low=0.0),
        "similarity_lr_scale": Float(low=0.0),
        "num_steps": Int(low=1),
        "seed": Seed(),
        "device": Device(),
        "out_dir": Text(),
        "log_every": Int(low=1),
        "diagnostics_every": Int(low=1),
        "diagnostics_samples": Int(low=1),
        "checkpoint_every": Int(low=1),
        "progress": Flag(),
        "collapse_check_after": Int(low=0),
        "collapse_min_codes": Int(low=0),
        "collapse_loss_margin": Float(),
        "entanglement_check_after": Int(low=0),
        "entanglement_threshold": Float(low=0.0),
        "max_restarts": Int(low=0),
        "num_candidates": Int(low=1),
        "candidate_steps": Int(low=1),
        "screening_frames": Int(low=1),
    }

    # environment and play data
    env: str = "rearrangement"
    """environment: rearrangement, key-wall or key-corridor"""
    num_objects: int | None = None
    """objects of a rearrangement env (None: 2; 1 for the key rooms)"""
    num_frames: int = 100_000
    """play transitions to collect"""
    num_envs: int = 64
    """envs collecting play data side by side"""
    trajectory_length: int | None = None
    """steps per play trajectory (None: the env's, 1 for rearrangement)"""
    min_offset: int = 1
    """smallest offset k of the (o_t, o_t+k) training pairs"""
    max_offset: int = 1
    """largest offset k of the training pairs"""
    data_dir: str | None = None
    """folder of the play data (None: kept in memory)"""
    # encoder
    code_size: int = 32
    """codes per one-hot"""
    encoder_preset: str = "small"
    """encoder size: small or authors"""
    map_competition: str = "sigmoid"
    """how object maps share a pixel: sigmoid (independent) or softmax"""
    extractor_kernel_size: int = 3
    """kernel size of the object-map extractor (odd)"""
    # loss
    similarity: str = "dddp"
    """code similarity of the CPC loss: dddp, full or identity"""
    dddp_sign: str = "paper"
    """sign convention of DDDP: paper or authors"""
    alpha: float = 1.0
    """DDDP's alpha (dddp only)"""
    gumbel_side: str = "positive"
    """which side of a pair gets hard Gumbel codes: positive or anchor"""
    gumbel_temperature: float = 0.1
    """Gumbel-softmax temperature"""
    gumbel_temperature_start: float | None = None
    """start of a Gumbel temperature annealing (None: no annealing)"""
    gumbel_anneal_steps: int = 0
    """steps of the Gumbel temperature annealing"""
    ce_temperature: float = 0.1
    """temperature of the contrastive cross-entropy"""
    usage_weight: float = 0.0
    """weight of the code-usage term"""
    exclusivity_weight: float = 0.0
    """weight of the map-exclusivity term (objects on separate maps)"""
    sparsity_weight: float = 0.0
    """weight of the map-sparsity term"""
    motion_weight: float = 0.0
    """weight of the motion-coverage term (key rooms: the agent map on the agent)"""
    # optimisation
    batch_size: int = 128
    """pairs per step"""
    lr: float = 1e-3
    """Adam learning rate"""
    similarity_lr_scale: float = 1.0
    """learning rate of the similarity, as a multiple of lr"""
    num_steps: int = 2000
    """training steps (of the last attempt)"""
    # bookkeeping
    seed: int = 0
    """seed of play data, initialisation and sampling"""
    device: str = "cpu"
    """torch device"""
    out_dir: str = "outputs/representation"
    """folder of checkpoints and logs"""
    log_every: int = 50
    """steps between logged metrics"""
    diagnostics_every: int = 500
    """steps between ground-truth diagnostics"""
    diagnostics_samples: int = 2048
    """states drawn for the diagnostics"""
    checkpoint_every: int = 500
    """steps between checkpoints"""
    progress: bool = True
    """show a progress bar"""
    # collapse detection
    collapse_check_after: int = 300
    """steps of an attempt before the collapse check"""
    collapse_min_codes: int = 2
    """a one-hot using at most this many codes counts as collapsed"""
    collapse_loss_margin: float = 0.05
    """a loss within this margin of log(batch) counts as collapsed"""
    entanglement_check_after: int = 600
    """steps of an attempt before the entanglement check"""
    entanglement_threshold: float = 0.07
    """map entanglement above this restarts the attempt"""
    max_restarts: int = 3
    """restarts after a collapse or entanglement"""
    # initialisation screening
    num_candidates: int = 1
    """initialisations screened before training (1: no screening)"""
    candidate_steps: int = 1000
    """steps per screened initialisation"""
    screening_frames: int = 8192
    """play frames scoring each screened initialisation"""

    @classmethod
    def rearrangement(cls, num_objects: int = 2, **overrides: Any) -> RepresentationConfig:
        """k-object rearrangement: one-step play transitions, one one-hot per object.

        With several objects the map exclusivity term is on (weight 3) and the maps compete
        per pixel (softmax): without them most seeds learned one-hots that each follow
        several objects (see docs/RESULTS.md).
        """
        base = cls(
            env="rearrangement",
            num_objects=num_objects,
            code_size=16 if num_objects == 1 else 32,
            exclusivity_weight=3.0 if num_objects > 1 else 0.0,
            map_competition="softmax" if num_objects > 1 else "sigmoid",
        )
        return replace(base, **overrides)

    @classmethod
    def key_wall(cls, **overrides: Any) -> RepresentationConfig:
        """Key-wall: 1000-step random walks, a 16-code agent one-hot plus a 2-way key bit.

        Adam 1e-3 for 3000 steps with the motion-coverage term (weight 1), which puts the
        agent's object map on the agent (mean map value 0.999 on its pixel, where without
        it the map held 0.0003 there and the key decided the code at region borders), the
        map-sparsity term (weight 5) and the code-usage term (weight 1). A collapse
        restart fires when the agent one-hot uses at most 4 codes after 500 steps. Met
        the goal in 4 of 5 seeds (the fifth had two codes that were not connected
        regions); see docs/RESULTS.md, "key-wall".
        """
        base = cls(
            env="key-wall",
            num_objects=1,
            code_size=16,
            num_frames=64_000,
            **KEY_ROOM_RECIPE,
        )
        return replace(base, **overrides)

    @classmethod
    def key_corridor(cls, **overrides: Any) -> RepresentationConfig:
        """Key-corridor: 1500-step random walks, a 32-code agent one-hot plus a key bit.

        Same recipe as :meth:`key_wall`. Over seeds 0-2 (3000 steps) the agent is learned
        (8-15 codes) and the key bit in every seed, but only seed 0 met the key-wall goal:
        seed 1 had a code that was not a connected region, seed 2's agent one-hot changed
        with the key on 63% of key events.
        """
        base = cls(
            env="key-corridor",
            num_objects=1,
            code_size=32,
            num_frames=96_000,
            **KEY_ROOM_RECIPE,
        )
        return replace(base, **overrides)

    def encoder_config(self) -> EncoderConfig:
        """The encoder this config trains (preset, code sizes, map competition)."""
        preset = EncoderConfig.small if self.encoder_preset == "small" else EncoderConfig.authors
        enc_cfg = preset(self.code_sizes)
        enc_cfg.map_competition = self.map_competition
        enc_cfg.kernel_size = self.extractor_kernel_size
        return enc_cfg

    @property
    def code_sizes(self) -> tuple[int, ...]:
        if self.env == "rearrangement":
            return (self.code_size,) * self.num_objects
        return (self.code_size, 2)

    @property
    def play_trajectory_length(self) -> int:
        """Steps of each play trajectory: ``trajectory_length`` or the env's default."""
        return self.trajectory_length or env_class(self.env).PLAY_TRAJECTORY_LENGTH

    def check_relations(self) -> None:
        """Rules between fields; each message names the fields and what they allow."""
        self.check_num_objects()
        if not self.min_offset <= self.max_offset <= self.play_trajectory_length:
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
        if self.extractor_kernel_size % 2 == 0:
            raise ValueError(
                f"extractor_kernel_size must be an odd integer >= 1, got {self.extractor_kernel_size}."
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

    def make_env(self, **kwargs: Any) -> GridWorldEnv:
        """The environment this config trains on."""
        return make_env(self.env, num_objects=self.num_objects, device=self.device, **kwargs)


def diagnose(
    env: GridWorldEnv, encoder: DiscreteCodeEncoder, num_samples: int = 2048, seed: int = 0
) -> dict:
    """Ground-truth diagnostics of an encoder's codes on ``env`` (see :mod:`dorp_rl.eval`)."""
    from dorp_rl.eval.diagnostics import key_room_diagnostics, rearrangement_diagnostics

    encode = encoder.encode
    if isinstance(env, KeyRoomEnv):
        result = key_room_diagnostics(env, encode)
    else:
        result = rearrangement_diagnostics(env, encode, num_samples=num_samples, seed=seed)
    return result.to_dict() if hasattr(result, "to_dict") else dict(result)


class RepresentationTrainer(Trainer):
    """Trains a :class:`~dorp_rl.modules.DiscreteCodeEncoder` with :class:`~dorp_rl.objectives.CPCLoss`.

    Data come from a play buffer (collected, or loaded from ``config.data_dir``) through a
    :class:`~dorp_rl.data.FuturePairSampler` of the config's offsets. A ``buffer`` given
    instead must hold play data of the config's environment, with trajectories of at
    least ``max_offset`` steps (:func:`~dorp_rl.data.check_play_buffer`); it gets this
    trainer's sampler and generator. Logging, checkpoints and resume follow
    :class:`~dorp_rl.trainers.Trainer`: a torchrl CSV logger, a tqdm bar, ground-truth
    diagnostics every ``diagnostics_every`` steps, a checkpoint (config, weights,
    optimiser, step, RNG states, restarts) every ``checkpoint_every`` steps and at the
    end; ``train(resume=True)`` ends exactly where an uninterrupted run would.

    Collapse: after ``collapse_check_after`` steps of an attempt, if the anchor codes of a
    batch use at most ``collapse_min_codes`` codes on some one-hot, or the loss is still
    within ``collapse_loss_margin`` of ``log B`` (nothing learned), the attempt is declared
    collapsed: a warning names the cause, the encoder and similarity are re-initialised
    from a new seed and training restarts (up to ``max_restarts`` times). If the last
    attempt collapses too, ``train`` still returns, with ``collapsed=True`` in its result
    and a ``RuntimeWarning``: a dead encoder is never returned silently.

    Entanglement (with the exclusivity term on): after ``entanglement_check_after`` steps
    of an attempt, if the mean ``map_entanglement`` of the last five logged steps is above
    ``entanglement_threshold``, some object map still follows several objects or none;
    such attempts rarely recover, so they are restarted the same way. ``num_steps``
    counts the steps of the last attempt: restarts add steps rather than eat the budget.

    Screening (``num_candidates > 1``): some initialisations end in a poor local optimum
    that longer training does not leave (key-wall: the agent one-hot also codes the key,
    or uses few codes), with no higher contrastive loss to show it. The trainer then
    first trains ``num_candidates`` initialisations for ``candidate_steps`` steps each,
    scores each by :func:`~dorp_rl.eval.code_information`'s ``unique_information`` of
    its codes on ``screening_frames`` evenly spaced stored play frames (the one-hots'
    entropies minus what pairs of them share; no ground truth), and continues only the
    highest (the others' checkpoints stay in ``<out_dir>/checkpoints/candidate<i>.pt``).
    The chosen candidate's steps count towards ``num_steps``; the others add
    ``(num_candidates - 1) * candidate_steps`` steps. The result lists every candidate
    with its score and loss under ``candidates``, the one continued under
    ``chosen_candidate`` (a collapse restart after screening still starts afresh). The
    score is a proxy, not a guarantee: on key-wall (12 candidates of 1000 steps, with the
    preset of the time) the chosen run met the goal in 2 of 5 seeds, as without
    screening, and the highest-scoring final run was one that missed it
    (docs/RESULTS.md, "key-wall"); no preset turns it on.

    Examples:
        >>> from dorp_rl.trainers import RepresentationConfig, RepresentationTrainer
        >>> cfg = RepresentationConfig.rearrangement(1, num_steps=20, num_frames=2000,
        ...     progress=False, out_dir="/tmp/dorp_doc_repr", diagnostics_every=10**9)
        >>> result = RepresentationTrainer(cfg).train()
        >>> result["step"]
        20
    """

    kind = "representation"
    progress_metric = "loss_cpc"
    state_keys = ("encoder", "similarity", "optimizer")

    def __init__(
        self,
        config: RepresentationConfig,
        buffer: TensorDictReplayBuffer | None = None,
        logger: Any | None = None,
    ) -> None:
        config.validate()
        super().__init__(config, config.make_env(batch_size=(config.num_envs,)), logger)
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
                trajectory_length=config.trajectory_length,
                sampler=self.sampler,
                batch_size=config.batch_size,
                progress=config.progress,
            )
        self.buffer = buffer
        self.buffer.set_rng(self.data_generator)
        self.attempt = 0
        self.inits = 1
        self.attempt_start = 0
        self.history_start = 0
        self.restarts: list[dict[str, Any]] = []
        self.candidates: list[dict[str, Any]] = []
        self._build(seed=config.seed)

    # ------------------------------------------------------------------ #
    def _build(self, seed: int) -> None:
        """(Re-)creates encoder, similarity, loss and optimiser from ``seed``."""
        cfg = self.config
        torch.manual_seed(seed)
        self.encoder = DiscreteCodeEncoder(cfg.encoder_config()).to(self.device)
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
            "restarts": self.restarts,
            "candidates": self.candidates,
        }

    def load_extra_state(self, extra: dict[str, Any]) -> None:
        super().load_extra_state(extra)
        self.attempt = int(extra.get("attempt", 0))
        self.inits = int(extra.get("inits", self.attempt + 1))
        self.restarts = list(extra.get("restarts", []))
        self.candidates = list(extra.get("candidates", []))
        fallback = self.restarts[-1]["step"] if self.restarts else 0
        self.attempt_start = int(extra.get("attempt_start", fallback))
        self.history_start = int(extra.get("history_start", fallback))
        if self.attempt:  # the weights to load belong to the restarted attempt's modules
            self._build(seed=self._attempt_seed(self.attempt))

    def check_checkpoint_config(self, stored: dict[str, Any]) -> None:
        stored_sizes = RepresentationConfig.from_dict(stored).code_sizes
        if stored_sizes != self.config.code_sizes:
            raise ValueError(
                f"checkpoint has code sizes {stored_sizes}, this trainer {self.config.code_sizes}."
            )

    def _attempt_seed(self, attempt: int) -> int:
        return derive_seed(self.config.seed, 7919 * attempt)

    # ------------------------------------------------------------------ collapse
    def collapse_reason(self, metrics: dict[str, float], attempt_steps: int) -> str | None:
        """Why the current attempt looks collapsed (``None`` if it does not)."""
        cfg = self.config
        if attempt_steps < cfg.collapse_check_after:
            return None
        if metrics["min_codes_in_batch"] <= cfg.collapse_min_codes:
            return (
                f"a one-hot uses only {int(metrics['min_codes_in_batch'])} code(s) in a batch "
                f"of {cfg.batch_size}"
            )
        loss = self.recent_loss(metrics)
        if loss > math.log(cfg.batch_size) - cfg.collapse_loss_margin:
            return (
                f"the loss is flat at log B = {math.log(cfg.batch_size):.3f} (mean of the "
                f"last logged steps {loss:.3f})"
            )
        return None

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

    def entanglement_reason(self, attempt_steps: int) -> str | None:
        """Why the object maps look entangled (``None`` if they do not or it is too early)."""
        cfg = self.config
        recent = [
            h["map_entanglement"]
            for h in self.history[-5:]
            if h["step"] > self.history_start and "map_entanglement" in h
        ]
        if attempt_steps < cfg.entanglement_check_after or len(recent) < 5:
            return None
        value = sum(recent) / len(recent)
        if value > cfg.entanglement_threshold:
            return (
                f"the object maps are still entangled (map_entanglement {value:.3f} > "
                f"{cfg.entanglement_threshold}): some map follows several objects or none"
            )
        return None

    def _new_init(self) -> None:
        """Re-initialises encoder, similarity and optimiser from the next attempt seed."""
        self.attempt = self.inits
        self.inits += 1
        self._build(seed=self._attempt_seed(self.attempt))
        self.attempt_start = self.history_start = self.step

    @property
    def screening(self) -> bool:
        """Whether candidates are still being trained (see the class docstring)."""
        n = self.config.num_candidates
        return n > 1 and len(self.candidates) < n

    @property
    def chosen_candidate(self) -> dict[str, Any] | None:
        """The highest-scoring candidate once screening has ended (else ``None``)."""
        if self.screening or not self.candidates:
            return None
        return max(self.candidates, key=lambda c: c["score"])

    def screening_score(self) -> float:
        """Label-free ``unique_information`` (nats) of the codes of evenly spaced stored play frames."""
        stored = len(self.buffer)
        count = min(stored, self.config.screening_frames)
        index = torch.linspace(0, stored - 1, count).round().long()
        pixels = self.buffer.storage[index]["pixels"]
        codes = self.encoder.encode(pixels.reshape(-1, *pixels.shape[-3:]))
        return float(code_information(codes)["unique_information"])

    def _end_candidate(self, metrics: dict[str, float]) -> None:
        """Scores the current candidate; starts the next one or continues the best."""
        score = self.screening_score()
        path = self.checkpoint_path.with_name(f"candidate{len(self.candidates)}.pt")
        self.save(path)
        self.candidates.append(
            {
                "attempt": self.attempt,
                "step": self.step,
                "score": score,
                "loss": self.recent_loss(metrics),
                "path": str(path),
            }
        )
        self.logger.log_scalar("candidate_score", score, step=self.step)
        if self.screening:
            self._new_init()
            return
        best = self.chosen_candidate
        if best["attempt"] != self.attempt:
            self.attempt = best["attempt"]
            self._build(seed=self._attempt_seed(self.attempt))
            payload = load_checkpoint(
                best["path"],
                kind=self.kind,
                env_config=self.env.config(),
                state_keys=self.state_keys,
            )
            self.load_state_dict(payload["state"])
        self.attempt_start = self.step - self.config.candidate_steps
        self.history_start = self.step

    def after_step(self, metrics: dict[str, float], logged: bool) -> None:
        """Screens candidates, restarts a collapsed or entangled attempt (see the class docstring)."""
        cfg = self.config
        if self.screening:
            if self.step - self.attempt_start >= cfg.candidate_steps:
                self._end_candidate(metrics)
            return
        reason = self.collapse_reason(metrics, self.step - self.attempt_start)
        if logged:
            reason = reason or self.entanglement_reason(self.step - self.attempt_start)
        if reason is None or len(self.restarts) >= cfg.max_restarts:
            return
        self._new_init()
        self.restarts.append({"step": self.step, "attempt": self.attempt, "reason": reason})
        warnings.warn(
            f"representation restarted at step {self.step} ({reason}); re-initialising "
            f"encoder and similarity (restart {len(self.restarts)}/{cfg.max_restarts}).",
            RuntimeWarning,
            stacklevel=4,
        )
        self.logger.log_scalar("restart", float(len(self.restarts)), step=self.step)

    @property
    def planned_steps(self) -> int:
        cfg = self.config
        screened = (cfg.num_candidates - 1) * cfg.candidate_steps if cfg.num_candidates > 1 else 0
        return cfg.num_steps + screened

    def done(self) -> bool:
        return not self.screening and self.step - self.attempt_start >= self.config.num_steps

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
        attempt still looks collapsed; a ``RuntimeWarning`` says so too).
        """
        result = super().train(resume=resume)
        metrics = result["metrics"]
        final_reason = (
            self.collapse_reason(metrics, self.step - self.attempt_start) if metrics else None
        )
        if final_reason is not None:
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
            "diagnostics": result["evaluation"],
        }

    @property
    def evaluate_every(self) -> int:
        return self.config.diagnostics_every

    def evaluate(self) -> dict[str, Any]:
        """The ground-truth diagnostics of the current encoder (see :func:`diagnose`)."""
        return diagnose(
            self.config.make_env(),
            self.encoder,
            num_samples=self.config.diagnostics_samples,
            seed=self.config.seed,
        )

    diagnose = evaluate


def load_encoder(
    path: str | Path, env: GridWorldEnv | None = None, device: str | torch.device = "cpu"
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
    payload = load_checkpoint(
        path,
        kind="representation",
        env_config=None if env is None else env.config(),
        state_keys=("encoder",),
    )
    cfg = RepresentationConfig.from_dict(payload["config"])
    encoder = DiscreteCodeEncoder(cfg.encoder_config())
    load_module_state(encoder, payload["state"]["encoder"], path, "encoder")
    return encoder.to(device).eval()
