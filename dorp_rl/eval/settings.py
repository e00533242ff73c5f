"""Planning settings: an env profile, its object count and the code graph's groups.

The ``dorp`` command (and any script) builds the same codes, graph and task set per
setting (the code and world-model presets come from the env profile:
``RepresentationConfig.for_env(setting.env, setting.num_objects)``). :data:`SETTINGS`
holds the paper's named settings (``"2obj"``, ``"keywall"``, ...), declared beside its
envs (:mod:`dorp_rl.envs.paper`); any other env profile is a setting of its own
(:meth:`Setting.of_env`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from torchrl.envs import EnvBase

from dorp_rl.envs import EnvProfile, env_profile
from dorp_rl.envs.paper import PAPER_SETTINGS, PAPER_SUCCESS

__all__ = ["PAPER_SUCCESS", "SETTINGS", "Setting", "paper_methods", "setting_of"]


@dataclass(frozen=True)
class Setting:
    """One planning setting: an env profile, its object count and the graph's groups.

    Attributes:
        env: env profile name or import path (:func:`~dorp_rl.envs.env_profile`).
        num_objects: objects of an env that counts them (1 for the others).
        groups: graph groups (:meth:`~dorp_rl.planners.CodeGraph.from_play_data`):
            ``"onehot"``, ``"full"`` or tuples of one-hot indices.
        paper: the paper's figure for DORP, for comparison in result tables.
        methods: the methods of the paper's Table 1 in this setting (``()``: none).

    Examples:
        >>> from dorp_rl.eval import SETTINGS
        >>> setting = SETTINGS["5obj"]
        >>> setting.env, setting.num_objects, setting.groups
        ('rearrangement', 5, ((0, 1), (2, 3, 4)))
        >>> setting.make_env(batch_size=(2,)).batch_size
        torch.Size([2])
    """

    env: str
    num_objects: int
    groups: Any
    paper: str = ""
    methods: tuple[str, ...] = ()

    @classmethod
    def of_env(cls, env: str | EnvProfile, num_objects: int | None = None) -> Setting:
        """The setting of an env profile: its object count (default: the profile's) and
        its graph groups, no paper figure."""
        profile = env_profile(env)
        count = profile.resolve_num_objects(num_objects)
        name = env if isinstance(env, str) else profile.name
        return cls(name, count, profile.graph_groups(count), "")

    @property
    def profile(self) -> EnvProfile:
        """The env profile of this setting."""
        return env_profile(self.env)

    def make_env(self, **kwargs: Any) -> EnvBase:
        """The acting environment of this setting."""
        return self.profile.build(self.num_objects, **kwargs)

    def completes_graph(self, groups: Any = None) -> bool:
        """Whether this setting's graphs over ``groups`` (default: its own) are completed
        (:meth:`~dorp_rl.planners.CodeGraph.completed`): when the profile says so, never
        for the full graph."""
        groups = self.groups if groups is None else groups
        return bool(self.profile.graph_completion) and groups != "full"

    def make_graph(self, buffer: Any, encoder: Any, groups: Any = None, **kwargs: Any) -> Any:
        """The code graph of this setting over a play buffer (``groups`` default: its own),
        completed when :meth:`completes_graph`; ``kwargs`` go to
        :meth:`~dorp_rl.planners.CodeGraph.from_play_data`."""
        from dorp_rl.planners import CodeGraph

        groups = self.groups if groups is None else groups
        graph = CodeGraph.from_play_data(buffer, encoder, groups, **kwargs)
        return graph.completed() if self.completes_graph(groups) else graph


def setting_of(name: str) -> Setting:
    """The setting called ``name``: one of :data:`SETTINGS`, else the setting of the env
    profile ``name`` (a registered profile or an import path, :meth:`Setting.of_env`).

    Raises:
        ValueError: ``name`` is neither, naming the settings.
    """
    if name in SETTINGS:
        return SETTINGS[name]
    try:
        return Setting.of_env(name)
    except ValueError as err:
        raise ValueError(
            f"setting {name!r} is none of {sorted(SETTINGS)} and no env profile: {err}"
        ) from None


#: The paper's named settings (:data:`dorp_rl.envs.paper.PAPER_SETTINGS`).
SETTINGS: dict[str, Setting] = {name: Setting(**spec) for name, spec in PAPER_SETTINGS.items()}


def paper_methods(setting: str) -> tuple[str, ...]:
    """The methods of the paper's Table 1 in ``setting`` (one of :data:`SETTINGS`).

    Examples:
        >>> from dorp_rl.eval import paper_methods
        >>> paper_methods("keywall")
        ('dorp',)
    """
    if setting not in SETTINGS:
        raise ValueError(f"{setting!r} is not one of the paper's settings {sorted(SETTINGS)}.")
    return SETTINGS[setting].methods
