"""A node's status: what ``mso status``, the dashboard and the metrics endpoint show, built
from each component's own figures.

The core answers a status request with :func:`node_status`; each app's part is
:func:`app_status` (placement, chains, parked chains and recoveries, each edge's channel, each
vertex instance's counters and state), the rest the node's (monitor, routes, membership,
procedures, what was refused). Everything in it is plain data (JSON and msgpack safe).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any, Protocol

from mso.protocol import messages as m
from mso.protocol.state import AppState, crash_status

if TYPE_CHECKING:
    from mso.node.manager import Manager
    from mso.node.monitor import Monitor
    from mso.protocol.dataplane import DataPlane
    from mso.protocol.procedures.membership.peers import Membership


class StatusSource(Protocol):
    """The core, as status reads it: its tables and its components."""

    id: str
    routes: dict[str, tuple[str, int]]
    apps: dict[str, AppState]
    monitor: Monitor
    dataplane: DataPlane
    membership: Membership
    manager: Manager
    dropped_messages: int
    refusals: dict[str, int]
    illegal_transitions: int
    handler_errors: int
    last_handler_error: str

    @property
    def links(self) -> dict[str, Any]: ...

    def open_procedures(self, now: float) -> list[dict[str, Any]]: ...


def app_status(dep: AppState, now: float) -> dict[str, Any]:
    """One app as this node holds and runs it."""
    up = max(now - dep.started_at, 1e-9) if dep.running else 0.0
    edges = {}
    for i, e in enumerate(dep.app.edges):
        if i in dep.out or i in dep.inc:
            inc = dep.inc.get(i)
            out = dep.out.get(i)
            sent = out.next_seq if out else 0
            edges[f"{e.src}->{e.dst}"] = {
                "sent": sent,
                "delivered": inc.expected if inc else 0,
                "duplicates": inc.duplicates if inc else 0,
                "in_flight": out.in_flight if out else 0,
                "events_per_s": (sent / up) if up else 0.0,
            }
    return {
        "running": dep.running,
        "parked": {dep.layout.chains[c].name: why for c, why in dep.parked.items()},
        "recoveries": list(dep.recoveries),
        "dropped_parked": {
            f"{dep.app.edges[e].src}->{dep.app.edges[e].dst}": n
            for e, n in sorted(dep.dropped.items())
        },
        "chain_delay_ms": {
            dep.layout.chains[c].name: round(ms, 3) for c, ms in sorted(dep.delays.items())
        },
        "slo_ms": dep.app.slo_ms,
        "origin": dep.origin,
        "placement": dict(dep.placed),
        "chains": [list(c.vertices) for c in dep.layout.chains],
        "vertices": {
            vid: {
                "kind": h.kind,
                "state": h.state(now),
                "busy_s": round(now - h.busy_since, 3) if h.busy_since else 0.0,
                "queued": h.queued
                + sum(len(p[1]) for p in h.pending if not isinstance(p, m.Marker)),
                "processed": h.processed,
                "emitted": h.emitted,
                "calls": h.calls,
                "ended": h.ended,  # its stream is over (a source's, or every input's)
                "errors": h.errors,
                "cpu_s": h.cpu_s,
                "last_error": h.last_error,
                "stats": h.stats,
            }
            | crash_status(dep.crashes.get(vid))
            for vid, h in (dep.crashed | dep.instances).items()
        },
        "edges": edges,
    }


def node_status(core: StatusSource, now: float) -> dict[str, Any]:
    """The node's status: the driver's links, then each component's part."""
    dp = core.dataplane
    return (
        core.links
        | {
            "node": core.id,
            "monitor": core.monitor.snapshot() | {"work_ms": dp.work_ms, "cpu_ms": dp.cpu_ms},
            "routes": {d: list(r) for d, r in sorted(core.routes.items())},
            "neighbours": sorted(n for n, (hop, _) in core.routes.items() if hop == n),
            "apps": {name: app_status(dep, now) for name, dep in core.apps.items()},
            "dropped_messages": core.dropped_messages,
            "refusals": dict(sorted(core.refusals.items())),
            "illegal_transitions": core.illegal_transitions,
            "handler_errors": core.handler_errors,
            "last_handler_error": core.last_handler_error,
            "procedures": core.open_procedures(now),
            "management": core.manager.status(),
        }
        | core.membership.status()
    )
