"""Table 1's operations, each timed ``runs`` times on a running line: mapping, relocations,
remaps, and the measurement app's interruption by a relocation and by a stop-and-redeploy.
:class:`Bench` is the state they share and the few requests they make, through :mod:`mso.api`
over the emulator's kept connections (a timed call pays no connect): a refusal's reply is
recorded as a failure of the run, not raised.
"""

from __future__ import annotations

import asyncio
import itertools
import json
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import mso.examples
from mso.client import NodeUnreachable
from mso.emu.controller import Emulator
from mso.errors import MsoError
from mso.model.appfile import loads_app
from mso.protocol import messages as m

MODULE = "mso.benchmarks.vertices.table1"  # the measurement app's vertex code

EXAMPLES = Path(mso.examples.__file__).resolve().parent
APP_FILE = EXAMPLES / "convoy.yaml"
SCENARIO_FILE = EXAMPLES / "convoy-line.yaml"
CONVOY = "convoy"
BEATS = "beats"
BEAT_RATE = 200.0
PERIOD_MS = 1e3 / BEAT_RATE
NODES = ("N1", "N2", "N3", "N4")
PAUSE_S = 0.02  # between operations
SETTLE_S = 0.04  # after a relocation of the relay, before its sink is read
RESUME_S = 3.0  # how long the flow may take to resume after a relocation


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
        nodes = await self.emu.overlay(node).status(everywhere=False, timeout=5.0)
        status: dict[str, Any] = nodes[node]
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

    async def deploy(self, document: str, file: str, *, check: bool = False) -> m.DeployReply:
        """Deploy from N1; ``check``: a failure raises (the setup cannot go on without it)."""
        return await asyncio.wait_for(self.emu.deploy(document, file, "N1", check=check), 30.0)

    async def remap(self, chains: list[int], everything: bool = False) -> m.RemapReply:
        """Remap through :attr:`remap_via`, waiting up to 30 s: a whole-app remap is slow."""
        ov = self.emu.overlay(self.remap_via)
        return await ov.remap(
            CONVOY, chains=chains, everything=everything, check=False, timeout=30.0
        )


async def trial_remap(emu: Emulator, node: str, chain: int) -> m.RemapReply:
    """An untimed no-op remap of ``chain`` coordinated by ``node``, on a connection of its own,
    so a node that drops the connection does not take the emulator's connection with it."""
    ov = await emu.open_overlay(node, "table1-remap-trial", timeout=2.0)
    try:
        return await ov.remap(CONVOY, chains=[chain], check=False, timeout=10.0)
    finally:
        await ov.close()


async def pick_remap_via(b: Bench, chain: int) -> None:
    """The node remaps are sent to: N1 if it can coordinate one, else the first node that can
    (each tried once, with :func:`trial_remap`)."""
    for node in ("N1", "N4", "N3", "N2"):
        try:
            reply = await trial_remap(b.emu, node, chain)
        except NodeUnreachable as exc:
            b.notes.append(
                f"a remap coordinated by {node} failed ({exc}); see node_log_errors in the JSON"
            )
            continue
        if reply.ok:
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
