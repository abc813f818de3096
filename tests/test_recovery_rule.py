"""The recovery rule as pure functions of what every node holds (remap.py): who coordinates,
when the routes allow it, what is remapped, what parks. Every node must derive the same
answers from the same placement and failure set."""

from __future__ import annotations

from mso.model.appfile import loads_app
from mso.planning.placement import Layout
from mso.protocol.procedures.remap import (
    pinned_to_failed,
    recovery_coordinator,
    recovery_plan,
    routes_settled,
)

# two chains: src -> a -> join and join -> b -> sink (join ends one, heads the other)
TWO = """
name: two
vertices:
  src: {pinned: N1}
  a: {}
  join: {}
  other: {pinned: N1}
  b: {}
  sink: {pinned: N5}
edges:
  - [src, a]
  - [a, join]
  - [other, join]
  - [join, b]
  - [b, sink]
"""
PLACED = {"src": "N1", "a": "N2", "join": "N3", "other": "N1", "b": "N4", "sink": "N5"}


def layout() -> Layout:
    return Layout(loads_app(TWO), "N1")


def test_the_lowest_node_still_hosting_part_of_the_app_coordinates() -> None:
    assert recovery_coordinator(PLACED, {"a"}, {"N1", "N3", "N4", "N5"}) == "N1"
    placed = PLACED | {"src": "N6", "other": "N6"}  # N1 hosts nothing of it any more
    assert recovery_coordinator(placed, {"a"}, {"N1", "N3", "N6"}) == "N3"


def test_with_every_instance_gone_the_lowest_node_alive_coordinates() -> None:
    lost = set(PLACED)
    assert recovery_coordinator(PLACED, lost, {"N4", "N7", "N9"}) == "N4"


def test_a_recovery_waits_for_routes_that_go_around_the_failed_node() -> None:
    assert not routes_settled({"N3": ("N2", 2)}, {"N2"})  # a next hop through it
    assert not routes_settled({"N2": ("N2", 1)}, {"N2"})  # still a destination
    assert routes_settled({"N3": ("N4", 2)}, {"N2"})


def test_an_interior_vertex_lost_is_a_chain_remap_of_its_chain_only() -> None:
    lay = layout()
    plan = recovery_plan(lay, PLACED, {"a"}, parked=set())
    assert plan is not None and plan.kind == "chain"
    touched = [list(lay.chains[c].vertices) for c in plan.chains]
    assert touched == [["src", "a", "join"]]
    assert plan.movable == {"a"}  # its ends and everything else stay where they are
    assert plan.stays == {v: n for v, n in PLACED.items() if v != "a"}


def test_a_lost_chain_end_is_a_global_remap_of_every_chain_it_ends_or_heads() -> None:
    lay = layout()
    plan = recovery_plan(lay, PLACED, {"join"}, parked=set())
    assert plan is not None and plan.kind == "global"
    chains = [list(lay.chains[c].vertices) for c in plan.chains]
    assert ["join", "b", "sink"] in chains and ["src", "a", "join"] in chains
    assert chains.index(["src", "a", "join"]) < chains.index(["join", "b", "sink"])  # in order
    assert "join" in plan.movable and "src" not in plan.movable and "sink" not in plan.movable


def test_parked_chains_are_not_remapped_and_pins_to_a_failed_node_park() -> None:
    lay = layout()
    app = loads_app(TWO)
    parked = pinned_to_failed(app, lay, {"N5"})
    assert [list(lay.chains[c].vertices) for c in parked] == [["join", "b", "sink"]]
    assert "pinned to failed node N5" in next(iter(parked.values()))
    assert recovery_plan(lay, PLACED, {"b", "sink"}, parked=set(parked)) is None
    assert pinned_to_failed(app, lay, {"N2"}) == {}  # nothing is pinned there


def test_with_every_instance_lost_a_live_holder_coordinates_not_the_lowest_node() -> None:
    """Only the nodes that take part in an app hold it (issue 24.1): with every instance
    gone at once, the lowest-named node alive may hold none of it; the app's origin (or a
    replica's node) coordinates instead."""
    placed = {"a": "N5", "b": "N5"}
    alive = {"N1", "N2", "N3"}
    assert recovery_coordinator(placed, {"a", "b"}, alive, {"N3", "N9"}) == "N3"
    assert recovery_coordinator(placed, {"a", "b"}, alive, {"N9"}) == "N1"  # none left


def test_every_vertex_on_one_failed_node_is_recovered_by_the_origin() -> None:
    """The whole app on N3 (origin N2, which runs nothing of it), N3 fails: N1, the lowest
    node alive, holds none of the app; N2 restores it all."""
    from mso.model.network import LinkSpec, Network, NodeSpec
    from mso.protocol import messages as m
    from mso.sim.runner import Simulation
    from runtime_vertices import pipe_app

    ids = ["N1", "N2", "N3", "N4"]
    links = [("N1", "N2"), ("N2", "N3"), ("N3", "N4"), ("N4", "N1"), ("N2", "N4")]
    sim = Simulation(Network([NodeSpec(i) for i in ids], [LinkSpec(a, b, 1.0) for a, b in links]))
    doc = pipe_app(50).replace("pinned: N1", "pinned: N3").replace("pinned: N4", "pinned: N3")
    doc = doc.replace("planner: paper\n", "")
    sim.request("N2", m.DeployRequest(doc, "app.yaml"))
    sim.run_until(2.0)
    assert set(sim.cores["N3"].instances("pipe")) == {"src", "mid", "sink"}
    assert "pipe" not in sim.cores["N1"].apps
    sim.kill("N3", convergence_s=0.2)
    sim.network.add_link(LinkSpec("N3", "N4", 1.0))  # (back at once, empty: a restart)
    sim.revive("N3")
    sim.run_until(sim.now + 5.0)
    assert set(sim.cores["N3"].instances("pipe")) == {"src", "mid", "sink"}
