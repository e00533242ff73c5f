"""The paper's planning settings: environment, object count, graph groups and paper figures.

One table that the ``dorp`` command (and any script) uses to build the same codes, graph
and task set per setting (the code and world-model presets come from the env profile:
``RepresentationConfig.for_env(setting.env, setting.num_objects)``): :data:`SETTINGS` maps a name (``"2obj"``, ``"keywall"``, ...)
to a :class:`Setting`; :data:`PAPER_SUCCESS` holds the paper's success rates per setting
and method, to draw next to ours.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from torchrl.envs import EnvBase

from dorp_rl.envs import EnvProfile, env_profile


@dataclass(frozen=True)
class Setting:
    """One planning setting: an env profile, its object count and the graph's groups.

    Attributes:
        env: env profile name or import path (:func:`~dorp_rl.envs.env_profile`).
        num_objects: objects of an env that counts them (1 for the others).
        groups: graph groups (:meth:`~dorp_rl.planners.CodeGraph.from_play_data`):
            ``"onehot"``, ``"full"`` or tuples of one-hot indices.
        paper: the paper's figure for DORP, for comparison in result tables.

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
    paper: str

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


SETTINGS: dict[str, Setting] = {
    "1obj": Setting("rearrangement", 1, "onehot", "1.00 in 25 steps"),
    "2obj": Setting("rearrangement", 2, "onehot", "1.00 in 49 steps"),
    "3obj": Setting("rearrangement", 3, "onehot", "1.00 in 75 steps"),
    "5obj": Setting("rearrangement", 5, ((0, 1), (2, 3, 4)), "0.87 in 1091 steps"),
    "3obj-full": Setting("rearrangement", 3, "full", "1.00 (full graph)"),
    "5obj-full": Setting("rearrangement", 5, "full", "0.00 (full graph)"),
    # Not in the paper: six blocks, planned in three pairs.
    "6obj": Setting("rearrangement", 6, ((0, 1), (2, 3), (4, 5)), "not in the paper"),
    "6obj-full": Setting("rearrangement", 6, "full", "not in the paper"),
    "keywall": Setting("key-wall", 1, ((0, 1),), "37/40 (gt), 9/10 (SV2P)"),
    "keycorridor": Setting("key-corridor", 1, ((0, 1),), "33/40 (gt)"),
}

#: The paper's success rates per setting and method: DORP with the true dynamics, VF-RS
#: and VF-CEM through the paper's SV2P video model (the figures docs/RESULTS.md compares
#: with). Settings or methods the paper did not report are absent.
PAPER_SUCCESS: dict[str, dict[str, float]] = {
    "1obj": {"dorp": 1.00, "vf-rs": 0.83, "vf-cem": 1.00},
    "2obj": {"dorp": 1.00, "vf-rs": 0.58, "vf-cem": 0.60},
    "3obj": {"dorp": 1.00, "vf-rs": 0.25, "vf-cem": 0.30},
    "5obj": {"dorp": 0.87, "vf-rs": 0.00, "vf-cem": 0.10},
    "3obj-full": {"dorp": 1.00},
    "5obj-full": {"dorp": 0.00},
    "keywall": {"dorp": 37 / 40},
    "keycorridor": {"dorp": 33 / 40},
}


def paper_methods(setting: str) -> tuple[str, ...]:
    """The methods of the paper's Table 1 in ``setting``: every method at 1-3 objects; no
    similarity ablations at 5 objects (the paper reports none); DORP only in key rooms.
    Six objects (not in the paper): DORP, the full graph and VF-CEM (the stronger
    baseline)."""
    if SETTINGS[setting].env in ("key-wall", "key-corridor"):
        return ("dorp",)
    if SETTINGS[setting].num_objects >= 6:
        return ("dorp", "dorp-full", "vf-cem")
    if SETTINGS[setting].num_objects >= 5:
        return ("dorp", "dorp-full", "vf-rs", "vf-cem")
    return ("dorp", "dorp-arbitrary", "dorp-identity", "dorp-full", "vf-rs", "vf-cem")
