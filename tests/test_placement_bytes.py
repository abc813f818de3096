"""The bytes-aware split of Algorithm 1 (issue 25) on hand-computed cases, and the paper's split
kept exactly as ``planner: paper``."""

from __future__ import annotations

import itertools
import math
from pathlib import Path

import pytest

from mso.errors import AppError, PlanningError
from mso.model.app import App
from mso.model.appfile import load_app, loads_app
from mso.model.network import LinkSpec, Network, NodeSpec, PowerModel
from mso.planning.objectives import energy_per_event
from mso.planning.placement import Hop, Layout, assign_bytes, network_probe, plan, vertex_loads
from mso.scenario import load_scenario

ROOT = Path(__file__).resolve().parent.parent
EXAMPLES = ROOT / "examples"


def line(n: int = 4, cpu: float = 1.0) -> Network:
    ids = [f"N{i + 1}" for i in range(n)]
    return Network(
        [NodeSpec(i, cpu=cpu) for i in ids], [LinkSpec(a, b) for a, b in itertools.pairwise(ids)]
    )


def chain_app(sizes: list[int], costs: list[float], rate: float = 1.0) -> App:
    """src (pinned N1) -> v1 .. vk -> sink (pinned on the line's last node, set by the caller)."""
    app = App("chain")
    app.vertex("src", pinned="N1", cost=0, rate=rate)
    names = [f"v{i + 1}" for i in range(len(costs))]
    for name, c in zip(names, costs, strict=True):
        app.vertex(name, cost=c)
    app.vertex("sink", pinned="N4", cost=0)
    for (a, b), s in zip(itertools.pairwise(["src", *names, "sink"]), sizes, strict=True):
        app.edge(a, b, size=s)
    return app.validate(resolve_code=False)


def test_chain_is_cut_at_its_smallest_edge() -> None:
    # Sizes 1000, 800, 10, 900, 700: every hop costs 3 µJ per byte (tx 2 + rx 1) and CPU is
    # the same everywhere, so the cheapest split carries the 10-byte edge over all 3 hops:
    # v1, v2 on N1 and v3, v4 on N4 (30 µJ of radio against at least 3 * 700 elsewhere).
    app = chain_app([1000, 800, 10, 900, 700], [1, 1, 1, 1])
    p = plan(app, line(), planner="bytes").placement
    assert [p[v] for v in ("v1", "v2", "v3", "v4")] == ["N1", "N1", "N4", "N4"]
    # The paper's split spreads by cost and carries the big edges.
    paper = plan(app, line(), planner="paper").placement
    assert [paper[v] for v in ("v1", "v2", "v3", "v4")] == ["N1", "N2", "N3", "N4"]
    net = line()
    assert energy_per_event(app, net, p) < energy_per_event(app, net, paper)


def test_assign_bytes_hand_values() -> None:
    hops = [Hop(f"N{i}", 1.0) for i in range(1, 5)]
    # one vertex, 100 bytes in and 10 out to the end: crossing with the 10 is cheaper
    assert assign_bytes([1.0], [1.0], [100, 10], hops, to_end=True) == [0]
    assert assign_bytes([1.0], [1.0], [10, 100], hops, to_end=True) == [3]
    # nothing downstream to carry to (no target): stays by the anchor
    assert assign_bytes([1.0, 1.0], [1.0, 1.0], [10, 10, 0], hops, to_end=False) == [0, 0]
    # a node with no CPU is never used for work
    hops0 = [Hop("N1", 0.0), *hops[1:]]
    assert assign_bytes([1.0], [1.0], [100, 10], hops0, to_end=True) == [1]
    assert assign_bytes([], [], [5], hops, to_end=True) == []


def test_faster_cheaper_cpu_draws_work() -> None:
    # CPU energy 5 ms * 4 W = 20 mJ on N1; on N2 (cpu 4) 5 mJ; 100 bytes over a hop is 0.3 mJ.
    hops = [Hop("N1", 1.0), Hop("N2", 4.0), Hop("N3", 1.0)]
    assert assign_bytes([5.0], [5.0], [100, 100], hops, to_end=True) == [1]


def test_capacity_respected() -> None:
    # At 100 events/s, v1 and v2 (6 ms each) load a node of cpu 1 to 1.2: they cannot share
    # N1 even though the edge between them is the big one.
    app = chain_app([10, 5000, 10], [6, 6], rate=100)
    net = line()
    p = plan(app, net, planner="bytes").placement
    assert p["v1"] == "N1" and p["v2"] != "N1"
    loads = vertex_loads(app)
    assert loads["v1"] == pytest.approx(600.0)
    for n in net.nodes:
        assert sum(loads[v] for v in app.vertices if p[v] == n) <= 1000.0 * net.nodes[n].cpu
    # with room for both they share the camera node
    roomy = plan(app, line(cpu=2.0), planner="bytes").placement
    assert roomy["v1"] == roomy["v2"] == "N1"


def test_capacity_counts_what_is_already_placed() -> None:
    hops = [Hop("N1", 1.0), Hop("N2", 1.0), Hop("N3", 1.0)]
    # N1 is already 900 ms/s busy: a 200 ms/s vertex goes on, despite the big input edge
    assert assign_bytes([2.0], [200.0], [5000, 10], hops, [900.0, 0, 0], to_end=True) == [1]
    # nowhere fits: capacity is given up rather than the placement
    full = [1000.0, 1000.0, 1000.0]
    assert assign_bytes([2.0], [200.0], [5000, 10], hops, full, to_end=True) == [0]


def test_anchors_kept() -> None:
    # mid is pinned to N3: the split never moves it, and v1 stays between src and mid
    app = App("anchored")
    app.vertex("src", pinned="N1", cost=0)
    app.vertex("v1", cost=1)
    app.vertex("mid", pinned="N3", cost=1)
    app.vertex("v2", cost=1)
    app.vertex("sink", pinned="N4", cost=0)
    for a, b, s in [("src", "v1", 5000), ("v1", "mid", 10), ("mid", "v2", 10), ("v2", "sink", 9)]:
        app.edge(a, b, size=s)
    app.validate(resolve_code=False)
    p = plan(app, line(), planner="bytes").placement
    assert p["src"] == "N1" and p["mid"] == "N3" and p["sink"] == "N4"
    assert p["v1"] == "N1"  # the 5000-byte edge stays local
    order = {f"N{i}": i for i in range(1, 5)}
    assert order["N1"] <= order[p["v1"]] <= order["N3"] <= order[p["v2"]] <= order["N4"]


def test_paper_reproduces_todays_placements() -> None:
    """``planner: paper`` is the split the placement tests pin down (§3.3, Fig. 2, convoy)."""
    sec = load_app(EXAMPLES / "section33.yaml", resolve_code=False)
    assert plan(sec, line(), planner="paper").placement == {
        "A": "N1", "B": "N2", "C": "N2", "D": "N3", "E": "N1", "F": "N4",
    }  # fmt: skip
    fig2 = load_app(EXAMPLES / "fig2.yaml", resolve_code=False)
    assert plan(fig2, line(), planner="paper").placement == {
        "A": "N1", "B": "N2", "C": "N2", "D": "N3", "E": "N4",
        "F": "N1", "G": "N2", "H": "N3", "I": "N4",
    }  # fmt: skip
    convoy = load_app(EXAMPLES / "convoy.yaml", resolve_code=False)
    net = load_scenario(EXAMPLES / "convoy-line.yaml").network
    assert plan(convoy, net, planner="paper").placement == {
        "laser": "N1", "odometry": "N1", "scan_filter": "N1", "scan_matcher": "N1",
        "odom_filter": "N1", "localization": "N2", "path_planning": "N4", "trajectory": "N4",
        "visible_camera": "N1", "infrared_camera": "N1", "visible_blobs": "N2",
        "infrared_blobs": "N2", "blob_fusion": "N2", "bayes_inference": "N4",
        "target_map": "N4", "storage": "N4",
    }  # fmt: skip
    # and the app's key, the default and the override agree
    sec.planner = "paper"
    assert plan(sec, line()).placement == plan(sec, line(), planner="paper").placement


def test_camera_pipeline_keeps_raw_frames_local() -> None:
    app = load_app(EXAMPLES / "camera.yaml", resolve_code=False)
    net = load_scenario(EXAMPLES / "camera-line.yaml").network
    p = plan(app, net, planner="bytes").placement
    assert p["downscale"] == "R1"  # the 50 KB frames never cross the radio
    paper = plan(app, net, planner="paper").placement
    assert paper["downscale"] == "R2"  # issue 25's complaint
    assert energy_per_event(app, net, p) < energy_per_event(app, net, paper) / 2


def test_power_figures_come_from_the_probe() -> None:
    # N2's radio is ten times as dear: the bytes planner avoids making N2 carry a big edge
    # out of a vertex it hosts; the probe reports each node's power model.
    nodes = [NodeSpec("N1"), NodeSpec("N2", power=PowerModel(tx_uj_per_byte=20.0)), NodeSpec("N3")]
    net = Network(nodes, [LinkSpec("N1", "N2"), LinkSpec("N2", "N3")])
    hops = network_probe(net)("N1", "N3")
    assert [h.tx_uj_per_byte for h in hops] == [2.0, 20.0, 2.0]


def test_planner_key_validated_with_its_line() -> None:
    text = "name: a\nplanner: fastest\nvertices:\n  s: {pinned: N1}\n  t: {}\nedges:\n  - [s, t]\n"
    with pytest.raises(AppError) as info:
        loads_app(text, file="app.yaml", resolve_code=False)
    assert info.value.line == 2 and info.value.field == "planner"
    assert "expected one of paper, bytes" in info.value.message
    ok = loads_app(text.replace("fastest", "bytes"), resolve_code=False)
    assert ok.planner == "bytes"
    assert Layout(ok, "N1").planner == "bytes"
    assert Layout(ok, "N1", "paper").planner == "paper"  # an override wins
    app = App("b", planner="fastest")
    app.vertex("s", pinned="N1")
    with pytest.raises(AppError, match="expected one of"):
        app.validate(resolve_code=False)
    with pytest.raises(PlanningError, match="unknown planner"):
        plan(ok, line(), planner="fastest")


def test_bytes_planner_costs_no_more_energy_than_paper_on_examples() -> None:
    for app_file, net_file in [
        ("camera.yaml", "camera-line.yaml"),
        ("fig2.yaml", "line4.yaml"),
        ("convoy.yaml", "convoy-line.yaml"),
    ]:
        app = load_app(EXAMPLES / app_file, resolve_code=False)
        net = load_scenario(EXAMPLES / net_file).network
        e_bytes = energy_per_event(app, net, plan(app, net, planner="bytes").placement)
        e_paper = energy_per_event(app, net, plan(app, net, planner="paper").placement)
        assert e_bytes <= e_paper * (1 + 1e-9), app_file
        assert math.isfinite(e_bytes)


def test_probe_reply_power_figures_validated() -> None:
    from mso.planning.placement import probed_hops

    good = probed_hops(["A", "B"], [1.0, 2.0], [[4.0, 2.0, 1.0], [8.0, 20.0, 1.0]])
    assert good[1] == Hop("B", 2.0, 8.0, 20.0, 1.0)
    # none (an older peer), too few, negative or not finite: the defaults for every hop
    for power in ([], [[4.0, 2.0, 1.0]], [[4.0, -2.0, 1.0]] * 2, [[math.nan, 2.0, 1.0]] * 2):
        assert probed_hops(["A", "B"], [1.0, 2.0], power) == [Hop("A", 1.0), Hop("B", 2.0)]


def test_with_planner_rewrites_the_document() -> None:
    from mso.model.appfile import with_planner

    text = (EXAMPLES / "section33.yaml").read_text()
    assert loads_app(with_planner(text, "bytes"), resolve_code=False).planner == "bytes"
    again = with_planner(with_planner(text, "bytes"), "paper")
    assert again.count("planner:") == 1
    assert loads_app(again, resolve_code=False).planner == "paper"
    with pytest.raises(AppError, match="unknown planner"):
        with_planner(text, "fastest")


def fork_app(big: int) -> App:
    """s (N1) -> f, a fork: f -> x (``big`` bytes) -> t1 (N4, 10 bytes) and f -> y -> t2 (N1)."""
    app = App("fork")
    app.vertex("s", pinned="N1", cost=0)
    for v in ("f", "x", "y"):
        app.vertex(v, cost=1)
    app.vertex("t1", pinned="N4", cost=0)
    app.vertex("t2", pinned="N1", cost=0)
    for a, b, size in [("s", "f", 100), ("f", "x", big), ("x", "t1", 10), ("f", "y", 50)]:
        app.edge(a, b, size=size)
    app.edge("y", "t2", size=50)
    return app.validate(resolve_code=False)


def test_a_fork_is_not_pulled_by_bytes_a_later_vertex_reduces() -> None:
    # f's 5000-byte output shrinks to 10 bytes at x, which may sit anywhere on the way to N4:
    # only 10 bytes must travel toward N4 from f (and nothing from f -> y -> t2 on N1), so f
    # stays by its 100-byte input and x carries the 10 bytes instead.
    app = fork_app(5000)
    lay = Layout(app, "N1", "bytes")
    flow = lay.bottleneck("N4")
    assert flow["x"] == 10 and flow["f"] == 10 and flow["y"] == 0 and flow["t1"] == math.inf
    p = plan(app, line(), planner="bytes").placement
    assert p["f"] == "N1" and p["x"] == "N1" and p["y"] == "N1"


def test_a_repinned_vertex_moves_what_was_derived_from_its_pin() -> None:
    # t1 (a capability's choice on N4) goes to N3 when N4 fails: the bytes that must travel
    # toward N4 are gone, toward N3 they are what they were toward N4 (a kept bottleneck()
    # once went on saying N4), and so are the pinned vertices below each vertex
    lay = Layout(fork_app(5000), "N1", "bytes")
    before = dict(lay.bottleneck("N4"))
    far = {"N1": 0, "N4": 3}  # (N3 out of these distances)
    assert lay.downstream.furthest_pinned("s", far) == "t1"
    lay.repin("t1", "N3")
    assert lay.pinned["t1"] == "N3" and lay.resolved["t1"] == "N3"
    assert lay.bottleneck("N4")["t1"] == 0 and lay.bottleneck("N4")["f"] == 0
    assert lay.bottleneck("N3") == before
    assert lay.downstream.furthest_pinned("s", far) == "s"  # t1 is no longer on N4
    assert lay.downstream.furthest_pinned("s", {**far, "N3": 5}) == "t1"


def test_a_merge_is_pulled_by_its_placed_inputs() -> None:
    # m merges a (N1 side, 10 bytes) and b (5000 bytes, pinned on N4) and sends 10 bytes to
    # t on N4: the chain that places m comes from N1, and the big input pulls m to N4.
    app = App("merge")
    app.vertex("s", pinned="N1", cost=0)
    app.vertex("b", pinned="N4", cost=0)
    app.vertex("a", cost=1)
    app.vertex("m", cost=1)
    app.vertex("t", pinned="N4", cost=0)
    for x, y, size in [("s", "a", 10), ("a", "m", 10), ("b", "m", 5000), ("m", "t", 10)]:
        app.edge(x, y, size=size)
    app.validate(resolve_code=False)
    p = plan(app, line(), planner="bytes").placement
    assert p["m"] == "N4"
    net = line()
    assert energy_per_event(app, net, p) < energy_per_event(
        app, net, plan(app, net, planner="paper").placement
    )


def test_load_of_vertices_with_nowhere_else_to_go_is_reserved() -> None:
    # c1 runs between two vertices pinned on N1 and must stay there (600 ms/s); c2's
    # vertex v (600 ms/s) would sit on N1 by its big input, but N1 has no room left for it.
    app = App("reserved")
    app.vertex("s", pinned="N1", cost=0, rate=100)
    app.vertex("k", cost=6)
    app.vertex("t1", pinned="N1", cost=0)
    app.vertex("v", cost=6)
    app.vertex("t2", pinned="N4", cost=0)
    for x, y, size in [("s", "v", 5000), ("v", "t2", 10), ("s", "k", 10), ("k", "t1", 10)]:
        app.edge(x, y, size=size)
    app.validate(resolve_code=False)
    lay = Layout(app, "N1", "bytes")
    assert lay.forced == {"k": "N1"}
    p = plan(app, line(), planner="bytes").placement
    assert p["k"] == "N1" and p["v"] != "N1"


def test_bytes_chains_are_placed_one_after_another() -> None:
    # every node places its chain knowing every earlier one: a deployment reaches the plan
    fig2 = load_app(EXAMPLES / "fig2.yaml", resolve_code=False)
    lay = Layout(fig2, "N1", "bytes")
    for earlier, later in itertools.pairwise(lay.order):
        assert earlier in lay.deps[later]
    paper = Layout(fig2, "N1", "paper")
    assert any(not paper.deps[c] for c in paper.order[1:])  # the paper's chains go concurrently
