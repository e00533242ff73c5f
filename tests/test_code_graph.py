"""CodeGraph: building from transitions and play data, BFS against networkx, edge removal,
saving and loading, and the errors on bad input."""

from __future__ import annotations

import networkx as nx
import pytest
import torch
from tensordict import TensorDict

from dorp_rl.data import collect_play_data
from dorp_rl.envs import KeyWallEnv, ObjectRearrangementEnv, OracleCodeEncoder
from dorp_rl.modules import DiscreteCodeEncoder, EncoderConfig
from dorp_rl.planners import CodeGraph, coupled_groups, encode_transitions, encoder_fingerprint


def random_walk_codes(num_onehots: int, size: int, steps: int, seed: int = 0):
    """Codes of a random walk where one one-hot moves by +-1 per step (like play data)."""
    gen = torch.Generator().manual_seed(seed)
    code = torch.randint(0, size, (num_onehots,), generator=gen)
    codes = [code.clone()]
    for _ in range(steps):
        which = int(torch.randint(0, num_onehots, (), generator=gen))
        delta = int(torch.randint(0, 2, (), generator=gen)) * 2 - 1
        code[which] = (code[which] + delta).clamp(0, size - 1)
        codes.append(code.clone())
    codes = torch.stack(codes)
    return codes[:-1], codes[1:]


def reference_graph(codes, next_codes, members):
    graph = nx.Graph()
    for a, b in zip(codes[:, members].tolist(), next_codes[:, members].tolist(), strict=True):
        graph.add_node(tuple(a))
        graph.add_node(tuple(b))
        if a != b:
            graph.add_edge(tuple(a), tuple(b))
    return graph


@pytest.mark.parametrize(
    ("groups", "dense_limit"),
    [("onehot", 1024), ([(0, 1), (2,)], 1024), ([(0, 1), (2,)], 4), ("full", 0)],
)
def test_distances_match_networkx(groups, dense_limit):
    codes, next_codes = random_walk_codes(3, 6, 3000)
    graph = CodeGraph.from_transitions(
        codes, next_codes, (6, 6, 6), groups, dense_limit=dense_limit
    )
    for g, members in enumerate(graph.groups):
        ref = reference_graph(codes, next_codes, members)
        assert graph.num_nodes(g) == ref.number_of_nodes()
        assert graph.num_edges(g) == ref.number_of_edges()
        starts = codes[
            torch.randperm(codes.shape[0], generator=torch.Generator().manual_seed(g))[:5]
        ]
        goals = next_codes[-5:]
        for start, goal in zip(starts, goals, strict=True):
            path = graph.shortest_path(g, start, goal)
            expected = nx.shortest_path_length(
                ref, tuple(start[members].tolist()), tuple(goal[members].tolist())
            )
            assert len(path) - 1 == expected
            # Consecutive nodes of the path are joined in the reference graph.
            nodes = [tuple(graph.node_code(n).tolist()) for n in path]
            assert all(ref.has_edge(a, b) for a, b in zip(nodes[:-1], nodes[1:], strict=True))


def test_edge_counts_and_tie_break():
    # Two equally short routes 0 -> 1 -> 3 and 0 -> 2 -> 3; the second is seen more often.
    pairs = [(0, 1), (1, 3), (0, 2), (2, 3), (0, 2), (2, 3), (2, 0)]
    codes = torch.tensor([[a] for a, _ in pairs])
    next_codes = torch.tensor([[b] for _, b in pairs])
    graph = CodeGraph.from_transitions(codes, next_codes, (4,))
    start, goal = int(graph.node_of(torch.tensor([0]), 0)), int(graph.node_of(torch.tensor([3]), 0))
    nxt, edge, distance = graph.next_waypoint(start, goal)
    assert graph.node_code(nxt).tolist() == [2] and distance == 2
    assert int(graph.edge_counts[edge]) == 3  # (0, 2) seen twice, (2, 0) once: undirected
    assert int(graph.node_counts.sum()) == 2 * len(pairs)


def test_removed_edges_change_the_path_and_leave_the_graph_alone():
    pairs = [(0, 1), (1, 3), (0, 2), (2, 3), (0, 2)]
    codes = torch.tensor([[a] for a, _ in pairs])
    next_codes = torch.tensor([[b] for _, b in pairs])
    graph = CodeGraph.from_transitions(codes, next_codes, (4,))
    node = {c: int(graph.node_of(torch.tensor([c]), 0)) for c in range(4)}
    nxt, edge, _ = graph.next_waypoint(node[0], node[3])
    assert nxt == node[2]
    # Removing 0 -> 2 (given in either direction) sends the path through 1.
    for removed in (edge, graph.edge_id(node[2], node[0])):
        assert graph.next_waypoint(node[0], node[3], torch.tensor([removed]))[0] == node[1]
    assert graph.next_waypoint(node[0], node[3])[0] == node[2]
    both = torch.tensor([edge, graph.edge_id(node[0], node[1])])
    assert graph.next_waypoint(node[0], node[3], both) == (-1, -1, -1)
    assert graph.shortest_path(0, node[0], node[3], both) == []
    # -1 entries are free slots, not edges.
    assert graph.next_waypoint(node[0], node[3], torch.tensor([-1, -1]))[0] == node[2]


def test_unseen_codes_have_no_node_and_no_path():
    codes, next_codes = random_walk_codes(2, 4, 50)
    graph = CodeGraph.from_transitions(codes, next_codes, (8, 8))
    assert int(graph.node_of(torch.tensor([7, 7]), 0)) == -1
    assert graph.shortest_path(0, codes[0], torch.tensor([7, 0])) == []


def test_from_play_data_with_oracle_codes_joins_neighbouring_regions():
    env = ObjectRearrangementEnv(num_objects=2, batch_size=(8,), seed=0)
    buffer = collect_play_data(env, 4000, seed=0)
    oracle = OracleCodeEncoder(env, cell_size=4)
    graph = CodeGraph.from_play_data(buffer, oracle)
    assert graph.env_config == env.config()
    assert graph.fingerprint == encoder_fingerprint(oracle)
    for g in range(2):
        assert graph.num_nodes(g) == 16  # every region of a 4 x 4 grid is seen
        src = graph.edge_source[
            graph.indptr[graph.node_offsets[g]] : graph.indptr[graph.node_offsets[g + 1]]
        ]
        for a, b in zip(src.tolist(), graph.indices[: src.numel()].tolist(), strict=True):
            (ca,), (cb,) = graph.node_code(a).tolist(), graph.node_code(b).tolist()
            # One cell moves the block into a 4-neighbouring region, never further.
            assert abs(ca // 4 - cb // 4) + abs(ca % 4 - cb % 4) == 1
    # The graph can also be built from a TensorDict of transitions.
    td = buffer[:500]
    small = CodeGraph.from_play_data(
        TensorDict(pixels=td["pixels"], next=td["next"].select("pixels"), batch_size=[500]), oracle
    )
    assert small.num_groups == 2
    # Codes encoded once build the same graphs as encoding again, for any groups.
    transitions = encode_transitions(buffer, oracle)
    for groups in ("onehot", "full"):
        again = CodeGraph.from_play_data(buffer, oracle, groups)
        shared = CodeGraph.from_play_data(buffer, oracle, groups, transitions=transitions)
        assert shared.config() == again.config()
        for name, value in again.state_dict().items():
            assert torch.equal(shared.state_dict()[name], value), name
    with pytest.raises(ValueError, match="transitions must be two code tensors of shape"):
        CodeGraph.from_play_data(buffer, oracle, transitions=(transitions[0][:10],) * 2)


def test_key_room_group_joins_agent_and_key_bit():
    env = KeyWallEnv(batch_size=(4,), seed=0)
    oracle = OracleCodeEncoder(env)
    graph = CodeGraph.from_play_data(collect_play_data(env, 8000, seed=0), oracle, groups=[(0, 1)])
    without_key = int(graph.node_of(torch.tensor([0, 0]), 0))
    with_key = [n for n in range(graph.num_nodes(0)) if graph.node_code(n)[1] == 1]
    assert without_key >= 0 and with_key
    # From the start region without the key, some region with the key is reachable.
    assert graph.shortest_path(0, without_key, with_key[0]) != []


def test_auto_groups_join_the_agent_and_the_key_it_takes_and_keep_blocks_apart():
    # Key-wall: the key is taken only where the agent stands, so one group of both.
    env = KeyWallEnv(batch_size=(8,), seed=0)
    oracle = OracleCodeEncoder(env)
    graph = CodeGraph.from_play_data(collect_play_data(env, 40_000, seed=0), oracle, groups="auto")
    assert graph.groups == [[0, 1]]
    # Blocks move whatever the others' codes: one graph each.
    blocks = ObjectRearrangementEnv(num_objects=3, batch_size=(8,), seed=0)
    codes, next_codes = encode_transitions(
        collect_play_data(blocks, 8000, seed=0), OracleCodeEncoder(blocks, cell_size=4)
    )
    choice = coupled_groups(codes, next_codes)
    assert choice.groups == ((0,), (1,), (2,)) and float(choice.dependence.max()) < 0.01
    assert "one graph each" in choice.why
    # Two one-hots of one object (a copy of a block's code) change together.
    doubled = coupled_groups(
        torch.cat([codes, codes[:, :1]], 1), torch.cat([next_codes, next_codes[:, :1]], 1)
    )
    assert doubled.groups == ((0, 3), (1,), (2,)) and float(doubled.co_change[0, 3]) == 1.0
    with pytest.raises(ValueError, match="dependence must be"):
        coupled_groups(codes, next_codes, dependence=0.0)
    with pytest.raises(ValueError, match=r"one shape \[N, C\]"):
        coupled_groups(codes, next_codes[:5])


def test_save_load_round_trip_and_refusals(tmp_path):
    env = ObjectRearrangementEnv(num_objects=2, batch_size=(8,), seed=0)
    encoder = DiscreteCodeEncoder(EncoderConfig.small((8, 8)))
    graph = CodeGraph.from_play_data(collect_play_data(env, 512, seed=0), encoder, groups="full")
    path = graph.save(tmp_path / "graph.pt")
    loaded = CodeGraph.load(path, encoder=encoder, env_config=env.config())
    for key, value in graph.state_dict().items():
        assert torch.equal(value, loaded.state_dict()[key])
    assert loaded.groups == [[0, 1]] and loaded.code_sizes == (8, 8)
    other = DiscreteCodeEncoder(EncoderConfig.small((8, 8)))
    with pytest.raises(ValueError, match="another encoder"):
        CodeGraph.load(path, encoder=other)
    with pytest.raises(ValueError, match=r"codes of sizes \(8, 8\).*sizes \(8, 8, 8\)"):
        CodeGraph.load(path, encoder=DiscreteCodeEncoder(EncoderConfig.small((8, 8, 8))))
    with pytest.raises(ValueError, match="another environment.*num_objects"):
        CodeGraph.load(path, env_config=ObjectRearrangementEnv(num_objects=3).config())
    (tmp_path / "broken.pt").write_bytes(path.read_bytes()[:100])
    with pytest.raises(ValueError, match="corrupted"):
        CodeGraph.load(tmp_path / "broken.pt")


@pytest.mark.parametrize(
    ("groups", "message"),
    [
        ([(0,), (1,)], r"leave one-hots \[2\] out"),
        ([(0, 1), (1, 2)], "one-hot 1 is in group 0 and group 1"),
        ([(0, 1, 2, 3)], "names one-hot 3"),
        ([(0, 1, 2), ()], "group 1 .* is empty"),
        ("pairs", "must be 'onehot', 'full', 'auto'"),
    ],
)
def test_bad_groups_are_refused(groups, message):
    codes, next_codes = random_walk_codes(3, 4, 20)
    with pytest.raises(ValueError, match=message):
        CodeGraph.from_transitions(codes, next_codes, (4, 4, 4), groups)


def test_bad_codes_are_refused():
    codes, next_codes = random_walk_codes(2, 4, 20)
    with pytest.raises(ValueError, match=r"shape \[N, 3\]"):
        CodeGraph.from_transitions(codes, next_codes, (4, 4, 4))
    with pytest.raises(ValueError, match="int64"):
        CodeGraph.from_transitions(codes.float(), next_codes, (4, 4))
    with pytest.raises(ValueError, match="code 3 for one-hot 0, which has 2 codes"):
        CodeGraph.from_transitions(codes.clamp_min(3), next_codes, (2, 4))


def test_buffers_can_be_shared_between_processes():
    codes, next_codes = random_walk_codes(3, 6, 500)
    graph = CodeGraph.from_transitions(codes, next_codes, (6, 6, 6), [(0, 1), (2,)])
    params = TensorDict.from_module(graph)
    params.share_memory_()  # what torchrl's collectors do with a policy's tensors
    assert all(t.is_shared() for t in params.values(True, True))


def test_group_of_edge_names_each_edges_group():
    code = torch.tensor([[0, 0], [1, 0], [1, 1]])
    nxt = torch.tensor([[1, 0], [1, 1], [2, 1]])
    graph = CodeGraph.from_transitions(code, nxt, (3, 2))
    groups = graph.group_of_edge(torch.arange(graph.indices.shape[0]))
    sources = graph.edge_source[torch.arange(graph.indices.shape[0])]
    expected = (sources >= graph.node_offsets[1]).long()
    assert torch.equal(groups, expected) and set(groups.tolist()) == {0, 1}
    assert graph.group_of_edge(-1).item() == -1
    with pytest.raises(ValueError, match="edge ids"):
        graph.group_of_edge(graph.indices.shape[0])


def test_completion_adds_the_edges_of_one_member_moving_alone():
    # Member 0 was seen moving 0 -> 1 only while member 1 held 0; member 1 moving 0 -> 1
    # only while member 0 held 0. The joint codes (1, 1) and (2, 1) were seen, never
    # entered or left: in the play data's graph they are cut off from (0, 0).
    codes = torch.tensor([[0, 0], [0, 0], [1, 1], [2, 1], [2, 1]])
    nexts = torch.tensor([[1, 0], [0, 1], [1, 1], [2, 1], [2, 1]])
    graph = CodeGraph.from_transitions(codes, nexts, (3, 2), [(0, 1)])
    start, goal = torch.tensor([0, 0]), torch.tensor([1, 1])
    assert graph.shortest_path(0, start, goal) == []
    done = graph.completed()
    node = {tuple(graph.node_code(i).tolist()): i for i in range(graph.num_nodes(0))}
    # (1, 0) -> (1, 1) by member 1's move and (0, 1) -> (1, 1) by member 0's; (2, 1)
    # stays apart: no member was seen moving to or from code 2.
    edges = {(int(a), int(b)) for a, b in zip(done.edge_source, done.indices, strict=True)}
    added = edges - {
        (int(a), int(b)) for a, b in zip(graph.edge_source, graph.indices, strict=True)
    }
    assert added == {
        (node[1, 0], node[1, 1]),
        (node[1, 1], node[1, 0]),
        (node[0, 1], node[1, 1]),
        (node[1, 1], node[0, 1]),
    }
    assert len(done.shortest_path(0, start, goal)) == 3
    assert done.shortest_path(0, start, torch.tensor([2, 1])) == []
    # Seen edges keep their counts, added ones count 0; nodes are unchanged.
    for a, b, count in zip(done.edge_source, done.indices, done.edge_counts, strict=True):
        key = (int(a), int(b))
        assert int(count) == (0 if key in added else 1)
    assert torch.equal(done.node_keys, graph.node_keys)
    # Groups of one one-hot have nothing to complete.
    single = CodeGraph.from_transitions(codes, nexts, (3, 2), "onehot")
    assert torch.equal(single.completed().indices, single.indices)


def test_settings_complete_the_graphs_their_profile_allows():
    from dorp_rl.eval import setting_of

    assert setting_of("5obj").completes_graph() and not setting_of("5obj-full").completes_graph()
    assert not setting_of("keywall").completes_graph()  # agent and key bit change together
    setting = setting_of("5obj")
    env = setting.make_env(batch_size=(4,), seed=0)
    play = collect_play_data(env, 3000, seed=0)
    oracle = OracleCodeEncoder(env, cell_size=8)
    plain = CodeGraph.from_play_data(play, oracle, setting.groups)
    made = setting.make_graph(play, oracle)
    assert torch.equal(made.indices, plain.completed().indices)
    assert made.num_edges(1) > plain.num_edges(1) and made.num_edges(0) >= plain.num_edges(0)


@pytest.mark.parametrize("dense_limit", [1024, 0])
def test_next_waypoints_answer_rows_of_several_groups_with_their_own_removed_edges(dense_limit):
    """One batched search: every row's next hop is one step down a shortest path of the
    graph without that row's removed edges (networkx as reference), the most-seen edge
    among the equally short ones, whatever the other rows ask."""
    codes, next_codes = random_walk_codes(3, 6, 3000)
    graph = CodeGraph.from_transitions(
        codes, next_codes, (6, 6, 6), [(0, 1), (2,)], dense_limit=dense_limit
    )
    gen = torch.Generator().manual_seed(0)
    rows = 40
    group = torch.randint(0, graph.num_groups, (rows,), generator=gen)
    pick = torch.randint(0, codes.shape[0], (2, rows), generator=gen)
    nodes = graph.nodes_of(codes[pick[0]], group)
    goals = graph.nodes_of(next_codes[pick[1]], group)
    removed = torch.full((rows, 3), -1)
    for i in range(rows):  # a few of the row's own group's edges, some rows none
        lo = int(graph.indptr[graph.node_offsets[group[i]]])
        hi = int(graph.indptr[graph.node_offsets[group[i] + 1]])
        count = i % 4
        removed[i, :count] = torch.randint(lo, hi, (count,), generator=gen)
    nxt, edge, distance = graph.next_waypoints(nodes, goals, removed)
    for i in range(rows):
        members = graph.groups[int(group[i])]
        ref = reference_graph(codes, next_codes, members)
        gone = [int(e) for e in removed[i] if e >= 0]
        for e in gone:
            a, b = int(graph.edge_source[e]), int(graph.indices[e])
            ref.remove_edges_from(
                [(tuple(graph.node_code(a).tolist()), tuple(graph.node_code(b).tolist()))]
            )
        start = tuple(graph.node_code(int(nodes[i])).tolist())
        goal = tuple(graph.node_code(int(goals[i])).tolist())
        if not nx.has_path(ref, start, goal):
            assert (int(nxt[i]), int(edge[i]), int(distance[i])) == (-1, -1, -1)
            continue
        expected = nx.shortest_path_length(ref, start, goal)
        assert int(distance[i]) == expected
        if expected == 0:
            assert int(nxt[i]) == int(nodes[i]) and int(edge[i]) == -1
            continue
        hop = tuple(graph.node_code(int(nxt[i])).tolist())
        assert ref.has_edge(start, hop)
        assert nx.shortest_path_length(ref, hop, goal) == expected - 1
        assert int(graph.edge_source[edge[i]]) == int(nodes[i])
        assert int(graph.indices[edge[i]]) == int(nxt[i])
        # the most-seen edge among the hops one step closer
        closer = [
            int(graph.edge_counts[e])
            for e in range(int(graph.indptr[nodes[i]]), int(graph.indptr[nodes[i] + 1]))
            if e not in gone
            and int(graph.edge_reverse[e]) not in gone
            and nx.has_path(ref, tuple(graph.node_code(int(graph.indices[e])).tolist()), goal)
            and nx.shortest_path_length(
                ref, tuple(graph.node_code(int(graph.indices[e])).tolist()), goal
            )
            == expected - 1
        ]
        assert int(graph.edge_counts[edge[i]]) == max(closer)
        # the same answer asked alone
        assert graph.next_waypoint(int(nodes[i]), int(goals[i]), removed[i]) == (
            int(nxt[i]),
            int(edge[i]),
            int(distance[i]),
        )
    assert (distance >= 1).sum() > rows // 2  # the draw asked real questions


def test_node_codes_give_each_node_s_group_codes():
    codes, next_codes = random_walk_codes(3, 6, 500)
    graph = CodeGraph.from_transitions(codes, next_codes, (6, 6, 6), [(0, 2), (1,)])
    nodes = torch.arange(graph.node_offsets[-1].item())
    values, onehots = graph.node_codes(nodes)
    for node in nodes.tolist():
        group = 0 if node < int(graph.node_offsets[1]) else 1
        assert onehots[node].nonzero().squeeze(-1).tolist() == sorted(graph.groups[group])
        assert values[node, graph.groups[group]].tolist() == graph.node_code(node).tolist()
