"""Whether a node out of reach must be declared: pure functions of the app and its placement."""

from __future__ import annotations

from mso.model.appfile import loads_app
from mso.protocol.procedures.membership.reach import re_placeable, replacing_helps

# two sources merged at m, then to a sink: s1 on N1, s2 on N2, the sink on N5
MERGE = loads_app("""
name: merge
vertices:
  s1: {code: mso.sim.vertices:Source, pinned: N1, rate: 10, output: mso.sim.vertices:Ev}
  s2: {code: mso.sim.vertices:Source, pinned: N2, rate: 10, output: mso.sim.vertices:Ev}
  m: {code: mso.sim.vertices:Pass, output: mso.sim.vertices:Ev}
  sink: {code: mso.sim.vertices:Sink, pinned: N5, params: {run: r}}
edges: [[s1, m], [s2, m], [m, sink]]
""")
PLACED = {"s1": "N1", "s2": "N2", "m": "N3", "sink": "N5"}


def test_a_vertex_is_re_placed_only_if_a_source_and_a_sink_it_joins_are_in_reach() -> None:
    assert replacing_helps(MERGE, {}, "m", {"N3"})
    assert replacing_helps(MERGE, {}, "m", {"N3", "N2"})  # s1 still reaches the sink
    assert not replacing_helps(MERGE, {}, "m", {"N3", "N5"})  # the sink is away
    assert not replacing_helps(MERGE, {}, "m", {"N3", "N1", "N2"})  # both sources away
    assert not replacing_helps(MERGE, {}, "sink", {"N5"})  # pinned: it cannot move


def test_a_vertex_fed_from_another_node_out_of_reach_is_not_re_placed() -> None:
    assert re_placeable(MERGE, PLACED, {}, "m", {"N3"})
    # s2's node is away too: s2 may be feeding m on N3, a replacement would be its twin
    assert not re_placeable(MERGE, PLACED, {}, "m", {"N3", "N2"})
    # a producer on m's own node does not count (it is out of reach with m)
    assert re_placeable(MERGE, PLACED | {"s1": "N3"}, {}, "m", {"N3"})


# seed 17236's shape: two branches into a merge m, then a stateful c and the sink
BRANCHES = loads_app("""
name: branches
vertices:
  s1: {code: mso.sim.vertices:Source, pinned: N2, rate: 10, output: mso.sim.vertices:Ev}
  s2: {code: mso.sim.vertices:Source, pinned: N5, rate: 10, output: mso.sim.vertices:Ev}
  a: {code: mso.sim.vertices:Pass, output: mso.sim.vertices:Ev}
  b: {code: mso.sim.vertices:Pass, output: mso.sim.vertices:Ev}
  m: {code: mso.sim.vertices:Pass, output: mso.sim.vertices:Ev}
  c: {code: mso.sim.vertices:Count, output: mso.sim.vertices:Ev}
  sink: {code: mso.sim.vertices:Sink, pinned: N5, params: {run: r}}
edges: [[s1, a], [a, m], [s2, b], [b, m], [m, c], [c, sink]]
""")
SPREAD = {"s1": "N2", "a": "N2", "s2": "N5", "b": "N4", "m": "N3", "c": "N4", "sink": "N5"}


def test_a_vertex_that_would_only_feed_a_merge_left_out_of_reach_is_not_re_placed() -> None:
    # N5 alone: m stays where it is (a, on N2, may feed it there), so a replacement of b
    # would feed a merge nobody reaches; N4 is not declared for it
    assert not re_placeable(BRANCHES, SPREAD, {}, "b", {"N2", "N3", "N4"})
    # a in reach: b is re-placed, m on the path with it (b is its only producer away); m
    # itself is not (b may feed it there): it follows once b's node is declared
    assert re_placeable(BRANCHES, SPREAD, {}, "b", {"N3", "N4"})
    assert not re_placeable(BRANCHES, SPREAD, {}, "m", {"N3", "N4"})
    # a chain across two nodes out of reach is re-placed from its head
    chain = SPREAD | {"m": "N4", "c": "N3"}
    assert re_placeable(BRANCHES, chain, {}, "c", {"N3"})
    assert not re_placeable(BRANCHES, chain, {}, "c", {"N3", "N4"})  # m on N4 may feed it
