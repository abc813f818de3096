"""Management rules running inside the nodes, in virtual time: each fires on its event and not
otherwise, a policy named in the app is loaded and obeyed, a flapping link causes no remap."""

from __future__ import annotations

import dataclasses

import msgspec

from mso.management import RuleSettings
from mso.model.network import LinkSpec, Network, NodeSpec, PowerModel
from mso.node.core import NodeCore
from mso.protocol import effects as fx
from mso.protocol import messages as m
from mso.sim.runner import Simulation
from runtime_vertices import pipe_app

POWER = PowerModel(idle_w=1.0, cpu_w=6.0)

WORK = """
name: work
vertices:
  src: {code: runtime_vertices:CountingSource, pinned: N1, rate: 50, cost: 0.1,
        output: runtime_vertices:Num}
  work: {code: runtime_vertices:Double, cost: 20, output: runtime_vertices:Num}
  sink: {code: runtime_vertices:Recorder, pinned: N3, cost: 0.1}
edges: [[src, work], [work, sink]]
"""


def robots(leader_wh: float) -> Network:
    """A fast leader (so Algorithm 1 puts the costly vertex on it) with a given battery."""
    nodes = [
        NodeSpec("N1", cpu=4.0, battery_wh=leader_wh, power=POWER),
        NodeSpec("N2", battery_wh=5.0, power=POWER),
        NodeSpec("N3", battery_wh=5.0, power=POWER),
    ]
    return Network(nodes, [LinkSpec("N1", "N2", delay_ms=1), LinkSpec("N2", "N3", delay_ms=1)])


def deployed(net: Network, doc: str, **kw: object) -> Simulation:
    sim = Simulation(net, **kw)  # type: ignore[arg-type]
    sim.request("N1", m.DeployRequest(doc, "app.yaml"))
    sim.run_until(1.0)
    (reply,) = [r for _, _, r in sim.replies if isinstance(r, m.DeployReply)]
    assert reply.ok, reply.error
    return sim


def sink(sim: Simulation, app: str, node: str) -> dict[str, int]:
    out: dict[str, int] = sim.instance(node, app, "sink").stats()
    return out


def test_energy_rule_moves_work_off_a_poor_battery_and_loses_nothing() -> None:
    sim = deployed(robots(leader_wh=0.5), WORK)
    assert sim.cores["N1"].placement("work")["work"] == "N1"
    sim.run_until(15.0)
    placed = sim.cores["N3"].placement("work")
    assert placed["work"] == "N2"  # one hop downstream, off the leader
    (done,) = sim.cores["N1"].manager.done
    assert "relocate work/work -> N2" in done and "lifetime" in done
    status = sim.cores["N1"].manager.status()
    draining = [d for d in status.decisions if "draining" in d.split(":")[0]]
    assert draining[0].split(" ", 1)[1].startswith("N1 draining")  # 0.5 Wh against 5 Wh
    warming = [d for d in status.decisions if "warming up" in d.split(":")[0]]
    decisions = [d for d in status.decisions if d not in draining + warming]
    ends = ("held: confirming 1/3", "held: confirming 2/3", "allowed")
    assert [d.endswith(e) for d, e in zip(decisions, ends, strict=False)] == [True] * 3
    got = sink(sim, "work", "N3")
    sent = sim.cores["N1"].instances("work")["src"].emitted
    assert got["repeats"] == 0 and got["out_of_order"] == 0
    assert sent - 3 <= got["count"] <= sent


def test_energy_rule_stays_put_when_nothing_is_gained() -> None:
    sim = deployed(robots(leader_wh=5.0), WORK)  # equal batteries: the fast leader is best
    sim.run_until(15.0)
    assert sim.cores["N1"].placement("work")["work"] == "N1"
    assert all(not c.manager.done for c in sim.cores.values())


def test_no_rule_runs_when_management_is_off() -> None:
    sim = deployed(robots(leader_wh=0.5), WORK, manage=False)
    sim.run_until(15.0)
    assert sim.cores["N1"].placement("work")["work"] == "N1"


def test_a_policy_named_in_the_app_is_loaded_and_obeyed() -> None:
    doc = WORK.replace("name: work", "name: work\npolicy: {code: custom_policy:PreferNode, "
                       "params: {node: N2}}")  # fmt: skip
    sim = deployed(robots(leader_wh=5.0), doc)  # lifetime would keep it on N1 (test above)
    sim.run_until(15.0)
    assert sim.cores["N1"].placement("work")["work"] == "N2"
    assert "prefer-node" in sim.cores["N1"].manager.status().app_policies.values()


def test_a_policy_that_cannot_be_loaded_fails_the_deployment_clearly() -> None:
    sim = Simulation(robots(leader_wh=5.0))
    sim.request(
        "N1", m.DeployRequest(WORK.replace("name: work", "name: work\npolicy: fast"), "w.yaml")
    )
    sim.run_until(1.0)
    (reply,) = [r for _, _, r in sim.replies if isinstance(r, m.DeployReply)]
    assert not reply.ok
    assert reply.error.startswith("w.yaml: policy: unknown policy 'fast'")
    assert all(not c.apps for c in sim.cores.values())


SQUARE = [("N1", "N2"), ("N2", "N4"), ("N1", "N3"), ("N3", "N4")]


def square() -> Network:
    nodes = [NodeSpec(f"N{i}") for i in range(1, 5)]
    return Network(nodes, [LinkSpec(a, b, delay_ms=1) for a, b in SQUARE])


def remaps(sim: Simulation) -> list[str]:
    return [d for c in sim.cores.values() for d in c.manager.done if "remap" in d]


def test_a_route_change_inside_a_chain_remaps_it_once_routes_settle() -> None:
    sim = deployed(square(), pipe_app(100))
    mid = sim.cores["N1"].placement("pipe")["mid"]
    assert mid in ("N2", "N3")
    other = "N3" if mid == "N2" else "N2"
    sim.run_until(5.0)
    assert remaps(sim) == []  # no route changed: nothing to do
    sim.network.remove_link(mid, "N4")  # the chain's route now runs the other way
    sim.update_routes()
    sim.run_until(7.0)
    assert remaps(sim) == []  # settling (route_settle_s = 3 s)
    sim.run_until(12.0)
    (done,) = remaps(sim)
    assert done.startswith("8.0 remap pipe chain 0")  # by the head's node, once
    assert sim.cores["N4"].placement("pipe")["mid"] == other
    got = sink(sim, "pipe", "N4")
    sent = sim.cores["N1"].instances("pipe")["src"].emitted
    assert got["repeats"] == 0 and got["out_of_order"] == 0
    assert sent - 5 <= got["count"] <= sent


def test_a_link_flapping_every_second_never_triggers_a_remap_while_it_flaps() -> None:
    sim = deployed(square(), pipe_app(50))
    mid = sim.cores["N1"].placement("pipe")["mid"]
    t = 2.0
    for k in range(30):  # down, up, down, ... once a second for 30 s
        sim.run_until(t)
        if k % 2 == 0:
            sim.network.remove_link(mid, "N4")
        else:
            sim.network.add_link(LinkSpec(mid, "N4", delay_ms=1))
        sim.update_routes()
        t += 1.0
    assert remaps(sim) == []
    assert all(not c.failed for c in sim.cores.values())  # nobody was taken for dead either
    sim.run_until(t + 10.0)
    assert len(remaps(sim)) <= 1  # once it is stable, at most one remap
    got = sink(sim, "pipe", "N4")
    assert got["repeats"] == 0 and got["out_of_order"] == 0


def slo_app(slo_ms: float) -> str:
    return pipe_app(100).replace("name: pipe", f"name: pipe\nslo_ms: {slo_ms}\npolicy: delay")


def test_a_violated_delay_slo_makes_the_head_remap_its_chain() -> None:
    sim = deployed(square(), slo_app(1.0))  # three 1 ms hops: about 3 ms, over the SLO
    sim.run_until(12.0)
    done = remaps(sim)
    assert done and all("remap pipe chain 0" in d and "SLO 1 ms" in d for d in done)
    assert all(d in sim.cores["N1"].manager.done for d in done)  # the head's node acts
    assert len(done) <= 1  # then the chain's rate limit (15 s) holds


def test_a_met_delay_slo_changes_nothing() -> None:
    sim = deployed(square(), slo_app(50.0))
    sim.run_until(12.0)
    assert remaps(sim) == []
    delay = sim.cores["N4"].status(sim.now)["apps"]["pipe"]["chain_delay_ms"]["src-mid-sink"]
    assert 2.0 < delay < 50.0


# planner: paper: the join starts on the relay the paper's split gives it, which the rules shed
JOINED = """
name: joined
planner: paper
vertices:
  s1: {code: runtime_vertices:CountingSource, pinned: N1, rate: 20, cost: 0.1,
       output: runtime_vertices:Num}
  s2: {code: runtime_vertices:CountingSource, pinned: N1, rate: 20, cost: 0.1,
       output: runtime_vertices:Num}
  join: {code: runtime_vertices:Counter, cost: 10, output: runtime_vertices:Num}
  sink: {code: runtime_vertices:Recorder, pinned: N4, cost: 0.1}
edges: [[s1, join], [s2, join], [join, sink]]
"""


def line4(small: str) -> Network:
    """Four robots in a line; ``small`` has a fifth of the others' battery."""
    nodes = [
        NodeSpec(f"N{i}", battery_wh=1.0 if f"N{i}" == small else 5.0, power=POWER)
        for i in range(1, 5)
    ]
    links = [LinkSpec(f"N{i}", f"N{i + 1}", delay_ms=1) for i in range(1, 4)]
    return Network(nodes, links)


def test_a_draining_node_sheds_a_join_by_an_energy_remap_and_loses_nothing() -> None:
    """The join (tail of two chains, head of a third) is never relocated; on the small
    battery it makes N2 draining, and the rules remap its chains with the join placed on a
    longer-lived neighbour, once: nothing sends it back, no event is lost or repeated."""
    sim = deployed(line4(small="N2"), JOINED)
    assert sim.cores["N1"].placement("joined")["join"] == "N2"  # Algorithm 1's choice
    sim.run_until(40.0)
    done = [d for c in sim.cores.values() for d in c.manager.done]
    (remap,) = done  # the only reconfiguration, by N2
    assert remap in sim.cores["N2"].manager.done
    assert "remap joined chains 0, 1, 2" in remap and "N2 draining, sheds join/fork join" in remap
    maps = [dict(c.placement("joined")) for c in sim.cores.values() if "joined" in c.apps]
    assert all(mp == maps[0] for mp in maps)
    assert maps[0]["join"] in ("N1", "N3")
    got = sink(sim, "joined", "N4")
    stones = sim.cores["N1"].instances("joined")
    sent = stones["s1"].emitted + stones["s2"].emitted
    assert got["repeats"] == 0 and got["out_of_order"] == 0  # the counter's state moved with it
    assert sent - 5 <= got["count"] <= sent


def test_an_energy_remap_keeps_the_join_off_the_robot_with_the_sensors() -> None:
    """N1 runs the pinned sources and outlives N3: the lifetime policy alone would put the join
    on N1; the rules as shipped (spare_pinned) put it on N3 and leave N1 its battery."""
    nodes = [
        NodeSpec(n, battery_wh=b, power=POWER)
        for n, b in (("N1", 5.0), ("N2", 1.0), ("N3", 2.0), ("N4", 5.0))
    ]
    net = Network(nodes, [LinkSpec(f"N{i}", f"N{i + 1}", delay_ms=1) for i in range(1, 4)])
    for rules, where in ((None, "N3"), (RuleSettings(spare_pinned=False), "N1")):
        sim = deployed(net, JOINED, **({} if rules is None else {"rules": rules}))
        sim.run_until(20.0)
        (remap,) = [d for c in sim.cores.values() for d in c.manager.done]
        assert "N2 draining, sheds join/fork join" in remap and f"better on {where}" in remap
        assert sim.cores["N1"].placement("joined")["join"] == where


def lying(core: NodeCore) -> None:
    """``core`` claims a full battery, no drain and an idle 100x CPU in every beat."""
    honest = core.figures

    def figures() -> m.Figures:
        f = honest()
        return msgspec.structs.replace(
            f, cpu=100.0, load=0.0, drain_w=0.01, remaining_j=1e9, lifetime_s=1e9
        )

    core.figures = figures  # type: ignore[method-assign]


def test_an_energy_remap_never_puts_the_join_on_a_node_with_no_part_in_the_app() -> None:
    """N5, a neighbour of the draining N2 alone that hosts and relays nothing of the app,
    claims a full battery, no drain and an idle 100x CPU in every beat (a captured node's
    false figures: nothing else measures them). The remap took the join onto it — an app it
    had no part in, now hosted by it; only the app's own nodes are candidates now, and the
    join goes to N3 as without the lie (``energy_outsiders`` brings the old rule back)."""
    nodes = [
        NodeSpec(f"N{i}", battery_wh=1.0 if i in (2, 5) else 5.0, power=POWER) for i in range(1, 6)
    ]
    links = [LinkSpec(f"N{i}", f"N{i + 1}", delay_ms=1) for i in range(1, 4)]
    net = Network(nodes, [*links, LinkSpec("N2", "N5", delay_ms=1)])
    for rules, where in ((None, "N3"), (RuleSettings(energy_outsiders=True), "N5")):
        sim = deployed(net, JOINED, **({} if rules is None else {"rules": rules}))
        assert sim.cores["N1"].placement("joined")["join"] == "N2"
        lying(sim.cores["N5"])
        sim.run_until(20.0)
        (remap,) = [d for c in sim.cores.values() for d in c.manager.done]
        assert "N2 draining, sheds join/fork join" in remap and f"better on {where}" in remap
        assert {sim.cores[n].placement("joined")["join"] for n in ("N1", "N4")} == {where}


# planner: paper: work and tail start on the relays, as the paper's split spreads them
BURST = """
name: burst
planner: paper
vertices:
  src: {code: runtime_vertices:CountingSource, pinned: N1, rate: 50, cost: 0.1,
        output: runtime_vertices:Num}
  work: {code: runtime_vertices:Double, cost: 4, output: runtime_vertices:Num}
  tail: {code: runtime_vertices:Double, cost: 1, output: runtime_vertices:Num}
  sink: {code: runtime_vertices:Recorder, pinned: N4, cost: 0.1}
edges: [[src, work], [work, tail], [tail, sink]]
"""


def slow_starts(sim: Simulation, node: str, cpu_s: float) -> None:
    """Every vertex instance ``node`` starts takes ``cpu_s`` of CPU to open (imports, a
    database, a map), as a device's executor measures it; the simulator's measures none."""
    ex = sim.executors[node]
    push = ex.push

    def started(at: float, result: fx.VertexResult) -> None:
        if isinstance(result, fx.VertexStarted):
            result = dataclasses.replace(result, cpu_s=cpu_s)
        push(at, result)

    ex.push = started


def test_a_start_up_burst_is_not_taken_for_draining() -> None:
    """N4 has a battery as large as N2's and N3's, but opening its vertices costs it 1 s of CPU
    each, charged as measured (as in the demo): for a few seconds its drain says it will die
    several times sooner than they will. Warming up, it is not judged draining and moves
    nothing; the leader, whose small battery really runs down, is judged draining once warm
    and sheds work. Without the warm-up the burst made N4 draining and moved ``tail``."""
    measured = dataclasses.replace(POWER, cpu_energy="measured")
    nodes = [NodeSpec("N1", cpu=4.0, battery_wh=0.5, power=POWER)] + [
        NodeSpec(n, battery_wh=5.0, power=measured if n == "N4" else POWER)
        for n in ("N2", "N3", "N4")
    ]
    net = Network(nodes, [LinkSpec(f"N{i}", f"N{i + 1}", delay_ms=1) for i in range(1, 4)])
    for rules in (RuleSettings(), RuleSettings(warmup_s=0.0)):
        sim = Simulation(net, rules=rules)
        slow_starts(sim, "N4", 1.0)
        sim.request("N1", m.DeployRequest(BURST, "burst.yaml"))
        draining: dict[str, float] = {}  # node -> when first judged draining
        for t in range(1, 21):
            sim.run_until(float(t))
            for n, core in sim.cores.items():
                if n in core.manager.engine.draining:
                    draining.setdefault(n, sim.now)
            if t == 1:  # Algorithm 1's placement: each robot has a vertex it may shed
                placed = sim.cores["N1"].placement("burst")
                assert (placed["work"], placed["tail"]) == ("N1", "N4")
            if t == 2:  # the start-up dominates N4's drain: it looks short-lived
                life = {n: c.monitor.lifetime_s or 0.0 for n, c in sim.cores.items()}
                assert life["N4"] < rules.critical_ratio * life["N3"]
            if t == 10 and rules.warmup_s:  # still warming up (instances started just after 0)
                assert draining == {} and all(not c.manager.done for c in sim.cores.values())
        placed = sim.cores["N1"].placement("burst")
        done = {n: c.manager.done for n, c in sim.cores.items() if c.manager.done}
        if rules.warmup_s:
            assert draining == {"N1": 11.0}  # the leader, once warm; never N4
            assert list(done) == ["N1"] and "relocate burst/work -> N2" in done["N1"][0]
            assert "N1 draining" in done["N1"][0]
            assert placed["tail"] == "N4" and placed["work"] == "N2"
        else:  # the bug: N4 judged by its start-up, and a move for nothing
            assert draining == {"N1": 2.0, "N4": 2.0}
            assert "relocate burst/tail -> N3" in done["N4"][0] and placed["tail"] == "N3"
        got = sink(sim, "burst", "N4")
        assert got["repeats"] == 0 and got["out_of_order"] == 0


def test_a_rule_move_says_which_rule_on_which_node_asked_and_why_in_words() -> None:
    sim = deployed(robots(leader_wh=0.5), WORK)
    sim.cores["N1"].drain_happened()
    sim.run_until(15.0)
    (move,) = [h for h in sim.cores["N1"].drain_happened() if h.what == "relocation"]
    assert move.by == "rule" and move.took_ms is not None
    assert move.asked.startswith("the relocation rule on N1: lifetime policy, downstream to N2: ")
    assert "shortest battery life" in move.asked and "score" not in move.asked
    (rec,) = sim.cores["N1"].status(sim.now)["moves"]
    assert rec["asked"] == move.asked and rec["vertex"] == "work" and rec["detail"] == "N1 -> N2"
    assert 0 < rec["ago_s"] < 15.0


def test_a_route_remap_says_how_long_ago_the_route_changed_not_a_clock_reading() -> None:
    sim = deployed(square(), pipe_app(100))
    mid = sim.cores["N1"].placement("pipe")["mid"]
    sim.network.remove_link(mid, "N4")
    sim.update_routes()
    sim.run_until(12.0)
    moves = [rec for n in sim.cores for rec in sim.cores[n].status(sim.now)["moves"]]
    (remap,) = [r for r in moves if r["what"] == "remap"]
    assert remap["asked"].startswith("the route rule on N1: its route changed 3.0 s ago")
