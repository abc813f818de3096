"""Reconfiguration is local (issue 24.1): a relocation and a chain remap cost the same number of
control messages on 25 nodes as on 100, and involve only the app's nodes and the relays between
them — not every node, as a broadcast of each move did."""

from __future__ import annotations

import pytest

from mso.benchmarks.locality import APP, Step, grid, measure, measured_app
from mso.protocol import messages as m
from mso.sim.runner import Simulation


@pytest.fixture(scope="module")
def runs() -> dict[int, dict[str, Step]]:
    return {k * k: {s.kind: s for s in measure(k)} for k in (5, 10)}


@pytest.mark.parametrize("kind", ["relocation", "chain remap"])
def test_control_messages_do_not_grow_with_the_network(
    runs: dict[int, dict[str, Step]], kind: str
) -> None:
    small, large = runs[25][kind], runs[100][kind]
    assert small.ok and large.ok
    assert small.before != small.after and large.before != large.after  # something moved
    # flat within 20% (a broadcast of the move alone was N - 1 messages: 24 against 99)
    assert 0.8 * small.tally.control_messages <= large.tally.control_messages
    assert large.tally.control_messages <= 1.2 * small.tally.control_messages
    assert large.tally.control_messages < 25
    assert len(large.tally.nodes_involved) <= len(small.tally.nodes_involved) + 2


@pytest.mark.parametrize("kind", ["relocation", "chain remap", "global remap"])
@pytest.mark.parametrize("n", [25, 100])
def test_only_the_apps_nodes_and_relays_between_them_take_part(
    runs: dict[int, dict[str, Step]], kind: str, n: int
) -> None:
    step = runs[n][kind]
    assert step.ok
    assert step.tally.control_messages > 0
    assert not step.outside, f"{kind} on {n} nodes involved {sorted(step.outside)}"
    assert len(step.allowed) <= 16  # the app's vicinity, whatever the network's size


def test_a_node_that_hosts_no_part_of_the_app_looks_the_placement_up_first() -> None:
    sim = Simulation(grid(5), manage=False, wire=False)
    sim.request("G0_0", m.DeployRequest(measured_app(5), "locality.yaml"))
    sim.run_until(2.0)
    where = {v: n for n, c in sim.cores.items() for v in c.instances(APP)}
    far = "G4_4"  # hosts nothing of the app
    assert far not in where.values()
    sim.request(where["s1"], m.RelocateRequest(APP, "a", "downstream"))
    sim.run_until(4.0)
    moved = {v: n for n, c in sim.cores.items() for v in c.instances(APP)}
    assert moved["a"] != where["a"]
    assert APP not in sim.cores[far].apps  # it takes no part: it holds none of the app
    n, t0 = len(sim.replies), sim.now
    sim.request(far, m.RelocateRequest(APP, "a", "upstream"))  # it asks, then moves it
    sim.run_until(t0 + 2.0)
    (reply,) = [r for _, _, r in sim.replies[n:]]
    assert isinstance(reply, m.RelocateReply) and reply.ok, reply
    assert reply.node == where["s1"]  # upstream of where a runs now, not of where far thought
    assert sim.hosts(APP, "a") == [where["s1"]]
    assert sim.census.tally(t0).by_type["PlacementQuery"] >= 1


def test_a_new_host_hears_of_a_move_made_while_it_joined() -> None:
    """Two moves at once from one coordinator: each target hosts nothing of the app when the
    other move is announced to the app's members, so only the coordinator's word at the end
    of its move tells it (fault seed 175875: a target kept the other vertex on its old node
    for good, and sent it nothing)."""
    sim = Simulation(grid(5), manage=False, wire=False)
    sim.request("G0_0", m.DeployRequest(measured_app(5), "locality.yaml"))
    sim.run_until(2.0)
    where = {v: n for n, c in sim.cores.items() for v in c.instances(APP)}
    assert (where["a"], where["b"]) == ("G1_1", "G1_0")  # the planner's, as measured
    coordinator, idle = where["b"], {"G0_1", "G2_0"}
    assert not idle & set(where.values())
    t0 = sim.now
    sim.request(coordinator, m.RelocateRequest(APP, "a", target="G0_1"))
    sim.request(coordinator, m.RelocateRequest(APP, "b", target="G2_0"))
    sim.run_until(t0 + 2.0)
    assert all(isinstance(r, m.RelocateReply) and r.ok for _, _, r in sim.replies[-2:])
    now = {v: n for n, c in sim.cores.items() for v in c.instances(APP)}
    assert (now["a"], now["b"]) == ("G0_1", "G2_0")
    for n in set(now.values()):
        assert sim.cores[n].apps[APP].placed == now, n
