"""The Prometheus endpoint of every node, read back with prometheus-client's own parser."""

from __future__ import annotations

import asyncio
import os
import time
import urllib.request
from collections.abc import Iterator
from pathlib import Path

import pytest
from click.testing import CliRunner
from prometheus_client.parser import text_string_to_metric_families
from prometheus_client.samples import Sample

from mso.cli import main
from mso.emu.controller import Emulator
from mso.node.metrics import render
from mso.scenario import loads_scenario
from waits import patience

TESTS = Path(__file__).resolve().parent

PAIR = """
name: pair
nodes: {N1: {battery_wh: 10}, N2: {}}
links: [[N1, N2]]
"""

APP = """
name: duo
vertices:
  src: {code: runtime_vertices:CountingSource, pinned: N1, rate: 200,
        output: runtime_vertices:Num}
  mid: {code: runtime_vertices:Double}
  sink: {code: runtime_vertices:Recorder, pinned: N2}
edges: [[src, mid], [mid, sink]]
"""


def parse(text: str) -> dict[str, list[Sample]]:
    """Family name -> samples; the parser refuses anything not in the exposition format."""
    return {f.name: f.samples for f in text_string_to_metric_families(text)}


def test_render_names_units_and_labels() -> None:
    status = {
        "node": "N7",
        "monitor": {"battery_fraction": 0.25, "drain_w": 3.5, "energy_j": 12.0, "lifetime_s": None},
        "traffic": {"bytes_in": 10, "bytes_out": 20, "bytes_forwarded": 0, "frames_rejected": 1},
        "neighbours": ["N6", "N8"],
        "refusals": {"stop_app_unauthorized": 3},
        "apps": {
            "a": {
                "chains": [["s", "t"]],
                "chain_delay_ms": {"s-t": 2.5},
                "parked": {"s-t": "no route"},
                "vertices": {"s": {"kind": "source", "emitted": 5, "processed": 0, "cpu_s": 0.5,
                                   "errors": 0, "queued": 0}},
                "edges": {"s->t": {"sent": 5, "delivered": 0, "duplicates": 0, "in_flight": 5}},
            }
        },
    }  # fmt: skip
    fams = parse(render(status).decode())
    assert "mso_node_lifetime_seconds" not in fams  # unknown (wall power or no drain yet)
    (battery,) = fams["mso_node_battery_ratio"]
    assert battery.labels == {"node": "N7"} and battery.value == 0.25
    assert fams["mso_node_energy_joules"][0].name == "mso_node_energy_joules_total"
    assert fams["mso_node_neighbours"][0].value == 2
    (delay,) = fams["mso_chain_delay_seconds"]
    assert delay.labels == {"node": "N7", "app": "a", "chain": "s-t"} and delay.value == 0.0025
    assert fams["mso_chain_parked"][0].value == 1
    (emitted,) = (s for s in fams["mso_vertex_emitted_events"] if s.name.endswith("_total"))
    assert emitted.labels == {"node": "N7", "app": "a", "vertex": "s"} and emitted.value == 5
    (flight,) = fams["mso_edge_in_flight_events"]
    assert flight.labels == {"node": "N7", "app": "a", "edge": "s->t"} and flight.value == 5
    member = fams["mso_vertex_chain_info"][0]
    assert member.labels == {"node": "N7", "app": "a", "chain": "s-t", "vertex": "s"}
    (refused,) = (s for s in fams["mso_node_refused_messages"] if s.name.endswith("_total"))
    assert refused.labels == {"node": "N7", "reason": "stop_app_unauthorized"}
    assert refused.value == 3


@pytest.fixture
def node_pythonpath(monkeypatch: pytest.MonkeyPatch) -> Iterator[None]:
    path = os.environ.get("PYTHONPATH", "")
    monkeypatch.setenv("PYTHONPATH", f"{TESTS}{os.pathsep}{path}" if path else str(TESTS))
    yield


def scrape(url: str, deadline: float) -> str:
    while True:
        try:
            with urllib.request.urlopen(url, timeout=5) as r:
                assert r.headers["Content-Type"].startswith("text/plain; version=0.0.4")
                return str(r.read().decode())
        except OSError:
            if time.monotonic() > deadline:
                raise
            time.sleep(0.05)


def test_every_node_serves_its_metrics(node_pythonpath: None) -> None:
    async def run() -> dict[str, dict[str, list[Sample]]]:
        emu = Emulator(loads_scenario(PAIR), metrics_port=0, manage=False)
        await emu.start()
        try:
            reply = await emu.deploy(APP, "duo.yaml", "N1")
            assert reply.ok, reply.error
            deadline = time.monotonic() + patience(20)
            while True:  # until the sink has something to count
                got = {
                    n: parse(await asyncio.to_thread(
                        scrape, f"http://{node.host}:{emu.metrics_port}/metrics", deadline))
                    for n, node in emu.nodes.items()
                }  # fmt: skip
                delivered = got["N2"].get("mso_edge_delivered_events", [])
                if any(s.value > 0 and s.labels["edge"] == "mid->sink" for s in delivered):
                    return got  # (the sink's own edge: under load mid's may come first)
                assert time.monotonic() < deadline, got
                await asyncio.sleep(0.1)
        finally:
            await emu.stop()

    got = asyncio.run(run())
    for nid, fams in got.items():
        for fam in fams.values():
            assert all(s.labels["node"] == nid for s in fam)  # each node speaks for itself
    n1, n2 = got["N1"], got["N2"]
    assert 0 < n1["mso_node_battery_ratio"][0].value <= 1
    assert "mso_node_battery_ratio" not in n2  # wall power
    assert n1["mso_node_power_watts"][0].value > 0
    placed = {s.labels["vertex"] for f in (n1, n2) for s in f["mso_vertex_processed_events"]}
    assert placed == {"src", "mid", "sink"}
    edges = {s.labels["edge"] for s in n2["mso_edge_delivered_events"]}
    assert "mid->sink" in edges
    chains = {s.labels["chain"] for s in n1["mso_chain_parked"]}
    assert chains == {"src-mid-sink"}


def test_bad_metrics_address_is_a_user_error() -> None:
    result = CliRunner().invoke(main, ["node", "--id", "N1", "--metrics", "127.0.0.1:http"])
    assert result.exit_code == 2
    assert "expected HOST:PORT" in result.stderr
