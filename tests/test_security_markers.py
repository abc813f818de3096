"""A move's markers carry a warrant too, and a chain end's remap is bounded (issue 27).

With operator keys, a vertex's host hands it over at a marker only for a move it holds a
warrant for — one it coordinates, or one whose coordinator told it with a ``Moving`` it
checked as a ``Prepare`` (mso.protocol.warrant.Leaving). The producer of every input of a
vertex used to steer its handover: it switched its own edge to a node it named (itself, with
an instance it prepared there) and the host handed the vertex's state to it at the marker.
A chain end's remap moves a vertex at most once per interval at each node, and not at all
without an operator's order on nodes told ``strict_moves``.

The simulator's line N1 - N2 - N3 - N4 - N5 runs src -> a -> b -> c -> sink, one vertex a
node; the captured N2 hosts ``a``, which feeds every input of ``b`` (on N3)."""

from __future__ import annotations

import itertools
from pathlib import Path

import pytest

from mso.daemon.config import NodeFlags, settle
from mso.errors import MsoError
from mso.management import RemapChain
from mso.protocol import messages as m
from mso.protocol.procedures.relocation import SWITCH_DEADLINE_S
from mso.protocol.warrant import CHAIN_END_INTERVAL_S, HOLD_S
from mso.sim.runner import Simulation
from test_captured_robot import OPERATOR, robot
from test_security_steps import PLACED, flows_on, line, order, sink


def test_the_producer_of_every_input_cannot_have_a_vertex_handed_to_it() -> None:
    """N2 prepares ``b`` on itself and switches its own edge to it: its marker reaches N3,
    which holds no warrant for that move and keeps ``b`` (and its state); the marker is
    refused and counted once the move's deadline has passed."""
    sim = line()
    host = sim.cores["N3"]
    processed = host.instances("line")["b"].processed
    robot(sim, "N2", m.Prepare("line", "b", 70), src="N2")  # its own node: no warrant needed
    robot(sim, "N2", m.Switch("line", 1, "N2", 70), src="N2")
    sim.run_until(sim.now + 1.0)
    assert "b" in host.apps["line"].instances and "b" not in sim.cores["N2"].apps["line"].instances
    assert host.instances("line")["b"].processed >= processed  # its state stayed with it
    assert all(c.apps["line"].placed["b"] == "N3" for n, c in sim.cores.items() if n != "N2")
    assert "marker_no_warrant" not in host.refusals  # (it waits for its move's Moving)
    sim.run_until(sim.now + HOLD_S + 1.5)
    assert host.refusals["marker_no_warrant"] == 1
    assert "b" in host.apps["line"].instances


def test_a_marker_that_comes_before_its_moves_warrant_waits_for_it() -> None:
    """An operator's move of ``b`` to N4, coordinated by N5 (neither b's host nor an end of
    its chain) on the order it carries: N2 switches on it and its marker reaches N3 before
    the coordinator's ``Moving`` does. N3 keeps it until the ``Moving`` comes, then hands
    ``b`` over; the stream goes on with nothing lost, repeated or reordered."""
    sim = line()
    flowing = sink(sim)["processed"]
    ordered = order(m.RelocateRequest("line", "b", target="N4"))
    robot(sim, "N4", m.Prepare("line", "b", 71, order=ordered), src="N5")
    sim.run_until(sim.now + 0.1)
    assert "b" in sim.cores["N4"].apps["line"].awaiting
    robot(sim, "N2", m.Switch("line", 1, "N4", 71, order=ordered), src="N5")
    sim.run_until(sim.now + 0.2)
    host = sim.cores["N3"]
    assert "b" in host.apps["line"].instances  # the marker is in, and waits
    robot(sim, "N3", m.Moving("line", "b", 71, "N4", ordered), src="N5")
    sim.run_until(sim.now + 0.2)
    assert "b" not in host.apps["line"].instances
    assert "b" in sim.cores["N4"].apps["line"].instances
    assert all(c.apps["line"].placed == dict(PLACED, b="N4") for c in sim.cores.values())
    flows_on(sim, flowing)
    got = sink(sim)
    assert got["count"] == got["next"], got  # every number once, none skipped


def test_a_moving_without_a_warrant_is_refused_and_takes_no_marker() -> None:
    """The captured N2 tells N3 of its own move of ``b`` to N2: N3 checks its warrant as a
    ``Prepare``'s (N2 neither hosts b nor ends its chain) and refuses it."""
    sim = line()
    host = sim.cores["N3"]
    robot(sim, "N3", m.Moving("line", "b", 72, "N2"), src="N2")
    assert host.refusals["move_no_warrant"] == 1
    robot(sim, "N2", m.Prepare("line", "b", 72), src="N2")
    robot(sim, "N2", m.Switch("line", 1, "N2", 72), src="N2")
    sim.run_until(sim.now + 1.0)
    assert "b" in host.apps["line"].instances


# -- a chain end's remap (the line is one chain: src on N1 heads it, the sink on N5 ends it) --
def test_a_chain_end_moves_a_vertex_of_its_chain_at_most_once_per_interval() -> None:
    """The captured N1 hosts the chain's head: its remap may move ``c`` (its rules may), but
    a second move of ``c`` on that warrant within the interval is refused at each node, and
    taken again once the interval has passed."""
    sim = line()
    target = sim.cores["N3"]
    robot(sim, "N3", m.Prepare("line", "c", 80), src="N1")
    assert "c" in target.apps["line"].awaiting  # a chain end's remap: warranted
    robot(sim, "N3", m.Unprepare("line", "c", 80), src="N1")
    robot(sim, "N3", m.Prepare("line", "c", 80), src="N1")  # (a step of the same move again)
    assert target.refusals.get("move_chain_end_too_often", 0) == 0
    robot(sim, "N3", m.Unprepare("line", "c", 80), src="N1")
    robot(sim, "N3", m.Prepare("line", "c", 81), src="N1")  # another move, within 10 s
    assert target.refusals["move_chain_end_too_often"] == 1
    assert "c" not in target.apps["line"].awaiting
    sim.run_until(sim.now + CHAIN_END_INTERVAL_S)
    robot(sim, "N3", m.Prepare("line", "c", 82), src="N1")
    assert "c" in target.apps["line"].awaiting
    robot(sim, "N3", m.Unprepare("line", "c", 82), src="N1")


def test_with_strict_moves_a_chain_end_moves_nothing_of_its_chain_without_an_order() -> None:
    """Nodes told ``strict_moves``: the chain head's remap of ``c`` is refused at its
    target; the same move on an operator's order is taken; the head's own rules remap
    nothing (their remap is not started)."""
    sim = line()
    for core in sim.cores.values():
        core.authority.strict_moves = True
    target = sim.cores["N3"]
    robot(sim, "N3", m.Prepare("line", "c", 83), src="N1")
    assert target.refusals["move_chain_end_without_an_order"] == 1
    assert "c" not in target.apps["line"].awaiting
    ordered = order(m.RemapRequest("line", [0]))
    robot(sim, "N3", m.Prepare("line", "c", 84, order=ordered), src="N1")
    assert "c" in target.apps["line"].awaiting
    robot(sim, "N3", m.Unprepare("line", "c", 84), src="N1")
    head = sim.cores["N1"]
    head._carry_out(RemapChain("line", 0, "slo"), sim.now)  # what its rules would ask
    assert not [p for p in head.open() if p.name == "remap"]
    head.authority.strict_moves = False  # (the same action, not strict: a remap starts)
    head._carry_out(RemapChain("line", 0, "slo"), sim.now)
    assert [p for p in head.open() if p.name == "remap"]


def strict(flags: NodeFlags) -> bool:
    authority = settle(flags).authority
    assert authority is not None
    return authority.strict_moves


@pytest.mark.usefixtures("keep_allowlist")
def test_strict_moves_is_a_node_option_and_needs_an_operator_key(tmp_path: Path) -> None:
    pub = OPERATOR.public_text()
    cfg = tmp_path / "n1.yaml"
    cfg.write_text(f"id: N1\noperator_keys: [{pub}]\nstrict_moves: true\n")
    assert strict(NodeFlags(config_file=cfg))
    assert strict(NodeFlags(node_id="N1", operator_keys=(pub,), strict_moves=True))
    assert not strict(NodeFlags(node_id="N1", operator_keys=(pub,)))
    with pytest.raises(MsoError, match="--strict-moves needs --operator-key"):
        settle(NodeFlags(node_id="N1", strict_moves=True))
    cfg.write_text("id: N1\nstrict_moves: yes please\n")
    with pytest.raises(MsoError, match=r"strict_moves.*expected true or false"):
        settle(NodeFlags(config_file=cfg))


def test_a_chain_heads_remap_by_its_rules_moves_its_chains_vertices() -> None:
    """The honest case: N1's rules remap the chain, no operator's order, b and c kept off
    N3 and N4 (an energy remap's weights and places): every node takes every step (the
    hosts a ``Moving`` each), and the stream goes on, every event once and in order."""
    sim = line()
    flowing = sink(sim)["processed"]
    head = sim.cores["N1"]
    weights, place = {"N3": 0.0, "N4": 0.0}, {"b": "N2", "c": "N2"}
    head.remapper.remap(m.RemapRequest("line", [0]), sim.now, weights, place)
    sim.apply("N1", head._run(sim.now))  # (what the node's monitor tick hands its driver)
    sim.run_until(sim.now + 1.0)
    members = ("N1", "N2", "N5")
    assert all(sim.cores[n].apps["line"].placed == dict(PLACED, b="N2", c="N2") for n in members)
    assert not any(c.refusals for c in sim.cores.values())
    flows_on(sim, flowing)
    got = sink(sim)
    assert got["count"] == got["next"], got


def test_a_marker_is_taken_only_from_its_edges_producer() -> None:
    """An operator's move of ``b`` to N4, coordinated by N5 on its order: N3 (b's host) holds
    the move's ``Moving``, and N4 prepared ``b``. The captured N4 knows the move's number and
    target and sends N3 a marker of ``b``'s input edge before a's host N2 has switched: N3
    hands nothing over on it (it used to: the edge's drain ended early), then takes N2's own
    marker; the forged one is refused, counted, at the move's deadline. Every event once,
    in order."""
    sim = line()
    flowing = sink(sim)["processed"]
    host = sim.cores["N3"]
    ordered = order(m.RelocateRequest("line", "b", target="N4"))
    robot(sim, "N4", m.Prepare("line", "b", 73, order=ordered), src="N5")
    robot(sim, "N3", m.Moving("line", "b", 73, "N4", ordered), src="N5")
    sim.run_until(sim.now + 0.1)
    assert "b" in sim.cores["N4"].apps["line"].awaiting
    seq = host.apps["line"].inc[1].expected
    robot(sim, "N3", m.Marker("line", 1, seq, 73, "N4"), src="N4")
    sim.run_until(sim.now + 0.3)
    assert "b" in host.apps["line"].instances  # the forged marker ended nothing
    assert host.relocator.leaving.held == 1
    robot(sim, "N2", m.Switch("line", 1, "N4", 73, order=ordered), src="N5")
    sim.run_until(sim.now + 0.3)
    assert "b" not in host.apps["line"].instances  # a's host's own marker hands it over
    assert "b" in sim.cores["N4"].apps["line"].instances
    assert all(c.apps["line"].placed == dict(PLACED, b="N4") for c in sim.cores.values())
    flows_on(sim, flowing)
    got = sink(sim)
    assert got["count"] == got["next"], got  # every number once, none skipped
    sim.run_until(sim.now + HOLD_S + 1.5)
    assert host.refusals["marker_not_from_its_producer"] == 1


def test_a_chain_end_asking_as_fast_as_it_may_moves_each_vertex_once_per_interval() -> None:
    """The captured N5 (the sink's host: the chain's tail) asks its relocator every second
    for 12 s to move a, b and c round the other nodes. Each vertex moves at most once per
    interval (twice in 12 s), the rest refused, and the stream goes on: every event once,
    in order. (The old host used to keep the pace too, on its own clock: it refused the
    ``Moving`` of a move a producer had switched for, and the stream stopped.)"""
    sim = line()
    flowing = sink(sim)["processed"]
    end = sim.cores["N5"]
    dep = end.apps["line"]
    nodes = sorted(sim.cores)
    paths = {v: [dep.placed[v]] for v in ("a", "b", "c")}
    turn = itertools.count()
    for _ in range(12):
        for v in paths:
            others = [n for n in nodes if n != dep.placed[v]]
            to = others[next(turn) % len(others)]
            end.relocator.request(None, m.RelocateRequest("line", v, target=to), sim.now)
        sim.apply("N5", end._run(sim.now))
        sim.run_until(sim.now + 1.0)
        for v, path in paths.items():
            if dep.placed[v] != path[-1]:
                path.append(dep.placed[v])
    assert all(len(p) - 1 <= 2 for p in paths.values()), paths
    assert sum(len(p) - 1 for p in paths.values()) >= 3, paths  # (it did move them)
    assert sum(c.refusals.get("move_chain_end_too_often", 0) for c in sim.cores.values())
    flows_on(sim, flowing + 12 * 40)
    got = sink(sim)
    assert got["count"] == got["next"], got  # every number once, none skipped


def move(sim: Simulation, coordinator: str, vertex: str, to: str) -> None:
    """``coordinator``'s relocator moves ``vertex`` to ``to`` (its rules' way: no order)."""
    core = sim.cores[coordinator]
    assert core.relocator.request(None, m.RelocateRequest("line", vertex, target=to), sim.now)
    sim.apply(coordinator, core._run(sim.now))
    sim.run_until(sim.now + 1.0)


def test_an_instance_prepared_for_a_move_that_never_switched_does_not_take_a_later_one() -> None:
    """The captured N5 (the chain's tail) has N3 prepare ``c`` for a move it never switches.
    ``c``'s host N4 then moves it to N3 by its rules: refused while that move may still
    commit (it used to be answered as prepared, and the handover refused at N3: ``c``
    lost), and carried out once that move is past its deadline; every event once, in
    order."""
    sim = line()
    flowing = sink(sim)["processed"]
    robot(sim, "N3", m.Prepare("line", "c", 90), src="N5")
    assert "c" in sim.cores["N3"].apps["line"].awaiting
    host = sim.cores["N4"]
    assert host.relocator.request(None, m.RelocateRequest("line", "c", target="N3"), sim.now)
    sim.apply("N4", host._run(sim.now))
    sim.run_until(sim.now + 1.0)
    assert all(c.apps["line"].placed["c"] == "N4" for c in sim.cores.values())
    assert "c" in host.apps["line"].instances
    flows_on(sim, flowing)
    sim.run_until(sim.now + SWITCH_DEADLINE_S)
    move(sim, "N4", "c", "N3")
    assert all(c.apps["line"].placed == dict(PLACED, c="N3") for c in sim.cores.values())
    flows_on(sim, sink(sim)["processed"])
    got = sink(sim)
    assert got["count"] == got["next"], got


def c_moved_unheard_by_n6() -> tuple[Simulation, int]:
    """The line with N6 (hosting nothing, so told of no move) linked to N3: ``c`` moved N4
    -> N3 by its host's rules a chain end's interval ago; and where the sink stood."""
    sim = line(n6=("N3",))
    flowing = sink(sim)["processed"]
    move(sim, "N4", "c", "N3")
    n6 = sim.cores["N6"].apps.get("line")  # (it takes no part: issue 24.1, it holds none of
    assert n6 is None or n6.placed["c"] == "N4"  # the app, or it missed the Moved)
    sim.run_until(sim.now + CHAIN_END_INTERVAL_S)
    return sim, flowing


def test_a_target_that_missed_a_vertexs_last_move_takes_its_handover() -> None:
    """N6 hosts nothing of the app, so it hears none of its moves: ``c`` moves N4 -> N3 (its
    host's rules), then the chain's tail N5 remaps it on to N6, whose view still places
    ``c`` on N4. N6 takes the handover from N3, the node the move's ``Prepare`` names (it
    took it only from its own view's host, and ``c`` was lost); every event once, in
    order."""
    sim, flowing = c_moved_unheard_by_n6()
    move(sim, "N5", "c", "N6")
    assert "c" in sim.cores["N6"].apps["line"].instances
    assert "handover_not_from_its_host" not in sim.cores["N6"].refusals
    flows_on(sim, flowing)
    got = sink(sim)
    assert got["count"] == got["next"], got


def test_a_hosts_moving_does_not_keep_the_pace_its_producers_switch_by() -> None:
    """The chain's tail N5 tells ``c``'s host N4 of a move it never makes, then moves ``c``
    to N2 within the interval. The producer switches (it took no step of ``c`` before);
    the host takes the move's markers too (it used to refuse its ``Moving`` as too soon,
    hold the marker, keep ``c``: the producer's events went to a twin that never got the
    state, and the stream stopped). Every event once, in order."""
    sim = line()
    flowing = sink(sim)["processed"]
    robot(sim, "N4", m.Moving("line", "c", 95, "N3"), src="N5")
    move(sim, "N5", "c", "N2")
    assert all(c.apps["line"].placed == dict(PLACED, c="N2") for c in sim.cores.values())
    flows_on(sim, flowing)
    got = sink(sim)
    assert got["count"] == got["next"], got


def test_a_target_that_missed_a_neighbours_move_learns_it_from_the_moves_prepare() -> None:
    """N6 hosts nothing of the app, so it hears none of its moves: ``c`` moves N4 -> N3 (its
    host's rules); then the chain's tail N5 remaps ``b`` onto N6, which learns from the
    move's ``Prepare`` that ``c`` now runs on N3 (it kept ``c`` on N4 and sent ``b``'s
    output there: the stream stopped). Every event once, in order."""
    sim, flowing = c_moved_unheard_by_n6()
    move(sim, "N5", "b", "N6")
    assert sim.cores["N6"].apps["line"].placed == dict(PLACED, b="N6", c="N3")
    flows_on(sim, flowing)
    got = sink(sim)
    assert got["count"] == got["next"], got
