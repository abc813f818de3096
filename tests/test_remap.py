"""Chain remapping (§3.4.2) and global remapping (§3.4.3) under load."""

from __future__ import annotations

from mso.model.network import LinkSpec, Network, NodeSpec
from mso.protocol import messages as m
from mso.sim.runner import Simulation

# planner: paper: the scenario needs the chains spread over the route (it remaps and moves them);
# the default bytes split keeps the 64-byte edges on the sources' node
MERGE = """
name: merge
planner: paper
vertices:
  s1: {code: runtime_vertices:CountingSource, pinned: N1, rate: 200, output: runtime_vertices:Num}
  s2: {code: runtime_vertices:CountingSource, pinned: N1, rate: 100, output: runtime_vertices:Num}
  a: {code: runtime_vertices:Double, output: runtime_vertices:Num}
  b: {code: runtime_vertices:Double, output: runtime_vertices:Num}
  m: {code: runtime_vertices:Double, output: runtime_vertices:Num}
  c: {code: runtime_vertices:Double, output: runtime_vertices:Num}
  counter: {code: runtime_vertices:Counter, output: runtime_vertices:Num}
  d: {code: runtime_vertices:Double, output: runtime_vertices:Num}
  sink: {code: runtime_vertices:Recorder, pinned: N5}
edges: [[s1, a], [a, m], [s2, b], [b, m], [m, c], [c, counter], [counter, d], [d, sink]]
"""


def line5() -> Network:
    nodes = [NodeSpec(f"N{i}") for i in range(1, 6)]
    return Network(nodes, [LinkSpec(f"N{i}", f"N{i + 1}", delay_ms=1.0) for i in range(1, 5)])


def started(net: Network) -> Simulation:
    sim = Simulation(net)
    sim.request("N1", m.DeployRequest(MERGE, "merge.yaml"))
    sim.run_until(1.0)
    reply = sim.replies[-1][2]
    assert isinstance(reply, m.DeployReply) and reply.ok, reply
    return sim


def remap(sim: Simulation, via: str, chains: list[int], everything: bool = False) -> m.RemapReply:
    n = len(sim.replies)
    sim.request(via, m.RemapRequest("merge", chains, everything))
    sim.run_until(sim.now + 0.5)
    (reply,) = [r for _, _, r in sim.replies[n:]]
    assert isinstance(reply, m.RemapReply)
    return reply


def accounting(sim: Simulation) -> tuple[dict[str, int], int]:
    sink = sim.cores["N5"].status(sim.now)["apps"]["merge"]["vertices"]["sink"]["stats"]
    stones = sim.cores["N1"].instances("merge")
    return sink, stones["s1"].emitted + stones["s2"].emitted


def chain_index(sim: Simulation, head: str, tail: str) -> int:
    chains = sim.cores["N1"].apps["merge"].layout.chains
    return next(c.index for c in chains if c.head == head and c.tail == tail)


def test_chain_remap_follows_a_shorter_route_and_loses_nothing() -> None:
    net = line5()
    sim = started(net)
    tail_chain = chain_index(sim, "m", "sink")
    before = dict(sim.cores["N1"].placement("merge"))
    net.add_link(LinkSpec("N2", "N5", delay_ms=1.0))  # the convoy closes up: a shortcut (Fig. 4)
    sim.update_routes()
    reply = remap(sim, "N3", [tail_chain])
    assert reply.ok, reply.error
    placed = sim.cores["N4"].placement("merge")
    assert reply.moved and all(placed[v] == n for v, n in reply.moved.items())
    assert placed["m"] == before["m"] and placed["sink"] == "N5"  # head and tail stay
    assert all(placed[v] in ("N2", "N5") for v in ("c", "counter", "d"))  # along the new route
    sim.run_until(sim.now + 1.0)
    sink, emitted = accounting(sim)
    assert sink["repeats"] == 0 and sink["out_of_order"] == 0
    assert emitted - 10 <= sink["count"] <= emitted


def test_global_remap_in_dependency_order_loses_nothing() -> None:
    net = line5()
    sim = started(net)
    for node in ("N2", "N3"):  # the middle robots get faster: more should run on them
        net.nodes[node] = NodeSpec(node, cpu=4.0)
        sim.cores[node].capacity = 4.0
    reply = remap(sim, "N5", [], everything=True)
    assert reply.ok, reply.error
    assert reply.moved  # work moved toward the faster nodes
    sim.run_until(sim.now + 1.0)
    sink, emitted = accounting(sim)
    assert sink["repeats"] == 0 and sink["out_of_order"] == 0
    assert emitted - 10 <= sink["count"] <= emitted
    # every node agrees on the mapping, and each vertex runs exactly once
    maps = [dict(c.placement("merge")) for c in sim.cores.values()]
    assert all(mp == maps[0] for mp in maps)
    for v, node in maps[0].items():
        hosts = [n for n, c in sim.cores.items() if v in c.instances("merge")]
        assert hosts == [node]


def test_remap_refuses_unknown_chains() -> None:
    sim = started(line5())
    reply = remap(sim, "N2", [99])
    assert not reply.ok and "unknown chain 99" in reply.error


def test_reconfigurations_of_different_chains_at_the_same_time() -> None:
    net = line5()
    sim = started(net)
    n = len(sim.replies)
    # a relocation in one chain and a remap of another, requested at once from two nodes
    sim.request("N2", m.RelocateRequest("merge", "a", "upstream"))
    sim.request("N4", m.RelocateRequest("merge", "counter", "upstream"))
    sim.request("N3", m.RemapRequest("merge", [chain_index(sim, "s2", "m")]))
    sim.run_until(sim.now + 1.0)
    replies = [r for _, _, r in sim.replies[n:]]
    assert len(replies) == 3
    assert all(getattr(r, "ok", False) for r in replies), replies
    sink, emitted = accounting(sim)
    assert sink["repeats"] == 0 and sink["out_of_order"] == 0
    assert emitted - 10 <= sink["count"] <= emitted
    maps = [dict(c.placement("merge")) for c in sim.cores.values()]
    assert all(mp == maps[0] for mp in maps)
