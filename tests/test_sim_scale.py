"""What keeps the simulator linear in N: a node's retransmit timer runs only while it has
something unacknowledged, and a link change reaches only the nodes whose routes it changes."""

from __future__ import annotations

import itertools

from mso.model.network import LinkSpec, Network, NodeSpec
from mso.protocol import messages as m
from mso.protocol.events import Retransmit
from mso.scenario.generate import pipelines
from mso.sim.runner import Simulation


def _line(n: int) -> Network:
    ids = [f"N{i}" for i in range(1, n + 1)]
    return Network([NodeSpec(i) for i in ids], [LinkSpec(a, b) for a, b in itertools.pairwise(ids)])


def _armed(sim: Simulation) -> set[str]:
    return {node for (node, key) in sim._timers if isinstance(key, Retransmit)}


def test_the_retransmit_timer_runs_only_where_events_wait_for_an_ack() -> None:
    sim = Simulation(_line(8), manage=False)
    (src, doc), = pipelines(["N1", "N3"], 1, seed=0, rate=20.0)  # fmt: skip
    sim.request(src, m.DeployRequest(doc, "app.yaml"))
    sim.run_until(3.0)
    hosts = {sim.placement("N1", "app0")[v] for v in ("src", "p1", "p2", "sink")}
    assert hosts <= {"N1", "N2", "N3"}
    producers = {sim.placement("N1", "app0")[v] for v in ("src", "p1", "p2")}
    # the producers' timers come and go with their events in flight; nodes that only know
    # of the app (they were told of it at deployment) have none at all
    assert _armed(sim) <= producers
    assert not _armed(sim) & {"N4", "N5", "N6", "N7", "N8"}
    seen = set()
    for k in range(1, 40):
        sim.run_until(3.0 + k * 0.05)
        seen |= _armed(sim)
    assert seen & producers  # (while events were unacknowledged, they were armed)


def test_a_link_change_reaches_only_the_nodes_whose_routes_it_changes() -> None:
    sim = Simulation(_line(6), manage=False, wire=False)
    called: list[str] = []
    for n, core in sim.cores.items():
        original = core.change_routes

        def spy(delta, now=0.0, n=n, original=original):  # type: ignore[no-untyped-def]
            called.append(n)
            return original(delta, now)

        core.change_routes = spy  # type: ignore[method-assign]
    sim.network.add_link(LinkSpec("N5", "N6", delay_ms=3.0))  # attributes only: nothing
    sim.links_changed()
    assert called == []
    sim.network.add_link(LinkSpec("N4", "N6"))  # a shortcut at the end of the line
    sim.links_changed()
    assert sorted(called) == ["N1", "N2", "N3", "N4", "N6"]  # N5's routes stay as they were
    assert sim.cores["N1"].routes["N6"] == ("N2", 4)
