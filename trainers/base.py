"""Trainer: the loop, logging, checkpoint and resume conventions every dorp-rl trainer shares."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import torch

from dorp_rl.checkpoint import load_checkpoint, save_checkpoint
from dorp_rl.envs import GridWorldEnv


class Trainer:
    """Base class of :class:`RepresentationTrainer` and :class:`WorldModelTrainer`.

    A subclass sets :attr:`kind` (the checkpoint kind), builds its model, loss and
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
      and ends exactly where an uninterrupted run with the same seed would.

    The config must have ``to_dict``, ``num_steps``, ``log_every``,
    ``checkpoint_every``, ``out_dir`` and ``progress``.
    """

    kind = "base"
    #: the metric shown in the progress bar
    progress_metric = "loss"

    def __init__(self, config: Any, env: GridWorldEnv, logger: Any | None = None) -> None:
        self.config = config
        self.env = env
        self.out_dir = Path(config.out_dir)
        self.data_generator = torch.Generator()
        if logger is None:
            from torchrl.record.loggers import CSVLogger

            logger = CSVLogger(exp_name="logs", log_dir=str(self.out_dir))
        self.logger = logger
        self.step = 0
        self.history: list[dict[str, float]] = []
        #: the scalar results of every evaluation, with the step it was made at
        self.evaluations: list[dict[str, float]] = []
        self.last_evaluation: dict[str, Any] = {}

    # ------------------------------------------------------------------ hooks
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
        """Called after every step (after logging): restarts, schedules, ..."""

    def extra_state(self) -> dict[str, Any]:
        """JSON-like state saved with checkpoints besides the state dicts."""
        return {"history": self.history, "evaluations": self.evaluations}

    def load_extra_state(self, extra: dict[str, Any]) -> None:
        self.history = list(extra.get("history", []))
        self.evaluations = list(extra.get("evaluations", []))

    def check_checkpoint_config(self, stored: dict[str, Any]) -> None:
        """Raises ``ValueError`` if a stored config cannot be loaded into this trainer."""

    # ------------------------------------------------------------------ checkpoints
    @property
    def checkpoint_path(self) -> Path:
        return self.out_dir / "checkpoints" / "last.pt"

    def save(self, path: str | Path | None = None) -> Path:
        """Writes a checkpoint (default: ``<out_dir>/checkpoints/last.pt``)."""
        return save_checkpoint(
            path or self.checkpoint_path,
            kind=self.kind,
            config=self.config.to_dict(),
            env_config=self.env.config(),
            state=self.state_dict(),
            step=self.step,
            rng={"torch": torch.get_rng_state(), "data": self.data_generator.get_state()},
            extra=self.extra_state(),
        )

    def load(self, path: str | Path | None = None) -> dict[str, Any]:
        """Restores a checkpoint of this trainer and returns its payload.

        Raises:
            ValueError: a corrupted file, another kind of checkpoint, another
                environment, or a config this trainer cannot take.
        """
        payload = load_checkpoint(
            path or self.checkpoint_path, kind=self.kind, env_config=self.env.config()
        )
        self.check_checkpoint_config(payload["config"])
        self.load_extra_state(payload["extra"])
        self.load_state_dict(payload["state"])
        self.step = int(payload["step"])
        torch.set_rng_state(payload["rng"]["torch"])
        self.data_generator.set_state(payload["rng"]["data"])
        return payload

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

        Args:
            resume: continue from ``<out_dir>/checkpoints/last.pt`` if it exists.
        """
        cfg = self.config
        if resume and self.checkpoint_path.exists():
            self.load()
        bar = None
        if cfg.progress:
            from tqdm.auto import tqdm

            total = self.planned_steps
            bar = tqdm(total=total, initial=min(self.step, total), desc=self.kind)
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
                    bar.update(1)
        finally:
            if bar is not None:
                bar.close()
        self.save()
        if evaluated_at != self.step and self.evaluate_at_end:
            self._evaluate_and_log()
        return {"step": self.step, "metrics": metrics, "evaluation": self.last_evaluation}
