"""A move's markers carry a warrant too (issue 27): with operator keys, a vertex's host hands
it over at a marker only for a move it holds a warrant for — one it coordinates, or one whose
coordinator told it with a ``Moving`` it checked as a ``Prepare`` (mso.protocol.warrant.
Leaving). The producer of every input of a vertex used to steer its handover: it switched its
own edge to a node it named (itself, with an instance it prepared there) and the host handed
the vertex's state to it at the marker.

The simulator's line N1 - N2 - N3 - N4 - N5 runs src -> a -> b -> c -> sink, one vertex a
node; the captured N2 hosts ``a``, which feeds every input of ``b`` (on N3)."""

from __future__ import annotations

from mso.protocol import messages as m
from mso.protocol.warrant import HOLD_S
from test_captured_robot import robot
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
