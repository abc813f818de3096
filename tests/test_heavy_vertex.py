"""A vertex that computes for most of a second per event must not take its node down.

Vertex code runs on worker threads, off the control plane (mso.runtime.executor): while a
pure-Python vertex burns CPU, its node keeps sending heartbeats, so no neighbour declares it
failed, and backpressure (not loss) absorbs the backlog. On a 3-node emulated line N1-N2-N3:
``src`` (N1, one event a second, a fixed number of them) -> ``split`` (N1: each event becomes two)
-> ``burn`` (N2: ~0.7 s of busy loop per event) -> ``sink`` (N3, checks order).

Why ``split``: a vertex is reported ``busy`` once one effect has run for ``BUSY_AFTER_S`` (1 s);
the two events of a split travel in one batch, so ``burn`` gets one 1.4 s feed.

Node processes import the vertex classes below from this module (tests/ is on PYTHONPATH), so
it imports little at module level: the emulator and pytest are imported by the test alone.
"""

from __future__ import annotations

import asyncio
import os
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any

import msgspec

from mso.benchmarks.common import SequenceCheck
from mso.protocol.events import HeartbeatTick

if TYPE_CHECKING:
    import pytest

TESTS = Path(__file__).resolve().parent
EVENTS = 3  # source events; the sink gets twice as many
BURN_S = 0.7
DEADLINE_S = 60.0  # bound on the whole flow (about 6 s of burning; generous for a loaded CI)

LINE3 = """
name: line3
link_defaults: {delay_ms: 0.5, bandwidth_mbps: 54}
nodes: {N1: {}, N2: {}, N3: {}}
links: [[N1, N2], [N2, N3]]
"""

APP = f"""
name: heavy
vertices:
  src:   {{code: test_heavy_vertex:Limited, pinned: N1, rate: 1, params: {{limit: {EVENTS}}},
          output: test_heavy_vertex:Item}}
  split: {{code: test_heavy_vertex:Split, pinned: N1, input: test_heavy_vertex:Item,
          output: test_heavy_vertex:Item}}
  burn:  {{code: test_heavy_vertex:Burn, pinned: N2, params: {{seconds: {BURN_S}}},
          input: test_heavy_vertex:Item, output: test_heavy_vertex:Item}}
  sink:  {{code: test_heavy_vertex:InOrder, pinned: N3, input: test_heavy_vertex:Item}}
edges:
  - [src, split]
  - [split, burn]
  - [burn, sink]
"""


class Item(msgspec.Struct, array_like=True, frozen=True):
    seq: int


class Limited:
    """A rated source that emits ``limit`` events, then nothing (calls go on)."""

    def __init__(self, limit: int) -> None:
        self.limit = limit
        self.sent = 0

    def __call__(self, seq: int, now: float) -> Item | None:
        if self.sent >= self.limit:
            return None
        self.sent += 1
        return Item(self.sent - 1)


class Split:
    """Event k becomes events 2k and 2k+1, returned together (one batch downstream)."""

    def __call__(self, event: Item) -> list[Item]:
        return [Item(2 * event.seq), Item(2 * event.seq + 1)]


class Burn:
    """A pure-Python busy loop for ``seconds`` of wall time per event (no sleep; wall time so a
    loaded CI machine does not stretch the test)."""

    def __init__(self, seconds: float) -> None:
        self.seconds = seconds

    def __call__(self, event: Item) -> Item:
        end = time.perf_counter() + self.seconds
        x = 0
        while time.perf_counter() < end:
            for i in range(1000):
                x ^= i * i
        return event


class InOrder(SequenceCheck):
    """Counts arrivals; an arrival that is not the next expected number is counted as such."""

    def __call__(self, event: Item) -> None:
        self.see(event.seq)

    def stats(self) -> dict[str, int]:
        return vars(self).copy()


def test_heavy_vertex_keeps_its_node_alive_and_loses_nothing(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    from mso.emu.controller import Emulator
    from mso.scenario import loads_scenario

    path = os.environ.get("PYTHONPATH", "")  # node processes import the vertices from here
    monkeypatch.setenv("PYTHONPATH", f"{TESTS}{os.pathsep}{path}" if path else str(TESTS))

    async def run() -> tuple[list[dict[str, Any]], set[str]]:
        emu = Emulator(loads_scenario(LINE3), manage=False)
        await emu.start()
        polls: list[dict[str, Any]] = []
        burn_states: set[str] = set()
        try:
            reply = await emu.deploy(APP, "heavy.yaml", "N1")
            assert reply.ok, reply.error
            loop = asyncio.get_running_loop()
            deadline = loop.time() + DEADLINE_S
            while loop.time() < deadline:  # bounded poll until the sink has everything
                st = await emu.status()
                polls.append(st)
                burn = st["N2"]["apps"]["heavy"]["vertices"]["burn"]
                burn_states.add(burn["state"])
                sink = st["N3"]["apps"]["heavy"]["vertices"]["sink"].get("stats") or {}
                if sink.get("count", 0) >= 2 * EVENTS and "busy" in burn_states:
                    break
                await asyncio.sleep(0.1)  # poll period, not synchronisation
            return polls, burn_states
        finally:
            await emu.stop()

    polls, burn_states = asyncio.run(run())
    final = polls[-1]
    for st in polls:  # nobody was ever declared failed
        for node, s in st.items():
            assert s["failed_nodes"] == [], (node, s["failed_nodes"])
            assert s["failures"] == [], (node, s["failures"])
    src = final["N1"]["apps"]["heavy"]["vertices"]["src"]
    sink = final["N3"]["apps"]["heavy"]["vertices"]["sink"]["stats"]
    assert src["emitted"] == EVENTS
    assert sink == {"count": 2 * EVENTS, "next": 2 * EVENTS, "repeats": 0, "out_of_order": 0}
    assert "busy" in burn_states, burn_states
    burn = final["N2"]["apps"]["heavy"]["vertices"]["burn"]
    assert burn["processed"] == 2 * EVENTS and burn["errors"] == 0


def test_detection_settings_are_checked() -> None:
    """``--heartbeat``/``--dead-after`` (which the heavy-vertex figures depend on) refuse
    values that would declare live neighbours failed, before anything starts."""
    from click.testing import CliRunner

    from mso.cli import main

    for args in (
        ["--heartbeat", "0"],
        ["--heartbeat", "nan"],
        ["--dead-after", "inf"],
        ["--heartbeat", "0.2", "--dead-after", "0.1"],
    ):
        res = CliRunner().invoke(main, ["node", "--id", "N1", "--listen", "127.0.0.1:0", *args])
        assert res.exit_code == 2, (args, res.output)
        assert "--heartbeat" in res.output or "--dead-after" in res.output
    res = CliRunner().invoke(
        main, ["emulate", "x.yaml", "--heartbeat", "0.1", "--dead-after", "0.1"]
    )
    assert res.exit_code == 2 and "--dead-after" in res.output


def test_liveness_keeps_heartbeat_inter_arrivals() -> None:
    """Status shows how late each neighbour's heartbeats came (bounded, per neighbour)."""
    from mso.protocol import messages as m
    from mso.protocol.procedures.membership.liveness import GAP_SAMPLES, Liveness

    lv = Liveness(0.05, 0.15)
    lv.set_neighbours(0.0, {"N2"})
    beat = m.Heartbeat("N2", figures=m.Figures(1.0, 0.0, 0.0, None, None, (0.0, 0.0, 0.0, 0.0)))
    for k in range(GAP_SAMPLES + 10):
        lv.heard_from("N2", k * 0.05 + (0.02 if k == GAP_SAMPLES + 5 else 0.0), beat)
    gaps = lv.status().inter_arrival["N2"]
    assert gaps.n == GAP_SAMPLES + 9
    assert len(lv.gaps["N2"].recent) == GAP_SAMPLES
    assert gaps.p50_ms == 50.0 and gaps.max_ms == 70.0
    lv.set_neighbours(1e3, set())  # a lost link forgets the figures
    assert lv.status().inter_arrival == {} and lv.status().dead_after_s == 0.15


def test_heartbeats_carry_the_figures_once_a_monitor_period_and_to_a_new_neighbour() -> None:
    """Liveness and membership ride on every beat; the monitor's figures (they change once a
    second, the power model never) on one beat in ten, and on the first beat to a neighbour
    whose link just came up. The receiver keeps the last figures it was given."""
    from mso.node.core import NodeCore
    from mso.protocol import messages as m
    from mso.protocol.effects import Send

    core = NodeCore("N1")
    core.start(0.0)
    core.set_routes({"N2": ("N2", 1)}, 0.0)

    def beats(now: float) -> dict[str, m.Heartbeat]:
        for n in core.liveness.neighbours:  # they live: slim beats of theirs say so
            core.receive(n, m.Heartbeat(n), now)
        out = core.on_timer(HeartbeatTick(), now)
        return {
            e.dst: e.said for e in out if isinstance(e, Send) and isinstance(e.said, m.Heartbeat)
        }

    sent = [beats(0.1 * k) for k in range(1, 21)]
    with_figures = [k for k, b in enumerate(sent) if b["N2"].figures is not None]
    assert with_figures == [0, 10]  # the first beat, then one a period
    assert all(b["N2"].incarnation == core.incarnation for b in sent)
    # a new neighbour gets them on its first beat, the old one keeps to the period
    assert beats(2.1)["N2"].figures is not None  # the 21st beat: a period on
    core.set_routes({"N2": ("N2", 1), "N3": ("N3", 1)}, 2.15)
    b = beats(2.2)
    assert b["N3"].figures is not None and b["N2"].figures is None
    # a slim beat is a fraction of a full one on the wire
    full, slim = (len(m.encode(x)) for x in (sent[0]["N2"], sent[1]["N2"]))
    assert slim < full / 2

    # the receiver: figures from the last beat that had them, liveness from every beat
    rx = NodeCore("N2")
    rx.start(0.0)
    rx.set_routes({"N1": ("N1", 1)}, 0.0)
    rx.receive("N1", sent[0]["N2"], 0.1)
    rx.receive("N1", sent[1]["N2"], 0.2)
    at, fig = rx.liveness.heard["N1"]
    assert at == 0.1 and fig == sent[0]["N2"].figures
    assert rx.liveness.last_heard["N1"] == 0.2
