"""The one config system: flat dataclasses that round-trip through plain dicts.

Every config of the library (video model, trainers) is a dataclass with
:class:`ConfigMixin`: ``to_dict()`` gives JSON-friendly values (tuples as lists), the
form stored in checkpoints, and ``from_dict()`` rebuilds the config, refusing unknown
fields so that a checkpoint of another version fails loudly instead of half-loading.

Every field has a rule (``FIELD_RULES``, see :mod:`dorp_rl.validation`), checked when
the config is built (also by :func:`dataclasses.replace` and ``from_dict``): a wrong
value raises ``ValueError`` naming the field and its allowed range, and values are
normalised (``3.0`` steps become ``3``). Rules between fields live in
:meth:`ConfigMixin.check_relations`.
"""

from __future__ import annotations

import dataclasses
import typing
from typing import Any, ClassVar, TypeVar

from dorp_rl.validation import check_fields

T = TypeVar("T", bound="ConfigMixin")


class ConfigMixin:
    """``to_dict`` / ``from_dict`` and field validation for dataclass configs.

    Examples:
        >>> from dataclasses import dataclass
        >>> from dorp_rl.config import ConfigMixin
        >>> from dorp_rl.validation import Int
        >>> @dataclass
        ... class Sizes(ConfigMixin):
        ...     FIELD_RULES = {"widths": lambda name, v: tuple(v), "depth": Int(low=1)}
        ...     widths: tuple[int, ...] = (32, 32)
        ...     depth: int = 2
        >>> Sizes.from_dict(Sizes().to_dict())
        Sizes(widths=(32, 32), depth=2)
        >>> Sizes(depth=0)
        Traceback (most recent call last):
        ...
        ValueError: depth must be >= 1, got 0.
    """

    #: field name -> rule ``rule(name, value) -> normalised value`` (raises ``ValueError``)
    FIELD_RULES: ClassVar[dict[str, Any]] = {}

    def __post_init__(self) -> None:
        self.validate()

    def validate(self) -> None:
        """Checks every field against its rule, then :meth:`check_relations`."""
        names = [f.name for f in dataclasses.fields(self)]  # type: ignore[arg-type]
        check_fields(self, self.FIELD_RULES, names)
        self.check_relations()

    def check_relations(self) -> None:
        """Rules between fields (e.g. ``trajectory_length >= horizon``); none by default."""

    @classmethod
    def upgrade(cls, values: dict[str, Any]) -> dict[str, Any]:
        """Stored values of an older version, made valid (``from_dict`` calls it); as is by default."""
        return values

    def to_dict(self) -> dict[str, Any]:
        out = dataclasses.asdict(self)  # type: ignore[call-overload]
        return {k: list(v) if isinstance(v, tuple) else v for k, v in out.items()}

    @classmethod
    def from_dict(cls: type[T], values: dict[str, Any]) -> T:
        if not isinstance(values, dict):
            raise ValueError(f"{cls.__name__}.from_dict needs a dict, got {type(values).__name__}.")
        fields = {f.name: f for f in dataclasses.fields(cls)}  # type: ignore[arg-type]
        unknown = sorted(set(values) - set(fields))
        if unknown:
            raise ValueError(f"unknown {cls.__name__} fields {unknown}.")
        hints = typing.get_type_hints(cls)
        values = cls.upgrade(dict(values))
        for name, value in values.items():
            if isinstance(value, list) and "tuple" in str(hints.get(name, "")):
                values[name] = tuple(value)
        return cls(**values)


def config_differences(stored: dict[str, Any], current: dict[str, Any]) -> dict[str, tuple]:
    """``{field: (stored value, current value)}`` for the fields two config dicts disagree on."""
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
