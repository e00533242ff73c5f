"""The one config system: flat dataclasses that round-trip through plain dicts.

Every config of the library (encoder, video model, trainers) is a dataclass with
:class:`ConfigMixin`: ``to_dict()`` gives JSON-friendly values (tuples as lists), the
form stored in checkpoints, and ``from_dict()`` rebuilds the config, refusing unknown
fields so that a checkpoint of another version fails loudly instead of half-loading.
"""

from __future__ import annotations

import dataclasses
import typing
from typing import Any, TypeVar

T = TypeVar("T", bound="ConfigMixin")


class ConfigMixin:
    """``to_dict`` / ``from_dict`` for dataclass configs.

    Examples:
        >>> from dataclasses import dataclass
        >>> from dorp_rl.config import ConfigMixin
        >>> @dataclass
        ... class Sizes(ConfigMixin):
        ...     widths: tuple[int, ...] = (32, 32)
        >>> Sizes.from_dict(Sizes().to_dict())
        Sizes(widths=(32, 32))
    """

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
        values = dict(values)
        for name, value in values.items():
            if isinstance(value, list) and "tuple" in str(hints.get(name, "")):
                values[name] = tuple(value)
        return cls(**values)
