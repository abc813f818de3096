"""Capabilities and constraints (paper §3.3, issue 25 item 3): nodes declare what they offer,
a vertex says what it requires instead of a node, and the node is chosen by ability — centrally
in ``plan``, and in a deployment by a query the capable nodes answer; a constraint that cannot
be met is refused naming the vertex and what is missing."""

from __future__ import annotations

from pathlib import Path

import pytest
from click.testing import CliRunner

from mso.cli import main
from mso.daemon.config import node_capabilities
from mso.errors import AppError, MsoError, PlanningError, ScenarioError
from mso.model.appfile import loads_app
from mso.model.capabilities import Candidate, Needs, missing, parse_capabilities, rank, resolve
from mso.model.network import LinkSpec, Network, NodeSpec
from mso.planning.placement import plan
from mso.protocol import messages as m
from mso.protocol.procedures.deploy import CHOOSE_S
from mso.scenario import loads_scenario
from mso.sim.runner import Simulation

ROBOTS = """
name: robots
nodes:
  R1: {capabilities: [camera]}
  R2: {cpu: 2, capabilities: {gpu: 1, mem_mb: 1024}}
  R3: {cpu: 2, capabilities: {camera: 1, storage: true}}
  R4: {capabilities: [storage]}
links: [[R1, R2], [R2, R3], [R3, R4]]
"""

APP = """
name: watch
vertices:
  cam: {requires: [camera], rate: 10}
  detect: {requires: {gpu: 1, mem_mb: 512}, cost: 5}
  track: {cost: 3}
  log: {requires: [storage], apart_from: cam}
edges: [[cam, detect], [detect, track], [track, log]]
"""


def test_what_a_vertex_requires_is_validated_with_its_line() -> None:
    app = loads_app(APP, resolve_code=False)
    assert app.vertices["cam"].requires == {"camera": 1.0}
    assert app.vertices["detect"].requires == {"gpu": 1.0, "mem_mb": 512.0}
    assert [n.vertex for n in app.needs()] == ["cam", "detect", "log"]
    bad = {
        "requires: {gpu: -1}": "gpu: expected a non-negative amount",
        "requires: [1]": "expected a capability name",
        "requires: 7": "expected a list of names or a mapping",
        "near: nowhere": "expected another vertex of the app, got 'nowhere'",
        "near: track": "'track' is placed by Algorithm 1 after the constrained vertices",
        "pinned: R1, requires: [gpu]": "give pinned: or requires/near/apart_from, not both",
    }
    for attrs, why in bad.items():
        text = APP.replace(
            "detect: {requires: {gpu: 1, mem_mb: 512}, cost: 5}", f"detect: {{{attrs}}}"
        )
        with pytest.raises(AppError, match=why) as info:
            loads_app(text, file="watch.yaml", resolve_code=False)
        assert info.value.line == 5, attrs
    cycle = APP.replace("cam: {requires: [camera], rate: 10}", "cam: {near: log, rate: 10}")
    with pytest.raises(AppError, match="name each other in a cycle"):
        loads_app(cycle, resolve_code=False)


def test_a_capability_is_resolved_by_ability() -> None:
    net = loads_scenario(ROBOTS).network
    assert net.nodes["R3"].capabilities == {"camera": 1.0, "storage": 1.0}
    p = plan(loads_app(APP, resolve_code=False), net)
    # two cameras: R3 has the more CPU; the GPU is on R2 only; the storage apart from the
    # camera's node: R4
    assert p.capable == {"cam": ["R3", "R1"], "detect": ["R2"], "log": ["R4"]}
    assert (p.placement["cam"], p.placement["detect"], p.placement["log"]) == ("R3", "R2", "R4")


def test_rank_by_hops_then_cpu_then_battery() -> None:
    c = [
        Candidate("A", {"cpu": 1, "camera": 1}, 100.0, {"X": 2}),
        Candidate("B", {"cpu": 2, "camera": 1}, None, {"X": 3}),
        Candidate("C", {"cpu": 2, "camera": 1}, 50.0, {"X": 1}),
        Candidate("D", {"cpu": 1}, None, {"X": 0}),
    ]
    assert rank({"camera": 1}, c) == ["B", "C", "A"]  # wall power before 50 J
    assert rank({"camera": 1}, c, near="X") == ["C", "A", "B"]
    assert rank({"camera": 1}, c, apart=["B"]) == ["C", "A"]
    assert rank({"cpu": 1.5}, c) == ["B", "C"]
    assert missing({"gpu": 2, "camera": 1}, {"gpu": 1}) == ["gpu >= 2", "camera"]


def test_a_constraint_that_cannot_be_met_is_refused_naming_what_is_missing(
    tmp_path: Path,
) -> None:
    net = loads_scenario(ROBOTS).network
    lidar = loads_app(APP.replace("requires: [storage]", "requires: [lidar]"), resolve_code=False)
    with pytest.raises(PlanningError) as info:
        plan(lidar, net)
    assert str(info.value) == (
        "vertex 'log' requires lidar, and no node has lidar (nodes that answered: R1, R2, R3, R4)"
    )
    with pytest.raises(PlanningError, match="vertex 'x' requires camera apart from 'cam'"):
        resolve(
            [Needs("cam", {"camera": 1}), Needs("x", {"camera": 1}, apart_from="cam")],
            {},
            [Candidate("R1", {"cpu": 1, "camera": 1})],
        )
    app_file, net_file = tmp_path / "app.yaml", tmp_path / "net.yaml"
    app_file.write_text(APP.replace("requires: [storage]", "requires: [lidar]"))
    net_file.write_text(ROBOTS)
    result = CliRunner().invoke(main, ["plan", str(app_file), "--scenario", str(net_file)])
    assert result.exit_code == 2
    assert "vertex 'log' requires lidar, and no node has lidar" in result.output


def test_plan_and_validate_show_it(tmp_path: Path) -> None:
    app_file, net_file = tmp_path / "app.yaml", tmp_path / "net.yaml"
    app_file.write_text(APP)
    net_file.write_text(ROBOTS)
    out = CliRunner().invoke(main, ["validate", str(app_file)]).output
    assert "detect: placed by capability, requires gpu, mem_mb: 512" in out
    assert "log: placed by capability, requires storage, apart from cam" in out
    r = CliRunner().invoke(main, ["plan", str(app_file), "--scenario", str(net_file)])
    assert r.exit_code == 0, r.output
    assert "cam: placed by capability on R3 (requires camera; capable, best first: R3, R1)" in (
        r.output.replace("\n", " ")
    )
    r = CliRunner().invoke(main, ["compare", str(app_file), "--scenario", str(net_file)])
    assert r.exit_code == 0, r.output  # the baselines keep the vertices where they qualify


def test_node_capabilities_in_a_scenario_and_a_node_config() -> None:
    with pytest.raises(ScenarioError, match="camera: expected a non-negative amount") as info:
        loads_scenario(ROBOTS.replace("[camera]}", "{camera: -1}}"), file="net.yaml")
    assert info.value.line == 4
    assert node_capabilities(("camera", "mem_mb=4096"), None) == {"camera": 1, "mem_mb": 4096}
    assert node_capabilities((), ["lidar"]) == {"lidar": 1.0}
    assert node_capabilities(("gpu=2",), ["lidar"]) == {"gpu": 2.0}  # a flag wins
    with pytest.raises(MsoError, match="--capability: expected NAME or NAME=AMOUNT"):
        node_capabilities(("gpu=lots",), None)
    with pytest.raises(MsoError, match="capabilities: expected a list of names"):
        node_capabilities((), 3)
    assert parse_capabilities({"gpu": True}, "x") == {"gpu": 1.0}


STANDIN = """
name: watch
vertices:
  cam: {code: runtime_vertices:CountingSource, requires: [camera], rate: 10,
        output: runtime_vertices:Num}
  detect: {code: runtime_vertices:Double, requires: {gpu: 1}, cost: 5,
           output: runtime_vertices:Num}
  log: {code: runtime_vertices:Recorder, pinned: D}
edges: [[cam, detect], [detect, log]]
"""


def camera_net() -> Network:
    """Two camera robots A (cpu 2) and C, GPUs on B and E, the log on D."""
    nodes = [
        NodeSpec("A", cpu=2, capabilities={"camera": 1}),
        NodeSpec("B", capabilities={"gpu": 1}),
        NodeSpec("C", capabilities={"camera": 1}),
        NodeSpec("D"),
        NodeSpec("E", capabilities={"gpu": 1}),
    ]
    pairs = [("A", "B"), ("B", "C"), ("C", "D"), ("A", "E"), ("E", "C")]
    return Network(nodes, [LinkSpec(a, b, delay_ms=1.0) for a, b in pairs])


def test_a_deployment_asks_the_capable_nodes_and_the_choice_is_redone_on_failure() -> None:
    sim = Simulation(camera_net())
    sim.request("D", m.DeployRequest(STANDIN, "watch.yaml"))
    sim.run_until(3.0)
    reply = sim.replies[-1][2]
    assert isinstance(reply, m.DeployReply) and reply.ok, reply
    assert reply.placement["cam"] == "A" and reply.placement["detect"] == "B"
    # as the central plan decides it
    assert {v: n for v, n in plan(loads_app(STANDIN), camera_net(), origin="D").placement.items()
            } == reply.placement  # fmt: skip
    assert "watch" not in sim.cores["C"].apps  # a candidate not chosen takes no part
    st = sim.cores["D"].status(sim.now)["apps"]["watch"]
    assert st["capable"] == {"cam": ["A", "C"], "detect": ["B", "E"]}
    sim.kill("A", convergence_s=0.3)
    sim.run_until(sim.now + 7.0)
    live = [c for n, c in sim.cores.items() if n not in sim.killed]
    # the next camera robot, as every node of the app knows (the others are not told of
    # moves: they look the placement up before acting on it)
    members = [c for c in live if c.instances("watch")]
    assert members and all(c.placement("watch")["cam"] == "C" for c in members)
    recs = [(c.id, r) for c in live if "watch" in c.apps for r in c.apps["watch"].recoveries]
    assert len(recs) == 1, recs
    ((_, rec),) = recs
    assert rec["ok"] and rec["moved"] == {"cam": "C"}, rec
    before = sim.cores["D"].instances("watch")["log"].processed
    sim.run_until(sim.now + 2.0)
    assert sim.cores["D"].instances("watch")["log"].processed >= before + 15  # it flows again


def test_a_deployment_whose_nodes_have_all_answered_does_not_wait_for_the_deadline() -> None:
    # D offers nothing asked for and declines; A, B, C, E answer: the choice is made as soon as
    # the last of them is in (a few ms of links), not at CHOOSE_S, on the virtual clock
    sim = Simulation(camera_net())
    sim.request("D", m.DeployRequest(STANDIN, "watch.yaml"))
    sim.run_until(CHOOSE_S / 2)
    assert sim.replies, "no reply before half the capability deadline"
    at, _, reply = sim.replies[-1]
    assert isinstance(reply, m.DeployReply) and reply.ok, reply
    assert at < CHOOSE_S / 10
    assert reply.placement["cam"] == "A" and reply.placement["detect"] == "B"


def test_a_node_that_stays_silent_is_waited_for_until_the_deadline() -> None:
    # E's answer is lost (E is alive: membership holds it up): the choice waits for CHOOSE_S,
    # then is made from the answers in
    sim = Simulation(camera_net())
    sim.drop = lambda src, dst, msg: isinstance(msg, m.CapabilityReply) and msg.node == "E"
    sim.request("D", m.DeployRequest(STANDIN, "watch.yaml"))
    sim.run_until(3.0)
    at, _, reply = sim.replies[-1]
    assert isinstance(reply, m.DeployReply) and reply.ok, reply
    assert at >= CHOOSE_S
    assert reply.placement["detect"] == "B"


def test_a_node_that_fails_while_asked_is_not_waited_for() -> None:
    # E crashes as the query goes out: once membership declares it failed, nobody else is awaited
    sim = Simulation(camera_net())
    sim.drop = lambda src, dst, msg: isinstance(msg, m.CapabilityReply) and msg.node == "E"
    sim.request("D", m.DeployRequest(STANDIN, "watch.yaml"))
    sim.run_until(0.002)
    sim.crash("E")
    sim.run_until(3.0)
    at, _, reply = sim.replies[-1]
    assert isinstance(reply, m.DeployReply) and reply.ok, reply
    assert at < CHOOSE_S
    assert "E" in sim.cores["D"].failed


def test_a_deployment_no_node_can_serve_is_refused() -> None:
    sim = Simulation(camera_net())
    text = STANDIN.replace("requires: {gpu: 1}", "requires: {gpu: 1, lidar: 1}")
    sim.request("D", m.DeployRequest(text, "watch.yaml"))
    sim.run_until(3.0)
    reply = sim.replies[-1][2]
    assert isinstance(reply, m.DeployReply) and not reply.ok
    assert reply.error == (
        "vertex 'detect' requires gpu, lidar, and no node has lidar "
        "(nodes that answered: A, B, C, E)"
    )
    assert all("watch" not in c.apps for c in sim.cores.values())  # nothing was announced


def test_a_malformed_answer_is_refused() -> None:
    sim = Simulation(camera_net())
    core = sim.cores["D"]
    core.receive("A", m.CapabilityReply("watch", 99, "A", {"camera": 1}), sim.now)
    assert core.refusals.get("capability_reply_unexpected") == 1
    core.receive("A", m.CapabilityQuery("watch", 1, {"cam": {"camera": -5}}), sim.now)
    assert core.refusals.get("capability_query_malformed") == 1


def test_near_picks_the_capable_node_closest_to_that_vertex_in_a_deployment() -> None:
    # A has the more CPU, but C is one hop from the log on D: near: log puts the camera there,
    # from the hops the answering nodes report, as the central plan does from the network
    text = STANDIN.replace(
        "requires: [camera], rate: 10", "requires: [camera], near: log, rate: 10"
    )
    sim = Simulation(camera_net())
    sim.request("D", m.DeployRequest(text, "watch.yaml"))
    sim.run_until(3.0)
    reply = sim.replies[-1][2]
    assert isinstance(reply, m.DeployReply) and reply.ok, reply
    assert reply.placement["cam"] == "C"
    assert plan(loads_app(text), camera_net(), origin="D").placement == reply.placement


def test_a_node_that_rejoins_learns_the_nodes_chosen_by_capability() -> None:
    sim = Simulation(camera_net())
    sim.request("D", m.DeployRequest(STANDIN, "watch.yaml"))
    sim.run_until(3.0)
    sim.kill("B", convergence_s=0.3)  # the GPU node: detect goes to E, the next that qualified
    sim.run_until(sim.now + 7.0)
    assert sim.cores["D"].placement("watch")["detect"] == "E"
    for a, b in [("A", "B"), ("B", "C")]:
        sim.network.add_link(LinkSpec(a, b, delay_ms=1.0))
    sim.revive("B")
    sim.run_until(sim.now + 5.0)
    # B takes no part any more, and holds none of the app (issue 24.1); the nodes that do,
    # the sync's receivers among them, all know the choice
    assert "watch" not in sim.cores["B"].apps
    (back,) = [c.apps["watch"] for n, c in sim.cores.items() if n == "E"]
    assert back.layout.resolved == {"cam": "A", "detect": "E"}
    assert back.capable == {"cam": ["A", "C"], "detect": ["B", "E"]}
    assert back.placed["detect"] == "E"
