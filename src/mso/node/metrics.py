"""The node's Prometheus endpoint (``mso node --metrics HOST:PORT``, off by default).

A scrape reads the node's own status on the node's event loop (the core is never touched from
another thread) and renders it with ``prometheus-client``'s exposition code: conventional names
(``mso_`` prefix, base units in the name: ``_seconds``, ``_bytes``, ``_joules``, ``_watts``,
``_ratio``; counters end in ``_total``) and labels ``node``, ``app``, ``chain``, ``vertex``,
``edge``. Only this node's figures: Prometheus scrapes every node, as it would any fleet.
"""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import Callable, Iterator
from typing import Any

from prometheus_client import CollectorRegistry, generate_latest
from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily, Metric
from prometheus_client.registry import Collector

from mso.errors import MsoError
from mso.net.http import BadRequest, read_request, response

CONTENT_TYPE = "text/plain; version=0.0.4; charset=utf-8"


def families(st: dict[str, Any]) -> Iterator[Metric]:
    """The metric families of one node's status."""
    node = str(st["node"])
    mon = st.get("monitor", {})

    traffic = st.get("traffic", {})
    G, C = GaugeMetricFamily, CounterMetricFamily
    per_node: list[tuple[type[Metric], str, str, Any]] = [
        (G, "battery_ratio", "Remaining battery, 0 to 1 (absent on wall power).",
         mon.get("battery_fraction")),
        (G, "battery_remaining_joules", "Remaining battery energy.", mon.get("remaining_j")),
        (C, "energy_joules", "Energy spent: idle, modelled CPU work, radio.", mon.get("energy_j")),
        (G, "power_watts", "Drain, smoothed over recent samples.", mon.get("drain_w")),
        (G, "lifetime_seconds", "Expected battery lifetime at this drain.", mon.get("lifetime_s")),
        (G, "load_ratio", "Modelled CPU utilisation (1 = one busy CPU).", mon.get("load")),
        (C, "received_bytes", "Bytes received from neighbours.", traffic.get("bytes_in")),
        (C, "sent_bytes", "Bytes sent to neighbours, relayed included.", traffic.get("bytes_out")),
        (C, "forwarded_bytes", "Bytes relayed for other nodes.", traffic.get("bytes_forwarded")),
        (C, "rejected_frames", "Frames that failed authentication.",
         traffic.get("frames_rejected")),
        (G, "neighbours", "Neighbours (one radio hop).", len(st.get("neighbours", []))),
        (G, "failed_nodes", "Nodes this node holds failed.", len(st.get("failed_nodes", []))),
        (C, "handler_errors", "Messages whose handling raised.", st.get("handler_errors")),
        (C, "illegal_transitions", "Procedure events their state did not allow.",
         st.get("illegal_transitions")),
        (G, "incarnation", "This daemon's incarnation (a restart makes a new one).",
         st.get("incarnation")),
    ]  # fmt: skip
    for kind, name, doc, value in per_node:
        if value is not None:
            fam = kind(f"mso_node_{name}", doc, labels=["node"])  # type: ignore[call-arg]
            fam.add_metric([node], float(value))  # type: ignore[attr-defined]
            yield fam
    refused = CounterMetricFamily(
        "mso_node_refused_messages",
        "Messages refused for their meaning (or for want of authority), by reason.",
        labels=["node", "reason"],
    )
    for reason, n in sorted(st.get("refusals", {}).items()):
        refused.add_metric([node, reason], n)
    yield refused

    vl = ["node", "app", "vertex"]
    processed = CounterMetricFamily(
        "mso_vertex_processed_events", "Events a vertex took in.", labels=vl
    )
    emitted = CounterMetricFamily(
        "mso_vertex_emitted_events", "Events a source emitted.", labels=vl
    )
    cpu = CounterMetricFamily(
        "mso_vertex_cpu_seconds", "Measured CPU time in vertex code.", labels=vl
    )
    errors = CounterMetricFamily(
        "mso_vertex_errors", "Calls of vertex code that raised.", labels=vl
    )
    queued = GaugeMetricFamily(
        "mso_vertex_queued_events", "Events waiting for a vertex.", labels=vl
    )
    member = GaugeMetricFamily(
        "mso_vertex_chain_info", "1 for each chain a hosted vertex belongs to.",
        labels=["node", "app", "chain", "vertex"],
    )  # fmt: skip
    el = ["node", "app", "edge"]
    sent = CounterMetricFamily(
        "mso_edge_sent_events", "Events sent on an edge from here.", labels=el
    )
    delivered = CounterMetricFamily(
        "mso_edge_delivered_events", "Events delivered in order on an edge here.", labels=el
    )
    dups = CounterMetricFamily("mso_edge_duplicate_events", "Duplicates discarded.", labels=el)
    flight = GaugeMetricFamily(
        "mso_edge_in_flight_events", "Sent, not yet acknowledged.", labels=el
    )
    cl = ["node", "app", "chain"]
    delay = GaugeMetricFamily("mso_chain_delay_seconds", "End-to-end delay of a chain.", labels=cl)
    parked = GaugeMetricFamily("mso_chain_parked", "1 while a chain is parked.", labels=cl)
    for app, a in sorted(st.get("apps", {}).items()):
        for v, vs in sorted(a.get("vertices", {}).items()):
            labels = [node, app, v]
            processed.add_metric(labels, vs.get("processed", 0))
            emitted.add_metric(labels, vs.get("emitted", 0))
            cpu.add_metric(labels, vs.get("cpu_s", 0.0))
            errors.add_metric(labels, vs.get("errors", 0))
            queued.add_metric(labels, vs.get("queued", 0))
            for c in a.get("chains", []):
                if v in c:
                    member.add_metric([node, app, "-".join(c), v], 1)
        for e, es in sorted(a.get("edges", {}).items()):
            labels = [node, app, e]
            sent.add_metric(labels, es.get("sent", 0))
            delivered.add_metric(labels, es.get("delivered", 0))
            dups.add_metric(labels, es.get("duplicates", 0))
            flight.add_metric(labels, es.get("in_flight", 0))
        for c, ms in sorted(a.get("chain_delay_ms", {}).items()):
            delay.add_metric([node, app, c], ms / 1e3)
        names = ["-".join(c) for c in a.get("chains", [])]
        for c in names:
            parked.add_metric([node, app, c], 1.0 if c in a.get("parked", {}) else 0.0)
    yield from (processed, emitted, cpu, errors, queued, member)
    yield from (sent, delivered, dups, flight, delay, parked)


class _StatusCollector(Collector):
    def __init__(self, status: dict[str, Any]) -> None:
        self.status = status

    def collect(self) -> Iterator[Metric]:
        return families(self.status)


def render(status: dict[str, Any]) -> bytes:
    """The Prometheus text exposition of one node's status."""
    registry = CollectorRegistry(auto_describe=False)
    registry.register(_StatusCollector(status))
    return generate_latest(registry)


class MetricsServer:
    """Serves ``GET /metrics`` on the node's own event loop."""

    def __init__(self, status: Callable[[], dict[str, Any]], host: str, port: int) -> None:
        self.status, self.host, self.port = status, host, port
        self._server: asyncio.Server | None = None

    async def start(self) -> None:
        try:
            self._server = await asyncio.start_server(self._handle, self.host, self.port)
        except OSError as exc:
            raise MsoError(
                f"--metrics: cannot listen on {self.host}:{self.port}: {exc.strerror or exc}"
            ) from None
        self.port = self._server.sockets[0].getsockname()[1]

    async def stop(self) -> None:
        if self._server is not None:
            self._server.close()

    async def _handle(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        try:
            try:
                method, target, _, _ = await asyncio.wait_for(read_request(reader, 0), 10.0)
                if target.split("?")[0] not in ("/metrics", "/"):
                    raise BadRequest(404, "the metrics are at /metrics")
                if method != "GET":
                    raise BadRequest(405, "GET only")
                writer.write(response(200, CONTENT_TYPE, render(self.status())))
            except BadRequest as exc:
                writer.write(response(exc.status, "text/plain", str(exc).encode()))
            await writer.drain()
        except (TimeoutError, asyncio.IncompleteReadError, ConnectionError):
            pass
        finally:
            writer.close()
            with contextlib.suppress(Exception):
                await writer.wait_closed()
