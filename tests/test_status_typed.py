"""A node's status is a typed record (mso.node.status.NodeStatus) composed from the components'
own; the wire carries it as plain data, and a client can type it again. The keys below are
what every consumer (CLI, dashboard, metrics, the simulator's checkers) reads: a record that
gains, loses or renames a field fails here first."""

from __future__ import annotations

import json

import msgspec

from mso.api import typed_status
from mso.node.status import LinkStatus, NodeStatus, from_wire, node_status, to_wire
from mso.protocol import messages as m
from mso.protocol.authority import AuthorityStatus
from mso.sim.runner import Simulation
from test_runtime_sim import PIPE, deploy, line

NODE_KEYS = [
    "node",
    "monitor",
    "routes",
    "neighbours",
    "apps",
    "dropped_messages",
    "refusals",
    "illegal_transitions",
    "handler_errors",
    "last_handler_error",
    "procedures",
    "management",
    "failed_nodes",
    "suspected_nodes",
    "unreachable_nodes",
    "incarnation",
    "failures",
    "rejoins",
    "liveness",
    "heard",
    "moves",
    "clock",
    "control_streams",
]
LINK_KEYS = ["traffic", "connections", "connected", "tasks", "timers", "authority"]
MONITOR_KEYS = [
    "energy_j",
    "cpu_energy_j",
    "radio_energy_j",
    "battery_j",
    "remaining_j",
    "battery_fraction",
    "drain_w",
    "load",
    "lifetime_s",
    "route_changes",
    "neighbour_changes",
    "last_route_change",
    "last_start",
    "recent",
    "measured",
    "sources",
    "work_ms",
    "cpu_ms",
]
APP_KEYS = [
    "running",
    "parked",
    "recoveries",
    "given_up",
    "chain_delay_ms",
    "slo_ms",
    "origin",
    "placement",
    "chains",
    "vertices",
    "edges",
    "capable",
    "replication",
]
VERTEX_KEYS = [
    "kind",
    "state",
    "busy_s",
    "queued",
    "processed",
    "emitted",
    "calls",
    "ended",
    "errors",
    "cpu_s",
    "last_error",
    "stats",
    "crashes",
    "restarts",
    "last_crash",
    "not_restarted",
]
EDGE_KEYS = [
    "sent",
    "delivered",
    "duplicates",
    "in_flight",
    "events_per_s",
    "waiting",
    "held_bytes",
    "spilled_bytes",
    "dropped",
    "superseded",
    "expired",
    "lost",
    "resent",
    "resent_bytes",
    "deadline_missed",
    "late",
]
MANAGEMENT_KEYS = [
    "policy",
    "app_policies",
    "settings",
    "evaluations",
    "draining",
    "warming_until",
    "decisions",
    "enabled",
    "done",
]


def _running() -> Simulation:
    sim = Simulation(line(4))  # PIPE pins its sink to N4
    assert deploy(sim, PIPE).ok
    sim.run_until(sim.now + 3.0)
    return sim


def test_status_keys_are_what_consumers_read() -> None:
    sim = _running()
    st = sim.cores["N2"].status(sim.now)
    assert list(st) == NODE_KEYS  # the simulator's driver reports no links
    assert list(st["monitor"]) == MONITOR_KEYS
    assert list(st["management"]) == MANAGEMENT_KEYS
    assert list(st["liveness"]) == ["heartbeat_s", "dead_after_s", "inter_arrival"]
    assert list(st["liveness"]["inter_arrival"]["N1"]) == [
        "n",
        "p50_ms",
        "p99_ms",
        "max_ms",
        "recent_max_ms",
    ]
    assert list(st["heard"]["N1"]) == ["at", "load", "drain_w", "lifetime_s"]
    assert st["routes"] == {"N1": ["N1", 1], "N3": ["N3", 1], "N4": ["N3", 2]}
    apps = [c.status(sim.now)["apps"]["pipe"] for c in sim.cores.values() if "pipe" in c.apps]
    assert all(list(app) == APP_KEYS for app in apps)
    vertices = [v for app in apps for v in app["vertices"].values()]
    edges = [e for app in apps for e in app["edges"].values()]
    assert len(vertices) == 3 and all(list(v) == VERTEX_KEYS for v in vertices)
    assert len(edges) == 4 and all(list(e) == EDGE_KEYS for e in edges)  # each end's


def test_the_record_round_trips_through_plain_data() -> None:
    sim = _running()
    for core in sim.cores.values():
        wire = core.status(sim.now)
        record = node_status(core, sim.now)  # sampled already at this time: the same figures
        assert isinstance(record, NodeStatus)
        assert to_wire(record) == wire
        assert json.loads(json.dumps(wire)) == wire  # plain data: no tuple, no struct
        assert msgspec.convert(wire, NodeStatus) == record
        assert from_wire(wire) == record


def test_a_status_reply_from_the_wire_types_again() -> None:
    sim = _running()
    sim.request("N1", m.StatusRequest(everywhere=True))
    sim.run_until(sim.now + 0.5)
    (reply,) = [r for _, _, r in sim.replies if isinstance(r, m.StatusReply)]
    got = m.decode(m.unwrap(m.wrap("N1", "client", reply)).body)
    assert isinstance(got, m.StatusReply) and sorted(got.nodes) == ["N1", "N2", "N3", "N4"]
    for node, plain in got.nodes.items():
        typed = from_wire(plain)
        assert typed.node == node and to_wire(typed) == plain
        if "pipe" in typed.apps:  # (a node that takes no part holds none of it)
            assert typed.apps["pipe"].placement == reply.nodes[node]["apps"]["pipe"]["placement"]


def test_the_drivers_links_stand_at_the_top_level() -> None:
    sim = _running()
    core = sim.cores["N1"]
    links = LinkStatus(
        traffic={"bytes_in": 10, "bytes_out": 20},
        connections={"connections_refused": 0},
        connected=["N2"],
        tasks=7,
        timers=3,
        authority=AuthorityStatus(mode="open", operators=[], refused=0),
    )
    core.observe(sim.now, 0, 0, links=links)
    st = core.status(sim.now)
    assert list(st) == LINK_KEYS + NODE_KEYS
    assert st["authority"] == {"mode": "open", "operators": [], "refused": 0}
    assert st["connected"] == ["N2"] and st["tasks"] == 7
    typed = from_wire(st)
    assert typed == node_status(core, sim.now) and typed.authority == links.authority


def test_a_client_types_the_nodes_it_was_given() -> None:
    sim = _running()
    nodes = {n: c.status(sim.now) for n, c in sim.cores.items()}
    typed = typed_status(nodes)
    assert sorted(typed) == sorted(nodes)
    assert all(to_wire(t) == nodes[n] for n, t in typed.items())
    assert (
        typed["N1"].apps["pipe"].vertices["src"].kind
        == nodes["N1"]["apps"]["pipe"]["vertices"]["src"]["kind"]
    )


def test_a_vertex_whose_stats_cannot_be_sent_says_so_and_status_still_answers() -> None:
    """A user's ``stats()`` returning something msgpack cannot carry (a deque, an object) is
    shown as an error in status instead of breaking every status request of the node."""
    from collections import deque

    from mso.model.app import Vertex
    from mso.runtime.instance import Instance

    class Odd:
        def __call__(self, event: object) -> object:
            return event

        def stats(self) -> object:
            return {"recent": deque([1, 2]), "when": object()}

    out = Instance(Vertex("odd", code=Odd), "operator").stats()
    assert isinstance(out, dict) and out["error"].startswith("stats(): TypeError")
