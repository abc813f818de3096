"""The apps a node holds, kept in its store across a daemon restart (mso.protocol.kept)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest

from mso.daemon.spill import SqliteSpill
from mso.model.network import LinkSpec
from mso.node.core import NodeCore
from mso.protocol import kept
from mso.protocol import messages as m
from mso.protocol.spill import MemorySpill
from mso.sim.runner import Simulation
from runtime_vertices import pipe_app
from test_faults import deployed_on_a_line, line_net


@pytest.mark.parametrize("kind", ["sqlite", "memory"])
def test_an_app_kept_is_read_back_after_a_reopen_and_forgotten_with_it(
    tmp_path: Path, kind: str
) -> None:
    sim = deployed_on_a_line()
    dep = sim.cores["N1"].apps["pipe"]
    s: Any = SqliteSpill(tmp_path) if kind == "sqlite" else MemorySpill()
    s.save_position("pipe/1/0", 7)  # an edge's position beside it: not an app kept
    kept.keep(s, dep)
    kept.keep(s, dep)  # again, as its placement changed: one record
    if kind == "sqlite":
        s.close()
        s = SqliteSpill(tmp_path)
    (back,) = kept.recall(s)
    assert back == kept.record(dep)
    assert (back.app, back.origin, back.epoch) == ("pipe", "N1", dep.epoch)
    assert back.placed == dep.placed and set(back.placed) == set(dep.app.vertices)
    kept.forget(s, "pipe")
    assert kept.recall(s) == [] and s.position("pipe/1/0") == 7
    if kind == "sqlite":
        s.close()


def test_a_damaged_record_costs_the_app_not_the_node() -> None:
    """A record that does not decode as an app's sync (a damaged store) is skipped."""
    s = MemorySpill()
    s.append(kept.PREFIX + "pipe", 0, [b"\xc1 not msgpack"])
    s.note(kept.PREFIX + "pipe/", "epoch", 1)
    other = m.encode(m.StatusRequest())  # a message, but not a sync of that app
    s.append(kept.PREFIX + "other", 0, [other])
    s.note(kept.PREFIX + "other/", "epoch", 1)
    assert kept.recall(s) == []


def revive(sim: Simulation, nodes: list[str], links: list[tuple[str, str]]) -> None:
    """Restart killed ``nodes`` with ``links`` back (their links went with them)."""
    for a, b in links:
        sim.network.add_link(LinkSpec(a, b, delay_ms=1.0))
    for n in nodes:
        sim.revive(n)


def running(sim: Simulation) -> set[str]:
    """The vertices of the app that run on some node."""
    return {v for c in sim.cores.values() if "pipe" in c.apps for v in c.instances("pipe")}


def test_every_holder_restarted_at_once_takes_the_app_back() -> None:
    """src and the sink on N1, mid on N3 (N2 between them takes no part and holds nothing):
    N1 and N3 both crash, then restart. Nobody was left to sync the app back to them (issue
    24.1); each takes it back from its store, and the app runs again on them."""
    doc = pipe_app(50).replace("pinned: N4", "pinned: N1")
    sim = Simulation(line_net())
    sim.request("N1", m.DeployRequest(doc, "app.yaml"))
    sim.run_until(1.0)
    sim.request("N1", m.RelocateRequest("pipe", "mid", target="N3"))
    sim.run_until(3.0)  # (a monitor period or two: each keeps what it holds now)
    assert "mid" in sim.cores["N3"].instances("pipe") and "pipe" not in sim.cores["N2"].apps
    for n in ("N1", "N3"):
        sim.kill(n)
    sim.run_until(sim.now + 2.0)
    revive(sim, ["N1", "N3"], [("N1", "N2"), ("N2", "N3")])
    sim.run_until(sim.now + 4.0)
    assert running(sim) == {"src", "mid", "sink"}
    assert sim.cores["N1"].apps["pipe"].inc[1].expected > 0  # mid -> sink: events arrive


def test_an_app_its_origin_alone_holds_outlives_the_origins_restart() -> None:
    """src pinned to N3, the sink to N4, deployed at N1; N3 and N4 die, so the app's chains
    wait parked at N1, its one holder. N1's daemon restarts meanwhile: it takes the app back
    from its store, and when N3 and N4 are back the app runs again (before, no node held it
    and it had to be deployed again)."""
    doc = pipe_app(50).replace("pinned: N1", "pinned: N3")
    sim = Simulation(line_net(4))
    sim.request("N1", m.DeployRequest(doc, "app.yaml"))
    sim.run_until(2.0)
    assert sim.cores["N1"].apps["pipe"].origin == "N1"
    for n in ("N3", "N4"):
        sim.kill(n)
    sim.run_until(sim.now + 3.0)
    alive = {n for n, c in sim.cores.items() if "pipe" in c.apps and n not in sim.killed}
    assert alive == {"N1"}, sim.cores["N1"].placement("pipe")
    sim.kill("N1")
    sim.run_until(sim.now + 0.1)
    sim.network.add_link(LinkSpec("N1", "N2", delay_ms=1.0))
    sim.revive("N1")
    sim.run_until(sim.now + 2.0)
    assert "pipe" in sim.cores["N1"].apps  # taken back from its store
    revive(sim, ["N3", "N4"], [("N2", "N3"), ("N3", "N4")])
    sim.run_until(sim.now + 5.0)
    assert running(sim) == {"src", "mid", "sink"}


def _sync(src_view: dict[str, str], versions: dict[str, int]) -> m.AppSync:
    doc = pipe_app(50)
    return m.AppSync("pipe", "N1", doc, 0, src_view, [], {}, {}, {}, {}, versions, {})


@pytest.mark.parametrize("theirs", [1, 2, 3])
def test_a_kept_view_keeps_a_later_move_here_over_an_older_sync(theirs: int) -> None:
    """A restarted node's kept view places ``mid`` here at its second move; the first sync
    from a live node places it elsewhere at its ``theirs``-th. Older (1): ours is the later
    word, first-hand — ``mid`` ran here and went with the last process, so it is held here,
    vanished, for a recovery to restore (seed 125537: the sync's host had let the app go and a
    holder's recovery waited on it for ever). As new or newer (2, 3): the live node's view is
    taken, as a node back empty takes it."""
    core = NodeCore("N3")
    here = {"src": "N1", "mid": "N3", "sink": "N4"}
    core.receive("N3", _sync(here, {"mid": 2}), 5.0)  # its kept view, taken back at its start
    assert core.apps["pipe"].stored and core.apps["pipe"].vanished == {"mid"}
    core.receive("N1", _sync(dict(here, mid="N2"), {"mid": theirs}), 5.1)
    dep = core.apps["pipe"]
    if theirs < 2:
        assert (dep.placed["mid"], dep.versions["mid"]) == ("N3", 2) and "mid" in dep.vanished
    else:
        assert (dep.placed["mid"], dep.versions["mid"]) == ("N2", theirs)
        assert "mid" not in dep.vanished


def test_a_kept_view_synced_before_its_hosts_are_heard_names_their_incarnations() -> None:
    """Fault seed 265408's shape. N1 deployed the app and hosts none of it; everything runs on
    N3 until ``mid`` moves to N2 (N1, no host, is not told). N3 keeps that view (``mid`` on
    N2). All three crash; N1 comes back first, then N2 and N3 together. N1 hears N3 back
    (its kept view's vertices there vanished), then N2 back empty, and then N3's sync of the
    view N3's last process kept, placing ``mid`` on N2: sent before N3 heard N2, it named no
    incarnation of N2, and N1 took ``mid`` as running there. Then N1 held N2 the node to
    coordinate the recovery and N2 (and N3) held N1 it: nothing ran again. Now a kept record
    names the incarnations its process knew of the hosts, a sync of a kept view names them for
    the nodes not heard since, and N1 holds ``mid`` gone with N2's last process."""
    doc = pipe_app(20).replace("pinned: N1", "pinned: N3").replace("pinned: N4", "pinned: N3")
    sim = Simulation(line_net())
    sim.network.add_link(LinkSpec("N1", "N3", delay_ms=1.0))
    sim.request("N1", m.DeployRequest(doc, "app.yaml"))
    sim.run_until(1.0)
    assert set(sim.cores["N3"].instances("pipe")) == {"src", "mid", "sink"}
    sim.request("N3", m.RelocateRequest("pipe", "mid", target="N2"))
    sim.run_until(2.1)  # (a monitor period: N3 keeps its view, N2 has kept none of it yet)
    assert sim.cores["N1"].apps["pipe"].placed["mid"] == "N3"  # (not told of the move)
    assert "mid" in sim.cores["N2"].instances("pipe")
    (record,) = kept.recall(sim.spills["N3"])
    assert record.placed["mid"] == "N2" and record.incarnations == {"N2": 0}
    for n in ("N1", "N2", "N3"):
        sim.kill(n)
    sim.run_until(2.5)
    sim.revive("N1")  # (alone: no link yet)
    sim.run_until(3.0)
    sim.network.add_link(LinkSpec("N1", "N3", delay_ms=1.0))
    sim.network.add_link(LinkSpec("N1", "N2", delay_ms=1.5))
    sim.network.add_link(LinkSpec("N2", "N3", delay_ms=2.0))
    sim.revive("N2")
    sim.revive("N3")
    sim.run_until(3.01)
    assert "mid" in sim.cores["N1"].apps["pipe"].vanished  # (before: running on N2)
    sim.run_until(8.0)
    assert running(sim) == {"src", "mid", "sink"}
    hosts = [n for n, c in sim.cores.items() if "pipe" in c.apps and "mid" in c.instances("pipe")]
    assert len(hosts) == 1
