"""Twins a cut left behind: a vertex restored on both sides of a partition, one of whose hosts
reset at the heal. News of the other placement, relayed by a node that missed the reset, must
not make the node still running the vertex place it elsewhere (it ran a vertex its own view put
on a node that ran nothing: fault seed 92622); and the nodes holding that placement, its
instance gone with the reset, take the running host's word even though its version is older.

N1 - N2 - N3, no operator keys, ``pipe`` deployed: src on N1, mid on N2, sink on N3."""

from __future__ import annotations

from mso.model.network import LinkSpec, Network, NodeSpec
from mso.protocol import messages as m
from mso.protocol.effects import Send
from mso.sim.runner import Simulation
from runtime_vertices import pipe_app

APP = pipe_app(50).replace("pinned: N4", "pinned: N3")


def overlay() -> Simulation:
    net = Network(
        [NodeSpec("N1"), NodeSpec("N2"), NodeSpec("N3")],
        [LinkSpec("N1", "N2", delay_ms=1.0), LinkSpec("N2", "N3", delay_ms=1.0)],
    )
    sim = Simulation(net)
    sim.request("N1", m.DeployRequest(APP, "app.yaml"))
    sim.run_until(1.0)
    assert any(isinstance(r, m.DeployReply) and r.ok for _, _, r in sim.replies)
    assert sim.cores["N2"].apps["pipe"].placed["mid"] == "N2"
    return sim


def test_a_relayed_later_placement_does_not_move_a_vertex_running_here() -> None:
    sim = overlay()
    core = sim.cores["N2"]
    dep = core.apps["pipe"]
    relayed = m.Moved("pipe", "mid", "N3", incarnation=-1, version=2)  # N1 passes it on
    effects = core.receive("N1", relayed, sim.now)
    assert dep.placed["mid"] == "N2" and "mid" in dep.instances  # still ours, still runs
    assert dep.versions["mid"] == 2  # as of the version the others hold
    told = {e.dst: e.msg for e in effects if isinstance(e, Send) and isinstance(e.msg, m.Moved)}
    assert set(told) == {"N3"}  # the node it names, whose own word settles it
    for word in told.values():
        assert (word.vertex, word.node, word.version) == ("mid", "N2", 2)
        assert word.incarnation == core.incarnation  # the host's own word


def test_the_running_hosts_word_beats_a_vanished_later_placement() -> None:
    sim = overlay()
    core, host = sim.cores["N3"], sim.cores["N2"]
    dep = core.apps["pipe"]
    dep.placed["mid"], dep.versions["mid"] = "N1", 2  # restored on N1 across a cut; N1 reset:
    dep.vanished.add("mid")  # its instance went with that incarnation
    word = m.Moved("pipe", "mid", "N2", incarnation=host.incarnation, version=1)
    core.receive("N2", word, sim.now)
    assert dep.placed["mid"] == "N2" and "mid" not in dep.vanished
    assert dep.versions["mid"] == 2  # not older than the placement it replaced
    dep.placed["mid"] = "N1"  # not vanished: a live later placement, and the old word loses
    core.receive("N2", word, sim.now)
    assert dep.placed["mid"] == "N1"
