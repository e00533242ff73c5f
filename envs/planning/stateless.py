"""Any stateless TorchRL env as its own true dynamics (:class:`StatelessEnvModel`): its
steps on any leading batch shape, every entry it declares handed to its step.
"""

from __future__ import annotations

import re

import torch
from tensordict import TensorDictBase
from torchrl.data import Categorical, Composite, Unbounded
from torchrl.envs import EnvBase

from dorp_rl.envs.grid_base import (
    CheckedRolloutLength,
)
from dorp_rl.envs.spec import DiscreteActions
from dorp_rl.validation import (
    MissingKeyError,
)

__all__ = [
    "StatelessEnvModel",
]


class StatelessEnvModel(CheckedRolloutLength, EnvBase):
    """The true dynamics of any stateless TorchRL env as a planning model (any leading shape).

    A stateless env reads everything it needs from the tensordict it steps (torchrl's
    convention, e.g. ``PendulumEnv``): its state entries, here ``state``. This model
    hands the env's ``_step`` every entry of the env's observation (and state) spec that
    the planning tensordict holds, plus the action, so an env reading e.g. ``step_count``
    steps here as it does when acting; a missing ``goal_state`` is filled with ``state``
    and a missing ``goal_pixels`` with zeros (a goal is not needed to imagine a step) and
    left out of the output. A ``[*B]`` batch of candidates is flattened to rows: an env
    of any shape takes them at once; an env whose batch is fixed at ``(n,)`` takes them
    in chunks of ``n``, or at once if a probe on the first step finds that its ``_step``
    gives exactly the chunks' results on the whole batch. ``goal_pixels`` ride along
    unchanged; the done flags are always ``False`` and the reward 0 (imagined rollouts run
    the whole horizon and are scored by cost modules).

    Args:
        env: the env whose dynamics to use; it must step from a tensordict holding
            ``state`` and an action (``_supports_set_state`` and a ``state`` entry).

    Raises:
        MissingKeyError: (a ``ValueError`` and a ``KeyError``) from ``step`` when the
            env's ``_step`` looks up an entry the planning tensordict lacks.

    Examples:
        >>> from dorp_rl.envs import ObjectRearrangementEnv
        >>> from dorp_rl.envs.planning import StatelessEnvModel
        >>> model = StatelessEnvModel(ObjectRearrangementEnv(num_objects=1, batch_size=(4,)))
        >>> td = model.reset().expand(3, 5).clone()
        >>> td["action"] = model.action_spec.rand((3, 5))
        >>> model.step(td)["next", "pixels"].shape
        torch.Size([3, 5, 3, 16, 16])
    """

    _supports_set_state = True

    def __init__(self, env: EnvBase) -> None:
        if not isinstance(env, EnvBase):
            raise ValueError(f"env must be a TorchRL EnvBase, got {type(env).__name__}.")
        if "state" not in env.observation_spec.keys() or not getattr(
            env, "_supports_set_state", False
        ):
            raise ValueError(
                f"{type(env).__name__} cannot serve as its own true dynamics: a planning model "
                "steps copies of a situation, so the env must write a 'state' entry, step from "
                "it (stateless) and take it back on reset(td, set_state=True) "
                "(_supports_set_state = True)."
            )
        super().__init__(device=env.device, batch_size=())
        self.__dict__["_batch_locked"] = False
        self.true_env = env
        batch = len(env.batch_size)
        self.rows = int(env.batch_size.numel()) if env.batch_locked and batch else None
        #: whether the env's ``_step`` takes a whole flat batch (fixed batch only; ``None``:
        #: not probed yet)
        self.whole_batch: bool | None = None

        def unbatched(spec: Composite, keys) -> Composite:
            return Composite({k: spec[k][(0,) * batch].clone() for k in keys})

        self.observation_spec = unbatched(env.observation_spec, env.observation_spec.keys())
        observed = set(self.observation_spec.keys())
        extra = [k for k in env.state_spec.keys() if k not in observed]
        if extra:  # entries the env reads besides its observations (torchrl's "params")
            self.state_spec = unbatched(env.state_spec, extra)
        #: the entries handed to the env's ``_step`` when the tensordict holds them
        self._step_keys = [*self.observation_spec.keys(), *extra]
        # Planners draw indices; a one-hot env gets them in its own layout.
        self.actions = DiscreteActions.of(env)
        self.action_spec = Categorical(
            self.actions.num_actions, shape=(1,), dtype=torch.int64, device=self.device
        )
        self.reward_spec = Unbounded(shape=(1,), dtype=torch.float32, device=self.device)
        flag = Categorical(2, shape=(1,), dtype=torch.bool, device=self.device)
        self.done_spec = Composite(done=flag, terminated=flag.clone(), truncated=flag.clone())

    def _set_seed(self, seed: int | None) -> None:
        self.true_env.set_seed(seed)

    def _by_rows(self, rows: TensorDictBase, call) -> TensorDictBase:
        """``call`` on flat ``rows`` ``[n]``: at once for an env of any shape, else in
        chunks of the env's batch (the last one padded with repeats); ``[n]`` back."""
        if self.rows is None:
            return call(rows)
        n, size = rows.shape[0], self.rows
        pad = (-n) % size
        if pad:
            rows = torch.cat([rows, rows[:1].expand(pad).clone()], 0)
        batch = self.true_env.batch_size
        outs = [call(rows[i : i + size].reshape(batch)) for i in range(0, rows.shape[0], size)]
        return torch.cat([o.reshape(-1) for o in outs], 0)[:n]

    def _step_rows(self, rows: TensorDictBase) -> TensorDictBase:
        """The env's ``_step`` on flat ``rows`` ``[n]``: by chunks of a fixed batch until a
        probe (the first batch of another size than the env's) finds the whole batch at
        once gives exactly the same outputs; ``[n]`` back."""
        step = self.true_env._step
        n = rows.shape[0]
        if self.rows is None or n == self.rows:
            return self._by_rows(rows, step)
        if self.whole_batch:
            return step(rows)
        out = self._by_rows(rows, step)
        if self.whole_batch is None:
            self.whole_batch = _same_outputs(out, _try_call(step, rows))
        return out

    def _reset(self, tensordict: TensorDictBase | None = None, **kwargs) -> TensorDictBase:
        env = self.true_env
        keys = self._step_keys
        if tensordict is None or not kwargs.get("set_state", False):
            td = env.reset()
            return td.reshape(-1)[0].select(*keys, strict=False).clone()
        out = self._by_rows(
            tensordict.reshape(-1), lambda rows: env.reset(rows.clone(), set_state=True)
        )
        return out.select(*keys, strict=False).reshape(tensordict.batch_size)

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        shape = tensordict.batch_size
        rows = tensordict.select(*self._step_keys, "action", strict=False).reshape(-1)
        rows.set("action", self.actions.from_index(rows.get("action")))
        given = sorted(str(k) for k in rows.keys())
        filled = []  # a goal is not needed to imagine a step
        if "goal_state" not in rows.keys():
            rows.set("goal_state", rows.get("state").clone())
            filled.append("goal_state")
        if "goal_pixels" in self.observation_spec.keys() and "goal_pixels" not in rows.keys():
            rows.set("goal_pixels", self.observation_spec["goal_pixels"].zero(rows.batch_size))
            filled.append("goal_pixels")
        try:
            out = self._step_rows(rows)
        except KeyError as err:
            raise self._missing_entry(err, given) from err
        out = out.select(*self._step_keys, strict=False).exclude(*filled).reshape(shape)
        false = torch.zeros((*shape, 1), dtype=torch.bool, device=self.device)
        out.update(
            {
                "reward": torch.zeros((*shape, 1), dtype=torch.float32, device=self.device),
                "done": false,
                "terminated": false.clone(),
                "truncated": false.clone(),
            }
        )
        if "goal_pixels" in tensordict.keys():
            out.set("goal_pixels", tensordict.get("goal_pixels"))
        return out

    def _missing_entry(self, err: KeyError, given: list[str]) -> MissingKeyError:
        """The error naming the entry the env's ``_step`` looked up and did not find
        (``given``: the entries the planning tensordict held)."""
        name = type(self.true_env).__name__
        text = str(err.args[0]) if err.args else ""
        found = re.search(r'key "(.+?)" not found', text)
        key = found.group(1) if found else (err.args[0] if err.args else "?")
        specs = [self.observation_spec, self.state_spec]
        declared = {k for spec in specs for k in spec.keys(True)}
        declared |= {k[-1] for k in declared if isinstance(k, tuple)}  # tensordict names leaves
        if key in declared:
            why = (
                f"{key!r} is in {name}'s observation spec, and the planner hands the model "
                "the entries the acting tensordict holds: that tensordict lacks it (the env's "
                "reset writes it; keep it in what the policy is given)."
            )
        else:
            why = (
                f"{key!r} is not in {name}'s observation spec: the planning tensordict "
                "carries what the env declares there (as its reset writes it), so declare it."
            )
        return MissingKeyError(
            f"{name}._step looked up {key!r}, missing from the planning tensordict that "
            f"StatelessEnvModel (dorp_rl.envs.planning, the planning model of the env's true "
            f"dynamics) stepped it on, which holds {given}. {why}"
        )


def _try_call(call, rows: TensorDictBase) -> TensorDictBase | None:
    """``call(rows)``, or ``None`` if it raises."""
    try:
        return call(rows)
    except Exception:  # noqa: BLE001 (any failure means: step in chunks)
        return None


def _same_outputs(expected: TensorDictBase, got: TensorDictBase | None) -> bool:
    """Whether ``got`` holds exactly ``expected``'s entries (keys, shapes, dtypes, values)."""
    if not isinstance(got, TensorDictBase) or got.batch_size != expected.batch_size:
        return False
    keys = set(expected.keys(True, True))
    if set(got.keys(True, True)) != keys:
        return False
    for key in keys:
        a, b = expected.get(key), got.get(key)
        if isinstance(a, torch.Tensor) and isinstance(b, torch.Tensor):
            if a.dtype != b.dtype or not torch.equal(a, b):
                return False
            continue
        try:  # non-tensor entries
            if not bool(a == b):
                return False
        except Exception:  # noqa: BLE001 (no comparison: no proof of sameness)
            return False
    return True
