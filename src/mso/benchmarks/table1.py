"""Table 1 of the MSO paper (§4): the cost of mapping and remapping the convoy app, measured.

The convoy app of Fig. 6 (``mso/examples/convoy.yaml``: laser 967 B and odometry 38 B at
5 events/s, cameras ~3 KB at 0.5 events/s, sensors pinned to N1, storage to N4) runs on the
emulated four-robot line (``mso/examples/convoy-line.yaml``; one ``mso node`` process per robot
on 127.0.1.i). Every operation of Table 1 is run ``runs`` times; the figure is the coordinating
node's own measure (``elapsed_ms`` of the reply: request received -> operation complete):

* mapping: deploy the convoy via N1 (DeployReply: every chain built), then undeploy it and wait
  until no node holds it;
* upstream / downstream relocation: with the convoy flowing, move an interior vertex of the
  laser -> scan_filter -> scan_matcher -> localization chain (``scan_filter``, ``scan_matcher``)
  downstream then back upstream, alternately; the request goes to the node hosting the
  vertex's predecessor (§3.4.1: the node housing u relocates its successor v).
  Only moves that can succeed are asked for, and only successful ones are counted;
* chain remapping (§3.4.2) of the laser chain, global remapping (§3.4.3) of the navigation
  pipeline's three chains (part) and of every chain (whole): before each timed remap one
  interior vertex of the remapped chains is first relocated to another node (untimed), so the
  remap has something to move back; the runs that moved vertices are counted.

A small measurement app runs alongside the whole time (``beats``: a source at 200 events/s on N1
-> ``near`` (N2) -> ``relay`` -> ``far`` (N3) -> a sink on N4, all defined in this module). Its
sink records the wall time of every arrival, so the benchmark can measure the interruption of
the flow (largest inter-arrival gap minus the nominal 5 ms period):

* across each relocation of ``relay`` between N2 and N3 (the gap overlapping the request; an
  "idle" window of the same length just before it gives the undisturbed jitter), versus
* across a stop-and-redeploy: undeploy ``beats``, wait until no node holds it, deploy it again
  with ``relay`` pinned to the other node; the gap runs from the last arrival the old sink
  reported just before the stop to the first arrival at the new sink.

The source numbers its events and the relay carries a counter that must move with it, so the
sink counts repeats, events arriving ahead of their turn (a skipped seq: lost or reordered) and
relay-state errors. For an exact count the source is paused (by a file it checks) until
everything emitted has arrived. Events in flight when an instance is stopped are discarded by
design; they are not counted as lost.

The same runs are repeated on the same line with unshaped links (no bandwidth, no delay) to
separate mso's own cost from the emulated links'. The node processes import this module
(``mso.benchmarks.table1:GapSink`` ...), which is part of the package: no PYTHONPATH needed.

Usage: .venv/bin/python bench/table1.py [--runs 30] [--quick] [--json FILE]
"""

from __future__ import annotations

import argparse
import asyncio
import itertools
import json
import os
import statistics
import sys
import tempfile
import time
from collections import deque
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import msgspec

import mso.examples
from mso.benchmarks.common import Progress, SequenceCheck, percentile, provenance
from mso.client import NodeUnreachable, overlay_key
from mso.emu.controller import Emulator
from mso.errors import MsoError
from mso.model.appfile import loads_app
from mso.model.network import LinkSpec
from mso.protocol import messages as m
from mso.scenario import Scenario, load_scenario

MODULE = "mso.benchmarks.table1"

# -- the measurement app's vertex code (imported by the node processes) ------------------------


class Beat(msgspec.Struct, array_like=True, frozen=True):
    """One event of the measurement app: its number, and the relay's count when it passed."""

    seq: int
    sent_at: float
    relay: int = -1


class BeatSource:
    """Numbers its events from 0; emits nothing while ``pause_file`` exists."""

    def __init__(self, pause_file: str = "") -> None:
        self.pause_file = pause_file
        self.sent = 0

    def __call__(self, seq: int, now: float) -> Beat | None:
        if self.pause_file and os.path.exists(self.pause_file):
            return None
        event = Beat(self.sent, time.time())
        self.sent += 1
        return event

    def stats(self) -> dict[str, int]:
        return {"sent": self.sent}


class Forward:
    def __call__(self, event: Beat) -> Beat:
        return event


class Relay:
    """Stateful: stamps how many events it has processed. Its state must move with it."""

    def __init__(self) -> None:
        self.count = 0

    def __call__(self, event: Beat) -> Beat:
        out = Beat(event.seq, event.sent_at, self.count)
        self.count += 1
        return out

    def get_state(self) -> int:
        return self.count

    def set_state(self, state: int) -> None:
        self.count = int(state)


class GapSink(SequenceCheck):
    """Checks order and relay state; keeps the wall time of the last ``history`` arrivals."""

    def __init__(self, history: int = 600) -> None:
        super().__init__()
        self.relay_mismatch = 0
        self.first = 0.0
        self.last = 0.0
        self.max_gap = 0.0
        self.arrivals: deque[float] = deque(maxlen=history)

    def __call__(self, event: Beat) -> None:
        now = time.time()
        if self.count:
            self.max_gap = max(self.max_gap, now - self.last)
        else:
            self.first = now
        self.last = now
        self.arrivals.append(now)
        self.see(event.seq)
        if event.relay != event.seq:
            self.relay_mismatch += 1

    def stats(self) -> dict[str, Any]:
        return {
            "count": self.count,
            "next": self.next,
            "repeats": self.repeats,
            "out_of_order": self.out_of_order,
            "relay_mismatch": self.relay_mismatch,
            "first": self.first,
            "last": self.last,
            "max_gap_ms": self.max_gap * 1e3,
            "arrivals": list(self.arrivals),
        }


# -- the benchmark -------------------------------------------------------------------------------

EXAMPLES = Path(mso.examples.__file__).resolve().parent
APP_FILE = EXAMPLES / "convoy.yaml"
SCENARIO_FILE = EXAMPLES / "convoy-line.yaml"
CONVOY = "convoy"
BEATS = "beats"
BEAT_RATE = 200.0
PERIOD_MS = 1e3 / BEAT_RATE
NODES = ("N1", "N2", "N3", "N4")

OPERATIONS = (
    "mapping",
    "upstream_relocation",
    "downstream_relocation",
    "chain_remapping",
    "global_remapping_part",
    "global_remapping_whole",
)
LABELS = {
    "mapping": "Mapping",
    "upstream_relocation": "Upstream relocation",
    "downstream_relocation": "Downstream relocation",
    "chain_remapping": "Chain remapping",
    "global_remapping_part": "Global remapping (part)",
    "global_remapping_whole": "Global remapping (whole)",
}
PAPER_MS = {  # Table 1: mean, sigma (350 MHz Xeons, gSOAP control plane, 100 Mbit/s Ethernet)
    "mapping": (1390.0, 77.7),
    "upstream_relocation": (94.3, 6.4),
    "downstream_relocation": (56.3, 3.3),
    "chain_remapping": (2759.1, 217.0),
    "global_remapping_part": (2943.1, 265.8),
    "global_remapping_whole": (3327.2, 335.2),
}
TARGET_P50_MS = {
    "upstream_relocation": 2.0,
    "downstream_relocation": 2.0,
    "chain_remapping": 10.0,
    "global_remapping_part": 20.0,
    "global_remapping_whole": 30.0,
}
TARGET_GAP_MS = 5.0
TARGET_GAP_RATIO = 100.0
# the navigation pipeline's three chains, by (head, tail): localization also feeds the target
# map (its poses place camera frames in the map), a chain of its own left out of "part"
NAVIGATION = (("laser", "localization"), ("odometry", "localization"), ("localization", "storage"))
PAUSE_S = 0.02  # between operations
SETTLE_S = 0.04  # after a relocation of the relay, before its sink is read
RESUME_S = 3.0  # how long the flow may take to resume after a relocation
STALL_MS = 50.0  # an interruption longer than this is reported as a stall
DEADLINE_S = 110.0  # per scenario: no operation starts after this
QUICK_DEADLINE_S = 45.0


def summary(values: list[float]) -> dict[str, Any]:
    if not values:
        return {
            "mean_ms": None,
            "std_ms": None,
            "p50_ms": None,
            "p99_ms": None,
            "min_ms": None,
            "max_ms": None,
            "n": 0,
        }
    return {
        "mean_ms": statistics.fmean(values),
        "std_ms": statistics.stdev(values) if len(values) > 1 else 0.0,
        "p50_ms": percentile(values, 50),
        "p99_ms": percentile(values, 99),
        "min_ms": min(values),
        "max_ms": max(values),
        "n": len(values),
    }


def beats_document(pause_file: str, relay_node: str | None = None) -> str:
    """The measurement app; ``relay_node`` pins the relay (a redeployment forcing its place)."""
    fmt = f"{MODULE}:Beat"
    pin = f", pinned: {relay_node}" if relay_node else ""
    return f"""\
name: {BEATS}
vertices:
  beat:  {{code: {MODULE}:BeatSource, pinned: N1, rate: {BEAT_RATE:g}, cost: 0.01,
          params: {{pause_file: {json.dumps(pause_file)}}}, output: {fmt}}}
  near:  {{code: {MODULE}:Forward, pinned: N2, cost: 0.01, input: {fmt}, output: {fmt}}}
  relay: {{code: {MODULE}:Relay, cost: 0.01, input: {fmt}, output: {fmt}{pin}}}
  far:   {{code: {MODULE}:Forward, pinned: N3, cost: 0.01, input: {fmt}, output: {fmt}}}
  gaps:  {{code: {MODULE}:GapSink, pinned: N4, cost: 0.01, input: {fmt}}}
edges:
  - {{from: beat, to: near, size: 24}}
  - {{from: near, to: relay, size: 24}}
  - {{from: relay, to: far, size: 24}}
  - {{from: far, to: gaps, size: 24}}
"""


def unshaped(scenario: Scenario) -> Scenario:
    """The same line with neither bandwidth nor delay on its links."""
    net = scenario.network
    for (a, b), _link in list(net.links.items()):
        net.remove_link(a, b)
        net.add_link(LinkSpec(a, b))
    scenario.name += " (unshaped)"
    return scenario


def window_gap(arrivals: list[float], t0: float, t1: float) -> float | None:
    """Largest gap between consecutive arrivals that overlaps [t0, t1] (None: not covered)."""
    if len(arrivals) < 2 or arrivals[0] > t0 or arrivals[-1] < t1:
        return None
    best: float | None = None
    for a, b in itertools.pairwise(arrivals):
        if a <= t1 and b >= t0:
            best = b - a if best is None else max(best, b - a)
    return best


def interior(chain: list[str]) -> list[str]:
    return chain[1:-1]


@dataclass
class Bench:
    emu: Emulator
    runs: int
    deadline: float  # time.monotonic()
    pause_file: Path
    convoy_doc: str
    failures: list[str] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)
    remap_via: str = "N1"

    def late(self, phase: str) -> bool:
        if time.monotonic() > self.deadline:
            self.failures.append(f"{phase}: time budget reached, phase cut short")
            return True
        return False

    async def node_status(self, node: str) -> dict[str, Any]:
        reply = await self.emu.call(node, m.StatusRequest(), 5.0)
        assert isinstance(reply, m.StatusReply)
        status: dict[str, Any] = reply.nodes[node]
        return status

    async def app_view(self, app: str) -> tuple[dict[str, str], list[list[str]]]:
        """The placement and the chains of ``app`` as N1 knows them."""
        st = (await self.node_status("N1"))["apps"][app]
        return dict(st["placement"]), [list(c) for c in st["chains"]]

    async def vertex_stats(self, node: str, vertex: str) -> dict[str, Any] | None:
        st = (await self.node_status(node)).get("apps", {}).get(BEATS)
        if st is None or vertex not in st["vertices"]:
            return None
        v = st["vertices"][vertex]
        stats = v.get("stats")
        if not isinstance(stats, dict):
            return None
        return stats | {"_emitted": v["emitted"]}

    async def sink(self) -> dict[str, Any] | None:
        return await self.vertex_stats("N4", "gaps")

    async def wait_gone(self, app: str, timeout: float = 5.0) -> bool:
        loop = asyncio.get_running_loop()
        deadline = loop.time() + timeout
        for _ in range(500):
            nodes = await self.emu.status()
            if all(app not in st.get("apps", {}) for st in nodes.values()):
                return True
            if loop.time() > deadline:
                break
            await asyncio.sleep(0.002)
        return False

    async def deploy(self, document: str, file: str) -> m.DeployReply:
        return await asyncio.wait_for(self.emu.deploy(document, file, "N1"), 30.0)

    async def remap(self, chains: list[int], everything: bool = False) -> m.RemapReply:
        reply = await self.emu.call(
            self.remap_via, m.RemapRequest(CONVOY, chains, everything), 30.0
        )
        assert isinstance(reply, m.RemapReply)
        return reply


async def pick_remap_via(b: Bench, chain: int) -> None:
    """The node remaps are sent to: N1 if it can coordinate one, else the first node that can.

    Each node is tried once with an untimed no-op remap of ``chain`` on a connection of its own,
    so a node that drops the connection does not take the emulator's connection with it.
    """
    emu = b.emu
    for node in ("N1", "N4", "N3", "N2"):
        n = emu.nodes[node]
        client = emu.client_for(n, overlay_key(emu.key), "table1-remap-trial")
        try:
            await client.connect(2.0)
            reply = await client.call(m.RemapRequest(CONVOY, [chain]), 10.0)
        except NodeUnreachable as exc:
            b.notes.append(
                f"a remap coordinated by {node} failed ({exc}); see node_log_errors in the JSON"
            )
            continue
        finally:
            await client.close()
        if isinstance(reply, m.RemapReply) and reply.ok:
            b.remap_via = node
            return
        b.notes.append(f"a remap coordinated by {node} was refused: {reply}")
    raise MsoError("no node could coordinate a remap")


async def phase_mapping(b: Bench) -> tuple[list[float], list[float]]:
    elapsed: list[float] = []
    wall: list[float] = []
    app_vertices = set(loads_app(b.convoy_doc, file=str(APP_FILE)).vertices)
    for i in range(b.runs):
        if b.late("mapping"):
            break
        t0 = time.perf_counter()
        reply = await b.deploy(b.convoy_doc, str(APP_FILE))
        t1 = time.perf_counter()
        if not reply.ok:
            b.failures.append(f"mapping run {i}: {reply.error}")
        else:
            if set(reply.placement) != app_vertices:
                b.failures.append(f"mapping run {i}: placement covers {len(reply.placement)}")
            else:
                elapsed.append(reply.elapsed_ms)
                wall.append((t1 - t0) * 1e3)
        await b.emu.undeploy(CONVOY, "N1")
        if not await b.wait_gone(CONVOY):
            b.failures.append(f"mapping run {i}: undeploy did not reach every node in 5 s")
            break
        await asyncio.sleep(PAUSE_S)  # let stray frames of the stopped instance drain
    return elapsed, wall


async def phase_relocation(b: Bench, placed: dict[str, str], chain: list[str]) -> dict[str, Any]:
    """Alternate downstream and upstream moves of the chain's interior vertices."""
    up: list[float] = []
    down: list[float] = []
    refused: list[str] = []
    movers = interior(chain)
    tail = chain[-1]
    for step in range(4 * b.runs + 8):
        if len(up) >= b.runs and len(down) >= b.runs:
            break
        if b.late("relocation"):
            break
        v = movers[(step // 2) % len(movers)]
        k = chain.index(v)
        here, pred, succ = placed[v], placed[chain[k - 1]], placed[chain[k + 1]]
        can = {"upstream": here != pred, "downstream": succ != here or placed[tail] != here}
        first = "downstream" if len(down) <= len(up) else "upstream"
        other = "upstream" if first == "downstream" else "downstream"
        direction = first if can[first] else other
        if not can[direction]:
            continue
        # §3.4.1: the node housing the predecessor relocates its successor
        reply = await b.emu.relocate(CONVOY, v, direction=direction, via=pred)
        if reply.ok:
            (down if direction == "downstream" else up).append(reply.elapsed_ms)
            placed[v] = reply.node
        else:
            refused.append(f"{v} {direction} from {here}: {reply.error}")
        await asyncio.sleep(PAUSE_S)
    if refused:
        b.failures.append(f"relocation: {len(refused)} refusals, e.g. {refused[0]}")
    return {"upstream": up, "downstream": down, "refused": refused}


async def phase_remap(
    b: Bench,
    name: str,
    placed: dict[str, str],
    chains: list[int],
    everything: bool,
    movers: list[str],
) -> dict[str, Any]:
    """Perturb one vertex of the remapped chains (untimed), then time the remap."""
    warm = await b.remap(chains, everything)  # untimed: establishes the remap's own placement
    if not warm.ok:
        b.failures.append(f"{name}: warm-up remap failed: {warm.error}")
        return {"samples": [], "moved": [], "perturb": [], "restored": 0}
    placed.update(warm.moved)
    home = dict(placed)
    samples: list[float] = []
    moved: list[int] = []
    perturb: list[float] = []
    restored = 0
    for i in range(b.runs):
        if b.late(name):
            break
        v = movers[i % len(movers)]
        candidates = [n for n in NODES if n != home[v]]
        target = candidates[(i // len(movers)) % len(candidates)]
        rr = await b.emu.relocate(CONVOY, v, target=target, via=placed[v])
        if not rr.ok:
            b.failures.append(f"{name} run {i}: perturbing {v} -> {target}: {rr.error}")
            continue
        perturb.append(rr.elapsed_ms)
        placed[v] = rr.node
        await asyncio.sleep(PAUSE_S)
        reply = await b.remap(chains, everything)
        if not reply.ok:
            b.failures.append(f"{name} run {i}: {reply.error}")
            continue
        samples.append(reply.elapsed_ms)
        moved.append(len(reply.moved))
        placed.update(reply.moved)
        if placed == home:
            restored += 1
        else:
            home = dict(placed)
        await asyncio.sleep(PAUSE_S)
    actual, _ = await b.app_view(CONVOY)
    if actual != placed:
        diff = {v: (placed.get(v), n) for v, n in actual.items() if placed.get(v) != n}
        b.failures.append(f"{name}: tracked placement differs from N1's view: {diff}")
        placed.clear()
        placed.update(actual)
    return {"samples": samples, "moved": moved, "perturb": perturb, "restored": restored}


async def phase_interruption(b: Bench) -> dict[str, Any]:
    """Relocate the relay between N2 and N3; the sink's largest gap across each move.

    The sink is read once the flow has resumed past the move (however long that takes, up to
    RESUME_S), so a stalled flow is measured, not skipped.
    """
    placed, _ = await b.app_view(BEATS)
    here = placed["relay"]
    gaps: list[float] = []
    by_dir: dict[str, list[float]] = {"upstream": [], "downstream": []}
    idle: list[float] = []
    elapsed: list[float] = []
    loop = asyncio.get_running_loop()
    for i in range(b.runs):
        if b.late("interruption"):
            break
        direction = "upstream" if here == placed["far"] else "downstream"
        t0 = time.time()
        reply = await b.emu.relocate(BEATS, "relay", direction=direction, via=placed["near"])
        t1 = time.time()
        if not reply.ok:
            b.failures.append(f"interruption run {i}: relay {direction}: {reply.error}")
            await asyncio.sleep(PAUSE_S)
            continue
        here = reply.node
        elapsed.append(reply.elapsed_ms)
        arrivals: list[float] = []
        until = loop.time() + RESUME_S
        for _ in range(200):
            await asyncio.sleep(SETTLE_S)
            stats = await b.sink()
            arrivals = [float(t) for t in stats["arrivals"]] if stats else []
            if (arrivals and arrivals[-1] > t1) or loop.time() > until:
                break
        gap = window_gap(arrivals, t0, t1)
        before = window_gap(arrivals, t0 - 0.06, t0 - 0.06 + (t1 - t0))
        if gap is None:
            b.failures.append(
                f"interruption run {i}: relay {direction}: no event at the sink within "
                f"{RESUME_S:g} s of the move (or its history does not cover the move)"
            )
        else:
            gaps.append(gap * 1e3 - PERIOD_MS)
            by_dir[direction].append(gaps[-1])
        if before is not None:
            idle.append(before * 1e3 - PERIOD_MS)
        await asyncio.sleep(0.1)  # the next idle window must not see this move
    return {"gaps": gaps, "idle": idle, "elapsed": elapsed, "by_direction": by_dir}


async def account(b: Bench, label: str) -> dict[str, Any]:
    """Pause the source until everything it emitted has arrived; count what the sink saw."""
    b.pause_file.touch()
    try:
        await asyncio.sleep(0.05)
        loop = asyncio.get_running_loop()
        deadline = loop.time() + 3.0
        src: dict[str, Any] | None = None
        sink: dict[str, Any] | None = None
        for _ in range(100):
            src = await b.vertex_stats("N1", "beat")
            sink = await b.sink()
            if src and sink and sink["count"] - sink["repeats"] >= src["sent"]:
                break
            if loop.time() > deadline:
                break
            await asyncio.sleep(0.05)
    finally:
        b.pause_file.unlink(missing_ok=True)
    if src is None or sink is None:
        b.failures.append(f"events ({label}): no stats from the measurement app")
        return {}
    unique = sink["count"] - sink["repeats"]
    result = {
        "emitted": src["sent"],
        "delivered": sink["count"],
        "lost": src["sent"] - unique,
        "duplicated": sink["repeats"],
        "reordered": sink["out_of_order"],
        "relay_state_errors": sink["relay_mismatch"],
        "max_gap_ms": sink["max_gap_ms"],
    }
    bad = {k: result[k] for k in ("lost", "duplicated", "reordered", "relay_state_errors")}
    if any(bad.values()):
        b.failures.append(f"events ({label}): {bad}")
    return result


async def phase_stop_redeploy(b: Bench) -> dict[str, Any]:
    """Undeploy the measurement app and deploy it again with the relay on the other node."""
    placed, _ = await b.app_view(BEATS)
    relay_node = placed["relay"]
    gaps: list[float] = []
    lower: list[float] = []
    redeploy_ms: list[float] = []
    instances: list[dict[str, Any]] = []
    for i in range(b.runs):
        if b.late("stop_and_redeploy"):
            break
        before = await b.sink()
        if before is None or not before["count"]:
            b.failures.append(f"stop_and_redeploy run {i}: the sink has not received anything")
            break
        t_stop = time.time()
        await b.emu.undeploy(BEATS, "N1")
        instances.append({k: before[k] for k in ("count", "repeats", "out_of_order")})
        instances[-1]["relay_state_errors"] = before["relay_mismatch"]
        if not await b.wait_gone(BEATS):
            b.failures.append(f"stop_and_redeploy run {i}: undeploy did not reach every node")
            break
        relay_node = "N3" if relay_node == "N2" else "N2"
        doc = beats_document(str(b.pause_file), relay_node)
        reply = await b.deploy(doc, "beats.yaml")
        if not reply.ok or reply.placement.get("relay") != relay_node:
            b.failures.append(f"stop_and_redeploy run {i}: {reply.error or reply.placement}")
            break
        redeploy_ms.append(reply.elapsed_ms)
        after: dict[str, Any] | None = None
        for _ in range(400):
            after = await b.sink()
            if after is not None and after["count"]:
                break
            await asyncio.sleep(0.005)
        if after is None or not after["count"]:
            b.failures.append(f"stop_and_redeploy run {i}: no event at the new sink in time")
            break
        gaps.append((after["first"] - before["last"]) * 1e3 - PERIOD_MS)
        lower.append((after["first"] - t_stop) * 1e3 - PERIOD_MS)
        await asyncio.sleep(0.1)  # flowing again before the next stop
    return {"gaps": gaps, "lower": lower, "redeploy_ms": redeploy_ms, "instances": instances}


def node_log_errors(emu: Emulator) -> dict[str, list[str]]:
    """The last error lines of each node's log (the logs go away with the emulator)."""
    out: dict[str, list[str]] = {}
    for name, node in emu.nodes.items():
        if node.log is None or not node.log.exists():
            continue
        lines = node.log.read_text(errors="replace").splitlines()
        hits = [ln for ln in lines if "Error" in ln or "ERROR" in ln or "Traceback" in ln]
        if hits:
            out[name] = hits[-6:]
    return out


def _first_chain(chains: list[list[str]], head: str, tail: str | None = None) -> int:
    for i, c in enumerate(chains):
        if c[0] == head and (tail is None or c[-1] == tail):
            return i
    raise MsoError(f"no chain from {head!r} in {chains}")


async def measure(
    scenario: Scenario,
    runs: int,
    budget_s: float,
    backend: str = "user",
    progress: Progress | None = None,
) -> dict[str, Any]:
    """Every measurement on one emulated line (``backend`` netns: namespaces and babeld)."""
    step = progress or Progress("table1", quiet=True)
    logs = tempfile.TemporaryDirectory(prefix="mso-bench-table1-")
    pause = Path(logs.name) / "beats.pause"
    kind: type[Emulator] = Emulator
    if backend == "netns":
        from mso.emu.netns.emulator import NetnsEmulator

        kind = NetnsEmulator
    emu = kind(scenario, log_dir=Path(logs.name), manage=False)  # operations alone
    b = Bench(emu, runs, time.monotonic() + budget_s, pause, APP_FILE.read_text(encoding="utf-8"))
    out: dict[str, Any] = {"scenario": scenario.name}
    t_start = time.monotonic()
    mapping: list[float] = []
    mapping_wall: list[float] = []
    reloc: dict[str, Any] = {"upstream": [], "downstream": [], "refused": []}
    no_remap: dict[str, Any] = {"samples": [], "moved": [], "perturb": [], "restored": 0}
    chain_r = part_r = whole_r = no_remap
    inter: dict[str, Any] = {
        "gaps": [],
        "idle": [],
        "elapsed": [],
        "by_direction": {"upstream": [], "downstream": []},
    }
    events: dict[str, Any] = {}
    sr: dict[str, Any] = {"gaps": [], "lower": [], "redeploy_ms": [], "instances": []}
    final: dict[str, Any] = {}
    try:
        step(f"starting {len(scenario.network.nodes)} node processes ({backend} backend)")
        await emu.start()
        step("cold deployment of the convoy")
        # cold deployment (imports the vertex code on every node; not in the statistics), and
        # the node that coordinates remaps
        reply = await b.deploy(b.convoy_doc, str(APP_FILE))
        if not reply.ok:
            raise MsoError(f"convoy deployment failed: {reply.error}")
        out["cold_mapping_ms"] = reply.elapsed_ms
        _, chains = await b.app_view(CONVOY)
        await pick_remap_via(b, _first_chain(chains, "laser"))
        await emu.undeploy(CONVOY, "N1")
        if not await b.wait_gone(CONVOY):
            raise MsoError("the convoy did not go away")
        # the measurement app runs from here to the end
        reply = await b.deploy(beats_document(str(pause)), "beats.yaml")
        if not reply.ok:
            raise MsoError(f"measurement app deployment failed: {reply.error}")
        out["beats_placement"] = reply.placement
        await asyncio.sleep(0.5)

        step(f"mapping, {runs} runs")
        mapping, mapping_wall = await phase_mapping(b)

        reply = await b.deploy(b.convoy_doc, str(APP_FILE))  # stays, flowing at the paper's rates
        if not reply.ok:
            raise MsoError(f"convoy deployment failed: {reply.error}")
        await asyncio.sleep(1.0)
        placed, chains = await b.app_view(CONVOY)
        out["convoy_placement"] = dict(placed)
        out["convoy_chains"] = chains
        laser = _first_chain(chains, "laser")
        nav = [_first_chain(chains, h, t) for h, t in NAVIGATION]
        step(f"upstream and downstream relocations, {runs} runs each")
        reloc = await phase_relocation(b, placed, chains[laser])
        chain_movers = interior(chains[laser])
        nav_movers = [v for c in nav for v in interior(chains[c])]
        all_movers = [v for c in chains for v in interior(c)]
        step(f"chain remaps, {runs} runs")
        chain_r = await phase_remap(b, "chain_remapping", placed, [laser], False, chain_movers)
        step(f"global remaps of part of the app, {runs} runs")
        part_r = await phase_remap(b, "global_remapping_part", placed, nav, False, nav_movers)
        step(f"global remaps of the whole app, {runs} runs")
        whole_r = await phase_remap(b, "global_remapping_whole", placed, [], True, all_movers)

        step("interruption of the flow by a relocation")
        inter = await phase_interruption(b)
        events = await account(b, "relocations")
        await asyncio.sleep(0.2)
        step("interruption by stop and redeploy, for comparison")
        sr = await phase_stop_redeploy(b)
        final = await account(b, "last redeployed instance")

        conv = (await b.node_status("N1"))["apps"][CONVOY]["edges"]
        out["convoy_source_rates"] = {
            e: round(d["events_per_s"], 2) for e, d in conv.items() if e.split("->")[0] in
            ("laser", "odometry", "visible_camera", "infrared_camera")
        }  # fmt: skip
    except (MsoError, NodeUnreachable, TimeoutError, KeyError) as exc:
        b.failures.append(f"aborted: {type(exc).__name__}: {exc}")
        step(f"aborted: {type(exc).__name__}: {exc}")
    finally:
        step("stopping the node processes")
        await emu.stop()
        out["node_log_errors"] = node_log_errors(emu)
        logs.cleanup()

    ops = {
        "mapping": mapping,
        "upstream_relocation": reloc["upstream"],
        "downstream_relocation": reloc["downstream"],
        "chain_remapping": chain_r["samples"],
        "global_remapping_part": part_r["samples"],
        "global_remapping_whole": whole_r["samples"],
    }
    out["operations"] = {k: summary(v) for k, v in ops.items()}
    for name, r in (
        ("chain_remapping", chain_r),
        ("global_remapping_part", part_r),
        ("global_remapping_whole", whole_r),
    ):
        out["operations"][name] |= {
            "runs_moved": sum(1 for k in r["moved"] if k),
            "vertices_moved_mean": statistics.fmean(r["moved"]) if r["moved"] else 0.0,
            "runs_restored": r["restored"],
        }
    out["operations"]["mapping"]["wall"] = summary(mapping_wall)
    rel = summary(inter["gaps"])
    sr_s = summary(sr["gaps"])
    out["interruption_ms"] = {
        "relocation": rel,
        "stop_and_redeploy": sr_s,
        "relocation_idle_baseline": summary(inter["idle"]),
        "stop_and_redeploy_lower_bound": summary(sr["lower"]),
        "relocation_upstream": summary(inter["by_direction"]["upstream"]),
        "relocation_downstream": summary(inter["by_direction"]["downstream"]),
        "relocation_stalls": {
            "threshold_ms": STALL_MS,
            "upstream": sum(1 for g in inter["by_direction"]["upstream"] if g > STALL_MS),
            "downstream": sum(1 for g in inter["by_direction"]["downstream"] if g > STALL_MS),
        },
        "ratio_mean": _ratio(sr_s["mean_ms"], rel["mean_ms"]),
        "ratio_p50": _ratio(sr_s["p50_ms"], rel["p50_ms"]),
        "nominal_period_ms": PERIOD_MS,
    }
    out["events"] = events
    instances = sr["instances"]
    out["events_stop_and_redeploy"] = {
        "instances_stopped": len(instances),
        "duplicated": sum(x["repeats"] for x in instances),
        "reordered": sum(x["out_of_order"] for x in instances),
        "relay_state_errors": sum(x["relay_state_errors"] for x in instances),
        "last_instance": final,
        "note": "events in flight when an instance is stopped are discarded by design",
    }
    out["extra"] = {
        "targeted_relocation_ms": summary(
            chain_r["perturb"] + part_r["perturb"] + whole_r["perturb"]
        ),
        "relay_relocation_ms": summary(inter["elapsed"]),
        "beats_redeploy_ms": summary(sr["redeploy_ms"]),
        "refused_relocations": reloc["refused"],
        "samples_ms": ops,
    }
    out["remap_via"] = b.remap_via
    out["notes"] = b.notes
    out["failures"] = b.failures
    out["seconds"] = time.monotonic() - t_start
    return out


def _ratio(num: float | None, den: float | None) -> float | None:
    if num is None or den is None:
        return None
    return num / max(den, 0.01)


def _f(x: float | None, digits: int = 1) -> str:
    return "-" if x is None else f"{x:,.{digits}f}"


def render(result: dict[str, Any]) -> str:
    ops = result["operations"]
    lines = [
        "| Operation (convoy, 4-node line) | mean ms | σ ms | p50 ms | p99 ms | n "
        "| paper mean ms | paper σ ms | ratio mean/paper | target p50 |",
        "|---|---:|---:|---:|---:|---:|---:|---:|---:|---|",
    ]
    for op in OPERATIONS:
        s = ops[op]
        pm, ps = PAPER_MS[op]
        ratio = "-" if s["mean_ms"] is None else f"{s['mean_ms'] / pm:.4f}"
        tgt = TARGET_P50_MS.get(op)
        verdict = "-"
        if tgt is not None and s["p50_ms"] is not None:
            verdict = f"<= {tgt:g} ms: {'met' if s['p50_ms'] <= tgt else 'MISSED'}"
        lines.append(
            f"| {LABELS[op]} | {_f(s['mean_ms'], 2)} | {_f(s['std_ms'], 2)} "
            f"| {_f(s['p50_ms'], 2)} | {_f(s['p99_ms'], 2)} | {s['n']} | {pm:,.1f} | {ps} "
            f"| {ratio} | {verdict} |"
        )
    un = result.get("unshaped")
    ns = result.get("netns")
    titles = {
        "unshaped": "(mso's own cost, no link emulation)",
        "netns": "on the netns backend (a namespace per node, babeld routes, the kernel "
        "forwards; tbf 100 Mbit/s, no delay: no netem here)",
    }
    for key, other in (("unshaped", un), ("netns", ns)):
        if not other:
            continue
        lines += ["", f"Same runs, {other['scenario']} {titles[key]}:", ""]
        lines += [
            "| Operation | mean ms | σ ms | p50 ms | p99 ms | n | ratio mean/paper |",
            "|---|---:|---:|---:|---:|---:|---:|",
        ]
        for op in OPERATIONS:
            s = other["operations"][op]
            ratio = "-" if s["mean_ms"] is None else f"{s['mean_ms'] / PAPER_MS[op][0]:.4f}"
            lines.append(
                f"| {LABELS[op]} | {_f(s['mean_ms'], 2)} | {_f(s['std_ms'], 2)} "
                f"| {_f(s['p50_ms'], 2)} | {_f(s['p99_ms'], 2)} | {s['n']} | {ratio} |"
            )
    lines += [
        "",
        f"Interruption of a {BEAT_RATE:g} events/s flow at its sink (largest inter-arrival gap "
        f"minus the nominal {PERIOD_MS:g} ms):",
        "",
        "| Interruption | mean ms | σ ms | p50 ms | p99 ms | max ms | n |",
        "|---|---:|---:|---:|---:|---:|---:|",
    ]
    variants = (
        [("", result)] + ([(" (unshaped)", un)] if un else []) + ([(" (netns)", ns)] if ns else [])
    )
    for suffix, r in variants:
        it = r["interruption_ms"]
        for key, label in (
            ("relocation", "relocation of the relay"),
            ("relocation_upstream", "- upstream moves (onto its producer's node)"),
            ("relocation_downstream", "- downstream moves"),
            ("relocation_idle_baseline", "no operation (same-length window before it)"),
            ("stop_and_redeploy", "stop and redeploy"),
            ("stop_and_redeploy_lower_bound", "stop and redeploy, from the stop request"),
        ):
            s = it[key]
            lines.append(
                f"| {label}{suffix} | {_f(s['mean_ms'], 2)} | {_f(s['std_ms'], 2)} "
                f"| {_f(s['p50_ms'], 2)} | {_f(s['p99_ms'], 2)} | {_f(s['max_ms'], 2)} "
                f"| {s['n']} |"
            )
    lines.append("")
    for suffix, r in variants:
        it = r["interruption_ms"]
        rel, sr = it["relocation"], it["stop_and_redeploy"]
        if rel["p50_ms"] is not None and sr["p50_ms"] is not None:
            ok_gap = rel["p50_ms"] <= TARGET_GAP_MS
            ok_ratio = (it["ratio_p50"] or 0) >= TARGET_GAP_RATIO
            lines.append(
                f"- interruption{suffix}: relocation p50 {rel['p50_ms']:.2f} ms (target <= "
                f"{TARGET_GAP_MS:g} ms: {'met' if ok_gap else 'MISSED'}); stop-and-redeploy / "
                f"relocation = {it['ratio_p50']:.0f}x at p50, {it['ratio_mean']:.0f}x at the mean "
                f"(target >= {TARGET_GAP_RATIO:g}x: {'met' if ok_ratio else 'MISSED'})"
            )
        st = it["relocation_stalls"]
        lines.append(
            f"- interruption{suffix}: relocations that stalled the flow for more than "
            f"{st['threshold_ms']:g} ms: {st['upstream']} upstream, {st['downstream']} downstream "
            f"(of {it['relocation_upstream']['n']} and {it['relocation_downstream']['n']})"
        )
        ev = r["events"]
        if ev:
            lines.append(
                f"- events{suffix} (measurement app, through every operation but "
                f"stop-and-redeploy): emitted {ev['emitted']}, delivered {ev['delivered']}, lost "
                f"{ev['lost']}, duplicated {ev['duplicated']}, reordered {ev['reordered']}, relay "
                f"state errors {ev['relay_state_errors']}"
            )
        es = r["events_stop_and_redeploy"]
        lines.append(
            f"- events{suffix} over {es['instances_stopped']} stop-and-redeploys: duplicated "
            f"{es['duplicated']}, reordered {es['reordered']}, relay state errors "
            f"{es['relay_state_errors']} (in-flight events of a stopped instance are discarded "
            "by design)"
        )
        for name in ("chain_remapping", "global_remapping_part", "global_remapping_whole"):
            s = r["operations"][name]
            lines.append(
                f"- {LABELS[name]}{suffix}: {s['runs_moved']}/{s['n']} runs moved vertices "
                f"(mean {s['vertices_moved_mean']:.2f}), {s['runs_restored']} restored the "
                "placement before the perturbation"
            )
        lines.append(f"- remaps{suffix} coordinated by {r['remap_via']}")
        for note in r["notes"]:
            lines.append(f"- note{suffix}: {note}")
        for fail in r["failures"]:
            lines.append(f"- FAILURE{suffix}: {fail}")
    lines.append(
        "- paper: 350 MHz Xeons, gSOAP control plane, 100 Mbit/s Ethernet; ratio = ours / paper"
    )
    return "\n".join(lines) + "\n"


async def run(
    runs: int = 30,
    quick: bool = False,
    variants: bool = True,
    netns: bool = False,
    progress: Progress | None = None,
) -> dict[str, Any]:
    """Every Table 1 operation ``runs`` times (``quick``: 5, the specified line only);
    ``netns``: the same runs again on the netns backend, in the same run."""
    if quick:
        runs = min(runs, 5)
    t0 = time.monotonic()
    budget = QUICK_DEADLINE_S if quick else DEADLINE_S
    main_result = await measure(load_scenario(SCENARIO_FILE), runs, budget, progress=progress)
    result: dict[str, Any] = {
        "benchmark": "table1",
        "operations": main_result.pop("operations"),
        "interruption_ms": main_result.pop("interruption_ms"),
        "events": main_result.pop("events"),
    }
    result |= main_result
    if variants and not quick:
        if progress:
            progress("the same on unshaped links")
        result["unshaped"] = await measure(
            unshaped(load_scenario(SCENARIO_FILE)), runs, budget, progress=progress
        )
    if netns:
        from mso.emu.netns.emulator import check_available

        check_available()
        result["netns"] = await measure(
            load_scenario(SCENARIO_FILE), runs, budget, "netns", progress=progress
        )
    result["paper_ms"] = {k: {"mean_ms": v[0], "std_ms": v[1]} for k, v in PAPER_MS.items()}
    result["ratio_to_paper"] = {
        k: (None if s["mean_ms"] is None else s["mean_ms"] / PAPER_MS[k][0])
        for k, s in result["operations"].items()
    }
    result["targets"] = {
        "p50_ms": TARGET_P50_MS,
        "relocation_interruption_ms": TARGET_GAP_MS,
        "stop_and_redeploy_over_relocation": TARGET_GAP_RATIO,
    }
    result["runs"] = runs
    result["quick"] = quick
    result |= provenance()
    result["app"] = "mso/examples/convoy.yaml"
    result["scenario_file"] = "mso/examples/convoy-line.yaml"
    result["seconds"] = time.monotonic() - t0
    return result


def _default_json(quick: bool) -> Path:
    root = Path(__file__).resolve().parents[3]
    results = root / "bench" / "results"
    name = "table1.quick.json" if quick else "table1.json"
    return results / name if results.parent.is_dir() else Path(name)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=(__doc__ or "").split("\n")[0])
    ap.add_argument("--runs", type=int, default=30, help="runs of each operation (>= 30)")
    ap.add_argument("--quick", action="store_true", help="smoke run: 5 runs, no unshaped variant")
    ap.add_argument("--no-variants", action="store_true", help="skip the unshaped-links variant")
    ap.add_argument("--json", type=Path, help="where to write the JSON (a .md goes beside it)")
    ap.add_argument(
        "--netns",
        action="store_true",
        help="also run on the netns backend (root or a user namespace; babeld), in this run",
    )
    ap.add_argument("--quiet", action="store_true", help="no progress lines on stderr")
    args = ap.parse_args(argv)
    if not 1 <= args.runs <= 1000:
        ap.error("--runs: 1..1000")
    out: Path = args.json or _default_json(args.quick)
    progress = Progress("table1", quiet=args.quiet)
    result = asyncio.run(
        run(
            args.runs,
            args.quick,
            variants=not args.no_variants,
            netns=args.netns,
            progress=progress,
        )
    )
    table = render(result)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(result, indent=2) + "\n")
    out.with_suffix(".md").write_text(table)
    print(table)
    print(f"written: {out} and {out.with_suffix('.md')} ({result['seconds']:.0f} s)")
    failures = (
        result["failures"]
        + (result.get("unshaped") or {}).get("failures", [])
        + (result.get("netns") or {}).get("failures", [])
    )
    return 1 if failures else 0


if __name__ == "__main__":
    sys.exit(main())
