"""A source whose daemon restarted numbers its edge on from the bound its last process saved,
past numbers its consumer never got; the positions of that process's last ack may be gone with
it (its ack lost). The consumer's answer to the source's restore says where its outputs stand
(exact: it has processed everything before), and the edge keeps them at its new start: a later
replacement of the consumer, fed the replay from there, numbers what it makes as the lost
instance did (fault seed 202193: with none, a chain's replacement numbered the replay to a sink
from where the sink stood, and 6 events reached it twice).

N1 - N2 - N3 - N4, ``pipe`` deployed: src on N1, mid on N3, sink on N4."""

from __future__ import annotations

from mso.model.network import LinkSpec, Network, NodeSpec
from mso.protocol import messages as m
from mso.sim.runner import Simulation
from runtime_vertices import pipe_app


def test_a_restarted_sources_edge_keeps_its_consumers_positions_at_its_new_start() -> None:
    net = Network(
        [NodeSpec(n) for n in ("N1", "N2", "N3", "N4")],
        [LinkSpec(a, b, delay_ms=1.0) for a, b in (("N1", "N2"), ("N2", "N3"), ("N3", "N4"))],
    )
    sim = Simulation(net)
    sim.request("N1", m.DeployRequest(pipe_app(20), "app.yaml"))
    sim.run_until(1.5)
    assert sim.hosts("pipe", "mid") == ["N3"]
    # the source's node hears no ack from here on: its last saved positions fall behind
    sim.drop = lambda src, dst, msg: dst == "N1" and isinstance(msg, m.Ack)
    sim.run_until(2.0)
    sim.crash("N1")
    sim.run_until(2.05)
    sim.revive("N1")
    sim.run_until(2.5)
    edge = sim.cores["N1"].apps["pipe"].out[0]  # src -> mid, restored
    mid = sim.cores["N3"].apps["pipe"]
    assert edge.acked < edge.next_seq == mid.inc[0].expected  # mid took the new numbers
    assert 1 in edge.positions, edge.positions  # where mid's output stood at the edge's start
    made = mid.inc[0].expected - edge.acked  # mid makes one event of each (Double)
    assert edge.positions[1] + made == mid.out[1].next_seq
