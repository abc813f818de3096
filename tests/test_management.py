"""Management rules and policies (mso.management) on hand-built snapshots.

The usual picture: chain A -> B -> C of app "app", head A on U, B on H (this node), tail C on D.
B is the only movable vertex; it costs 10 ms per event at 50 events/s, i.e. half of a cpu-1.0
node, 2 W at the default 4 W cpu_w.
"""

from __future__ import annotations

import dataclasses
import itertools
from collections.abc import Sequence

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mso.errors import MsoError
from mso.management import (
    POLICIES,
    BalancePolicy,
    ChainView,
    DelayPolicy,
    EnergyPolicy,
    EnergyRemapRule,
    Guard,
    LifetimePolicy,
    NodeView,
    Policy,
    Proposal,
    Relocate,
    RelocationRule,
    RemapChain,
    RemapChains,
    RuleEngine,
    RuleSettings,
    Snapshot,
    VertexView,
    estimate,
    improvement,
    lifetime_weight,
    load_policy,
    move_cost_j,
    relays,
)
from mso.management.rules import lifetime_ratio
from mso.model.network import PowerModel

WHERE = "app.yaml: policy"


def node(
    id: str,
    *,
    drain: float = 1.0,
    remaining: float | None = 3600.0,
    load: float = 0.1,
    cpu: float = 1.0,
    power: PowerModel | None = None,
) -> NodeView:
    life = None if remaining is None or drain <= 0 else remaining / drain
    return NodeView(id, cpu, power or PowerModel(), load, drain, remaining, life, 0.0)


def vertex(
    id: str = "B",
    *,
    host: str = "H",
    up: str | None = "U",
    down: str | None = "D",
    state: int = 1000,
    movable: bool = True,
    moved_at: float | None = None,
    moved_from: str | None = None,
    out_bytes: float = 200.0,
) -> VertexView:
    return VertexView(
        app="app",
        id=id,
        node=host,
        chain=0,
        cost=10.0,
        rate=50.0,
        in_bytes_per_s=100.0,
        out_bytes_per_s=out_bytes,
        state_bytes=state,
        upstream=up,
        downstream=down,
        movable=movable,
        moved_at=moved_at,
        moved_from=moved_from,
    )


def chain(
    *,
    vertices: Sequence[str] = ("A", "B", "C"),
    nodes: Sequence[str] = ("U", "H", "D"),
    coordinator: bool = False,
    delay: float | None = None,
    slo: float | None = None,
    route_changed_at: float | None = None,
    placed_at: float | None = None,
) -> ChainView:
    return ChainView(
        "app",
        0,
        tuple(vertices),
        tuple(nodes),
        delay,
        slo,
        route_changed_at,
        coordinator,
        placed_at,
    )


def snap(
    now: float,
    nodes: Sequence[NodeView],
    vertices: Sequence[VertexView] = (),
    chains: Sequence[ChainView] = (),
    here: str = "H",
) -> Snapshot:
    return Snapshot(now, here, {n.id: n for n in nodes}, tuple(vertices), tuple(chains))


def poor_here(**vkw: object) -> Snapshot:
    """H is nearly flat and hosts B; U upstream is rich; D downstream is as poor as H."""
    nodes = [node("H", drain=3.0), node("U", remaining=360_000.0), node("D")]
    return snap(0.0, nodes, [vertex(**vkw)], [chain()])  # type: ignore[arg-type]


def at(s: Snapshot, now: float) -> Snapshot:
    return Snapshot(now, s.here, s.nodes, s.vertices, s.chains)


def run(engine: RuleEngine, s: Snapshot, times: Sequence[float]) -> list[tuple[float, str]]:
    """Evaluate the same picture at each time; the actions allowed, with when."""
    return [(t, str(a)) for t in times for a in engine.evaluate(at(s, t))]


# -- views ----------------------------------------------------------------------------------


def test_actions_are_hashable_readable_and_keyed_without_reason() -> None:
    a = Relocate("app", "B", "U", "cheaper")
    b = Relocate("app", "B", "U", "other words")
    assert str(a) == "relocate app/B -> U (cheaper)"
    assert str(RemapChain("app", 2, "route changed")) == "remap app chain 2 (route changed)"
    assert len({a, Relocate("app", "B", "U", "cheaper")}) == 1
    assert a.key == b.key != Relocate("app", "B", "D").key
    assert RemapChain("app", 2).key != RemapChain("app", 3).key


# -- the estimate ---------------------------------------------------------------------------


def test_estimate_moves_cpu_and_radio_by_hand() -> None:
    fast = PowerModel(cpu_w=2.0)
    s = snap(
        0.0,
        [node("H", drain=3.0, load=0.6), node("U", cpu=2.0, power=fast), node("D")],
        [vertex()],
        [chain()],
    )
    est = estimate(s, {"app/B": "U"})
    # CPU: 0.5 busy leaves H (2 W); 0.5 / cpu 2 = 0.25 busy arrives at U at 2 W -> 0.5 W.
    # Radio: A(U)->B 100 B/s was U tx 2 µJ/B + H rx 1 µJ/B, becomes local: U -2e-4, H -1e-4 W.
    # B->C(D) 200 B/s moves its sending end from H to U: H -4e-4 W, U +4e-4 W, D unchanged.
    assert est["H"].load == pytest.approx(0.1)
    assert est["H"].drain_w == pytest.approx(3.0 - 2.0 - 1e-4 - 4e-4)
    assert est["U"].load == pytest.approx(0.35)
    assert est["U"].drain_w == pytest.approx(1.0 + 0.5 - 2e-4 + 4e-4)
    assert est["D"].drain_w == pytest.approx(1.0)
    assert est["H"].lifetime_s == pytest.approx(3600.0 / est["H"].drain_w)
    assert estimate(s, {})["H"].drain_w == 3.0
    assert estimate(s, {"app/B": "H"}) == estimate(s, {})


def test_estimate_uses_the_chain_when_the_successor_shares_the_node() -> None:
    # A(U) -> B(H) -> C(H) -> E(D): B's downstream relocation would take it to D, but its
    # successor C is here, so its output is free now and costs radio H <- U once B is on U.
    s = snap(
        0.0,
        [node("H"), node("U"), node("D")],
        [vertex(out_bytes=200.0)],
        [chain(vertices=("A", "B", "C", "E"), nodes=("U", "H", "H", "D"))],
    )
    est = estimate(s, {"app/B": "U"})
    assert est["D"].drain_w == pytest.approx(1.0)  # not involved at all
    assert est["U"].drain_w == pytest.approx(1.0 + 2.0 - 2e-4 + 4e-4)  # cpu, in local, out tx
    assert est["H"].drain_w == pytest.approx(1.0 - 2.0 - 1e-4 + 2e-4)  # cpu, in rx gone, out rx


def with_hops(view: NodeView, **hops: int) -> NodeView:
    return dataclasses.replace(view, hops=hops)


def test_estimate_charges_the_relay_a_move_leaves_behind() -> None:
    # the line U - H - D: B moves from H downstream to D, but A's output (100 B/s from U)
    # still crosses H on its way to D: H saves its receiving and its sending B's output
    # (200 B/s to D), and pays 100 B/s received and sent again as the relay
    nodes = [
        with_hops(node("H"), U=1, D=1),
        with_hops(node("U"), H=1, D=2),
        with_hops(node("D"), H=1, U=2),
    ]
    s = snap(0.0, nodes, [vertex()], [chain()])
    est = estimate(s, {"app/B": "D"})
    assert est["H"].drain_w == pytest.approx(1.0 - 2.0 - 1e-4 - 4e-4 + 3e-4)
    assert est["U"].drain_w == pytest.approx(1.0)  # it sends as many bytes as before
    assert est["D"].drain_w == pytest.approx(1.0 + 2.0 - 2e-4 + 1e-4)  # cpu, out local, in rx
    # the same picture without the routes: the relay is not seen (the estimate before)
    blind = estimate(snap(0.0, [node("H"), node("U"), node("D")], [vertex()], [chain()]), {})
    assert blind["H"].drain_w == pytest.approx(1.0)
    assert estimate(s, {})["H"].drain_w == pytest.approx(1.0)


def test_relays_share_a_mesh_hop_and_need_a_known_distance() -> None:
    # U reaches D through X or Y (equal routes): each is charged half
    nodes = [
        with_hops(node("U"), X=1, Y=1, D=2),
        with_hops(node("X"), U=1, D=1, Y=2),
        with_hops(node("Y"), U=1, D=1, X=2),
        node("D"),
        with_hops(node("Z"), U=1, D=3),  # off every shortest route
    ]
    s = snap(0.0, nodes, here="X")
    assert relays(s, "U", "D") == {"X": 0.5, "Y": 0.5}
    assert relays(s, "D", "U") == {"X": 0.5, "Y": 0.5}  # D reports no routes; U's do
    assert relays(s, "U", "X") == {}  # neighbours: no relay
    assert relays(snap(0.0, [node("X"), node("Y")], here="X"), "U", "D") == {}


def test_estimate_refuses_unknown_vertices_and_nodes() -> None:
    s = poor_here()
    with pytest.raises(ValueError, match="no view"):
        estimate(s, {"app/B": "N9"})
    with pytest.raises(ValueError, match="not hosted"):
        estimate(s, {"app/Z": "U"})


def test_move_cost_is_state_bytes_at_tx_plus_rx() -> None:
    s = poor_here(state=1_000_000)
    assert move_cost_j(s, s.vertices[0], "U") == pytest.approx(1e6 * (2 + 1) * 1e-6)
    assert move_cost_j(s, "app/B", "H") == 0.0


@settings(max_examples=60, deadline=None)
@given(
    cost=st.floats(0.0, 50.0),
    rate=st.floats(0.0, 200.0),
    cpu_here=st.floats(0.25, 4.0),
    cpu_there=st.floats(0.25, 4.0),
)
def test_estimate_conserves_cpu_work(
    cost: float, rate: float, cpu_here: float, cpu_there: float
) -> None:
    s = snap(
        0.0,
        [node("H", cpu=cpu_here), node("U", cpu=cpu_there), node("D")],
        [VertexView("app", "B", "H", 0, cost, rate, 0.0, 0.0, 0, "U", "D", True, None, None)],
        [chain()],
    )
    est = estimate(s, {"app/B": "U"})
    work = cost * rate / 1000.0
    assert (0.1 - est["H"].load) * cpu_here == pytest.approx(work, abs=1e-9)
    assert (est["U"].load - 0.1) * cpu_there == pytest.approx(work, abs=1e-9)
    assert est["U"].drain_w - 1.0 == pytest.approx(4.0 * work / cpu_there, abs=1e-9)


# -- shipped policies -----------------------------------------------------------------------


def three_way() -> Snapshot:
    """Lifetime, energy and balance each want something else for B.

    H: flat battery, hosts B. U: fast, frugal CPU but a small battery and already busy.
    D: slow CPU on wall power.
    """
    nodes = [
        node("H", drain=3.0, load=0.6),
        node("U", cpu=2.0, power=PowerModel(cpu_w=2.0), remaining=5000.0, load=0.6),
        node("D", cpu=0.5, remaining=None, drain=2.0, load=0.1),
    ]
    return snap(0.0, nodes, [vertex()], [chain()])


@pytest.mark.parametrize(
    ("policy", "choice"),
    [(LifetimePolicy(), "D"), (EnergyPolicy(), "U"), (BalancePolicy(), None)],
)
def test_each_policy_prefers_its_own_objective(policy: Policy, choice: str | None) -> None:
    # lifetime: B on U leaves U 3333 s, on D leaves H 3600 s, staying 1200 s -> D.
    # energy: 6 W now, 4.5 W with B on U, 8 W on slow D -> U.
    # balance: max load 0.6 now, 0.85 on U, 1.1 on D -> stay.
    # (D would be loaded past its CPU: allowed here to compare the objectives alone)
    rule = RelocationRule(policy, RuleSettings(margin=0.0, max_load=2.0))
    targets = [p.action.target for p in rule.propose(three_way())]  # type: ignore[union-attr]
    assert targets == ([] if choice is None else [choice])


def test_lifetime_falls_back_to_drain_without_batteries() -> None:
    nodes = [node(n, remaining=None, drain=2.0) for n in ("H", "U", "D")]
    p = LifetimePolicy()
    s = snap(0.0, nodes, [vertex()], [chain()])
    assert p.score(s, {}) == pytest.approx(EnergyPolicy().score(s, {}))


def test_improvement_is_relative_and_never_negative() -> None:
    assert improvement(10.0, 8.0) == pytest.approx(0.2)
    assert improvement(-1000.0, -1200.0) == pytest.approx(0.2)
    assert improvement(5.0, 6.0) == 0.0
    assert improvement(5.0, float("nan")) == 0.0


# -- the relocation rule --------------------------------------------------------------------


def test_poor_node_relocates_toward_rich_neighbour_after_confirm_and_not_before() -> None:
    engine = RuleEngine()
    s = poor_here()
    assert engine.evaluate(at(s, 0.0)) == []
    assert engine.evaluate(at(s, 1.0)) == []
    (action,) = engine.evaluate(at(s, 2.0))
    assert isinstance(action, Relocate)
    assert (action.app, action.vertex, action.target) == ("app", "B", "U")
    assert "lifetime policy, upstream to U: shortest battery life 20 min -> 60 min" in action.reason
    decisions = [d for _, what, d in engine.log if what.startswith("relocate app/B -> U")]
    assert decisions == ["held: confirming 1/3", "held: confirming 2/3", "allowed"]


def test_confirmation_restarts_when_the_best_choice_lapses() -> None:
    engine = RuleEngine()
    poor, balanced = poor_here(), balanced_here()
    assert engine.evaluate(at(poor, 0.0)) == []
    assert engine.evaluate(at(poor, 1.0)) == []
    assert engine.evaluate(at(balanced, 2.0)) == []  # no longer wanted: the count restarts
    assert engine.evaluate(at(poor, 3.0)) == []
    assert engine.evaluate(at(poor, 4.0)) == []
    assert len(engine.evaluate(at(poor, 5.0))) == 1


def balanced_here() -> Snapshot:
    nodes = [node("H", drain=3.0), node("U", drain=3.0), node("D", drain=3.0)]
    return snap(0.0, nodes, [vertex()], [chain()])


def test_balanced_nodes_do_not_relocate() -> None:
    for policy in POLICIES.values():
        engine = RuleEngine(policy())
        assert run(engine, balanced_here(), [float(t) for t in range(20)]) == []


def test_unmovable_vertex_is_never_proposed() -> None:
    engine = RuleEngine()
    assert run(engine, poor_here(movable=False), [float(t) for t in range(20)]) == []
    assert RelocationRule(LifetimePolicy(), RuleSettings()).propose(poor_here(movable=False)) == []


def test_state_too_large_to_be_worth_moving_stays() -> None:
    big = poor_here(state=1_000_000_000)  # 3 kJ to ship: H would spend 2 kJ of its 3.6 kJ
    rule = RelocationRule(LifetimePolicy(), RuleSettings())
    assert rule.propose(poor_here()) != []  # the same picture with a small state moves
    assert rule.propose(big) == []
    stay, *moves = rule.options(big, big.vertices[0])
    assert all(m.score > stay.score for m in moves)
    assert run(RuleEngine(), big, [float(t) for t in range(10)]) == []


def test_candidates_need_a_view_of_the_target() -> None:
    s = poor_here()
    blind = Snapshot(0.0, "H", {"H": s.nodes["H"], "D": s.nodes["D"]}, s.vertices, s.chains)
    assert run(RuleEngine(), blind, [float(t) for t in range(10)]) == []


def test_relocation_waits_while_the_chains_routes_settle() -> None:
    s = poor_here()
    settling = Snapshot(
        0.0, "H", s.nodes, s.vertices, (chain(route_changed_at=0.0, placed_at=0.0),)
    )
    rule = RelocationRule(LifetimePolicy(), RuleSettings())
    assert rule.propose(at(settling, 2.0)) == []
    assert rule.propose(at(settling, 3.0)) != []


def test_one_relocation_per_node_interval() -> None:
    # A(U) -> B(H) -> E(H) -> C(D): both B and E want to leave flat H.
    nodes = [node("H", drain=5.0), node("U", remaining=1e6), node("D", remaining=1e6)]
    vs = [vertex("B", up="U", down="D"), vertex("E", up=None, down="D")]
    ch = chain(vertices=("A", "B", "E", "C"), nodes=("U", "H", "H", "D"))
    engine = RuleEngine()
    allowed = run(engine, snap(0.0, nodes, vs, [ch]), [float(t) for t in range(12)])
    assert [t for t, _ in allowed] == [2.0, 7.0]  # one per evaluation, then node_interval_s
    assert {what.split(" ")[1] for _, what in allowed} == {"app/B", "app/E"}
    engine = RuleEngine(settings=RuleSettings(node_interval_s=0.0))
    allowed = run(engine, snap(0.0, nodes, vs, [ch]), [float(t) for t in range(12)])
    assert [t for t, _ in allowed] == [2.0, 3.0]  # still one per evaluation


# -- the oscillation guard ------------------------------------------------------------------


def pingpong(
    here: str, host: str, now: float, moved_at: float | None, moved_from: str | None
) -> Snapshot:
    """Chain A(U) -> B -> C(H); B runs on ``host`` (U or H). Both nodes alike, but the host
    always reads its own drain a little high and its neighbour's report lags without B: each
    side in turn thinks the other is the better place for B."""
    other = "U" if host == "H" else "H"
    nodes = [node(host, drain=3.5), node(other, drain=1.0)]
    up, down = ("U", None) if host == "H" else (None, "H")
    vs = [vertex(host=host, up=up, down=down, moved_at=moved_at, moved_from=moved_from)]
    ch = chain(nodes=("U", host, "H"))
    return snap(now, nodes, vs if here == host else [], [ch], here=here)


def count_pingpong_moves(rule_settings: RuleSettings, evaluations: int = 120) -> int:
    engines = {n: RuleEngine(LifetimePolicy(), rule_settings) for n in ("H", "U")}
    host, moved_at, moved_from, moves = "H", None, None, 0
    for t in range(evaluations):
        for here in ("H", "U"):
            for a in engines[here].evaluate(pingpong(here, host, float(t), moved_at, moved_from)):
                assert isinstance(a, Relocate)
                host, moved_at, moved_from = a.target, float(t), host
                moves += 1
    return moves


def test_pingpong_scenario_oscillates_without_the_guard() -> None:
    unguarded = RuleSettings(vertex_interval_s=0.0, node_interval_s=0.0)
    assert count_pingpong_moves(unguarded) >= 30  # every `confirm` evaluations


def test_guard_stops_pingpong_between_equal_nodes() -> None:
    assert count_pingpong_moves(RuleSettings()) == 1


def test_pingpong_is_held_by_moved_from_and_explained() -> None:
    engine = RuleEngine()
    for t in range(40, 45):
        assert engine.evaluate(pingpong("U", "U", float(t), 0.0, "H")) == []
    assert engine.log[-1][2].startswith("held: would go back to H, which it left at 0.0")
    assert engine.evaluate(pingpong("U", "U", 119.0, 0.0, "H")) == []  # ping_pong_s = 120
    (back,) = engine.evaluate(pingpong("U", "U", 120.0, 0.0, "H"))
    assert isinstance(back, Relocate) and back.target == "H"


@settings(max_examples=40, deadline=None)
@given(
    st.lists(
        st.lists(st.tuples(st.sampled_from("BEF"), st.sampled_from("UD")), max_size=4),
        min_size=1,
        max_size=60,
    )
)
def test_guard_rate_limits_hold_for_any_proposals(rounds: list[list[tuple[str, str]]]) -> None:
    rs = RuleSettings(confirm=1)
    guard = Guard(rs)
    nodes = [node("H"), node("U"), node("D")]
    s = snap(0.0, nodes, [vertex(v) for v in "BEF"], [chain()])
    allowed: list[tuple[float, str]] = []
    for t, props in enumerate(rounds):
        proposals = [Proposal(Relocate("app", v, target), 1) for v, target in props]
        for p, why in guard.review(proposals, at(s, float(t))):
            if why is None:
                allowed.append((float(t), p.action.vertex))  # type: ignore[union-attr]
    times = [t for t, _ in allowed]
    assert all(b - a >= rs.node_interval_s for a, b in itertools.pairwise(times))
    for v in "BEF":
        mine = [t for t, w in allowed if w == v]
        assert all(b - a >= rs.vertex_interval_s for a, b in itertools.pairwise(mine))


# -- chain remap on route change ------------------------------------------------------------


def coordinated(now: float, changed: float | None, **kw: object) -> Snapshot:
    ch = chain(nodes=("H", "U", "D"), coordinator=True, route_changed_at=changed, **kw)  # type: ignore[arg-type]
    return snap(now, [node("H"), node("U"), node("D")], [], [ch])


def test_route_change_remaps_only_after_settling_and_only_once() -> None:
    engine = RuleEngine()
    remaps = []
    for t in range(10, 41):
        remaps += [(t, a) for a in engine.evaluate(coordinated(float(t), 10.0))]
    assert [(t, type(a).__name__) for t, a in remaps] == [(13, "RemapChain")]
    assert "its route changed 3.0 s ago" in remaps[0][1].reason


def test_route_change_needs_the_coordinator() -> None:
    engine = RuleEngine()
    ch = chain(nodes=("U", "H", "D"), coordinator=False, route_changed_at=10.0)
    s = snap(0.0, [node("H"), node("U"), node("D")], [], [ch])
    assert run(engine, s, [float(t) for t in range(10, 40)]) == []


def test_route_change_older_than_the_mapping_needs_no_remap() -> None:
    engine = RuleEngine()
    assert run(engine, coordinated(0.0, 10.0, placed_at=12.0), [20.0, 30.0]) == []
    assert len(run(engine, coordinated(0.0, 14.0, placed_at=12.0), [20.0, 30.0])) == 1


def test_flapping_route_never_remaps_while_it_flaps_then_once() -> None:
    engine = RuleEngine()
    remaps: list[float] = []
    for tick in range(0, 1200):  # 0.1 s steps; the rules run every second
        now = tick / 10
        changed = float(int(now)) if now < 60 else 59.0  # a change every second until 60 s
        if tick % 10 == 5:
            remaps += [now for _ in engine.evaluate(coordinated(now, changed))]
    assert remaps == [62.5]


def test_a_remap_held_by_the_chain_interval_happens_later() -> None:
    engine = RuleEngine()
    assert len(engine.evaluate(coordinated(13.0, 10.0))) == 1
    got = [t for t in range(14, 40) for _ in engine.evaluate(coordinated(float(t), 16.0))]
    assert got == [28]  # settled at 19, but the chain was remapped at 13: not before 28


# -- SLO ------------------------------------------------------------------------------------


def slo(now: float, delay: float, *, coordinator: bool = True) -> Snapshot:
    ch = chain(nodes=("H", "U", "D"), coordinator=coordinator, delay=delay, slo=100.0)
    return snap(now, [node("H"), node("U"), node("D")], [], [ch])


def test_slo_violation_remaps_after_slo_confirm() -> None:
    engine = RuleEngine(DelayPolicy())
    assert engine.evaluate(slo(0.0, 150.0)) == []
    assert engine.evaluate(slo(1.0, 150.0)) == []
    (a,) = engine.evaluate(slo(2.0, 150.0))
    assert isinstance(a, RemapChain) and (a.app, a.chain) == ("app", 0)
    assert a.reason == "delay 150.0 ms > SLO 100 ms"
    # still violated: the next remap waits for chain_interval_s
    later = [t for t in range(3, 20) for _ in engine.evaluate(slo(float(t), 150.0))]
    assert later == [17]


def test_slo_met_or_not_coordinator_or_intermittent_does_nothing() -> None:
    engine = RuleEngine(DelayPolicy())
    assert [a for t in range(20) for a in engine.evaluate(slo(float(t), 90.0))] == []
    assert [
        a for t in range(20) for a in engine.evaluate(slo(float(t), 150.0, coordinator=False))
    ] == []
    flicker = [150.0, 150.0, 90.0] * 7
    assert [a for t, d in enumerate(flicker) for a in engine.evaluate(slo(float(t), d))] == []


def test_slo_is_the_delay_policys_job() -> None:
    engine = RuleEngine(LifetimePolicy())
    assert [a for t in range(20) for a in engine.evaluate(slo(float(t), 150.0))] == []


# -- loading policies -----------------------------------------------------------------------


def test_load_policy_by_name_default_and_params() -> None:
    assert isinstance(load_policy(None, where=WHERE), LifetimePolicy)
    assert isinstance(load_policy("energy", where=WHERE), EnergyPolicy)
    delay = load_policy({"name": "delay", "params": {"fallback": "energy"}}, where=WHERE)
    assert isinstance(delay, DelayPolicy) and isinstance(delay.fallback, EnergyPolicy)
    p = BalancePolicy()
    assert load_policy(p, where=WHERE) is p


def test_load_policy_by_import_path() -> None:
    import custom_policy

    p = load_policy("custom_policy:PreferNode", where=WHERE)
    assert isinstance(p, custom_policy.PreferNode) and p.node == "D" and p.name == "prefer-node"
    p = load_policy({"code": "custom_policy:PreferNode", "params": {"node": "U"}}, where=WHERE)
    assert isinstance(p, custom_policy.PreferNode) and p.node == "U"
    assert load_policy("custom_policy:Unnamed", where=WHERE).name == "custom_policy:Unnamed"
    duck = load_policy("custom_policy:make_scorer", where=WHERE)
    assert isinstance(duck, Policy) and duck.name == "score-only"
    assert duck.score(poor_here(), {}) == 0.0 and duck.actions(poor_here()) == []


@pytest.mark.parametrize(
    ("spec", "message"),
    [
        (
            "fast",
            "app.yaml: policy: unknown policy 'fast' (expected one of balance, delay, energy, "
            "lifetime, or an import path pkg.module:attr)",
        ),
        ({"name": "fast"}, "app.yaml: policy: unknown policy 'fast'"),
        ("custom_policy:Missing", "app.yaml: policy: import path 'custom_policy:Missing' does "),
        ("no_such_module_xyz:P", "no module named 'no_such_module_xyz'"),
        ({"code": "not a path"}, "app.yaml: policy: expected an import path"),
        (
            "custom_policy:NotAPolicy",
            "'custom_policy:NotAPolicy' does not provide score()/actions()",
        ),
        (
            {"code": "custom_policy:PreferNode", "params": {"colour": 1}},
            "app.yaml: policy: cannot create 'custom_policy:PreferNode' with params {'colour': 1}",
        ),
        ({"name": "lifetime", "params": {"x": 1}}, "cannot create policy 'lifetime'"),
        ({"name": "delay", "params": {"fallback": "delay"}}, "fallback must be one of"),
        ({"name": "lifetime", "code": "a:b"}, "expected exactly one of name"),
        ({"policy": "lifetime"}, "unexpected key 'policy'"),
        ({"name": "energy", "params": [1]}, "params: expected a mapping"),
        (42, "app.yaml: policy: expected a policy name"),
    ],
)
def test_load_policy_errors_are_clear(spec: object, message: str) -> None:
    with pytest.raises(MsoError) as info:
        load_policy(spec, where=WHERE)  # type: ignore[arg-type]
    assert message in str(info.value)
    assert "\n" not in str(info.value)


def test_custom_policy_is_obeyed() -> None:
    # Lifetime would take B upstream to rich U (see above); the plug-in wants it on D.
    policy = load_policy({"code": "custom_policy:PreferNode", "params": {"node": "D"}}, where=WHERE)
    engine = RuleEngine(policy)
    (action,) = [a for t in range(3) for a in engine.evaluate(at(poor_here(), float(t)))]
    assert isinstance(action, Relocate) and action.target == "D"
    assert "prefer-node policy, downstream to D: score 1 -> 0" in action.reason


def test_app_policy_overrides_the_nodes() -> None:
    engine = RuleEngine(LifetimePolicy())
    engine.set_app_policy("app", load_policy("custom_policy:PreferNode", where=WHERE))
    allowed = run(engine, poor_here(), [0.0, 1.0, 2.0])
    assert [what.split(" (")[0] for _, what in allowed] == ["relocate app/B -> D"]
    assert engine.status().app_policies == {"app": "prefer-node"}


def test_broken_and_misbehaving_policies_are_reported_not_fatal() -> None:
    engine = RuleEngine(load_policy("custom_policy:Broken", where=WHERE))
    assert run(engine, poor_here(), [0.0, 1.0]) == []
    assert [e for e in engine.log if "draining" not in e[1]] == [
        (0.0, "policy broken for app", "error: RuntimeError: sensor table missing")
    ]
    engine = RuleEngine(load_policy("custom_policy:MovesChainHead", where=WHERE))
    allowed = run(engine, poor_here(), [0.0, 1.0, 2.0])
    assert [what.split(" (")[0] for _, what in allowed] == ["relocate app/B -> U"]
    ignored = [d for _, what, d in engine.log if what.startswith("relocate app/A")]
    assert ignored == ["ignored: app/A is not hosted on H"]  # logged once, not every evaluation
    spec = {"code": "custom_policy:MovesChainHead", "params": {"vertex": "B"}}
    engine = RuleEngine(load_policy(spec, where=WHERE))
    assert run(engine, poor_here(movable=False), [0.0, 1.0, 2.0]) == []
    assert [d for _, what, d in engine.log if "draining" not in what] == [
        "ignored: app/B is a chain end or pinned: never relocated"
    ]


# -- settings and status --------------------------------------------------------------------


def test_settings_are_validated() -> None:
    assert RuleSettings().ping_pong_s == 120.0
    with pytest.raises(MsoError, match="confirm: expected an integer >= 1"):
        RuleSettings(confirm=0)
    with pytest.raises(MsoError, match="margin: expected a number >= 0"):
        RuleSettings(margin=-0.1)


def test_status_shows_policy_settings_and_decisions() -> None:
    engine = RuleEngine()
    run(engine, poor_here(), [0.0, 1.0, 2.0])
    status = engine.status()
    assert status.policy == "lifetime" and status.evaluations == 3
    assert status.settings["confirm"] == 3
    assert status.decisions[-1].startswith("2.0 relocate app/B -> U (")
    assert status.decisions[-1].endswith(": allowed")


def test_a_move_that_would_saturate_the_target_is_never_proposed() -> None:
    """On D, B would load it to 1.1 (more than its CPU): lifetime's choice goes, U remains."""
    view = three_way()
    rule = RelocationRule(LifetimePolicy(), RuleSettings(margin=0.0))
    assert [o.target for o in rule.options(view, view.vertices[0])] == [None, "U"]
    loose = RelocationRule(LifetimePolicy(), RuleSettings(margin=0.0, max_load=2.0))
    assert [o.target for o in loose.options(view, view.vertices[0])] == [None, "U", "D"]


# -- a draining node and a flat battery -------------------------------------------------------


def leader_line(h_remaining: float, *, u_remaining: float = 36_000.0) -> Snapshot:
    """H hosts B, which costs H a little: moving B to U saves H 2 % of its 5 W drain, less than
    the margin. U has ``u_remaining`` J at the same drain."""
    nodes = [
        node("H", drain=5.0, remaining=h_remaining),
        node("U", drain=5.0, remaining=u_remaining),
    ]
    light = VertexView("app", "B", "H", 0, 1.0, 25.0, 0.0, 0.0, 100, "U", None, True)
    return snap(0.0, nodes, [light], [chain(vertices=("A", "B"), nodes=("U", "H"))])


def test_a_draining_node_sheds_work_the_margin_would_keep() -> None:
    # same drains: with equal batteries the 2 % gain is within the margin and nothing moves
    assert run(RuleEngine(), leader_line(36_000.0), [float(t) for t in range(10)]) == []
    # H's battery holds a tenth of U's: it is draining, and any gain for it is worth a move
    engine = RuleEngine()
    allowed = run(engine, leader_line(3_600.0), [float(t) for t in range(10)])
    assert [(t, what.split(" (")[0]) for t, what in allowed] == [(2.0, "relocate app/B -> U")]
    assert "H draining" in allowed[0][1]
    assert engine.draining == {"H"}
    assert any("H draining" in line for line in engine.status().decisions)


def test_draining_has_hysteresis() -> None:
    s = RuleSettings()  # enters under 0.5, leaves above 0.625
    engine = RuleEngine(settings=s)
    for ratio, expected in [(0.55, set()), (0.45, {"H"}), (0.55, {"H"}), (0.6, {"H"}),
                            (0.7, set()), (0.55, set())]:  # fmt: skip
        engine.evaluate(leader_line(36_000.0 * ratio))
        assert engine.draining == expected, ratio


def test_a_node_warming_up_is_not_judged_by_its_start_up() -> None:
    """A vertex started on H at 0.5: for ``warmup_s`` its drain includes the start-up, so its
    draining state stands (either way) and its rules move nothing; then H is judged."""
    assert RuleSettings().warmup_s == 10.0
    with pytest.raises(MsoError, match="warmup_s: expected a number >= 0"):
        RuleSettings(warmup_s=-1.0)
    poor = dataclasses.replace(leader_line(3_600.0), last_start=0.5)  # H looks draining
    engine = RuleEngine()
    for t in range(1, 11):  # warming up until 10.5
        assert engine.evaluate(dataclasses.replace(poor, now=float(t))) == []
        assert engine.draining == frozenset()
    assert engine.status().warming_until == 10.5
    assert engine.status().decisions == [
        "1.0 H warming up: a vertex started 0.5 s ago: its drain is judged 9.5 s from now"
    ]
    allowed = [
        (t, str(a).split(" (")[0])
        for t in (11.0, 12.0, 13.0)
        for a in engine.evaluate(dataclasses.replace(poor, now=t))
    ]
    assert allowed == [(13.0, "relocate app/B -> U")]  # confirmed 3 times after the warm-up
    assert engine.draining == {"H"} and engine.status().warming_until is None
    # a judgement made on steady figures stands while another instance warms up
    rich = dataclasses.replace(leader_line(36_000.0), last_start=20.0)
    engine.evaluate(dataclasses.replace(rich, now=21.0))
    assert engine.draining == {"H"}
    engine.evaluate(dataclasses.replace(rich, now=30.0))
    assert engine.draining == frozenset()


def test_a_wall_powered_neighbour_alone_makes_no_battery_node_draining() -> None:
    # it did before issue 25 (an infinite lifetime to compare with)
    nodes = [node("H", drain=5.0), node("U", drain=5.0, remaining=None)]
    engine = RuleEngine()
    engine.evaluate(snap(0.0, nodes))
    assert engine.draining == frozenset()


def test_nothing_moves_onto_a_flat_battery() -> None:
    # U is empty: every lifetime there is 0 and the lifetime score of staying and of moving
    # ties at its first level, where U's 0 used to decide nothing and H's relief won
    nodes = [node("H", drain=5.0, remaining=3_600.0), node("U", drain=5.0, remaining=0.0)]
    light = VertexView("app", "B", "H", 0, 10.0, 50.0, 0.0, 0.0, 100, "U", None, True)
    s = snap(0.0, nodes, [light], [chain(vertices=("A", "B"), nodes=("U", "H"))])
    for policy in POLICIES.values():
        rule = RelocationRule(policy(), RuleSettings(margin=0.0), frozenset({"H"}))
        assert rule.options(s, light) == [], policy.name
        assert run(RuleEngine(policy()), s, [float(t) for t in range(10)]) == []
    alive = snap(0.0, [nodes[0], node("U", drain=5.0, remaining=36_000.0)], [light], s.chains)
    assert run(RuleEngine(), alive, [float(t) for t in range(10)]) != []  # the same, U charged


def test_critical_ratio_is_checked() -> None:
    for bad in (1.0, -0.1, float("nan")):
        with pytest.raises(MsoError, match="critical_ratio"):
            RuleSettings(critical_ratio=bad)


# -- the energy remap of a join -----------------------------------------------------------------


def test_lifetime_weight_scales_capacity_by_remaining_lifetime() -> None:
    nodes = [
        node("H", drain=2.0),  # 1800 s
        node("U"),  # 3600 s: the longest among the battery nodes
        node("D", remaining=0.0),  # flat
        node("W", remaining=None),  # wall powered
        node("N", drain=0.0),  # draws nothing yet: no lifetime known
    ]
    s = snap(0.0, nodes)
    weights = {n: lifetime_weight(s, n) for n in ("H", "U", "D", "W", "N", "far")}
    assert weights == {"H": 0.5, "U": 1.0, "D": 0.0, "W": 1.0, "N": 1.0, "far": 1.0}
    assert Policy().capacity_weight(s, "H") == 0.5  # every policy weighs so by default


def joined(*, moved_at: float | None = None, moved_from: str | None = None) -> Snapshot:
    """J joins chains 0 (A -> J) and 1 (B -> J) and heads chain 2 (J -> C): A and B on U, J on
    H, C on D. H's battery holds a tenth of U's and D's: H is draining."""
    j = dataclasses.replace(
        vertex("J", movable=False, state=10), moved_at=moved_at, moved_from=moved_from
    )
    chains = [
        dataclasses.replace(chain(vertices=("A", "J"), nodes=("U", "H")), index=0),
        dataclasses.replace(chain(vertices=("B", "J"), nodes=("U", "H")), index=1),
        dataclasses.replace(chain(vertices=("J", "C"), nodes=("H", "D")), index=2),
    ]
    nodes = [node("H", drain=3.0, remaining=360.0), node("U"), node("D", drain=2.0)]
    return snap(100.0, nodes, [j], chains)


def test_a_draining_node_asks_to_remap_the_chains_of_a_join_it_cannot_relocate() -> None:
    s = joined()
    engine = RuleEngine(LifetimePolicy())
    assert RelocationRule(LifetimePolicy(), RuleSettings(), frozenset({"H"})).propose(s) == []
    allowed = run(engine, s, [100.0, 101.0, 102.0, 103.0])
    assert len(allowed) == 1 and allowed[0][0] == 102.0  # confirmed 3 times
    (action,) = [a for _, a in engine.guard.allowed]
    assert isinstance(action, RemapChains) and action.chains == (0, 1, 2)
    assert action.place == (("J", "U"),)  # U outlives D: the join goes there
    weights = dict(action.weights)
    assert weights["H"] == 0.0 and weights["U"] == 1.0 and weights["D"] == 0.5
    assert "H draining, sheds join/fork J" in action.reason
    # one energy remap per app per energy_interval_s from this node
    later = run(engine, s, [110.0 + k for k in range(100)])
    assert later == []
    assert any("remapped for energy at 102.0" in d for d in engine.status().decisions)


def test_an_energy_remap_waits_while_the_app_is_being_reconfigured_here() -> None:
    engine = RuleEngine(LifetimePolicy())
    for t in (100.0, 101.0, 102.0, 103.0):
        busy = dataclasses.replace(joined(), now=t, busy=frozenset({"app"}))
        assert engine.evaluate(busy) == []
    assert any("in flight here" in d for d in engine.status().decisions)


def test_the_energy_remap_never_sends_a_join_back_nor_onto_a_shorter_lived_node() -> None:
    rule = EnergyRemapRule(LifetimePolicy(), RuleSettings(), frozenset({"H"}))
    # it came from U 60 s ago: U is out (no ping-pong), D is the only candidate
    (p,) = rule.propose(joined(moved_at=40.0, moved_from="U"))
    assert isinstance(p.action, RemapChains) and p.action.place == (("J", "D"),)
    assert dict(p.action.weights)["U"] == 0.0
    # past the no-ping-pong window U is back
    (p,) = rule.propose(joined(moved_at=-30.0, moved_from="U"))
    assert isinstance(p.action, RemapChains) and p.action.place == (("J", "U"),)
    # ... unless H would die before the hold lifts (30 s left at 3 W, the hold 60 s more):
    # then it goes back rather than die with it
    dying = joined(moved_at=40.0, moved_from="U")
    dying.nodes["H"] = dataclasses.replace(dying.nodes["H"], remaining_j=90.0, lifetime_s=30.0)
    (p,) = rule.propose(dying)
    assert isinstance(p.action, RemapChains) and p.action.place == (("J", "U"),)
    # ... or too soon after it lifts to act then (within vertex_interval_s, 30 s): 64 s left
    # goes back now; 100 s left waits for the hold to lift (D is the candidate meanwhile)
    for life, back in ((64.0, True), (100.0, False)):
        s = joined(moved_at=40.0, moved_from="U")
        s.nodes["H"] = dataclasses.replace(s.nodes["H"], remaining_j=3 * life, lifetime_s=life)
        (p,) = rule.propose(s)
        assert isinstance(p.action, RemapChains)
        assert p.action.place == (("J", "U" if back else "D"),), life
    # it arrived 10 s ago: the drains in view do not show it yet
    assert rule.propose(joined(moved_at=90.0, moved_from="U")) == []
    # every neighbour expected to die sooner than H: nowhere to go
    s = joined()
    poorer = {
        n: dataclasses.replace(v, remaining_j=10.0, lifetime_s=10.0) for n, v in s.nodes.items()
    }
    poorer["H"] = s.nodes["H"]
    assert rule.propose(dataclasses.replace(s, nodes=poorer)) == []
    # not draining: nothing
    assert EnergyRemapRule(LifetimePolicy(), RuleSettings()).propose(joined()) == []
    # energy remaps switched off: a draining node only relocates
    off = RuleSettings(energy_remap=False)
    assert EnergyRemapRule(LifetimePolicy(), off, frozenset({"H"})).propose(joined()) == []
    with pytest.raises(MsoError, match="energy_remap: expected true or false"):
        RuleSettings(energy_remap=1)  # type: ignore[arg-type]


def test_an_energy_remap_spares_a_node_that_runs_pinned_vertices() -> None:
    """U runs the pinned sources (A, B): the join goes to D, though U outlives D, while a
    node without pinned vertices is in view; the rest of the chains are still weighed by
    lifetime (U may take movable work back). When D is ruled out for now (the join just came
    from it) the remap waits rather than fall back on U. When every other node runs pinned
    vertices, or spare_pinned is off, U is a candidate like any other."""
    s = dataclasses.replace(joined(), pinned_hosts=frozenset({"U"}))
    rule = EnergyRemapRule(LifetimePolicy(), RuleSettings(), frozenset({"H"}))
    (p,) = rule.propose(s)
    assert isinstance(p.action, RemapChains) and p.action.place == (("J", "D"),)
    assert dict(p.action.weights) == {"H": 0.0, "U": 1.0, "D": 0.5}
    back = dataclasses.replace(joined(moved_at=40.0, moved_from="D"), pinned_hosts=frozenset({"U"}))
    assert rule.propose(back) == []
    for other in (
        rule.propose(dataclasses.replace(s, pinned_hosts=frozenset({"U", "D"}))),
        EnergyRemapRule(
            LifetimePolicy(), RuleSettings(spare_pinned=False), frozenset({"H"})
        ).propose(s),
    ):
        (p,) = other
        assert isinstance(p.action, RemapChains) and p.action.place == (("J", "U"),)
    with pytest.raises(MsoError, match="spare_pinned: expected true or false"):
        RuleSettings(spare_pinned="yes")  # type: ignore[arg-type]


class KeepOff(Policy):
    name = "keep-off"

    def capacity_weight(self, snap: Snapshot, node: str) -> float:
        return 0.0 if node == "U" else 1.0


def test_a_policy_decides_the_weights_of_an_energy_remap() -> None:
    (p,) = EnergyRemapRule(KeepOff(), RuleSettings(), frozenset({"H"})).propose(joined())
    assert isinstance(p.action, RemapChains) and p.action.place == (("J", "D"),)
    assert dict(p.action.weights) == {"H": 0.0, "U": 0.0, "D": 1.0}


def test_a_wall_powered_neighbour_does_not_make_a_node_draining() -> None:
    """Issue 25: R4 with 9.8 h of battery beside a wall-powered node is not "draining" (it
    used to be: the wall node counted as an infinite lifetime, so any gain moved its work);
    a move onto the wall node must now beat the margin like any other."""
    # H: 9.8 h at 5 W; U on wall power; moving B saves H 2 % -- within the margin
    nodes = [node("H", drain=5.0, remaining=9.8 * 3600 * 5.0), node("U", remaining=None)]
    light = VertexView("app", "B", "H", 0, 1.0, 25.0, 0.0, 0.0, 100, "U", None, True)
    s = snap(0.0, nodes, [light], [chain(vertices=("A", "B"), nodes=("U", "H"))])
    assert lifetime_ratio(s, "H") is None  # no battery peer to compare with
    engine = RuleEngine()
    assert run(engine, s, [float(t) for t in range(10)]) == []
    assert engine.draining == frozenset()
    # the wall node is still a place to put work: a gain beyond the margin moves B there
    heavy = dataclasses.replace(light, cost=20.0)  # 0.5 of H busy: 2 W of its 5 W
    s2 = snap(0.0, nodes, [heavy], [chain(vertices=("A", "B"), nodes=("U", "H"))])
    moved = run(RuleEngine(), s2, [float(t) for t in range(10)])
    assert [what.split(" (")[0] for _, what in moved] == ["relocate app/B -> U"]
    assert "draining" not in moved[0][1]
    # beside a battery peer that lasts ten times longer, H is draining as before
    rich = node("D", drain=5.0, remaining=10 * 9.8 * 3600 * 5.0)
    assert lifetime_ratio(snap(0.0, [*nodes, rich]), "H") == pytest.approx(0.1)
