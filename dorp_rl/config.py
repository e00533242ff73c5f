"""The one config system: dataclasses that round-trip through plain dicts.

Every config of the library (encoder, video model, trainers) is a dataclass with
:class:`ConfigMixin`: ``to_dict()`` gives JSON-friendly values (tuples as lists, nested
configs as dicts), the form stored in checkpoints, and ``from_dict()`` rebuilds the
config, refusing unknown fields so that a checkpoint of another version fails loudly
instead of half-loading. A config may embed another as a field (a trainer config holds
its model's config); :meth:`ConfigMixin.replace` changes fields of both at once.

Every field has a rule, given beside it with :func:`checked` (``lr: float =
checked(1e-3, Float(low=0.0))``; the rules below: :class:`Int`, :class:`Float`, ..., :class:`Nested` for
an embedded config), checked when the config is built (also by
:func:`dataclasses.replace` and ``from_dict``): a wrong value raises ``ValueError``
naming the field and its allowed range, and values are normalised (``3.0`` steps become
``3``). A subclass inherits its parent's fields with their rules. Rules between fields
live in :meth:`ConfigMixin.check_relations`.
"""

from __future__ import annotations

import dataclasses
import os
import re
import typing
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any, TypeVar

from dorp_rl.validation import (
    check_bool,
    check_choice,
    check_device,
    check_float,
    check_int,
    check_seed,
)

T = TypeVar("T", bound="ConfigMixin")


@dataclasses.dataclass(frozen=True)
class Nested:
    """Rule of a field holding another config: an instance of ``cls`` or a dict of its fields.

    A dict changes the fields it names of ``default()`` (the field's default config, if
    given) or of ``cls()``. The value is validated and copied (two configs never share
    one nested config); a wrong nested value raises ``ValueError`` naming
    ``<field>.<nested field>``.
    """

    cls: type
    default: Any = None

    def __call__(self, name: str, value: Any) -> Any:
        try:
            if isinstance(value, dict):
                fields = {f.name for f in dataclasses.fields(self.cls)}
                unknown = sorted(set(value) - fields)
                if unknown:
                    raise ValueError(f"unknown {self.cls.__name__} fields {unknown}.")
                base = self.default() if self.default is not None else self.cls()
                return base.replace(**value)
            if not isinstance(value, self.cls):
                raise ValueError(
                    f"must be a {self.cls.__name__} or a dict of its fields, "
                    f"got {type(value).__name__}."
                )
            return dataclasses.replace(value)
        except ValueError as err:
            raise _nested_error(name, self.cls, err) from None


def _nested_error(name: str, cls: type, err: ValueError) -> ValueError:
    """``err`` of a nested config ``cls`` in field ``name``, naming ``<name>.<field>``."""
    text = str(err)
    if text.startswith(f"{name}.") or text.startswith(f"{name}:"):
        return err
    first = re.split(r"[\s\[(,:]", text, maxsplit=1)[0]
    names = {f.name for f in dataclasses.fields(cls)}
    return ValueError(f"{name}.{text}" if first in names else f"{name}: {text}")


def _plain(value: Any) -> Any:
    """JSON-friendly ``value``: nested configs as dicts, tuples as lists."""
    if isinstance(value, ConfigMixin):
        return value.to_dict()
    if isinstance(value, (tuple, list)):
        return [_plain(v) for v in value]
    if isinstance(value, dict):
        return {k: _plain(v) for k, v in value.items()}
    return value


def checked(default: Any = dataclasses.MISSING, rule: Any = None, *, factory: Any = None) -> Any:
    """A dataclass field with its rule beside it: ``lr: float = checked(1e-3, Float(low=0.0))``.

    ``rule(name, value) -> value`` checks and normalises the field (raising ``ValueError``)
    whenever the config is built; a :class:`Nested` rule without a default makes its
    field's default from ``factory`` (else the rule's ``default`` or ``cls``). Without a
    default and a factory (and not :class:`Nested`), the field is required:
    ``checked(rule=Ints(low=1))``. Extra ``field`` options are not needed by the configs,
    so there are none.
    """
    if rule is None:
        raise TypeError("checked() needs a rule, e.g. checked(1, Int(low=1)).")
    metadata = {"rule": rule}
    if default is not dataclasses.MISSING:
        if factory is not None:
            raise TypeError("checked() takes a default or a factory, not both.")
        return dataclasses.field(default=default, metadata=metadata)
    if factory is None and isinstance(rule, Nested):
        factory = rule.default if rule.default is not None else rule.cls
    if factory is None:
        return dataclasses.field(metadata=metadata)
    return dataclasses.field(default_factory=factory, metadata=metadata)


def field_rules(cls: Any) -> dict[str, Any]:
    """``{field: rule}`` of a config class or instance (the rules given with :func:`checked`)."""
    return {f.name: f.metadata["rule"] for f in dataclasses.fields(cls) if "rule" in f.metadata}


class ConfigMixin:
    """``to_dict`` / ``from_dict``, ``replace`` and field validation for dataclass configs.

    Examples:
        >>> from dataclasses import dataclass
        >>> from dorp_rl.config import ConfigMixin, Nested, checked
        >>> from dorp_rl.config import Int, Ints
        >>> @dataclass
        ... class Sizes(ConfigMixin):
        ...     widths: tuple[int, ...] = checked((32, 32), Ints(low=1))
        ...     depth: int = checked(2, Int(low=1))
        >>> Sizes.from_dict(Sizes().to_dict())
        Sizes(widths=(32, 32), depth=2)
        >>> Sizes(depth=0)
        Traceback (most recent call last):
        ...
        ValueError: depth must be >= 1, got 0.
        >>> @dataclass
        ... class Run(ConfigMixin):
        ...     model: Sizes = checked(rule=Nested(Sizes))  # default: Sizes()
        ...     steps: int = checked(10, Int(low=1))
        >>> Run().replace(steps=5, model={"depth": 3})
        Run(model=Sizes(widths=(32, 32), depth=3), steps=5)
        >>> Run().to_dict()
        {'model': {'widths': [32, 32], 'depth': 2}, 'steps': 10}
        >>> Run(model=Sizes(depth=1)).replace(model={"depth": 0})
        Traceback (most recent call last):
        ...
        ValueError: model.depth must be >= 1, got 0.
    """

    def __post_init__(self) -> None:
        self.validate()

    def validate(self) -> None:
        """Checks every field against its rule, then :meth:`check_relations`."""
        names = [f.name for f in dataclasses.fields(self)]  # type: ignore[arg-type]
        check_fields(self, field_rules(self), names)
        self.check_relations()

    def check_relations(self) -> None:
        """Rules between fields (e.g. ``trajectory_length >= horizon``); none by default."""

    @classmethod
    def upgrade(cls, values: dict[str, Any]) -> dict[str, Any]:
        """Stored values of an older version, made valid (``from_dict`` calls it); as is by default."""
        return values

    @classmethod
    def nested_fields(cls) -> dict[str, type]:
        """``{field: config class}`` of the fields holding another config."""
        return {k: r.cls for k, r in field_rules(cls).items() if isinstance(r, Nested)}

    def to_dict(self) -> dict[str, Any]:
        """Every field as JSON-friendly values (nested configs as dicts, tuples as lists)."""
        return {f.name: _plain(getattr(self, f.name)) for f in dataclasses.fields(self)}  # type: ignore[arg-type]

    @classmethod
    def from_dict(cls: type[T], values: dict[str, Any]) -> T:
        """The config of ``values`` (a :meth:`to_dict` result, possibly of an older version).

        Raises:
            ValueError: not a dict, a field this class does not have, or a value that
                breaks its rule.
        """
        if not isinstance(values, dict):
            raise ValueError(f"{cls.__name__}.from_dict needs a dict, got {type(values).__name__}.")
        values = cls.upgrade(dict(values))
        fields = {f.name: f for f in dataclasses.fields(cls)}  # type: ignore[arg-type]
        unknown = sorted(set(values) - set(fields))
        if unknown:
            raise ValueError(f"unknown {cls.__name__} fields {unknown}.")
        hints = typing.get_type_hints(cls)
        for name, value in values.items():
            if isinstance(value, list) and "tuple" in str(hints.get(name, "")):
                values[name] = tuple(value)
        return cls(**values)

    def replace(self: T, **changes: Any) -> T:
        """A copy with ``changes``; a dict given for a nested config changes only its fields.

        ``cfg.replace(lr=1e-4, encoder={"code_sizes": (16,)})`` keeps every other field
        of ``cfg.encoder``. Validated like a new config.
        """
        for name, cls in self.nested_fields().items():
            value = changes.get(name)
            if isinstance(value, dict):
                current = getattr(self, name)
                base = current if isinstance(current, cls) else cls()
                try:
                    changes[name] = base.replace(**value)
                except (ValueError, TypeError) as err:
                    raise _nested_error(name, cls, ValueError(str(err))) from None
        return dataclasses.replace(self, **changes)  # type: ignore[type-var]


def flatten_dict(values: dict[str, Any], prefix: str = "") -> dict[str, Any]:
    """``{"encoder": {"code_sizes": [8]}}`` as ``{"encoder.code_sizes": [8]}`` (dicts only)."""
    out: dict[str, Any] = {}
    for key, value in values.items():
        if isinstance(value, dict) and value:
            out.update(flatten_dict(value, f"{prefix}{key}."))
        else:
            out[f"{prefix}{key}"] = value
    return out


def config_differences(stored: dict[str, Any], current: dict[str, Any]) -> dict[str, tuple]:
    """``{field: (stored value, current value)}`` for the fields two config dicts disagree on.

    Nested configs are compared field by field and named ``<field>.<nested field>``
    (e.g. ``encoder.code_sizes``).
    """
    stored, current = flatten_dict(stored), flatten_dict(current)
    keys = sorted(set(stored) | set(current))
    return {k: (stored.get(k), current.get(k)) for k in keys if stored.get(k) != current.get(k)}


def format_differences(diff: dict[str, tuple], left: str, right: str, width: int = 60) -> str:
    """``"seed: stored 0, requested 1; ..."`` for :func:`config_differences`-style entries.

    Long values (an env layout) are cut to ``width`` characters.
    """

    def show(value: Any) -> str:
        text = repr(value)
        return text if len(text) <= width else text[: width - 3] + "..."

    return "; ".join(f"{k}: {left} {show(a)}, {right} {show(b)}" for k, (a, b) in diff.items())


def carry_changes(target: Any, given: Any, default: Any, skip: Sequence[str] = ()) -> Any:
    """``target`` (a config dataclass, e.g. another env's preset) with every field in which
    ``given`` differs from ``default`` (the changes someone made), nested configs field by
    field; the fields in ``skip`` are left as ``target`` has them.

    Examples:
        >>> from dorp_rl.config import carry_changes
        >>> from dorp_rl.policies import DORPConfig
        >>> given = DORPConfig(planner="cem")  # a change against the defaults
        >>> preset = DORPConfig.for_env("key-wall")
        >>> carried = carry_changes(preset, given, DORPConfig())
        >>> carried.planner, carried.reenter  # the change, and the preset's own setting
        ('cem', True)
    """
    changes: dict[str, Any] = {}
    for f in dataclasses.fields(given):
        value, base = getattr(given, f.name), getattr(default, f.name)
        if f.name in skip or value == base:
            continue
        if dataclasses.is_dataclass(value) and type(value) is type(base):
            value = carry_changes(getattr(target, f.name), value, base, skip)
        changes[f.name] = value
    return dataclasses.replace(target, **changes)


# --------------------------------------------------------------------------- field rules
@dataclass(frozen=True)
class Int:
    """Rule of an integer config field."""

    low: int | None = None
    high: int | None = None
    optional: bool = False

    def __call__(self, name: str, value: Any) -> int | None:
        return check_int(name, value, low=self.low, high=self.high, optional=self.optional)


@dataclass(frozen=True)
class Ints:
    """Rule of a tuple-of-integers field (e.g. conv dilations), each ``>= low``."""

    low: int | None = None
    min_length: int = 1
    max_length: int | None = None

    def __call__(self, name: str, value: Any) -> tuple[int, ...]:
        if isinstance(value, (str, bytes)) or not isinstance(value, Iterable):
            raise ValueError(f"{name} must be a sequence of integers, got {value!r}.")
        items = tuple(check_int(f"{name}[{i}]", v, low=self.low) for i, v in enumerate(value))
        if len(items) < self.min_length:
            raise ValueError(
                f"{name} must hold at least {self.min_length} integer(s), got {value!r}."
            )
        if self.max_length is not None and len(items) > self.max_length:
            raise ValueError(
                f"{name} must hold at most {self.max_length} integer(s), got {value!r}."
            )
        return items


@dataclass(frozen=True)
class Floats:
    """Rule of a tuple-of-floats field (e.g. per-one-hot weights), each finite and ``>= low``;
    with ``allow_scalar`` one number is also taken (and kept as a float)."""

    low: float | None = None
    allow_scalar: bool = False

    def __call__(self, name: str, value: Any) -> float | tuple[float, ...]:
        if self.allow_scalar and not isinstance(value, (str, bytes, Iterable)):
            return check_float(name, value, low=self.low)
        if isinstance(value, (str, bytes)) or not isinstance(value, Iterable):
            what = (
                "a number or a sequence of numbers"
                if self.allow_scalar
                else "a sequence of numbers"
            )
            raise ValueError(f"{name} must be {what}, got {value!r}.")
        items = tuple(check_float(f"{name}[{i}]", v, low=self.low) for i, v in enumerate(value))
        if not items:
            raise ValueError(f"{name} must hold at least one number, got {value!r}.")
        return items


@dataclass(frozen=True)
class Float:
    """Rule of a float config field (finite unless ``allow_inf``)."""

    low: float | None = None
    high: float | None = None
    low_open: bool = False
    high_open: bool = False
    allow_inf: bool = False
    optional: bool = False
    #: appended to the error message (what the value means, how to turn a feature off)
    hint: str = ""

    def __call__(self, name: str, value: Any) -> float | None:
        try:
            return check_float(
                name,
                value,
                low=self.low,
                high=self.high,
                low_open=self.low_open,
                high_open=self.high_open,
                allow_inf=self.allow_inf,
                optional=self.optional,
            )
        except ValueError as err:
            if not self.hint:
                raise
            raise ValueError(f"{err} {self.hint}") from None


@dataclass(frozen=True)
class Choice:
    """Rule of a field taking one of a few values."""

    options: tuple[Any, ...]
    optional: bool = False

    def __call__(self, name: str, value: Any) -> Any:
        return check_choice(name, value, self.options, optional=self.optional)


@dataclass(frozen=True)
class Flag:
    """Rule of a ``bool`` field (``optional``: ``None`` too)."""

    optional: bool = False

    def __call__(self, name: str, value: Any) -> bool | None:
        if value is None and self.optional:
            return None
        return check_bool(name, value)


@dataclass(frozen=True)
class Text:
    """Rule of a non-empty string field (paths too: a ``pathlib.Path`` is stored as ``str``)."""

    optional: bool = False

    def __call__(self, name: str, value: Any) -> str | None:
        if value is None and self.optional:
            return None
        if isinstance(value, os.PathLike):
            value = os.fspath(value)
        if not isinstance(value, str) or not value:
            extra = " or None" if self.optional else ""
            raise ValueError(f"{name} must be a non-empty string{extra}, got {value!r}.")
        return value


@dataclass(frozen=True)
class Seed:
    """Rule of a seed field (see :func:`check_seed`)."""

    def __call__(self, name: str, value: Any) -> int:
        return check_seed(value, name)


@dataclass(frozen=True)
class Device:
    """Rule of a torch device field, stored as a string (``"cpu"``, ``"cuda:0"``); see :func:`check_device`."""

    def __call__(self, name: str, value: Any) -> str:
        return str(check_device(value, name))


def check_fields(obj: Any, rules: Mapping[str, Any], fields: Iterable[str]) -> None:
    """Checks every field of a dataclass ``obj`` with its rule and stores the normalised value.

    Raises:
        ValueError: the first field that breaks its rule (the message names it).
        TypeError: a field without a rule (a bug of the config class, not of its user).
    """
    missing = [name for name in fields if name not in rules]
    if missing:
        raise TypeError(f"{type(obj).__name__} has no validation rule for fields {missing}.")
    for name in fields:
        object.__setattr__(obj, name, rules[name](name, getattr(obj, name)))
