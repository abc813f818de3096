"""The bytes planner weighs each link's rate (issue 25): an edge is not put on a link too slow
to carry it, whatever energy says; the probe collects the rates hop by hop, in a deployment as
in the central plan."""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path

import pytest

from mso.model.app import App
from mso.model.appfile import load_app
from mso.model.network import LinkSpec, Network
from mso.planning.bytesplit import CARRY_UJ_PER_MS, LINK_SHARE, Hop, assign_bytes, carry_prefix
from mso.planning.objectives import energy_per_event
from mso.planning.placement import network_probe, plan, probed_hops
from mso.protocol import messages as m
from mso.scenario import load_scenario
from mso.sim.runner import Simulation

EXAMPLES = Path(__file__).resolve().parent.parent / "src" / "mso" / "examples"


def camera_app() -> App:
    """A 10 Hz camera's 50 KB frames (4 Mb/s) into a cheap downscale, then small edges."""
    return load_app(EXAMPLES / "camera-slow.yaml", resolve_code=False)


def robots(first_link_mbps: float | None) -> Network:
    """examples/slow-link.yaml with the R1-R2 link at ``first_link_mbps``. R1 computes slowly
    (its CPU energy per event is ten times R2's), so energy alone sends the raw frames over
    the R1-R2 link to be downscaled on R2."""
    net = load_scenario(EXAMPLES / "slow-link.yaml").network
    assert net.link("R1", "R2") == LinkSpec("R1", "R2", bandwidth_mbps=2.0)
    nodes = list(net.nodes.values())
    links = [LinkSpec("R1", "R2", bandwidth_mbps=first_link_mbps), LinkSpec("R2", "R3")]
    return Network(nodes, links)


def test_a_link_too_slow_for_an_edge_is_not_given_it() -> None:
    # Hand values: downscale on R1 costs 5 ms / 0.1 * 4 W = 200 mJ per event; on R2 the frame's
    # 50,000 B * 3 µJ = 150 mJ plus 20 mJ of CPU = 170 mJ: energy alone moves it to R2. The
    # frames need 50,000 B * 10/s * 8 = 4 Mb/s; a 2 Mb/s link carries at most 1.6 (LINK_SHARE).
    app = camera_app()
    unshaped = plan(app, robots(None), planner="bytes").placement
    assert unshaped["downscale"] == "R2"
    fast = plan(app, robots(54.0), planner="bytes").placement
    assert fast["downscale"] == "R2"  # a link that carries the frames changes nothing
    slow_net = robots(2.0)
    slow = plan(app, slow_net, planner="bytes").placement
    assert slow["downscale"] == "R1"  # the raw frames stay off the 2 Mb/s link
    assert slow["track"] != "R1"  # and the small edge after it still crosses
    # dearer in energy, as it must be: the rate is a limit energy alone does not see
    assert energy_per_event(app, slow_net, slow) > energy_per_event(app, slow_net, unshaped)


def test_the_link_rate_limit_is_the_edges_bytes_per_second() -> None:
    hops = [Hop("A", 1.0, cpu_w=40.0), Hop("B", 1.0, rate_mbps=1.0)]
    # one vertex of cost 1: 40 mJ on A, 4 mJ on B plus carrying its input there
    assert assign_bytes([1.0], [1.0], [1000, 0], hops, to_end=False) == [1]  # 8 kb/s fits
    # 1,000 B at 125 events/s is 1 Mb/s: over 0.8 of the link's rate
    assert assign_bytes([1.0], [1.0], [1000, 0], hops, to_end=False, events=[125, 125]) == [0]
    assert LINK_SHARE * 1e6 >= 1000 * 100 * 8  # 100 events/s fit
    assert assign_bytes([1.0], [1.0], [1000, 0], hops, to_end=False, events=[100, 100]) == [1]


def test_the_tails_output_is_kept_off_a_slow_link_too() -> None:
    # the vertex's output goes on to the route's end. In: 10,000 B at 1/s; out: 1,000 B at
    # 100/s. Energy alone keeps it on A (its output's 6,000 µJ against the input's 60,000)
    hops = [Hop("A", 1.0), Hop("B", 1.0), Hop("C", 1.0)]
    assert assign_bytes([1.0], [1.0], [10_000, 1_000], hops, to_end=True, events=[1, 100]) == [0]
    # the link into C carries 0.4 Mb/s: the input's 80 kb/s, not the output's 800: the
    # vertex goes to C itself
    slow = [*hops[:2], Hop("C", 1.0, rate_mbps=0.5)]
    assert assign_bytes([1.0], [1.0], [10_000, 1_000], slow, to_end=True, events=[1, 100]) == [2]


def test_nowhere_feasible_gives_the_limits_up() -> None:
    # every link too slow and no CPU to spare at the anchor: a placement still comes back
    hops = [Hop("A", 0.001), Hop("B", 1.0, rate_mbps=0.001)]
    assert assign_bytes([5.0], [5.0], [10_000, 0], hops, to_end=False) == [1]


def test_carrying_time_weighs_in_at_the_links_rate() -> None:
    hops = [Hop("A", 1.0), Hop("B", 1.0, rate_mbps=1.0), Hop("C", 1.0)]
    # a byte takes 8 µs at 1 Mb/s: 0.008 ms, weighed CARRY_UJ_PER_MS µJ per ms; C's rate unknown
    per_byte = 3.0 + CARRY_UJ_PER_MS * 8e-3
    assert carry_prefix(hops) == pytest.approx([0.0, per_byte, per_byte + 3.0])
    # a slower link costs more time: between equal energies the faster link is chosen
    a, b = Hop("B", 1.0, rate_mbps=1.0), Hop("B2", 1.0, rate_mbps=10.0)
    assert carry_prefix([hops[0], a])[1] > carry_prefix([hops[0], b])[1]


def test_the_probe_collects_each_links_rate() -> None:
    hops = network_probe(robots(2.0))("R1", "R3")
    assert [h.rate_mbps for h in hops] == [None, 2.0, None]  # the first node is not reached
    good = probed_hops(["A", "B", "C"], [1.0, 1.0, 1.0], rates=[2.0, 0.0])
    assert [h.rate_mbps for h in good] == [None, 2.0, None]  # 0: not known
    # none (an older peer), too few, negative or not finite: no rates at all
    for rates in ([], [2.0], [2.0, -1.0], [math.inf, 1.0]):
        got = probed_hops(["A", "B", "C"], [1.0, 1.0, 1.0], rates=rates)
        assert [h.rate_mbps for h in got] == [None, None, None]


def test_a_deployment_probes_the_rates_and_reaches_the_plan() -> None:
    # the distributed probe: each node that forwards it adds the rate of the link it uses
    # (the scenario's bandwidth_mbps in a simulation), so the deployment keeps the frames off
    # the slow link exactly as the central plan does
    doc = (EXAMPLES / "camera-slow.yaml").read_text()  # planner: bytes, the default
    for rate, downscale in ((2.0, "R1"), (None, "R2")):
        net = robots(rate)
        sim = Simulation(net)
        seen: list[m.Message] = []
        sim.taps.append(lambda _a, _b, msg, seen=seen: seen.append(msg))
        sim.request("R1", m.DeployRequest(doc, "app.yaml"))
        sim.run_until(sim.now + 2.0)
        replies = [r for _, _, r in sim.replies if isinstance(r, m.DeployReply)]
        assert replies and replies[-1].ok, replies
        assert replies[-1].placement == plan(camera_app(), net).placement
        assert replies[-1].placement["downscale"] == downscale
        probes = [r for r in seen if isinstance(r, m.ProbeReply)]
        assert any(r.rates == [rate or 0.0, 0.0] for r in probes)


def test_compare_says_which_placements_cannot_run() -> None:
    # the busiest CPU and, where links have rates, the busiest link: a share over 1 cannot run
    from click.testing import CliRunner

    from mso.cli import main

    def rows(app: str, scenario: str) -> dict[str, dict[str, float]]:
        args = ["compare", str(EXAMPLES / app), "--scenario", str(EXAMPLES / scenario), "--json"]
        r = CliRunner().invoke(main, args)
        assert r.exit_code == 0, r.output
        out: dict[str, dict[str, float]] = json.loads(r.output)
        return out

    slow = rows("camera-slow.yaml", "slow-link.yaml")
    assert slow["algorithm1"]["link_share"] == pytest.approx(0.04)  # 80 kb/s of 2 Mb/s
    # the ILP keeps links within their rates too (energy and hops; not max_load, by CPU alone)
    assert slow["optimal:energy"]["link_share"] <= 0.8
    assert slow["optimal:energy"]["energy"] == pytest.approx(slow["algorithm1"]["energy"])
    assert slow["optimal:max_load"]["link_share"] == pytest.approx(2.0)  # 4 Mb/s of 2
    camera = rows("camera.yaml", "camera-line.yaml")
    assert camera["source"]["cpu_share"] == pytest.approx(1.14)  # 38 ms at 30 Hz on one CPU
    assert camera["optimal:energy"]["cpu_share"] <= 1.0
    assert camera["algorithm1"]["link_share"] == 0.0  # no link has a rate
    r = CliRunner().invoke(
        main, ["compare", str(EXAMPLES / "camera-slow.yaml"), "--scenario",
               str(EXAMPLES / "slow-link.yaml")], env={"COLUMNS": "120"},
    )  # fmt: skip
    assert "busiest link" in r.output and "200% over" in r.output


def test_a_remap_does_not_keep_an_edge_on_a_link_too_slow_for_it() -> None:
    # issue 25's camera at 30 Hz: downscale's 12,500 B out are 3 Mb/s; over a 2 Mb/s R1-R2 link
    # the current placement (edges on R2) cannot be kept, however little the new plan saves
    from mso.model.appfile import loads_app
    from mso.planning.placement import Layout
    from test_remap_keeps import CAMERA, walk

    lay = Layout(loads_app(CAMERA, resolve_code=False), "R1", "paper")
    (c,) = lay.chains
    now = {"camera": "R1", "downscale": "R1", "edges": "R2", "tracker": "R3", "logger": "R5"}
    new = {**now, "edges": "R1", "tracker": "R2"}  # 1,600 B at 30/s: 384 kb/s over R1-R2

    def keep(route: list[Hop]) -> tuple[dict[str, str], str]:
        return lay.keep_current(
            c.index, new, now, route, alive=lambda n: True, others=now, margin=0.5
        )

    fast = walk([f"R{i}" for i in range(1, 6)])
    assert keep(fast)[0] == now  # saves 20%, under the margin: kept
    slow = [fast[0], dataclasses.replace(fast[1], rate_mbps=2.0), *fast[2:]]
    assert lay.overloads_link(c.index, now, slow) and not lay.overloads_link(c.index, new, slow)
    assert keep(slow) == (new, "a link it uses cannot carry its edge at the link's rate")


def test_a_netns_node_is_configured_with_its_links_rates(tmp_path: Path) -> None:
    # the kernel's routes say nothing of rates: the netns emulator gives each node its links'
    from mso.emu.controller import EmulatedNode
    from mso.emu.netns.emulator import NetnsEmulator

    emu = NetnsEmulator(load_scenario(EXAMPLES / "slow-link.yaml"))
    emu.log_dir = tmp_path
    emu.nodes = {n: EmulatedNode(n, "10.0.0.1", 7000) for n in ("R1", "R2", "R3")}
    r1, r2, r3 = (emu._node_command(n) for n in ("R1", "R2", "R3"))
    assert r1[r1.index("--link-mbps") + 1] == "R2=2.0" and r1.count("--link-mbps") == 1
    assert r2.count("--link-mbps") == 1 and "R1=2.0" in r2  # R2-R3 is unshaped
    assert "--link-mbps" not in r3


def test_the_ilp_yardstick_keeps_every_link_within_its_rate() -> None:
    from mso.planning.baselines import optimal
    from mso.planning.objectives import busiest_link

    app, slow, fast = camera_app(), robots(2.0), robots(None)
    assert optimal(app, fast, "energy")["downscale"] == "R2"  # energy alone
    within = optimal(app, slow, "energy")
    assert within["downscale"] == "R1" and busiest_link(app, slow, within) <= LINK_SHARE
    assert within == plan(app, slow).placement
    # both edges over one link count together: 2 Mb/s carries 1.6 of them; three 0.6 Mb/s
    # edges from R1 (15 KB at 5/s each) cannot all cross it, one of three stays on R1
    trio = App("trio")
    trio.vertex("s", pinned="R1", cost=0, rate=5)
    for v in ("x", "y", "z"):
        trio.vertex(v, cost=5)
        trio.edge("s", v, size=15_000)
        trio.edge(v, "t", size=10)
    trio.vertex("t", pinned="R3", cost=0)
    trio.validate(resolve_code=False)
    got = optimal(trio, slow, "energy")
    # each is 200 mJ on R1 against 65 on R2 (20 of CPU, 45 to carry its input there)
    assert sum(got[v] == "R1" for v in ("x", "y", "z")) == 1
    assert busiest_link(trio, slow, got) <= LINK_SHARE
