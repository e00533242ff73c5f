"""The checks of user input, in one place: numbers, seeds, batch sizes, actions, states
(frames: :mod:`dorp_rl.frames`).

Every public entry point of dorp-rl checks its arguments with these helpers, so a mistake
always raises ``ValueError`` with a message that names the argument, what is allowed and
what was given. They run at the public boundary (constructors, ``reset``, a planner or
policy call, a trainer's construction). The checks that read tensor values (an action's
range, the range of float pixels) synchronise with the device, so they never run inside
per-step loops (an env's ``_step`` on its own output, a planner's imagined rollouts).

Config dataclasses give every field one rule beside it, built on these checks
(:mod:`dorp_rl.config`: :class:`~dorp_rl.config.Int`, :class:`~dorp_rl.config.Float`, ...).

Examples:
    >>> from dorp_rl.validation import check_int, check_seed
    >>> check_int("num_steps", 3.0, low=1)
    3
    >>> check_int("num_steps", 2.5, low=1)
    Traceback (most recent call last):
    ...
    ValueError: num_steps must be an integer >= 1, got 2.5.
    >>> check_seed(-1)
    Traceback (most recent call last):
    ...
    ValueError: seed must be in [0, 9223372036854775807], got -1.
"""

from __future__ import annotations

import inspect
import math
import numbers
import operator
from collections.abc import Iterable, Sequence
from typing import Any

import torch

#: Largest seed accepted anywhere (torch generators take 64-bit seeds; derived seeds add
#: small offsets, which still fit).
SEED_MAX = 2**63 - 1

__all__ = [
    "BatchShapeError",
    "MissingKeyError",
    "UnknownArgumentError",
    "SEED_MAX",
    "check_action",
    "check_batch_size",
    "check_bool",
    "check_choice",
    "check_device",
    "check_float",
    "check_int",
    "check_keywords",
    "check_seed",
    "check_state_layout",
    "derive_seed",
    "keyword_names",
]


class MissingKeyError(KeyError, ValueError):
    """A tensordict lacks a key a function needs (both a ``KeyError`` and a ``ValueError``)."""

    def __str__(self) -> str:  # KeyError would print the repr of the message
        return str(self.args[0]) if self.args else ""


class BatchShapeError(ValueError, RuntimeError):
    """A tensordict's batch shape does not fit the env (a ``ValueError``; torchrl raises ``RuntimeError``)."""


class UnknownArgumentError(TypeError, ValueError):
    """A keyword argument no callee takes (a ``TypeError``, as Python's own, and a ``ValueError``)."""


# --------------------------------------------------------------------------- numbers
def _bounds(low: float | None, high: float | None, low_open: bool, high_open: bool) -> str:
    lo, hi = (f"{b:g}" if isinstance(b, float) else str(b) for b in (low, high))
    if low is not None and high is not None:
        return f"in {'(' if low_open else '['}{lo}, {hi}{')' if high_open else ']'}"
    if low is not None:
        return f"{'>' if low_open else '>='} {lo}"
    if high is not None:
        return f"{'<' if high_open else '<='} {hi}"
    return ""


def _as_int(value: Any) -> int | None:
    """``value`` as an int if it is an integer (int, numpy int, integral float), else ``None``."""
    if isinstance(value, bool):
        return None
    try:
        return operator.index(value)
    except TypeError:
        pass
    if isinstance(value, numbers.Real) and math.isfinite(float(value)):
        as_int = int(value)
        return as_int if as_int == value else None
    return None


def check_int(
    name: str,
    value: Any,
    *,
    low: int | None = None,
    high: int | None = None,
    optional: bool = False,
) -> int | None:
    """``value`` as an ``int``; refuses non-integers (``2.5``, ``True``) and values out of range.

    Integral floats (``3.0``) are taken as ints; ``None`` is taken when ``optional``.
    """
    if value is None and optional:
        return None
    bounds = _bounds(low, high, False, False)
    as_int = _as_int(value)
    if as_int is None:
        what = " ".join(filter(None, ["an integer", bounds, "or None" if optional else ""]))
        raise ValueError(f"{name} must be {what}, got {value!r}.")
    if (low is not None and as_int < low) or (high is not None and as_int > high):
        raise ValueError(f"{name} must be {bounds}, got {value!r}.")
    return as_int


def check_float(
    name: str,
    value: Any,
    *,
    low: float | None = None,
    high: float | None = None,
    low_open: bool = False,
    high_open: bool = False,
    allow_inf: bool = False,
    optional: bool = False,
) -> float | None:
    """``value`` as a finite ``float`` in range (``nan`` is always refused; ``inf`` if asked)."""
    if value is None and optional:
        return None
    bounds = _bounds(low, high, low_open, high_open)
    finite = "" if allow_inf else "finite "
    what = f"a {finite}number {bounds}".rstrip()
    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        raise ValueError(f"{name} must be {what}, got {value!r}.")
    number = float(value)
    if math.isnan(number) or (math.isinf(number) and not allow_inf):
        raise ValueError(f"{name} must be {what}, got {value!r}.")
    too_low = low is not None and (number <= low if low_open else number < low)
    too_high = high is not None and (number >= high if high_open else number > high)
    if too_low or too_high:
        raise ValueError(f"{name} must be {bounds}, got {value!r}.")
    return number


def check_bool(name: str, value: Any) -> bool:
    """``value`` if it is a ``bool`` (numpy bools too); refuses ``0``, ``"yes"``, ..."""
    if isinstance(value, bool) or type(value).__name__ == "bool_":
        return bool(value)
    raise ValueError(f"{name} must be True or False, got {value!r}.")


def check_choice(name: str, value: Any, choices: Sequence[Any], *, optional: bool = False) -> Any:
    """``value`` if it is one of ``choices``."""
    if value is None and optional:
        return None
    if value not in tuple(choices):
        extra = " or None" if optional else ""
        raise ValueError(f"{name} must be one of {tuple(choices)}{extra}, got {value!r}.")
    return value


def check_seed(seed: Any, name: str = "seed", *, optional: bool = False) -> int | None:
    """A seed: an integer in ``[0, 2**63 - 1]`` (``None`` when ``optional``)."""
    return check_int(name, seed, low=0, high=SEED_MAX, optional=optional)


def derive_seed(seed: int, offset: int) -> int:
    """``seed + offset`` wrapped into ``[0, SEED_MAX]``: the seed of a derived generator."""
    return (int(seed) + int(offset)) % (SEED_MAX + 1)


def check_batch_size(batch_size: Any, name: str = "batch_size") -> torch.Size:
    """A batch shape: an int ``n`` (taken as ``(n,)``) or a sequence of ints ``>= 1``; ``()`` is allowed."""
    if _as_int(batch_size) is not None:
        batch_size = (batch_size,)
    if isinstance(batch_size, (str, bytes)) or not isinstance(batch_size, Iterable):
        raise ValueError(
            f"{name} must be a sequence of integers >= 1 (e.g. (8,) or ()), got {batch_size!r}."
        )
    dims = list(batch_size)
    if any(_as_int(d) is None or _as_int(d) < 1 for d in dims):
        raise ValueError(
            f"{name} must hold integers >= 1 (every dimension at least one env), got "
            f"{tuple(dims)!r}."
        )
    return torch.Size([_as_int(d) for d in dims])


#: Device types a ``device=`` argument may name (``"cuda"`` and ``"mps"`` only where available).
DEVICE_TYPES = ("cpu", "cuda", "mps")


def check_device(
    device: Any, name: str = "device", *, optional: bool = False
) -> torch.device | None:
    """``device`` as a :class:`torch.device`: ``"cpu"``, ``"cuda"``, ``"cuda:N"`` or ``"mps"``.

    Refuses names torch does not know (``"foo"``), other device types, and devices this
    machine does not have (``"cuda"`` without CUDA, ``"cuda:3"`` with one GPU), which torch
    would only report later with an ``AssertionError`` or a ``RuntimeError`` from deep
    inside. ``None`` is taken when ``optional``.
    """
    if device is None and optional:
        return None
    accepted = "'cpu', 'cuda', 'cuda:N' or 'mps' (a torch.device or its name)"
    if optional:
        accepted += " or None"
    if isinstance(device, bool) or not isinstance(device, (str, torch.device, int)):
        raise ValueError(f"{name} must be {accepted}, got {device!r}.")
    try:
        parsed = torch.device(device)
    except (RuntimeError, TypeError, ValueError):
        raise ValueError(f"{name} must be {accepted}, got {device!r}.") from None
    if parsed.type not in DEVICE_TYPES:
        raise ValueError(f"{name} must be {accepted}, got {device!r}.")
    if parsed.type == "cuda":
        if not torch.cuda.is_available():
            raise ValueError(
                f"{name}={device!r} but CUDA is not available on this machine "
                "(torch.cuda.is_available() is False): use 'cpu'."
            )
        count = torch.cuda.device_count()
        if parsed.index is not None and parsed.index >= count:
            raise ValueError(
                f"{name}={device!r} but this machine has {count} CUDA device(s) "
                f"(cuda:0 to cuda:{count - 1})."
            )
    if parsed.type == "mps" and not torch.backends.mps.is_available():
        raise ValueError(
            f"{name}={device!r} but MPS is not available on this machine "
            "(torch.backends.mps.is_available() is False): use 'cpu'."
        )
    return parsed


def keyword_names(function: Any) -> list[str]:
    """The names of the arguments ``function`` (or a class's ``__init__``) takes by keyword."""
    kinds = (inspect.Parameter.POSITIONAL_OR_KEYWORD, inspect.Parameter.KEYWORD_ONLY)
    parameters = inspect.signature(function).parameters.values()
    return [p.name for p in parameters if p.kind in kinds]


def check_keywords(given: Iterable[str], accepted: Iterable[str], where: str) -> None:
    """Refuses keyword arguments that ``where`` would pass on to a callee that does not take them.

    Raises:
        UnknownArgumentError: naming the unknown keywords and every accepted one (instead of
            a bare ``TypeError`` from inside the callee, or a keyword silently dropped).
    """
    accepted = sorted(set(accepted))
    unknown = sorted(set(given) - set(accepted))
    if unknown:
        raise UnknownArgumentError(
            f"{where} got unknown keyword argument(s) {unknown}; the keywords it passes on "
            f"are {accepted}."
        )


# --------------------------------------------------------------------------- tensors
def as_tensor(value: Any, name: str) -> torch.Tensor:
    """``value`` as a tensor: tensors pass, numpy arrays are wrapped without a copy."""
    if isinstance(value, torch.Tensor):
        return value
    if type(value).__module__ == "numpy" and hasattr(value, "__array__"):
        import numpy as np

        return torch.from_numpy(np.ascontiguousarray(value))
    raise ValueError(f"{name} must be a torch.Tensor or a numpy array, got {type(value).__name__}.")


def check_action(
    action: Any,
    num_actions: int,
    name: str = "action",
    *,
    shape: Sequence[int] | None = None,
) -> torch.Tensor:
    """Checks discrete actions int ``[*B, 1]`` in ``[0, num_actions - 1]``; returns them as int64.

    ``shape`` is the exact expected shape (else any ``[*B, 1]``). The range check reads the
    values (one device synchronisation).
    """
    if not isinstance(action, torch.Tensor):
        raise ValueError(f"{name} must be a torch.Tensor, got {type(action).__name__}.")
    if action.dtype.is_floating_point or action.dtype.is_complex or action.dtype == torch.bool:
        raise ValueError(f"{name} must be an integer tensor, got dtype {action.dtype}.")
    if shape is not None and tuple(action.shape) != tuple(shape):
        raise ValueError(
            f"{name} must have shape {list(shape)} ([*B, 1] with B = {list(shape[:-1])}), got "
            f"{list(action.shape)}."
        )
    if action.shape[-1:] != (1,):
        raise ValueError(f"{name} must have shape [*B, 1], got {list(action.shape)}.")
    if action.numel():
        low, high = torch.stack(torch.aminmax(action)).tolist()  # one sync
        if low < 0 or high >= num_actions:
            raise ValueError(
                f"{name} out of range: expected integers in [0, {num_actions - 1}] "
                f"(num_actions = {num_actions}), got min {low} and max {high}."
            )
    return action.to(torch.int64)


def check_state_layout(
    state: Any, state_shape: Sequence[int], name: str = "state", *, owner: str = ""
) -> torch.Tensor:
    """Checks the dtype (int64) and trailing shape of a batch of states ``[*B, *state_shape]``.

    Reads no values (no device synchronisation); the rules of a world (no overlap, no
    wall) are checked by the env, where it declares ``check_state``.
    """
    if not isinstance(state, torch.Tensor):
        raise ValueError(f"{name} must be a torch.Tensor, got {type(state).__name__}.")
    if state.dtype != torch.int64:
        raise ValueError(f"{name} must have dtype torch.int64, got {state.dtype}.")
    expected = tuple(state_shape)
    if state.dim() < len(expected) or tuple(state.shape[state.dim() - len(expected) :]) != expected:
        where = f" for {owner}" if owner else ""
        raise ValueError(
            f"{name} must have shape [*B, {', '.join(map(str, expected))}]{where}, "
            f"got {list(state.shape)}."
        )
    return state
