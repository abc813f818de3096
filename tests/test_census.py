"""The simulator's message census: counts by type, and the control messages of a reconfiguration
with the nodes they touched, as a test and ``mso simulate --json`` read them."""

from __future__ import annotations

import json
from collections import Counter
from pathlib import Path
from typing import Any

from click.testing import CliRunner

from mso.cli import main
from mso.protocol import messages as m
from mso.sim.census import Census
from test_relocation import relocate, started
from test_sim_scenario import APP, files


def test_census_counts_what_a_tap_sees_and_tallies_a_relocation() -> None:
    sim = started()
    seen: Counter[str] = Counter()
    sim.taps.append(lambda a, b, msg: seen.update([m.name_of(msg)]))
    before = Counter(sim.census.by_type)
    t0 = sim.now
    reply = relocate(sim, "N1", vertex="counter", direction="downstream")
    assert reply.ok, reply
    sim.run_until(sim.now + 1.0)
    assert Counter(sim.census.by_type) - before == seen  # every message, by type
    tally = sim.census.tally(t0)
    # the handshake (Prepare, Prepared, Switch, Marker, Handover, HandoverDone) plus the news
    handshake = {"Prepare", "Prepared", "Switch", "Marker", "Handover", "HandoverDone"}
    assert handshake <= set(tally.by_type)
    assert "Data" not in tally.by_type and "Ack" not in tally.by_type
    assert "Heartbeat" not in tally.by_type and "ChainDelay" not in tally.by_type
    control = sum(k for t, k in seen.items() if t not in {"Data", "Ack", "Heartbeat", "ChainDelay"})
    assert tally.control_messages == control
    assert tally.nodes_involved == {"N1", "N2", "N3", "N4"}  # the app's whole line
    (episode,) = [e for e in sim.census.episodes(cuts=[t0]) if e.since >= t0]
    assert episode.control_messages == tally.control_messages


def test_episodes_split_at_quiet_gaps_and_at_cuts() -> None:
    census = Census()
    for t in (0.0, 0.1, 0.2, 5.0, 5.1, 5.3):
        census.note(t, "A", "B", m.HandoverDone("x", "v", 1), ["A", "R", "B"])
    census.note(5.2, "A", "B", m.ChainDelay("x", 0, 1.0), ["A", "B"])  # periodic: not counted
    gaps = census.episodes(quiet_s=1.0)
    assert [(e.since, e.until, e.control_messages) for e in gaps] == [(0.0, 0.2, 3), (5.0, 5.3, 3)]
    assert gaps[0].nodes_involved == {"A", "B"} and gaps[0].relays == {"R"}
    cut = census.episodes(quiet_s=1.0, cuts=[5.05])
    assert [e.control_messages for e in cut] == [3, 1, 2]
    assert census.by_type == {"HandoverDone": 6, "ChainDelay": 1}
    assert census.hops_by_type == {"HandoverDone": 12, "ChainDelay": 1}


def test_simulate_json_reports_messages_and_each_episodes_cost(tmp_path: Path) -> None:
    sc, app = files(tmp_path, "changes:\n  - {at: 2, fail: N3}\n  - {at: 4, restart: N3}\n")
    # mid on N3 but not pinned there: its node is declared failed and mid re-placed (a node
    # that runs only what cannot move is held unreachable until it is back, not declared)
    unpinned = APP.replace("name: pipe\n", "name: pipe\nplanner: paper\n")
    Path(app).write_text(unpinned.replace("Double, pinned: N3}", "Double}"))
    result = CliRunner().invoke(main, ["simulate", sc, "--app", app, "--duration", "6", "--json"])
    assert result.exit_code == 0, result.output
    r: dict[str, Any] = json.loads(result.output)
    by_type = r["messages"]["by_type"]
    assert by_type["Heartbeat"] > 0 and by_type["Data"] > 0 and by_type["Suspect"] > 0
    assert r["messages"]["total"] == sum(by_type.values())
    deploy, failure, rejoin = r["reconfigurations"]["episodes"]
    # StartApp to the app's other holders, its vertices' two other nodes, not all five
    assert deploy["at"] == 0.0 and deploy["by_type"]["StartApp"] == 2
    assert failure["changes"] == ["fail N3"] and failure["failures"] == ["N3"]
    assert 2.0 < failure["at"] < 3.0  # from its detection, not the crash
    # N3 back: mid was re-placed meanwhile, so it takes no part and is not given the app
    assert rejoin["changes"] == ["restart N3"] and "NodeUp" in rejoin["by_type"]
    assert "AppSync" not in rejoin["by_type"]
    for ep in (deploy, failure, rejoin):
        assert ep["control_messages"] == sum(ep["by_type"].values()) > 0
        assert ep["nodes_involved"] == len(ep["nodes"])
    assert "N3" not in failure["nodes"]  # the failed node is sent nothing
    assert [f["node"] for f in r["failures"]] == ["N3"]  # one failure, one record (each
    # node records when it learned of it: one per gossip round once)
    for f in r["failures"]:
        assert f["control_messages"] == failure["control_messages"]
        assert f["nodes_involved"] == failure["nodes_involved"]
