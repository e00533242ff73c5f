"""Code graphs: which discrete codes follow each other in play data, and shortest paths.

DORP plans at the level of its codes: a node is a code (of one one-hot, of a group of
one-hots, or of the whole code), and an edge joins two codes that followed each other in
some trajectory of the play data. The graph is undirected and unweighted, as the
authors'; the number of transitions seen on each edge is kept for tie-breaking between
equally short paths and for diagnostics.

Groups
    ``groups="onehot"`` builds one graph per one-hot (the paper's factorized planning),
    ``groups="full"`` one graph over whole codes (the paper's full-graph ablation), and a
    sequence of index tuples, e.g. ``[(0, 1), (2, 3, 4)]``, one graph per group of
    one-hots (the paper's extended planning at 5 objects; agent plus key bit in the key
    rooms). Groups must cover every one-hot exactly once. ``groups="auto"`` reads them
    from the play data (:func:`~dorp_rl.planners.coupled_groups`): one graph per one-hot,
    except for one-hots whose changes depend on each other's codes (an agent and the key
    it takes), which share one.

Storage
    Every graph lives in fixed-shape tensors registered as buffers, so that torchrl's
    multi-process collectors can share a policy holding it (``share_memory_()`` does not
    support Python containers or sparse tensors). Nodes are the joint codes seen in the
    data, sorted per group (``node_keys``, a mixed-radix number of the members' codes);
    edges are one CSR over all groups (``indptr``, ``indices``, ``edge_counts``; group
    ``g`` owns nodes ``node_offsets[g]:node_offsets[g + 1]``). Groups of at most
    ``dense_limit`` nodes (one-hots, pairs) also get an all-pairs distance table, so that
    a query without removed edges is a table lookup; larger groups (triples, the full
    graph) are searched breadth-first on the CSR.

Edge removal
    The edges that failed during one task belong to that task, not to the graph: queries
    take ``removed``, a tensor of (directed) edge ids to ignore in both directions, that
    the caller keeps per task (:class:`~dorp_rl.policies.AbstractGoalPolicy` keeps it in
    the tensordict, one row per env).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import torch
from torch import nn

from dorp_rl.checkpoint import load_checkpoint, save_checkpoint
from dorp_rl.config import ConfigMixin, Int, Ints, checked, config_differences, format_differences
from dorp_rl.integrity import IntegrityError
from dorp_rl.planners.coupling import coupled_groups
from dorp_rl.planners.play_codes import (
    check_encoder_fits_play_data,
    check_is_encoder,
    describe_env_config,
    encode_transitions,
    encoder_fingerprint,
    play_actions,
)
from dorp_rl.validation import check_int

__all__ = [
    "CodeGraph",
    "CodeGraphConfig",
    "DEFAULT_DENSE_LIMIT",
    "resolve_groups",
]


#: Groups of at most this many nodes get a dense all-pairs distance table.
DEFAULT_DENSE_LIMIT = 1024


_UNREACHABLE = -1


def _index_groups(name: str, value: Any) -> tuple[tuple[int, ...], ...]:
    """Rule of :attr:`CodeGraphConfig.groups`: a sequence of sequences of one-hot indices."""
    if isinstance(value, (str, bytes)) or not isinstance(value, Sequence):
        raise ValueError(f"{name} must be a list of index groups, got {value!r}.")
    return tuple(Ints(low=0, min_length=0)(f"{name}[{g}]", group) for g, group in enumerate(value))


def _fingerprint(name: str, value: Any) -> str:
    """Rule of :attr:`CodeGraphConfig.fingerprint`: a string (``""``: unknown encoder)."""
    if not isinstance(value, str):
        raise ValueError(f"{name} must be a string, got {value!r}.")
    return value


@dataclasses.dataclass
class CodeGraphConfig(ConfigMixin):
    """What a saved :class:`CodeGraph` stores besides its tensors (:meth:`CodeGraph.config`).

    A config dict with a field this class lacks (a file of another version, or edited)
    is refused by :meth:`~dorp_rl.config.ConfigMixin.from_dict`, as encoder and
    world-model checkpoints refuse theirs.
    """

    code_sizes: tuple[int, ...] = checked(rule=Ints(low=1))
    """codes per one-hot"""
    groups: tuple[tuple[int, ...], ...] = checked(rule=_index_groups)
    """one-hot indices of every group"""
    fingerprint: str = checked("", _fingerprint)
    """:func:`encoder_fingerprint` of the encoder that made the codes (``""``: unknown)"""
    dense_limit: int = checked(DEFAULT_DENSE_LIMIT, Int(low=0))
    """groups with at most this many nodes get a distance table"""


def resolve_groups(groups: str | Sequence[Sequence[int]], num_onehots: int) -> list[list[int]]:
    """Turns ``"onehot"``, ``"full"`` or explicit index groups into a checked list of groups.

    Raises:
        ValueError: a group that is empty, names a one-hot outside ``[0, num_onehots)``,
            overlaps another group, or groups that leave a one-hot out.
    """
    if isinstance(groups, str):
        if groups == "onehot":
            return [[i] for i in range(num_onehots)]
        if groups == "full":
            return [list(range(num_onehots))]
        raise ValueError(
            f"groups must be 'onehot', 'full', 'auto' (with the play data's codes) or index "
            f"groups, got {groups!r}."
        )
    out: list[list[int]] = []
    seen: dict[int, int] = {}
    for g, group in enumerate(groups):
        members = [int(i) for i in group]
        if not members:
            raise ValueError(f"group {g} of {list(groups)} is empty.")
        for i in members:
            if not 0 <= i < num_onehots:
                raise ValueError(
                    f"group {g} names one-hot {i}, but the codes have {num_onehots} one-hots "
                    f"(indices 0..{num_onehots - 1})."
                )
            if i in seen:
                raise ValueError(
                    f"one-hot {i} is in group {seen[i]} and group {g}: groups must not overlap."
                )
            seen[i] = g
        out.append(members)
    missing = sorted(set(range(num_onehots)) - set(seen))
    if missing:
        raise ValueError(
            f"groups {[tuple(g) for g in out]} leave one-hots {missing} out: every one-hot "
            "must be in exactly one group."
        )
    return out


def _count_actions(
    codes: torch.Tensor, next_codes: torch.Tensor, actions: torch.Tensor, num_actions: int | None
) -> torch.Tensor:
    """``[C, A]`` counts of transitions in which action ``a`` changed one-hot ``j``."""
    if not isinstance(actions, torch.Tensor) or actions.is_floating_point():
        raise ValueError(f"actions must be an int64 tensor [N], got {_describe(actions)}.")
    actions = actions.reshape(-1).to(torch.int64)
    if actions.shape[0] != codes.shape[0]:
        raise ValueError(
            f"actions must hold one action per transition ({codes.shape[0]}), got "
            f"{actions.shape[0]}."
        )
    if actions.numel() and int(actions.min()) < 0:
        raise ValueError(f"actions must be >= 0, got {int(actions.min())}.")
    seen = int(actions.max()) + 1 if actions.numel() else 1
    width = seen if num_actions is None else check_int("num_actions", num_actions, low=1)
    if seen > width:
        raise ValueError(f"actions go up to {seen - 1}, but num_actions={width}.")
    changed = (codes != next_codes).to(torch.float64)  # [N, C]
    onehot = torch.nn.functional.one_hot(actions, width).to(torch.float64)  # [N, A]
    return (changed.T @ onehot).round().to(torch.int64)


class CodeGraph(nn.Module):
    """Undirected transition graphs over discrete codes, one per group of one-hots.

    Build one with :meth:`from_transitions` (codes of consecutive frames) or
    :meth:`from_play_data` (a play buffer and a trained encoder), query it with
    :meth:`node_of`, :meth:`next_waypoint` and :meth:`shortest_path`, and keep it with
    :meth:`save` / :meth:`load`.

    Args:
        code_sizes: codes per one-hot, e.g. ``(32, 32)``.
        groups: ``"onehot"``, ``"full"`` or explicit index groups (module docstring).
        node_keys: int64 ``[V]``, the joint code of every node, sorted within each group.
        node_offsets: int64 ``[G + 1]``, where each group's nodes start.
        node_counts: int64 ``[V]``, frames seen at each node.
        indptr: int64 ``[V + 1]``, CSR row pointers (global node ids).
        indices: int64 ``[E]``, CSR neighbours (global node ids), both directions.
        edge_counts: int64 ``[E]``, transitions seen on each undirected edge.
        fingerprint: :func:`encoder_fingerprint` of the encoder that made the codes.
        env_config: ``env.config()`` of the environment the play data came from.
        dense_limit: groups with at most this many nodes get a distance table.
        action_counts: int64 ``[C, A]``, play transitions in which action ``a`` changed
            one-hot ``j``'s code (``None``: the actions are unknown); read by
            :meth:`action_weights`.

    Examples:
        >>> import torch
        >>> from dorp_rl.planners import CodeGraph
        >>> codes = torch.tensor([[0, 0], [1, 0], [1, 1], [2, 1]])
        >>> graph = CodeGraph.from_transitions(codes[:-1], codes[1:], code_sizes=(4, 4))
        >>> graph.num_groups, graph.num_nodes(0), graph.num_edges(0)
        (2, 3, 2)
        >>> [graph.node_code(n).tolist() for n in graph.shortest_path(0, torch.tensor([0, 0]), torch.tensor([2, 0]))]
        [[0], [1], [2]]
    """

    def __init__(
        self,
        code_sizes: Sequence[int],
        groups: str | Sequence[Sequence[int]],
        *,
        node_keys: torch.Tensor,
        node_offsets: torch.Tensor,
        node_counts: torch.Tensor,
        indptr: torch.Tensor,
        indices: torch.Tensor,
        edge_counts: torch.Tensor,
        fingerprint: str = "",
        env_config: dict[str, Any] | None = None,
        dense_limit: int = DEFAULT_DENSE_LIMIT,
        action_counts: torch.Tensor | None = None,
    ) -> None:
        super().__init__()
        sizes = list(Ints(low=1)("code_sizes", code_sizes))
        self.code_sizes = tuple(sizes)
        self.groups = resolve_groups(groups, len(sizes))
        self.fingerprint = _fingerprint("fingerprint", fingerprint)
        if env_config is not None and not isinstance(env_config, Mapping):
            raise ValueError(
                f"env_config must be a dict (env.config()) or None, got {env_config!r}."
            )
        self.env_config = dict(env_config) if env_config is not None else None
        self.dense_limit = check_int("dense_limit", dense_limit, low=0)
        g = len(self.groups)
        members = torch.full((g, max(len(m) for m in self.groups)), -1, dtype=torch.int64)
        radix = torch.zeros_like(members)
        for i, group in enumerate(self.groups):
            members[i, : len(group)] = torch.tensor(group)
            radix[i, : len(group)] = _radix([sizes[j] for j in group])
        for name, value in (
            ("node_keys", node_keys),
            ("node_offsets", node_offsets),
            ("node_counts", node_counts),
            ("indptr", indptr),
            ("indices", indices),
            ("edge_counts", edge_counts),
        ):
            if (
                not isinstance(value, torch.Tensor)
                or value.dtype != torch.int64
                or value.dim() != 1
            ):
                raise ValueError(f"{name} must be a 1-d int64 tensor, got {_describe(value)}.")
        v, e = node_keys.shape[0], indices.shape[0]
        if node_offsets.shape[0] != g + 1 or int(node_offsets[-1]) != v:
            raise ValueError(
                f"node_offsets must have {g + 1} entries ending at the {v} nodes, got "
                f"{node_offsets.tolist()}."
            )
        if node_counts.shape[0] != v or indptr.shape[0] != v + 1 or edge_counts.shape[0] != e:
            raise ValueError(
                f"inconsistent graph tensors: {v} nodes, {e} edges, node_counts "
                f"{node_counts.shape[0]}, indptr {indptr.shape[0]}, edge_counts {edge_counts.shape[0]}."
            )
        if e and (int(indices.min()) < 0 or int(indices.max()) >= v):
            raise ValueError(f"indices must lie in [0, {v}), the node ids.")
        self.register_buffer("group_members", members)
        self.register_buffer("group_radix", radix)
        self.register_buffer("node_keys", node_keys)
        self.register_buffer("node_offsets", node_offsets)
        self.register_buffer("node_counts", node_counts)
        self.register_buffer("indptr", indptr)
        self.register_buffer("indices", indices)
        self.register_buffer("edge_counts", edge_counts)
        if action_counts is not None and (
            not isinstance(action_counts, torch.Tensor)
            or action_counts.dtype != torch.int64
            or action_counts.dim() != 2
            or action_counts.shape[0] != len(sizes)
            or bool((action_counts < 0).any())
        ):
            raise ValueError(
                f"action_counts must be a non-negative int64 tensor [{len(sizes)}, A] (one row "
                f"per one-hot), got {_describe(action_counts)}."
            )
        self.register_buffer("action_counts", action_counts)
        # Derived: source of every edge, its reverse, and the group of every node.
        src = torch.repeat_interleave(torch.arange(v), indptr.diff())
        self.register_buffer("edge_source", src, persistent=False)
        self.register_buffer("edge_reverse", _reverse_edges(src, indices, v), persistent=False)
        self._offsets = [int(x) for x in node_offsets]
        tables, table_offsets = [], []
        start = 0
        for i in range(g):
            n = self.num_nodes(i)
            if n <= self.dense_limit:
                tables.append(self._all_pairs_distances(i).to(torch.int16).reshape(-1))
                table_offsets.append(start)
                start += n * n
            else:
                table_offsets.append(-1)
        self.register_buffer(
            "dense_distances",
            torch.cat(tables) if tables else torch.zeros(0, dtype=torch.int16),
            persistent=False,
        )
        self._table_offsets = table_offsets

    # ------------------------------------------------------------------ #
    # Building
    # ------------------------------------------------------------------ #
    @classmethod
    def from_transitions(
        cls,
        codes: torch.Tensor,
        next_codes: torch.Tensor,
        code_sizes: Sequence[int],
        groups: str | Sequence[Sequence[int]] = "onehot",
        *,
        actions: torch.Tensor | None = None,
        num_actions: int | None = None,
        **kwargs: Any,
    ) -> CodeGraph:
        """Builds the graphs from the codes of consecutive frames.

        Args:
            codes: int64 ``[N, C]``, the code of each transition's first frame.
            next_codes: int64 ``[N, C]``, the code of the frame after it (same trajectory).
            code_sizes: codes per one-hot.
            groups: ``"onehot"``, ``"full"``, ``"auto"`` (:func:`coupled_groups` of these
                codes) or index groups.
            actions: int64 ``[N]`` (or ``[N, 1]``), the action of each transition; counted
                per one-hot whose code it changed (``action_counts``). ``None``: unknown.
            num_actions: the env's number of actions (default: the largest action + 1).
            **kwargs: ``fingerprint``, ``env_config``, ``dense_limit``.
        """
        sizes = [int(z) for z in code_sizes]
        for name, value in (("codes", codes), ("next_codes", next_codes)):
            if not isinstance(value, torch.Tensor) or value.dtype != torch.int64:
                raise ValueError(f"{name} must be an int64 tensor, got {_describe(value)}.")
            if value.dim() != 2 or value.shape[1] != len(sizes):
                raise ValueError(
                    f"{name} must have shape [N, {len(sizes)}] (one code per one-hot of "
                    f"code_sizes {tuple(sizes)}), got {list(value.shape)}."
                )
            bad = (value < 0) | (value >= torch.tensor(sizes))
            if bool(bad.any()):
                col = int(bad.any(0).nonzero()[0])
                raise ValueError(
                    f"{name} holds code {int(value[:, col][bad[:, col]][0])} for one-hot {col}, "
                    f"which has {sizes[col]} codes."
                )
        if codes.shape != next_codes.shape:
            raise ValueError(
                f"codes and next_codes must have the same shape, got {list(codes.shape)} "
                f"and {list(next_codes.shape)}."
            )
        if isinstance(groups, str) and groups == "auto":
            groups = coupled_groups(codes, next_codes).groups
        resolved = resolve_groups(groups, len(sizes))
        node_keys, node_counts, node_offsets = [], [], [0]
        sources, targets, counts = [], [], []
        for members in resolved:
            radix = _radix([sizes[j] for j in members])
            a = (codes[:, members] * radix).sum(-1)
            b = (next_codes[:, members] * radix).sum(-1)
            keys, frame_counts = torch.unique(torch.cat([a, b]), return_counts=True)
            offset = node_offsets[-1]
            changed = a != b
            lo = torch.minimum(a[changed], b[changed])
            hi = torch.maximum(a[changed], b[changed])
            pair_keys = torch.stack([lo, hi], -1)
            pairs, pair_counts = torch.unique(pair_keys, dim=0, return_counts=True)
            u = torch.searchsorted(keys, pairs[:, 0].contiguous()) + offset
            v = torch.searchsorted(keys, pairs[:, 1].contiguous()) + offset
            sources += [u, v]
            targets += [v, u]
            counts += [pair_counts, pair_counts]
            node_keys.append(keys)
            node_counts.append(frame_counts)
            node_offsets.append(offset + keys.shape[0])
        action_counts = None
        if actions is not None:
            action_counts = _count_actions(codes, next_codes, actions, num_actions)
        total = node_offsets[-1]
        src, dst, cnt = torch.cat(sources), torch.cat(targets), torch.cat(counts)
        order = torch.argsort(src * total + dst)
        src, dst, cnt = src[order], dst[order], cnt[order]
        indptr = torch.zeros(total + 1, dtype=torch.int64)
        indptr[1:] = torch.bincount(src, minlength=total).cumsum(0)
        return cls(
            sizes,
            resolved,
            node_keys=torch.cat(node_keys),
            node_offsets=torch.tensor(node_offsets, dtype=torch.int64),
            node_counts=torch.cat(node_counts),
            indptr=indptr,
            indices=dst,
            edge_counts=cnt,
            action_counts=action_counts,
            **kwargs,
        )

    @classmethod
    def from_play_data(
        cls,
        buffer: Any,
        encoder: nn.Module,
        groups: str | Sequence[Sequence[int]] = "onehot",
        *,
        chunk_size: int = 1024,
        progress: bool = False,
        dense_limit: int = DEFAULT_DENSE_LIMIT,
        transitions: tuple[torch.Tensor, torch.Tensor] | None = None,
        num_actions: int | None = None,
    ) -> CodeGraph:
        """Encodes every transition of a play buffer and builds the graphs.

        Each stored transition (``pixels`` -> ``("next", "pixels")``, one step of one
        trajectory) gives an edge when its two codes differ. Encoding is almost all of
        the time: to build several graphs (e.g. per group and full) from one buffer and
        encoder, encode once with :func:`encode_transitions` and pass ``transitions``.

        Args:
            buffer: a play buffer (:func:`~dorp_rl.data.collect_play_data`) or a
                TensorDict ``[N]`` holding ``pixels`` and ``("next", "pixels")``.
            encoder: a :class:`~dorp_rl.modules.DiscreteCodeEncoder` (``encode`` and
                ``code_sizes``), run in eval mode.
            groups: ``"onehot"``, ``"full"``, ``"auto"`` (module docstring) or index groups.
            chunk_size: transitions encoded at a time.
            progress: show a tqdm bar.
            dense_limit: see the class docstring.
            transitions: ``(codes, next_codes)`` of this buffer's transitions by this
                encoder (:func:`encode_transitions`); ``None`` encodes them here.
            num_actions: the env's number of actions, for ``action_counts`` (the play
                data's ``action`` per transition; default: the largest action + 1).

        Raises:
            ValueError: ``transitions`` that do not hold one code pair per transition of
                ``buffer`` with the encoder's one-hots, a ``chunk_size`` that is not an
                integer >= 1, or an encoder made for another environment than the play
                data's (:func:`check_encoder_fits_play_data`; the message names both).
        """
        chunk_size = check_int("chunk_size", chunk_size, low=1)
        dense_limit = check_int("dense_limit", dense_limit, low=0)
        check_is_encoder(encoder)
        check_encoder_fits_play_data(buffer, encoder)
        if transitions is None:
            codes, next_codes = encode_transitions(
                buffer, encoder, chunk_size=chunk_size, progress=progress
            )
        else:
            codes, next_codes = transitions
            wanted = [len(buffer), len(encoder.code_sizes)]
            if list(codes.shape) != wanted or list(next_codes.shape) != wanted:
                raise ValueError(
                    f"transitions must be two code tensors of shape {wanted} (one code per "
                    f"frame of each of the buffer's transitions, encode_transitions), got "
                    f"{list(codes.shape)} and {list(next_codes.shape)}."
                )
        metadata = getattr(buffer, "metadata", None) or {}
        return cls.from_transitions(
            codes,
            next_codes,
            encoder.code_sizes,
            groups,
            actions=play_actions(buffer, chunk_size=chunk_size),
            num_actions=num_actions,
            fingerprint=encoder_fingerprint(encoder),
            env_config=metadata.get("env_config"),
            dense_limit=dense_limit,
        )

    # ------------------------------------------------------------------ #
    # Structure
    # ------------------------------------------------------------------ #
    @property
    def num_groups(self) -> int:
        return len(self.groups)

    def num_nodes(self, group: int) -> int:
        """Nodes (distinct codes seen) of ``group``."""
        group = self._check_group(group)
        return self._offsets[group + 1] - self._offsets[group]

    def num_edges(self, group: int) -> int:
        """Undirected edges of ``group``."""
        group = self._check_group(group)
        lo, hi = self._offsets[group], self._offsets[group + 1]
        return int(self.indptr[hi] - self.indptr[lo]) // 2

    def group_of(self, onehot: int) -> int:
        """The group holding one-hot ``onehot`` (an integer in ``[0, C)``)."""
        onehot = check_int("onehot", onehot, low=0, high=len(self.code_sizes) - 1)
        for g, members in enumerate(self.groups):
            if onehot in members:
                return g
        raise ValueError(f"one-hot {onehot} is in no group (groups {self.groups}).")

    def group_keys(self, code: torch.Tensor, group: int) -> torch.Tensor:
        """Joint key ``[*B]`` of ``group``'s one-hots in codes ``[*B, C]``."""
        return self._group_keys(self._check_code(code, "code"), self._check_group(group))

    def _group_keys(self, code: torch.Tensor, group: int) -> torch.Tensor:
        members = self.groups[group]
        radix = self.group_radix[group, : len(members)]
        return (code[..., members].to(radix.device) * radix).sum(-1)

    def node_of(self, code: torch.Tensor, group: int) -> torch.Tensor:
        """Global node id ``[*B]`` of codes ``[*B, C]`` in ``group``; -1 where never seen.

        Raises:
            ValueError: a ``group`` that is not an integer in ``[0, num_groups)``, or codes
                that are not integers ``[*B, C]`` within :attr:`code_sizes`.
        """
        return self._node_of(self._check_code(code, "code"), self._check_group(group))

    def _node_of(self, code: torch.Tensor, group: int) -> torch.Tensor:
        lo, hi = self._offsets[group], self._offsets[group + 1]
        keys = self.node_keys[lo:hi]
        wanted = self._group_keys(code, group)
        if hi == lo:
            return torch.full_like(wanted, _UNREACHABLE)
        pos = torch.searchsorted(keys, wanted).clamp_max(hi - lo - 1)
        found = keys[pos] == wanted
        return torch.where(found, pos + lo, torch.full_like(pos, _UNREACHABLE))

    def node_code(self, node: int | torch.Tensor) -> torch.Tensor:
        """Codes of the group's one-hots at global node ``node`` (int64 ``[len(group)]``)."""
        node = self._check_node(node, "node")
        group = self._group_of_node(node)
        members = self.groups[group]
        key = int(self.node_keys[node])
        out = []
        for j in reversed(members):
            out.append(key % self.code_sizes[j])
            key //= self.code_sizes[j]
        return torch.tensor(out[::-1], dtype=torch.int64)

    def neighbours(self, node: int) -> torch.Tensor:
        """Global ids of the nodes joined to ``node``."""
        node = self._check_node(node, "node")
        return self.indices[self.indptr[node] : self.indptr[node + 1]]

    def edge_id(self, a: int, b: int) -> int:
        """Id of the directed edge ``a -> b`` (-1 if there is none)."""
        a, b = self._check_node(a, "a"), self._check_node(b, "b")
        lo, hi = int(self.indptr[a]), int(self.indptr[a + 1])
        hits = (self.indices[lo:hi] == b).nonzero()
        return lo + int(hits[0]) if hits.numel() else _UNREACHABLE

    def group_of_edge(self, edge: int | torch.Tensor) -> torch.Tensor:
        """Group index of each edge id (any shape); -1 for the ``-1`` (no edge) entries."""
        edge = self._check_edge_ids(edge, "edge")
        source = self.edge_source[edge.clamp(min=0)]
        offsets = torch.as_tensor(self._offsets[1:-1], dtype=torch.int64)
        group = torch.bucketize(source, offsets, right=True)
        return torch.where(edge >= 0, group, torch.full_like(group, -1))

    def nodes_of(self, code: torch.Tensor, groups: torch.Tensor) -> torch.Tensor:
        """Global node ids ``[N]`` of codes ``[N, C]``, row ``i`` in group ``groups[i]``;
        -1 where the code was never seen or the group is -1."""
        code = self._check_code(code, "code")
        groups = self._check_edge_ids(groups, "groups", high=self.num_groups - 1)
        out = torch.full(groups.shape, _UNREACHABLE, dtype=torch.int64)
        for group in groups[groups >= 0].unique().tolist():
            rows = groups == group
            out[rows] = self._node_of(code[rows], group).cpu()
        return out

    def node_codes(self, nodes: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The codes of global nodes ``[N]``: int64 ``[N, C]`` (0 outside each node's
        group) and bool ``[N, C]``, the one-hots of each node's group."""
        nodes = self._check_edge_ids(nodes, "nodes", high=self._offsets[-1] - 1).reshape(-1)
        if bool((nodes < 0).any()):
            raise ValueError(f"nodes must be node ids, got {nodes.tolist()}.")
        members = self.group_members[self._groups_of_nodes(nodes)]  # [N, M]
        radix = self.group_radix[self._groups_of_nodes(nodes)]
        sizes = torch.tensor(self.code_sizes)[members.clamp(min=0)]
        values = (self.node_keys[nodes].unsqueeze(-1) // radix.clamp(min=1)) % sizes
        codes = torch.zeros(nodes.shape[0], len(self.code_sizes), dtype=torch.int64)
        mask = torch.zeros(codes.shape, dtype=torch.bool)
        rows, slots = (members >= 0).nonzero(as_tuple=True)
        codes[rows, members[rows, slots]] = values[rows, slots]
        mask[rows, members[rows, slots]] = True
        return codes, mask

    def _groups_of_nodes(self, nodes: torch.Tensor) -> torch.Tensor:
        """Group of each global node id (any shape; -1 for -1 entries)."""
        offsets = torch.as_tensor(self._offsets[1:-1], dtype=torch.int64)
        group = torch.bucketize(nodes, offsets, right=True)
        return torch.where(nodes >= 0, group, torch.full_like(group, -1))

    # ------------------------------------------------------------------ #
    # Search
    # ------------------------------------------------------------------ #
    def distances_to(
        self,
        goal: int,
        removed: torch.Tensor | None = None,
        stop_at: int | None = None,
    ) -> torch.Tensor:
        """Hop distance from every node of ``goal``'s group to ``goal`` (-1: unreachable).

        Args:
            goal: a global node id.
            removed: edge ids to ignore (in both directions); entries < 0 are ignored.
            stop_at: stop the search once this node's distance is known.

        Returns:
            int64 ``[num_nodes(group)]``, indexed by ``node - node_offsets[group]``.
        """
        goal = self._check_node(goal, "goal")
        group = self._group_of_node(goal)
        if stop_at is not None:
            stop_at = self._check_node(stop_at, "stop_at", group)
        removed = self._removed(removed).unsqueeze(0)
        lo = self._offsets[group]
        alive = self._alive_edges(group, removed)
        start = None if stop_at is None else torch.tensor([stop_at - lo])
        return self._distance_fields(group, torch.tensor([goal - lo]), alive, start)[0]

    def next_waypoint(
        self, node: int, goal: int, removed: torch.Tensor | None = None
    ) -> tuple[int, int, int]:
        """The next node on a shortest path from ``node`` to ``goal`` (same group).

        Among neighbours one hop closer to the goal, the one joined by the edge seen most
        often in the play data wins (then the lowest id). :meth:`next_waypoints` answers
        many such questions at once.

        Returns:
            ``(next_node, edge_id, distance)``: ``distance`` is the hop count from ``node``
            to ``goal``; ``(-1, -1, -1)`` when the goal cannot be reached, ``(node, -1,
            0)`` when ``node == goal``.
        """
        node, goal = self._check_node(node, "node"), self._check_node(goal, "goal")
        removed = self._removed(removed).unsqueeze(0)
        nxt, edge, distance = self.next_waypoints(
            torch.tensor([node]), torch.tensor([goal]), removed
        )
        return int(nxt[0]), int(edge[0]), int(distance[0])

    def next_waypoints(
        self,
        nodes: torch.Tensor,
        goals: torch.Tensor,
        removed: torch.Tensor | None = None,
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """The next node on a shortest path from each of ``nodes`` to its goal, at once.

        Args:
            nodes: int64 ``[N]`` global node ids (-1: a code never seen: no path).
            goals: int64 ``[N]`` global node ids of the same groups (-1: no path).
            removed: int64 ``[N, S]`` edge ids each row must not use, in both directions
                (-1: a free slot); ``None``: none.

        Returns:
            ``(next_node, edge_id, distance)``, each int64 ``[N]``, per row as
            :meth:`next_waypoint`.

        Examples:
            >>> import torch
            >>> codes = torch.tensor([[0], [1], [2], [3]])
            >>> graph = CodeGraph.from_transitions(codes[:-1], codes[1:], code_sizes=(4,))
            >>> nxt, edge, distance = graph.next_waypoints(
            ...     torch.tensor([0, 3, 1]), torch.tensor([3, 0, 1]),
            ...     torch.tensor([[-1], [-1], [-1]]))
            >>> nxt.tolist(), distance.tolist()
            ([1, 2, 1], [3, 3, 0])
        """
        nodes = self._check_edge_ids(nodes, "nodes", high=self._offsets[-1] - 1).reshape(-1)
        goals = self._check_edge_ids(goals, "goals", high=self._offsets[-1] - 1).reshape(-1)
        if goals.shape != nodes.shape:
            raise ValueError(
                f"nodes and goals must have one entry per row, got {list(nodes.shape)} "
                f"and {list(goals.shape)}."
            )
        if removed is None:
            removed = torch.full((nodes.shape[0], 1), _UNREACHABLE, dtype=torch.int64)
        removed = self._check_edge_ids(removed, "removed")
        if removed.dim() != 2 or removed.shape[0] != nodes.shape[0]:
            raise ValueError(
                f"removed must be edge ids [N, S] (one row per node), got {list(removed.shape)}."
            )
        groups, goal_groups = self._groups_of_nodes(nodes), self._groups_of_nodes(goals)
        both = (nodes >= 0) & (goals >= 0)
        if bool((both & (groups != goal_groups)).any()):
            row = int((both & (groups != goal_groups)).nonzero()[0])
            raise ValueError(
                f"nodes {int(nodes[row])} and {int(goals[row])} belong to different groups."
            )
        nxt = torch.full_like(nodes, _UNREACHABLE)
        edge, distance = nxt.clone(), nxt.clone()
        same = both & (nodes == goals)
        nxt[same], distance[same] = nodes[same], 0
        todo = both & ~same
        for group in groups[todo].unique().tolist():
            rows = (todo & (groups == group)).nonzero().squeeze(-1)
            lo = self._offsets[group]
            alive = self._alive_edges(group, removed[rows])
            start = nodes[rows] - lo
            dist = self._distance_fields(group, goals[rows] - lo, alive, start)
            nxt[rows], edge[rows], distance[rows] = self._steps(group, dist, start, alive)
        return nxt, edge, distance

    def shortest_path(
        self,
        group: int,
        start: torch.Tensor | int,
        goal: torch.Tensor | int,
        removed: torch.Tensor | None = None,
    ) -> list[int]:
        """Global node ids of a shortest path in ``group`` (start and goal included).

        ``start`` and ``goal`` are codes ``[C]`` or global node ids of ``group``. Returns
        ``[]`` when no path exists (including when either code was never seen in the play
        data).

        Raises:
            ValueError: a ``group`` that is not an integer in ``[0, num_groups)``, a node id
                that is not an integer node of ``group``, or a code outside
                :attr:`code_sizes` (the message names the argument and its range).
        """
        group = self._check_group(group)
        a = self._as_node(start, group, "start")
        b = self._as_node(goal, group, "goal")
        if a < 0 or b < 0:
            return []
        lo = self._offsets[group]
        alive = self._alive_edges(group, self._removed(removed).unsqueeze(0))
        dist = self._distance_fields(group, torch.tensor([b - lo]), alive)
        path = [a]
        while path[-1] != b:
            nxt, _, _ = self._steps(group, dist, torch.tensor([path[-1] - lo]), alive)
            if int(nxt[0]) < 0:
                return []
            path.append(int(nxt[0]))
        return path

    def _alive_edges(self, group: int, removed: torch.Tensor) -> torch.Tensor:
        """bool ``[N, E_group]``: the group's directed edges each row may use (those in
        ``removed`` ``[N, S]``, and their reverses, may not)."""
        e_lo = int(self.indptr[self._offsets[group]])
        e_hi = int(self.indptr[self._offsets[group + 1]])
        alive = torch.ones(removed.shape[0], e_hi - e_lo, dtype=torch.bool)
        reverse = torch.where(removed >= 0, self.edge_reverse[removed.clamp(min=0)], -1)
        both = torch.cat([removed, reverse], dim=-1)
        rows, slots = ((both >= e_lo) & (both < e_hi)).nonzero(as_tuple=True)
        alive[rows, both[rows, slots] - e_lo] = False
        return alive

    def _distance_fields(
        self,
        group: int,
        goals: torch.Tensor,
        alive: torch.Tensor,
        stop_at: torch.Tensor | None = None,
    ) -> torch.Tensor:
        """int64 ``[N, n]``: hop distances of the group's ``n`` nodes to each row's goal
        (local ids ``[N]``) over the row's ``alive`` edges, by one breadth-first search of
        all rows at once (a row without removed edges reads the group's distance table);
        the search may stop once every row's ``stop_at`` node (local ids) is reached."""
        lo, hi = self._offsets[group], self._offsets[group + 1]
        e_lo, e_hi = int(self.indptr[lo]), int(self.indptr[hi])
        rows = torch.arange(goals.shape[0])
        dist = torch.full((goals.shape[0], hi - lo), _UNREACHABLE, dtype=torch.int64)
        table = self._table_offsets[group]
        search = torch.ones_like(goals, dtype=torch.bool)
        if table >= 0:
            search = ~alive.all(-1)
            n = hi - lo
            plain = ~search
            index = table + goals[plain].unsqueeze(-1) * n + torch.arange(n)
            dist[plain] = self.dense_distances[index].to(torch.int64)
        if not bool(search.any()):
            return dist
        src = self.edge_source[e_lo:e_hi] - lo
        dst = self.indices[e_lo:e_hi] - lo
        dist[rows[search], goals[search]] = 0
        frontier = torch.zeros_like(dist, dtype=torch.bool)
        frontier[rows[search], goals[search]] = True
        level = 0
        while True:
            hit_rows, hit_edges = (frontier[:, src] & alive).nonzero(as_tuple=True)
            reached = torch.zeros_like(frontier)
            reached[hit_rows, dst[hit_edges]] = True
            reached &= dist < 0
            if not bool(reached.any()):
                break
            level += 1
            dist[reached] = level
            frontier = reached
            if stop_at is not None and bool((dist[rows, stop_at] >= 0).all()):
                break
        return dist

    def _steps(
        self, group: int, dist: torch.Tensor, nodes: torch.Tensor, alive: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """One hop down each row's distance field ``dist`` ``[N, n]`` from ``nodes`` (local
        ids ``[N]``) over its ``alive`` edges: global ``(next_node, edge_id, distance)``."""
        lo, hi = self._offsets[group], self._offsets[group + 1]
        e_lo, e_hi = int(self.indptr[lo]), int(self.indptr[hi])
        src = self.edge_source[e_lo:e_hi] - lo
        dst = self.indices[e_lo:e_hi] - lo
        d = dist.gather(1, nodes.unsqueeze(-1))  # [N, 1]
        closer = dist[:, dst] == d - 1
        ok = (src == nodes.unsqueeze(-1)) & alive & closer & (d > 0)
        scores = torch.where(ok, self.edge_counts[e_lo:e_hi], -1)
        best = scores.argmax(-1)
        found = ok.any(-1)
        d = d.squeeze(-1)
        nxt = torch.where(found, dst[best] + lo, _UNREACHABLE)
        edge = torch.where(found, best + e_lo, _UNREACHABLE)
        distance = torch.where(found, d, torch.where(d == 0, 0, _UNREACHABLE))
        nxt = torch.where(d == 0, nodes + lo, nxt)
        return nxt, edge, distance

    # ------------------------------------------------------------------ #
    # Persistence
    # ------------------------------------------------------------------ #
    def action_weights(self, onehots: torch.Tensor, num_actions: int | None = None) -> torch.Tensor:
        """How often each action changed the given one-hots in the play data, normalised.

        Args:
            onehots: bool ``[R, C]``, per row the one-hots a move should change (a hop's).
            num_actions: width of the result (default: that of ``action_counts``); wider
                than the counts pads with actions never seen changing a code.

        Returns:
            float ``[R, A]``: per row, the share of each action among the play transitions
            that changed any of its one-hots (uniform for a row with none, or none seen).

        Raises:
            ValueError: a graph built without actions (``action_counts`` is ``None``), or
                ``onehots`` not of shape ``[R, C]``.
        """
        if self.action_counts is None:
            raise ValueError(
                "this graph has no action counts (built without the play data's actions, "
                "or saved by an older version): rebuild it with CodeGraph.from_play_data."
            )
        counts = self.action_counts.float()
        width = counts.shape[1] if num_actions is None else int(num_actions)
        if width < counts.shape[1]:
            raise ValueError(
                f"num_actions={width} is fewer than the {counts.shape[1]} actions of the "
                "graph's play data."
            )
        counts = torch.nn.functional.pad(counts, (0, width - counts.shape[1]))
        if onehots.dim() != 2 or onehots.shape[1] != counts.shape[0]:
            raise ValueError(
                f"onehots must be bool [R, {counts.shape[0]}], got {list(onehots.shape)}."
            )
        weights = onehots.to(counts.device, counts.dtype) @ counts
        total = weights.sum(-1, keepdim=True)
        uniform = torch.full_like(weights, 1.0 / width)
        return torch.where(total > 0, weights / total.clamp_min(1e-12), uniform)

    def completed(self) -> CodeGraph:
        """This graph with the edges that moving one group member alone implies.

        In a group of several one-hots (a pair or a triple of blocks) the play data sees
        only some of the joint codes' transitions, so the group's graph can split into
        parts and a goal can be out of reach although every member can get to its own
        goal code. When the play data saw member ``k`` go from code ``x`` to ``y``
        (others unchanged, in any joint code), this adds the edge from every joint node
        with ``x`` at ``k`` to the node with ``y`` at ``k`` and the other members the same,
        if that node was seen. That assumes the members move independently, as objects do
        while nothing blocks them (a hop that fails is removed like any other); it does
        not hold for one-hots that change together (an agent picking up a key), so it is
        a choice of the env (its profile's ``graph_completion``). The new edges have count
        0, so among equally short paths the policy prefers seen ones
        (:meth:`next_waypoint`). Groups of one one-hot are unchanged.

        Examples:
            >>> import torch
            >>> from dorp_rl.planners import CodeGraph
            >>> codes = torch.tensor([[0, 0], [0, 1]])
            >>> nexts = torch.tensor([[1, 0], [0, 0]])  # member 0 moves at (., 0) only
            >>> seen = torch.tensor([[1, 1], [1, 1]])  # (1, 1) is seen, never entered
            >>> graph = CodeGraph.from_transitions(
            ...     torch.cat([codes, seen]), torch.cat([nexts, seen]), (2, 2), [(0, 1)]
            ... )
            >>> graph.num_edges(0), graph.completed().num_edges(0)
            (2, 4)
        """
        src, dst, counts = [self.edge_source], [self.indices], [self.edge_counts]
        for g, members in enumerate(self.groups):
            if len(members) < 2:
                continue
            lo, hi = self._offsets[g], self._offsets[g + 1]
            keys = self.node_keys[lo:hi]
            radix = self.group_radix[g, : len(members)]
            sizes = torch.tensor([self.code_sizes[j] for j in members])
            codes = (keys.unsqueeze(-1) // radix) % sizes  # [n, m]
            inside = (self.edge_source >= lo) & (self.edge_source < hi)
            a, b = self.edge_source[inside] - lo, self.indices[inside] - lo
            changed = codes[a] != codes[b]
            for k in range(len(members)):
                alone = changed[:, k] & (changed.sum(-1) == 1)
                moves = torch.unique(
                    torch.stack([codes[a[alone], k], codes[b[alone], k]], -1), dim=0
                )
                if moves.shape[0] == 0:
                    continue
                # Every node with a move's first code at k, and the node it moves to.
                node, move = (codes[:, k].unsqueeze(1) == moves[:, 0]).nonzero(as_tuple=True)
                target = keys[node] + (moves[move, 1] - moves[move, 0]) * radix[k]
                pos = torch.searchsorted(keys, target).clamp_max(keys.shape[0] - 1)
                seen = keys[pos] == target
                src.append(node[seen] + lo)
                dst.append(pos[seen] + lo)
                counts.append(torch.zeros(int(seen.sum()), dtype=torch.int64))
        src, dst, cnt = torch.cat(src), torch.cat(dst), torch.cat(counts)
        total = int(self.node_keys.shape[0])
        # Seen edges first, so that unique keeps their counts over the added zeros.
        pair = src * total + dst
        order = torch.argsort(pair, stable=True)
        pair, cnt = pair[order], cnt[order]
        unique, first = torch.unique_consecutive(pair, return_inverse=True)
        keep = torch.zeros(unique.shape[0], dtype=torch.int64).scatter_reduce(
            0, first, cnt, reduce="amax", include_self=False
        )
        src, dst = unique // total, unique % total
        indptr = torch.zeros(total + 1, dtype=torch.int64)
        indptr[1:] = torch.bincount(src, minlength=total).cumsum(0)
        return type(self)(
            self.code_sizes,
            self.groups,
            node_keys=self.node_keys.clone(),
            node_offsets=self.node_offsets.clone(),
            node_counts=self.node_counts.clone(),
            indptr=indptr,
            indices=dst,
            edge_counts=keep,
            fingerprint=self.fingerprint,
            env_config=self.env_config,
            dense_limit=self.dense_limit,
            action_counts=self.action_counts,
        )

    def config(self) -> dict[str, Any]:
        """What identifies this graph: code sizes, groups, encoder fingerprint, limits.

        The :class:`CodeGraphConfig` fields, as plain lists and numbers.
        """
        return CodeGraphConfig(
            code_sizes=self.code_sizes,
            groups=tuple(tuple(g) for g in self.groups),
            fingerprint=self.fingerprint,
            dense_limit=self.dense_limit,
        ).to_dict()

    def save(self, path: str | Path) -> Path:
        """Writes the graph with the library's checkpoint format (kind ``"code_graph"``)."""
        return save_checkpoint(
            path,
            kind="code_graph",
            config=self.config(),
            env_config=self.env_config or {},
            state={k: v.cpu() for k, v in self.state_dict().items()},
            step=0,
        )

    @classmethod
    def load(
        cls,
        path: str | Path,
        *,
        encoder: nn.Module | None = None,
        env_config: dict[str, Any] | None = None,
    ) -> CodeGraph:
        """Reads a graph written by :meth:`save`.

        Args:
            path: the file.
            encoder: if given, the graph must have been built with this encoder (same
                code sizes and the same weights, by :func:`encoder_fingerprint`).
            env_config: if given, the play data must come from this environment.

        Raises:
            ValueError: a corrupted or incomplete file
                (:class:`~dorp_rl.integrity.IntegrityError`), another kind of checkpoint,
                a config with a field :class:`CodeGraphConfig` does not have (a file of
                another version, or edited), another environment, or another encoder (the
                message says which).
        """
        payload = load_checkpoint(path, kind="code_graph", env_config=env_config)
        cfg, state = payload["config"], payload["state"]
        names = ("node_keys", "node_offsets", "node_counts", "indptr", "indices", "edge_counts")
        missing = [k for k in names if k not in state]
        if not isinstance(cfg, dict):
            missing.append("config")
        else:
            missing += [k for k in ("code_sizes", "groups") if k not in cfg]
        if missing:
            raise IntegrityError(f"code graph {path} is incomplete: missing {missing}.")
        try:
            config = CodeGraphConfig.from_dict(cfg)
        except ValueError as err:
            raise ValueError(f"code graph {path} cannot be read: {err}") from None
        graph = cls(
            config.code_sizes,
            config.groups,
            **{k: state[k] for k in names},
            fingerprint=config.fingerprint,
            env_config=payload.get("env_config") or None,
            dense_limit=config.dense_limit,
            action_counts=state.get("action_counts"),
        )
        if encoder is not None:
            graph.check_encoder(encoder, source=str(path))
        return graph

    def check_encoder(self, encoder: nn.Module, source: str = "the graph") -> None:
        """Raises ``ValueError`` unless ``encoder`` has this graph's code sizes (and weights).

        An encoder that records its environment (an ``env_config`` attribute) must also
        record the one of the graph's play data.
        """
        own, mine = getattr(encoder, "env_config", None), self.env_config
        if isinstance(own, Mapping) and mine is not None:
            diff = config_differences(dict(own), mine)
            if diff:
                raise ValueError(
                    f"{source} was built from play data of {describe_env_config(mine)}, but the "
                    f"encoder was trained on {describe_env_config(own)} "
                    f"({format_differences(diff, 'encoder', 'graph')})."
                )
        sizes = tuple(int(z) for z in getattr(encoder, "code_sizes", ()))
        if sizes != self.code_sizes:
            raise ValueError(
                f"{source} was built for codes of sizes {self.code_sizes}, but the encoder "
                f"gives codes of sizes {sizes}."
            )
        if self.fingerprint and encoder_fingerprint(encoder) != self.fingerprint:
            raise ValueError(
                f"{source} was built with another encoder (fingerprint {self.fingerprint}, "
                f"this encoder's {encoder_fingerprint(encoder)}): its codes mean other things. "
                "Build the graph again with CodeGraph.from_play_data(buffer, encoder)."
            )

    def extra_repr(self) -> str:
        parts = [
            f"{tuple(m)}: {self.num_nodes(g)} nodes, {self.num_edges(g)} edges"
            for g, m in enumerate(self.groups)
        ]
        return f"code_sizes={self.code_sizes}, groups=[{'; '.join(parts)}]"

    # ------------------------------------------------------------------ #
    # Internals
    # ------------------------------------------------------------------ #
    def _all_pairs_distances(self, group: int) -> torch.Tensor:
        """Dense hop distances ``[n, n]`` of a group (multi-source BFS with matrices)."""
        lo, hi = self._offsets[group], self._offsets[group + 1]
        n = hi - lo
        e_lo, e_hi = int(self.indptr[lo]), int(self.indptr[hi])
        adjacency = torch.zeros(n, n)
        adjacency[self.edge_source[e_lo:e_hi] - lo, self.indices[e_lo:e_hi] - lo] = 1.0
        dist = torch.full((n, n), _UNREACHABLE, dtype=torch.int64)
        frontier = torch.eye(n)
        seen = frontier.bool()
        dist[seen] = 0
        level = 0
        while True:
            reached = (frontier @ adjacency > 0) & ~seen
            if not bool(reached.any()):
                break
            level += 1
            dist[reached] = level
            seen |= reached
            frontier = reached.float()
        return dist

    def _group_of_node(self, node: int) -> int:
        node = int(node)
        if not 0 <= node < self._offsets[-1]:
            raise ValueError(f"node {node} is not in the graph (nodes 0..{self._offsets[-1] - 1}).")
        for g in range(self.num_groups):
            if node < self._offsets[g + 1]:
                return g
        raise AssertionError("unreachable")

    def _as_node(self, value: torch.Tensor | int, group: int, name: str) -> int:
        """A code ``[C]`` (its node, -1 if never seen) or a node id of ``group``, as a node id."""
        if isinstance(value, torch.Tensor) and value.dim() >= 1:
            if value.dim() != 1:
                raise ValueError(
                    f"{name} must be a code [{len(self.code_sizes)}] or a node id, got a "
                    f"tensor of shape {list(value.shape)}."
                )
            return int(self._node_of(self._check_code(value, name), group))
        return self._check_node(value, name, group)

    def _check_group(self, group: Any) -> int:
        """``group`` as an int in ``[0, num_groups)`` (bools and floats refused)."""
        return check_int("group", group, low=0, high=self.num_groups - 1)

    def _check_node(self, node: Any, name: str, group: int | None = None) -> int:
        """``node`` as an int node id of the graph (and of ``group`` if given)."""
        if group is None:
            return check_int(name, node, low=0, high=self._offsets[-1] - 1)
        lo, hi = self._offsets[group], self._offsets[group + 1]
        try:
            return check_int(name, node, low=lo, high=hi - 1)
        except ValueError:
            raise ValueError(
                f"{name} must be a node id of group {group} (an integer in [{lo}, {hi - 1}]) "
                f"or a code [{len(self.code_sizes)}], got {node!r}."
            ) from None

    def _check_edge_ids(self, edge: Any, name: str, high: int | None = None) -> torch.Tensor:
        """Integer ids (any shape) in ``-1..high`` (default: the edge ids) as an int64 CPU
        tensor."""
        if isinstance(edge, torch.Tensor):
            if edge.dtype.is_floating_point or edge.dtype.is_complex or edge.dtype == torch.bool:
                raise ValueError(f"{name} ids must be integers, got {_describe(edge)}.")
            edge = edge.to(torch.int64).cpu()
        else:
            edge = torch.tensor(check_int(name, edge), dtype=torch.int64)
        top = int(self.indices.shape[0]) - 1 if high is None else int(high)
        if edge.numel() and (int(edge.min()) < -1 or int(edge.max()) > top):
            raise ValueError(f"{name} ids must lie in -1..{top}, got {edge.tolist()}.")
        return edge

    def _removed(self, removed: torch.Tensor | None) -> torch.Tensor:
        """Removed edge ids as a 1-d CPU tensor (entries < 0, padding, dropped)."""
        if removed is None:
            return torch.zeros(0, dtype=torch.int64)
        if not isinstance(removed, torch.Tensor):
            raise ValueError(
                f"removed must be an integer tensor of edge ids or None, got {_describe(removed)}."
            )
        removed = self._check_edge_ids(removed, "removed").reshape(-1)
        return removed[removed >= 0]

    def _check_code(self, code: torch.Tensor, name: str) -> torch.Tensor:
        """Integer codes ``[*B, C]`` within :attr:`code_sizes`, as int64 (one sync)."""
        if (
            not isinstance(code, torch.Tensor)
            or code.dtype.is_floating_point
            or code.dtype.is_complex
            or code.dtype == torch.bool
        ):
            raise ValueError(f"{name} must be an integer tensor [*B, C], got {_describe(code)}.")
        if code.shape[-1:] != (len(self.code_sizes),):
            raise ValueError(
                f"{name} must have {len(self.code_sizes)} codes (one per one-hot of "
                f"{self.code_sizes}), got shape {list(code.shape)}."
            )
        code = code.to(torch.int64)
        if code.numel():
            sizes = torch.tensor(self.code_sizes, device=code.device)
            bad = (code < 0) | (code >= sizes)
            if bool(bad.any()):
                column = int(bad.reshape(-1, len(self.code_sizes)).any(0).nonzero()[0])
                value = int(code[..., column][bad[..., column]][0])
                raise ValueError(
                    f"{name} holds code {value} for one-hot {column}, which has codes "
                    f"0..{self.code_sizes[column] - 1} (code_sizes {self.code_sizes})."
                )
        return code


def _radix(sizes: Sequence[int]) -> torch.Tensor:
    """Mixed-radix multipliers: the last one-hot varies fastest."""
    out, mult = [], 1
    for size in reversed(sizes):
        out.append(mult)
        mult *= int(size)
    if mult >= 2**62:
        raise ValueError(f"a group of code sizes {list(sizes)} has too many joint codes.")
    return torch.tensor(out[::-1], dtype=torch.int64)


def _reverse_edges(src: torch.Tensor, dst: torch.Tensor, num_nodes: int) -> torch.Tensor:
    """Index of ``b -> a`` for every edge ``a -> b`` (edges sorted by ``(src, dst)``)."""
    if src.numel() == 0:
        return src.clone()
    keys = src * num_nodes + dst
    return torch.searchsorted(keys, dst * num_nodes + src)


def _describe(value: Any) -> str:
    if isinstance(value, torch.Tensor):
        return f"{value.dtype} tensor of shape {list(value.shape)}"
    return type(value).__name__
