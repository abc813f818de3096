"""Moves limited to who may make them (issue 27): with operator keys, news that a vertex runs
elsewhere (``Moved``) is taken only from the node the receiver's view says hosts it (it handed
the vertex over), or, once that node failed or the vertex vanished with it, from whoever
restored it. A captured member hosting part of an app used to move any other vertex of the app
with one ``Moved`` — to itself, so that the vertex's neighbours sent it their events, or to a
node that never ran it. Now refused, counted, and the placement looked up from the hosts.

In the simulator, whose sources are proven as with node identities (a captured robot speaks
only in its own name): N1 - N2 - N3, src on N1, mid on N2, sink on N3, every node with the
operator's key; the robot is N1, which hosts src and nothing else."""

from __future__ import annotations

from mso.protocol import messages as m
from mso.protocol.procedures import placement
from test_captured_robot import apps, overlay, robot, sunk

ATTACKS = [
    # mid runs on me (N1): its consumer would ack N1, and its producer... is N1 itself
    m.Moved("pipe", "mid", "N1", incarnation=0, version=5),
    # mid runs on N3, which never ran it: N3 would take its own events for mid's
    m.Moved("pipe", "mid", "N3", version=5),
    # at the same version: the last word used to win
    m.Moved("pipe", "mid", "N3"),
]


def test_a_member_cannot_move_a_vertex_it_does_not_host() -> None:
    sim = overlay()
    core = sim.cores["N3"]
    before, flowing = apps(sim), sunk(sim)
    for msg in ATTACKS:
        counted = core.refusals.get("moved_not_by_its_host", 0)
        robot(sim, "N3", msg, src="N1")
        assert core.refusals.get("moved_not_by_its_host", 0) == counted + 1, msg
        assert core.apps["pipe"].placed["mid"] == "N2", msg
    sim.run_until(sim.now + 1.0)  # the lookups it started asked the hosts: nothing moved
    assert apps(sim) == before
    stats = core.status(sim.now)["apps"]["pipe"]["vertices"]["sink"]["stats"]
    assert sunk(sim) >= flowing + 40 and stats["repeats"] == 0 and stats["out_of_order"] == 0


def test_a_move_its_host_hands_over_is_learnt_by_every_node() -> None:
    """The operator relocates mid from N2 to N1 through N1 (which coordinates, hosting no part
    of mid): N2, mid's host, hands it over and tells the app's nodes, which take its word."""
    sim = overlay()
    sim.request("N1", m.RelocateRequest("pipe", "mid", target="N1"))  # (verified by N1's transport)
    sim.run_until(sim.now + 1.5)
    for n in ("N1", "N2", "N3"):
        assert sim.cores[n].apps["pipe"].placed["mid"] == "N1", n
        assert not sim.cores[n].refusals.get("moved_not_by_its_host"), n
    assert "mid" in sim.cores["N1"].apps["pipe"].instances
    flowing = sunk(sim)
    sim.run_until(sim.now + 1.0)
    assert sunk(sim) >= flowing + 40  # 50 events a second


def test_a_lookups_answers_move_a_vertex_only_on_its_hosts_word() -> None:
    """The lookup a refused claim starts asks the app's nodes, the robot among them: its
    answer is weighed like its ``Moved``."""
    sim = overlay()
    dep = sim.cores["N3"].apps["pipe"]
    forged = {"src": "N1", "mid": "N1", "sink": "N3"}
    placement.merge(dep, "N1", forged, {"mid": 9}, [], sim.now, failed=set(), here="N3")
    assert dep.placed["mid"] == "N2" and dep.versions.get("mid", 0) == 0
    handed = {"src": "N1", "mid": "N3", "sink": "N3"}  # mid's host says where it went
    placement.merge(dep, "N2", handed, {"mid": 1}, [], sim.now, failed=set(), here="N3")
    assert dep.placed["mid"] == "N3" and dep.versions["mid"] == 1
    dep.placed["mid"] = "N2"  # its host failed: whoever restored it says where
    placement.merge(dep, "N1", forged, {"mid": 9}, [], sim.now, failed={"N2"}, here="N3")
    assert dep.placed["mid"] == "N1"
