"""The scenario timeline: one sans-IO player for scripted changes and mobility."""

from __future__ import annotations

import textwrap

import pytest

from mso.model.mobility import WaypointTracks
from mso.scenario import loads_scenario
from mso.scenario.format import NodeFailure, NodeRestart
from mso.scenario.timeline import Crash, Cut, LinksChanged, Move, Restart, Timeline

SQUARE = """
nodes: {A: {}, B: {}, C: {}, D: {}}
link_defaults: {delay_ms: 2}
links: [[A, B], [B, C], [C, D], [D, A]]
changes:
"""


def timeline(changes: str) -> Timeline:
    return Timeline(loads_scenario(SQUARE + textwrap.indent(textwrap.dedent(changes), "  ")))


def links(tl: Timeline) -> set[tuple[str, str]]:
    return set(tl.network.links)


def test_a_failure_takes_the_nodes_links_and_a_restart_brings_them_back_first() -> None:
    tl = timeline("""
    - {at: 1, fail: B}
    - {at: 2, down: [C, D]}
    - {at: 3, restart: B}
    """)
    assert tl.next_at() == 1
    assert tl.advance(0.5) == []
    crash = tl.advance(1.0)
    assert crash[0] == Crash(1.0, "B")
    assert isinstance(crash[1], LinksChanged) and set(crash[1].removed) == {("A", "B"), ("B", "C")}
    assert links(tl) == {("C", "D"), ("A", "D")}
    tl.advance(2.0)
    assert links(tl) == {("A", "D")}
    back = tl.advance(10.0)
    # the driver must see the links before it starts the node (Simulation.revive wants them)
    assert isinstance(back[0], LinksChanged) and back[1] == Restart(3.0, "B")
    assert links(tl) == {("A", "B"), ("B", "C"), ("A", "D")}  # C-D stays down
    assert tl.network.link("A", "B") is not None and tl.network.link("A", "B").delay_ms == 2.0
    assert tl.next_at() is None


def test_a_partition_cuts_links_across_groups_and_a_heal_restores_what_the_radio_gives() -> None:
    tl = timeline("""
    - {at: 1, partition: [[A, B], [C]]}
    - {at: 2, down: [A, B]}
    - {at: 3, heal: true}
    """)
    tl.advance(1.0)
    # D is in no group: it sides with the other unlisted nodes (none), so it is cut off too
    assert links(tl) == {("A", "B")}
    tl.advance(2.0)
    assert links(tl) == set()
    (healed,) = tl.advance(3.0)
    assert isinstance(healed, LinksChanged) and healed.removed == ()
    assert links(tl) == {("B", "C"), ("C", "D"), ("A", "D")}
    assert [what for _, what in tl.played] == ["partition A,B | C", "down A-B", "heal"]


def test_a_restart_during_a_partition_links_the_node_on_its_side_only() -> None:
    tl = timeline("""
    - {at: 1, fail: A}
    - {at: 2, partition: [[A, B], [C, D]]}
    - {at: 3, restart: A}
    """)
    tl.advance(3.0)
    assert links(tl) == {("A", "B"), ("C", "D")}


def test_loss_changes_one_link_or_every_link() -> None:
    tl = timeline("""
    - {at: 1, loss: 0.2, between: [B, A]}
    - {at: 2, loss: 0.05}
    - {at: 3, loss: 0.3, between: [C, D]}
    """)
    (changed,) = tl.advance(1.0)
    assert isinstance(changed, LinksChanged) and [(s.a, s.b, s.loss) for s in changed.added] == [
        ("A", "B", 0.2)
    ]
    tl.advance(3.0)
    loss = {k: s.loss for k, s in tl.network.links.items()}
    assert loss == {("A", "B"): 0.05, ("B", "C"): 0.05, ("C", "D"): 0.3, ("A", "D"): 0.05}
    tl.advance(3.0)  # nothing left: nothing changes
    assert {k: s.loss for k, s in tl.network.links.items()} == loss


def test_a_loss_lifted_for_every_link_is_lifted_on_a_link_that_was_down_then() -> None:
    """A link down while the loss on every link was lifted comes back lossless, not with the
    loss it had before it went down (fault seed 74864: 26% loss on one link through the
    whole quiet phase of a schedule, which stalled its sinks)."""
    tl = timeline("""
    - {at: 1, loss: 0.26, between: [C, D]}
    - {at: 2, down: [C, D]}
    - {at: 3, loss: 0}
    - {at: 4, up: [C, D]}
    """)
    tl.advance(4.0)
    assert {k: s.loss for k, s in tl.network.links.items()} == {
        ("A", "B"): 0.0,
        ("B", "C"): 0.0,
        ("C", "D"): 0.0,
        ("A", "D"): 0.0,
    }


MOVING = """
radio_range: 120
nodes:
  R1: {pos: [0, 0]}
  R2: {pos: [100, 0]}
  R3: {pos: [200, 0]}
mobility: {model: random_waypoint, area: [300, 300], speed: [20, 60], seed: 4, fixed: [R1],
           step_s: 0.5}
changes:
  - {at: 1.0, fail: R3}
"""


def test_mobility_steps_relink_by_range_and_a_failed_node_stays_unlinked() -> None:
    sc = loads_scenario(MOVING)
    tl = Timeline(sc)
    tracks = WaypointTracks(sc.mobility, {"R1": (0, 0), "R2": (100, 0), "R3": (200, 0)})  # type: ignore[arg-type]
    seen = set()
    for _ in range(20):  # ten virtual seconds of 0.5 s steps
        at = tl.next_at()
        assert at is not None
        acts = tl.advance(at)
        pos = tracks.positions(at)
        near = {
            (a, b)
            for a, b in (("R1", "R2"), ("R1", "R3"), ("R2", "R3"))
            if ((pos[a][0] - pos[b][0]) ** 2 + (pos[a][1] - pos[b][1]) ** 2) ** 0.5 <= 120
            and (at < 1.0 or "R3" not in (a, b))
        }
        assert links(tl) == near, at
        seen |= {type(a).__name__ for a in acts}
    assert tl.positions["R1"] == (0, 0)  # fixed
    assert {"Crash", "LinksChanged"} <= seen


def test_the_timeline_can_play_only_the_changes_or_only_mobility() -> None:
    sc = loads_scenario(MOVING)
    only_changes = Timeline(sc, mobility=False)
    assert only_changes.next_at() == 1.0
    only_changes.advance(1.0)
    assert only_changes.next_at() is None
    only_mobility = Timeline(loads_scenario(MOVING), changes=False)
    assert only_mobility.next_at() == 0.5
    assert all(not isinstance(a, Crash) for a in only_mobility.advance(5.0))


def test_an_operator_cut_holds_until_healed_and_a_node_found_dead_loses_its_links() -> None:
    tl = timeline("""
    - {at: 5, up: [A, B]}
    - {at: 6, restart: B}
    """)
    (cut,) = tl.apply(Cut(1.0, "B", "A"))
    assert isinstance(cut, LinksChanged) and cut.removed == (("A", "B"),)
    tl.advance(5.0)  # a scripted `up` does not undo an operator's cut
    assert ("A", "B") not in links(tl)
    # a node killed by hand (no script said so): its links go, a scripted restart brings it back
    crash = tl.apply(NodeFailure(5.5, "C"))
    assert crash[0] == Crash(5.5, "C") and links(tl) == {("A", "D")}
    assert tl.advance(6.0) == []  # B never failed: its restart is nothing to do
    back = tl.apply(NodeRestart(7.0, "C"))
    assert back[-1] == Restart(7.0, "C") and links(tl) == {("B", "C"), ("C", "D"), ("A", "D")}
    tl.apply(Cut(8.0, "A", "B", cut=False))
    assert links(tl) == {("A", "B"), ("B", "C"), ("C", "D"), ("A", "D")}
    with pytest.raises(ValueError, match="unknown node 'Z'"):
        tl.apply(Cut(9.0, "A", "Z"))


def test_a_node_moved_by_hand_relinks_by_range_and_stays_there() -> None:
    sc = loads_scenario(MOVING)
    tl = Timeline(sc, changes=False)
    tl.apply(Move(0.1, "R3", (0.0, 50.0)))  # next to R1
    assert ("R1", "R3") in links(tl)
    for _ in range(6):  # mobility moves R2, never R3 again
        at = tl.next_at()
        assert at is not None
        tl.advance(at)
        assert tl.positions["R3"] == (0.0, 50.0) and ("R1", "R3") in links(tl)
