"""The node core's distributed procedures in virtual time: deployment and the data plane."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import pytest

from mso.model.appfile import loads_app
from mso.model.network import LinkSpec, Network, NodeSpec
from mso.planning.placement import plan
from mso.protocol import messages as m
from mso.scenario import load_scenario
from mso.sim.runner import Simulation
from runtime_vertices import pipe_app

EXAMPLES = Path(__file__).resolve().parent.parent / "src" / "mso" / "examples"

PIPE = pipe_app(100)


def line(n: int, delay_ms: float = 1.0) -> Network:
    nodes = [NodeSpec(f"N{i}") for i in range(1, n + 1)]
    links = [LinkSpec(f"N{i}", f"N{i + 1}", delay_ms=delay_ms) for i in range(1, n)]
    return Network(nodes, links)


def deploy(sim: Simulation, doc: str, via: str = "N1") -> m.DeployReply:
    sim.request(via, m.DeployRequest(doc, "app.yaml"))
    sim.run_until(sim.now + 2.0)
    replies = [r for _, _, r in sim.replies if isinstance(r, m.DeployReply)]
    assert replies, "no deploy reply"
    return replies[-1]


def sink_stats(sim: Simulation, app: str, vertex: str) -> dict[str, int]:
    for core in sim.cores.values():
        st = core.status(sim.now)["apps"].get(app)
        if st and vertex in st["vertices"]:
            stats: dict[str, int] = st["vertices"][vertex]["stats"]
            return stats
    raise AssertionError(f"{vertex} not hosted anywhere")


@pytest.mark.parametrize(
    ("app_file", "scenario_file"),
    [
        ("convoy.yaml", "convoy-line.yaml"),
        ("section33.yaml", "line4.yaml"),
        ("fig2.yaml", "line4.yaml"),
    ],
)
def test_distributed_deployment_matches_central_plan(app_file: str, scenario_file: str) -> None:
    doc = (EXAMPLES / app_file).read_text()
    scenario = load_scenario(EXAMPLES / scenario_file)
    expected = plan(loads_app(doc), scenario.network).placement
    sim = Simulation(scenario.network)
    reply = deploy(sim, doc, via=next(iter(scenario.network.nodes)))
    assert reply.ok, reply.error
    assert reply.placement == expected
    # every node that takes part learned the whole mapping and hosts exactly its own
    # vertices; the others hold none of the app (issue 24.1)
    for node, core in sim.cores.items():
        dep = core.apps.get(loads_app(doc).name)
        if dep is None:
            assert node not in expected.values()
            continue
        assert dep.placed == expected
        assert set(dep.instances) == {v for v, n in expected.items() if n == node}


def test_every_event_arrives_once_and_in_order() -> None:
    sim = Simulation(line(4))
    reply = deploy(sim, PIPE)
    assert reply.ok, reply.error
    sim.run_until(sim.now + 5.0)
    stats = sink_stats(sim, "pipe", "sink")
    emitted = sim.cores["N1"].instances("pipe")["src"].emitted
    assert emitted >= 450
    assert stats["repeats"] == 0 and stats["out_of_order"] == 0
    # only what is still in flight (a few ms at 100 events/s) may be missing
    assert emitted - 5 <= stats["count"] <= emitted


def test_backpressure_bounds_what_is_in_flight() -> None:
    doc = PIPE.replace("rate: 100,", "")  # a source that emits as fast as it is allowed
    sim = Simulation(line(4, delay_ms=20.0), window=16)
    assert deploy(sim, doc).ok
    peak = 0
    for _ in range(50):
        sim.run_until(sim.now + 0.01)
        for core in sim.cores.values():
            for ch in (core.apps["pipe"].out if "pipe" in core.apps else {}).values():
                peak = max(peak, ch.in_flight)
    assert 0 < peak <= 16
    stats = sink_stats(sim, "pipe", "sink")
    assert stats["count"] > 0 and stats["repeats"] == 0 and stats["out_of_order"] == 0


def test_traffic_follows_a_route_change() -> None:
    # a square: N1-N2-N4 and N1-N3-N4; the sink's traffic moves to N3 when N1-N2 breaks
    nodes = [NodeSpec(n) for n in ("N1", "N2", "N3", "N4")]
    links = [
        LinkSpec(a, b, delay_ms=1.0)
        for a, b in (("N1", "N2"), ("N2", "N4"), ("N1", "N3"), ("N3", "N4"))
    ]
    net = Network(nodes, links)
    doc = PIPE.replace(
        "  mid: {code: runtime_vertices:Double, output: runtime_vertices:Num}",
        "  mid: {code: runtime_vertices:Double, output: runtime_vertices:Num, pinned: N1}",
    )
    sim = Simulation(net)
    assert deploy(sim, doc).ok
    sim.run_until(sim.now + 1.0)
    before = sink_stats(sim, "pipe", "sink")["count"]
    net.remove_link("N1", "N2")
    sim.update_routes()
    sim.run_until(sim.now + 2.0)
    after = sink_stats(sim, "pipe", "sink")
    assert after["count"] >= before + 150
    assert after["repeats"] == 0 and after["out_of_order"] == 0
    assert sim.cores["N1"].routes["N4"][0] == "N3"


def test_bad_app_document_is_refused_with_its_error() -> None:
    sim = Simulation(line(2))
    sim.request("N1", m.DeployRequest("name: x\nvertices:\n  A: {cost: -1}\n", "bad.yaml"))
    ((_, _, reply),) = sim.replies
    assert isinstance(reply, m.DeployReply) and not reply.ok
    assert "bad.yaml:3: vertices.A.cost" in reply.error


def test_pinned_to_unreachable_node_is_refused() -> None:
    sim = Simulation(line(2))
    sim.request("N1", m.DeployRequest(PIPE, "pipe.yaml"))  # pins the sink to N4
    ((_, _, reply),) = sim.replies
    assert isinstance(reply, m.DeployReply) and not reply.ok
    assert "N4" in reply.error and "not reachable" in reply.error


def test_user_code_that_fails_never_takes_a_node_down() -> None:
    broken = PIPE.replace("code: runtime_vertices:Double,", "code: runtime_vertices:Broken,")
    sim = Simulation(line(4))
    sim.request("N1", m.DeployRequest(broken, "broken.yaml"))
    sim.run_until(2.0)
    ((_, _, reply),) = sim.replies
    assert isinstance(reply, m.DeployReply) and not reply.ok
    assert "sensor not found" in reply.error
    sim.run_until(3.0)
    assert all(not c.apps for c in sim.cores.values())  # stopped everywhere, nothing half-built
    flaky = PIPE.replace("code: runtime_vertices:Double,", "code: runtime_vertices:Flaky,")
    assert deploy(sim, flaky).ok  # the same nodes still deploy and run the next app
    sim.run_until(sim.now + 2.0)
    mid = next(c for c in sim.cores.values() if "mid" in c.instances("pipe"))
    stone = mid.instances("pipe")["mid"]
    assert stone.errors > 50 and "bad reading" in stone.last_error
    assert sink_stats(sim, "pipe", "sink")["count"] >= 2 * stone.errors - 5


def test_end_to_end_delay_is_measured_per_chain_and_reported_to_its_head() -> None:
    sim = Simulation(line(4, delay_ms=2.0), hop_latency_s=0.0)
    assert deploy(sim, PIPE).ok
    sim.run_until(sim.now + 3.0)
    tail = sim.cores["N4"].status(sim.now)["apps"]["pipe"]["chain_delay_ms"]
    assert tail == {"src-mid-sink": pytest.approx(6.0)}  # three 2 ms hops, src on N1, sink on N4
    ms, _ = sim.cores["N1"].apps["pipe"].chain_delay[0]  # the head's node knows it too
    assert ms == pytest.approx(6.0)


FORK = """
name: fork
vertices:
  src: {code: runtime_vertices:CountingSource, pinned: N1, rate: 100,
        output: runtime_vertices:Num}
  left: {code: runtime_vertices:Recorder, pinned: N3}
  right: {code: runtime_vertices:Recorder, pinned: N3}
edges:
  - [src, left]
  - [src, right]
"""


def lose_first(kind: type, lost: list[m.Message]) -> Callable[[str, str, m.Message], bool]:
    """A ``Simulation.drop`` that loses the first message of type ``kind`` (into ``lost``)."""

    def drop(node: str, dst: str, msg: m.Message) -> bool:
        if isinstance(msg, kind) and not lost:
            lost.append(msg)
            return True
        return False

    return drop


def data_frames(sim: Simulation) -> list[tuple[str, str, m.Data]]:
    """Every Data frame the simulation puts on its network, from now on (a send hook)."""
    sent: list[tuple[str, str, m.Data]] = []

    def tap(node: str, dst: str, msg: m.Message) -> None:
        if isinstance(msg, m.Data):
            sent.append((node, dst, msg))

    sim.taps.append(tap)
    return sent


def test_a_fork_to_one_node_sends_each_batch_once() -> None:
    """src feeds two vertices on N3: each batch crosses the two hops once, in one frame that
    names both edges, and each consumer still gets every event once and in order."""
    sim = Simulation(line(3))
    sent = data_frames(sim)
    reply = deploy(sim, FORK)
    assert reply.ok, reply.error
    sim.run_until(sim.now + 3.0)
    fresh = [d for _, _, d in sent if d.edge == 0 or d.also]
    assert fresh and all(d.also == [(1, d.seq, d.floor)] for d in fresh if d.edge == 0)
    assert not [d for _, _, d in sent if d.edge == 1 and not d.also]  # never sent alone
    emitted = sim.cores["N1"].instances("fork")["src"].emitted
    for sink in ("left", "right"):
        stats = sink_stats(sim, "fork", sink)
        assert stats["repeats"] == 0 and stats["out_of_order"] == 0
        assert emitted - 5 <= stats["count"] <= emitted


@pytest.mark.parametrize(
    "also",
    [[(0, 0, 0)], [(1, 0, 0), (1, 0, 0)], [(2, 0, 0)], [(-1, 0, 0)]],
    ids=["the main edge again", "an edge twice", "an edge the app lacks", "a negative edge"],
)
def test_a_folded_frame_naming_a_wrong_edge_is_dropped_whole(
    also: list[tuple[int, int, int]],
) -> None:
    """Nothing of such a frame is delivered, not even to its valid edges; the node goes on."""
    sim = Simulation(line(3))
    reply = deploy(sim, FORK)
    assert reply.ok, reply.error
    core = sim.cores["N3"]
    dep = core.apps["fork"]
    before, expected = core.dropped_messages, dep.inc[0].expected
    frame = m.Data("fork", 0, dep.epoch, expected, [b"\x91\x00"], 0.0, 0, also)
    core.receive("N1", frame, sim.now)
    assert core.dropped_messages == before + 1
    assert dep.inc[0].expected == expected  # the main edge took nothing either
    core.receive("N1", m.Data("fork", 0, dep.epoch, expected, [b"\x91\x00"]), sim.now)
    assert dep.inc[0].expected == expected + 1  # the same frame, unfolded, is taken


@pytest.mark.parametrize(
    ("app_file", "scenario_file"),
    [("camera.yaml", "camera-line.yaml"), ("fig2.yaml", "line4.yaml")],
)
def test_distributed_bytes_planner_matches_central_plan(app_file: str, scenario_file: str) -> None:
    """``planner: bytes`` in the document: the probes carry each hop's power figures and
    every node reaches the central plan's placement."""
    from mso.model.appfile import with_planner

    doc = with_planner((EXAMPLES / app_file).read_text(), "bytes")
    scenario = load_scenario(EXAMPLES / scenario_file)
    expected = plan(loads_app(doc, resolve_code=False), scenario.network).placement
    assert expected == plan(loads_app(doc), scenario.network, planner="bytes").placement
    sim = Simulation(scenario.network)
    reply = deploy(sim, doc, via=next(iter(scenario.network.nodes)))
    assert reply.ok, reply.error
    assert reply.placement == expected
