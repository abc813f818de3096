"""Faults under a running app: a relay killed, its mso node crashed on a live router, a node
partitioned then healed, a route the routing daemon starves -- on the user-space backend and on
netns with babeld or batmand. Detection time, recovery time, recoveries failing within 12 s,
events lost and duplicated.

The app ``src -> mid -> sink`` (``vertices.failure``: a counting source at 200 events/s pinned to
the first node, a stateless pass-through ``mid`` left unpinned, a gap-timing sink pinned to the
last node) runs on an emulated topology, one ``mso node`` process per node:

* ``mesh``: 6 nodes, links N1-N2, N2-N3, N3-N6, N1-N4, N4-N5, N5-N6, N2-N5, N3-N5; ``mid`` lands
  on an interior node (N3 or N5) and the others survive it;
* ``line``: a convoy of 5 robots R1..R5 100 m apart with ``radio_range: 250``; ``mid`` on R3,
  and killing R3 leaves R1-R2-R4-R5.

Each run starts a fresh emulator (management rules off, so only the fault moves ``mid``),
deploys the app via the first node, lets it flow for 1.5 s, then injects the fault on the node
hosting ``mid`` (the *victim*, read from the placement just before):

* ``kill``: the device dies (``Emulator.kill``: SIGKILL to the node process and, on netns, its
  routing daemon);
* ``crash``: only the ``mso node`` process dies; its links stay, and on netns its routing daemon
  keeps routing (a daemon that never drops the node: only mso's own heartbeats can tell);
* ``partition``: every link of the victim goes down for ``--hold`` seconds (default twice the
  failure timeout, at least 2 s), then comes back; lost and duplicated are counted after the
  heal, once the victim is back;
* ``starve`` (netns): the kernel of the victim loses its route to the sink's node for
  ``--starve-s`` seconds (60) while the routing daemon keeps its own: a policy rule sends the
  address to a table that says ``unreachable``, what babeld's starvation looks like to mso. In
  even runs both ends lose the route, in odd runs only the victim (no return route). mso should
  relay at the overlay (through a node whose kernel still reaches the sink) and lose nothing;
  nobody should be declared failed.

It polls the sink's node (its own status) until the sink has received a good half second of
events after the fault (at most 12 s), reads the source's ``emitted`` and waits (at most 3 s)
until the sink has everything up to it. Figures per run:

* detection_ms: the earliest ``failures[*].at`` for the victim over the survivors minus the fault
  time (node loop times and the controller's are the same CLOCK_MONOTONIC);
* recovery_ms: the largest inter-arrival gap at the sink that ends after the fault (for
  ``starve``: during the starvation); a run whose flow did not resume within 12 s counts in
  ``unrecovered`` (and fails);
* lost: events the source emitted that the sink never got (target 0); duplicated: events the
  sink got twice (target 0); relayed: bytes the nodes forwarded at the overlay (the kernel
  forwards otherwise).

Results go to ``bench/results/failure.json`` / ``.md``, one cell per (setup, fault, topology),
merged with the cells already there (so the cells can be measured one invocation at a time);
``--json FILE`` writes elsewhere. ``--heartbeat``/``--dead-after``/``--convergence`` set the
detection and the user-space routing delay (netns defaults: heartbeat 0.2 s, 3 s).

Usage: .venv/bin/python bench/failure.py [--backend user|netns] [--routing babeld|batmand]
          [--case kill,crash,partition,starve] [--topology mesh,line] [--runs 20] [--quick]
          [--starve-s 60] [--hold S] [--convergence 0] [--heartbeat S] [--dead-after S]
"""

from __future__ import annotations

import argparse
import asyncio
import json
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from mso.benchmarks.common import percentile, provenance, write_results
from mso.emu.controller import Emulator
from mso.emu.netns.emulator import DEAD_AFTER_NETNS_S, HEARTBEAT_NETNS_S
from mso.errors import MsoError
from mso.model.network import LinkSpec
from mso.scenario import loads_scenario

HERE = Path(__file__).resolve().parent
RESULTS = HERE / "results"
VERTICES = "mso.benchmarks.vertices.failure"  # the vertex code the nodes import
APP = "fail"
RATE = 200.0
STEADY_S = 1.5  # flow before the kill
RECOVER_S = 12.0  # bound on waiting for the flow to resume: a longer outage is a failure
DRAIN_S = 3.0  # bound on waiting for in-flight events after it resumed
REJOIN_S = 3.0  # after a partition heals: time for the victim to rejoin before counting
POLL_S = 0.05
RUN_TIMEOUT_S = 60.0  # a whole run (start, deploy, fault, recover, drain, stop) ...
RUN_BUDGET_S = 25.0  # per planned run: no run starts once runs x this has passed
CASES = ("kill", "crash", "partition", "starve")
NETNS_DETECTION = (HEARTBEAT_NETNS_S, DEAD_AFTER_NETNS_S)
STARVE_TABLE = 199  # the policy table a starved route is sent to (holds "unreachable")
STARVE_PREF = 100  # ahead of main (32766) and batmand's rules (6600)

TOPOLOGIES: dict[str, tuple[str, str, str]] = {  # name -> (scenario, first node, last node)
    "line": (
        """\
name: convoy5
link_defaults: {bandwidth_mbps: 54, delay_ms: 0.5}
radio_range: 250
nodes:
  R1: {pos: [0, 0]}
  R2: {pos: [100, 0]}
  R3: {pos: [200, 0]}
  R4: {pos: [300, 0]}
  R5: {pos: [400, 0]}
""",
        "R1",
        "R5",
    ),
    "mesh": (
        """\
name: mesh
link_defaults: {delay_ms: 0.5}
nodes: {N1: {}, N2: {}, N3: {}, N4: {}, N5: {}, N6: {}}
links: [[N1, N2], [N2, N3], [N3, N6], [N1, N4], [N4, N5], [N5, N6], [N2, N5], [N3, N5]]
""",
        "N1",
        "N6",
    ),
}


def app_yaml(first: str, last: str, rate: float) -> str:
    """src (pinned to ``first``) -> mid (unpinned) -> sink (pinned to ``last``)."""
    fmt = f"{VERTICES}:Seq"
    return f"""\
name: {APP}
planner: paper  # mid on an interior node, the victim (bytes: on the source's node)
vertices:
  src:  {{code: {VERTICES}:CountingSource, pinned: {first}, rate: {rate:g},
         output: {fmt}}}
  mid:  {{code: {VERTICES}:PassThrough, input: {fmt}, output: {fmt}}}
  sink: {{code: {VERTICES}:GapSink, pinned: {last}, input: {fmt}}}
edges:
  - [src, mid]
  - [mid, sink]
"""


def summary(values: list[float]) -> dict[str, Any]:
    """mean / p50 / p99 / max (and min, n) of a list, None when it is empty."""
    if not values:
        return {"mean": None, "p50": None, "p99": None, "max": None, "min": None, "n": 0}
    return {
        "mean": statistics.fmean(values),
        "p50": percentile(values, 50),
        "p99": percentile(values, 99),
        "max": max(values),
        "min": min(values),
        "n": len(values),
    }


async def node_status(emu: Emulator, node: str) -> dict[str, Any]:
    """One node's own status (not ``everywhere``: that waits up to 1 s for a dead node)."""
    nodes = await emu.overlay(node).status(everywhere=False, timeout=5.0)
    st: dict[str, Any] = nodes[node]
    return st


def vertex(st: dict[str, Any], name: str) -> dict[str, Any]:
    """A vertex's status entry on a node ({} if the node does not host it)."""
    v: dict[str, Any] = st.get("apps", {}).get(APP, {}).get("vertices", {}).get(name, {})
    return v


def outage(stats: dict[str, Any], kill_t: float) -> tuple[float, float] | None:
    """The largest recorded gap that ends after the kill: (last before, first after)."""
    after_kill = [(b, a) for b, a in stats.get("gaps", []) if a > kill_t]
    if not after_kill:
        return None
    return max(after_kill, key=lambda g: g[1] - g[0])


def log_lines(emu: Emulator, limit: int = 12) -> dict[str, list[str]]:
    """The last warning/error lines of each node's log (they go with the emulator)."""
    words = ("Error", "ERROR", "WARNING", "Traceback", "failed", "refused")
    out: dict[str, list[str]] = {}
    for name, node in emu.nodes.items():
        if node.log is None or not node.log.exists():
            continue
        lines = node.log.read_text(errors="replace").splitlines()
        hits = [ln for ln in lines if any(w in ln for w in words)]
        if hits:
            out[name] = hits[-limit:]
    return out


class Setup:
    """What a cell runs on: the backend, its routing daemon, detection and convergence."""

    def __init__(
        self,
        backend: str,
        routing: str,
        convergence: float,
        rate: float,
        detection: tuple[float, float],
        hold_s: float,
        starve_s: float,
    ) -> None:
        self.backend, self.routing = backend, routing
        self.convergence, self.rate = convergence, rate
        self.detection = detection
        self.hold_s, self.starve_s = hold_s, starve_s

    @property
    def label(self) -> str:
        """The cell's setup: backend (and daemon), and detection when not its default."""
        base = "user" if self.backend == "user" else f"netns-{self.routing}"
        default = (0.1, 0.5) if self.backend == "user" else NETNS_DETECTION
        if self.detection != default:
            base += f" hb{self.detection[0]:g}/dead{self.detection[1]:g}"
        if self.convergence:
            base += f" conv{self.convergence:g}"
        return base

    def emulator(self, topology: str, log_dir: Path) -> Emulator:
        scenario = loads_scenario(TOPOLOGIES[topology][0])
        kw: dict[str, Any] = {
            "convergence_s": self.convergence,
            "log_dir": log_dir,
            "manage": False,
            "heartbeat_s": self.detection[0],
            "dead_after_s": self.detection[1],
        }
        if self.backend == "netns":  # a namespace per node, the daemon, the kernel view
            from mso.emu.netns.emulator import NetnsEmulator

            return NetnsEmulator(scenario, routing=self.routing, **kw)
        return Emulator(scenario, **kw)


def crash(emu: Emulator, victim: str) -> tuple[float, Any]:
    """Kill only the node process; its links (and its routing daemon) stay. The emulator's
    watcher must not see it die (it would take the links away), so the process is hidden from
    it until the run ends; returns the time and the process."""
    node = emu.nodes[victim]
    proc, node.process = node.process, None
    assert proc is not None
    proc.kill()
    proc.wait(timeout=5)
    return asyncio.get_running_loop().time(), proc


async def cut(emu: Emulator, victim: str) -> list[LinkSpec]:
    """Take every link of ``victim`` down at once; returns them, to heal with."""
    net = emu.scenario.network
    links = [spec for (a, b), spec in net.links.items() if victim in (a, b)]
    for spec in links:
        net.remove_link(spec.a, spec.b)
    await emu._links_changed()
    return links


async def heal(emu: Emulator, links: list[LinkSpec]) -> None:
    for spec in links:
        emu.scenario.network.add_link(spec)
    await emu._links_changed()


def starve(emu: Emulator, node: str, dst: str, on: bool) -> None:
    """On ``node``'s kernel, send ``dst``'s address to a table saying unreachable (or stop)."""
    from mso.emu.netns.emulator import NetnsEmulator

    assert isinstance(emu, NetnsEmulator) and emu.testbed is not None
    ns, addr = emu.testbed.netns(node), emu.testbed.address(dst)
    ip = ["ip", "-n", ns]
    if on:
        cmds = [
            [*ip, "route", "replace", "unreachable", f"{addr}/32", "table", str(STARVE_TABLE)],
            [*ip, "rule", "add", "to", f"{addr}/32", "lookup", str(STARVE_TABLE), "pref",
             str(STARVE_PREF)],
        ]  # fmt: skip
    else:
        cmds = [
            [*ip, "rule", "del", "pref", str(STARVE_PREF)],
            [*ip, "route", "flush", "table", str(STARVE_TABLE)],
        ]
    for cmd in cmds:
        proc = subprocess.run(cmd, capture_output=True, text=True)
        if proc.returncode != 0 and on:
            raise MsoError(f"{' '.join(cmd)}: {proc.stderr.strip()}")


async def sink_stats(emu: Emulator, last: str) -> dict[str, Any]:
    stats: dict[str, Any] = vertex(await node_status(emu, last), "sink").get("stats", {})
    return stats


async def wait_resumed(
    emu: Emulator, last: str, since: float, want: int, bound: float
) -> dict[str, Any] | None:
    """Poll the sink until it has ``want`` events and a gap after ``since`` it has left behind;
    None if that did not happen within ``bound`` seconds of ``since``."""
    loop = asyncio.get_running_loop()
    while loop.time() < since + bound:
        await asyncio.sleep(POLL_S)
        stats = await sink_stats(emu, last)
        gap = outage(stats, since)
        if stats.get("count", 0) >= want and gap is not None and stats["last"] > gap[1]:
            return stats
    return None


async def drain(emu: Emulator, first: str, last: str) -> tuple[int, dict[str, Any]]:
    """Everything the source has emitted so far reaches the sink (at most DRAIN_S)."""
    loop = asyncio.get_running_loop()
    emitted = int(vertex(await node_status(emu, first), "src").get("emitted", 0))
    deadline = loop.time() + DRAIN_S
    stats: dict[str, Any] = {}
    while loop.time() < deadline:
        stats = await sink_stats(emu, last)
        if stats.get("next", 0) >= emitted and not stats.get("missing", 0):
            break
        await asyncio.sleep(POLL_S)
    return emitted, stats


async def one_run(setup: Setup, case: str, topology: str, k: int, logs: Path) -> dict[str, Any]:
    """One fresh emulator: deploy, flow, inject ``case`` on the node hosting ``mid``, measure."""
    _, first, last = TOPOLOGIES[topology]
    row: dict[str, Any] = {"case": case, "topology": topology, "run": k, "error": None}
    log_dir = logs / f"{case}-{topology}-{k}"
    log_dir.mkdir()
    emu = setup.emulator(topology, log_dir)
    loop = asyncio.get_running_loop()
    hidden: tuple[str, Any] | None = None
    try:
        await emu.start()
        app = app_yaml(first, last, setup.rate)
        reply = await emu.deploy(app, "failure.yaml", first, check=True)
        row["placed"] = reply.placement["mid"]
        await asyncio.sleep(STEADY_S)
        before = await node_status(emu, first)
        victim = before["apps"][APP]["placement"]["mid"]
        row["victim"] = victim
        if victim in (first, last):
            raise MsoError(f"mid is on an end node ({victim}), not on a relay")
        row["count_before"] = (await sink_stats(emu, last)).get("count", 0)
        want = row["count_before"] + int(setup.rate * 0.55)
        healed_at = None
        if case == "kill":
            fault_t = emu.kill(victim)
        elif case == "crash":
            fault_t, proc = crash(emu, victim)
            hidden = (victim, proc)
        elif case == "partition":
            fault_t = loop.time()
            links = await cut(emu, victim)
        elif case == "starve":
            ends = [victim, last] if k % 2 == 0 else [victim]
            row["starved"] = ends
            fault_t = loop.time()
            for node in ends:
                starve(emu, node, last if node == victim else victim, True)
        else:
            raise MsoError(f"unknown case {case!r}")

        if case == "starve":
            await asyncio.sleep(setup.starve_s)
            stats = await sink_stats(emu, last)
            for node in row["starved"]:
                starve(emu, node, last if node == victim else victim, False)
            row["resumed"] = stats.get("count", 0) >= want
        else:
            stats = await wait_resumed(emu, last, fault_t, want, RECOVER_S) or {}
            row["resumed"] = bool(stats)
            if not stats:
                row["error"] = f"no recovery within {RECOVER_S:g} s"
        row["resumed_wait_s"] = loop.time() - fault_t
        if case == "partition":
            await asyncio.sleep(max(0.0, fault_t + setup.hold_s - loop.time()))
            await heal(emu, links)
            healed_at = loop.time()
            await asyncio.sleep(REJOIN_S)
        emitted, stats = await drain(emu, first, last)
        everywhere = await emu.status(first)

        row["emitted"] = emitted
        row["sink_count"] = stats.get("count", 0)
        row["lost"] = int(stats.get("missing", 0)) + max(0, emitted - int(stats.get("next", 0)))
        row["duplicated"] = int(stats.get("repeats", 0))
        row["out_of_order"] = int(stats.get("out_of_order", 0))
        row["relayed_bytes"] = sum(
            int(st.get("traffic", {}).get("bytes_forwarded", 0)) for st in everywhere.values()
        )
        ats = [
            f["at"]
            for n, st in everywhere.items()
            if n != victim
            for f in st.get("failures", [])
            if f["node"] == victim
        ]
        row["detection_ms"] = (min(ats) - fault_t) * 1e3 if ats else None
        gap = outage(stats, fault_t)
        if case == "starve":  # the largest gap during the starvation, if any event waited
            gaps = [(b, a) for b, a in stats.get("gaps", []) if a > fault_t]
            gap = max(gaps, key=lambda g: g[1] - g[0]) if gaps else None
        row["recovery_ms"] = (gap[1] - gap[0]) * 1e3 if gap is not None else None
        row["healed_at_ms"] = (healed_at - fault_t) * 1e3 if healed_at is not None else None
        hosts = [n for n, st in everywhere.items() if vertex(st, "mid")]
        row["mid_after"] = hosts[0] if len(hosts) == 1 else hosts
        declared = sorted(  # by the survivors (a partitioned victim declares the others)
            {
                f["node"]
                for st in everywhere.values()
                for f in st.get("failures", [])
                if f.get("detector") != victim or case == "starve"
            }
        )
        row["declarations"] = sorted(
            {(f["node"], f.get("detector")) for st in everywhere.values()
             for f in st.get("failures", [])}
        )  # fmt: skip
        row["declared_failed"] = declared
        if case == "starve":
            if declared:
                row["error"] = row["error"] or f"nodes declared failed: {declared}"
        elif row["detection_ms"] is None:
            row["error"] = row["error"] or "no survivor recorded the failure"
        elif set(declared) - {victim}:
            row["error"] = row["error"] or f"live nodes declared failed: {declared}"
    except Exception as exc:  # a failed run is reported, the others still run
        row["error"] = f"{type(exc).__name__}: {exc}"
    finally:
        if hidden is not None:  # give the stopped process back to the emulator
            emu.nodes[hidden[0]].process = hidden[1]
        if row["error"] or row.get("lost") or row.get("duplicated"):
            row["logs"] = log_lines(emu)
        await emu.stop()
        shutil.rmtree(log_dir, ignore_errors=True)
    return row


def cell_summary(rows: list[dict[str, Any]]) -> dict[str, Any]:
    """Summary figures of one cell's runs (failed runs count in ``failed`` and in the losses)."""

    def col(key: str) -> list[float]:  # every run that measured it, whatever else failed
        return [float(r[key]) for r in rows if r.get(key) is not None]

    good = [r for r in rows if not r["error"]]
    moves: dict[str, int] = {}
    for r in good:
        key = f"{r.get('victim')}->{r.get('mid_after')}"
        moves[key] = moves.get(key, 0) + 1
    return {
        "runs": len(rows),
        "ok": len(good),
        "failed": len(rows) - len(good),
        "unrecovered": sum(1 for r in rows if r.get("resumed") is False),
        "false_declarations": sum(
            1 for r in rows if "declared failed" in str(r.get("error") or "")
        ),
        "detection_ms": summary(col("detection_ms")),
        "recovery_ms": summary(col("recovery_ms")),
        "lost_total": sum(int(r.get("lost") or 0) for r in rows),
        "duplicated_total": sum(int(r.get("duplicated") or 0) for r in rows),
        "emitted_total": sum(int(r.get("emitted") or 0) for r in rows),
        "relayed_bytes_p50": summary(col("relayed_bytes"))["p50"],
        "mid_moves": moves,
        "errors": sorted({str(r["error"]) for r in rows if r["error"]}),
    }


async def run(
    setup: Setup, cases: list[str], topologies: list[str], runs: int, tmp: Path
) -> dict[str, Any]:
    """``runs`` fresh-emulator runs per (case, topology), each cell within its time budget."""
    cells: dict[str, Any] = {}
    for case in cases:
        for topology in topologies:
            t0 = time.monotonic()
            per_run = RUN_BUDGET_S + (setup.starve_s if case == "starve" else setup.hold_s)
            rows: list[dict[str, Any]] = []
            notes = []
            for k in range(runs):
                if time.monotonic() - t0 > per_run * runs:
                    notes.append(f"budget spent after {k} runs")
                    break
                try:
                    row = await asyncio.wait_for(
                        one_run(setup, case, topology, k, tmp), RUN_TIMEOUT_S + per_run
                    )
                except TimeoutError:
                    row = {"case": case, "topology": topology, "run": k, "error": "timed out"}
                rows.append(row)
                status = "ok" if not row["error"] else f"FAILED: {row['error']}"
                print(
                    f"{setup.label} {case} {topology} run {k}: {row.get('victim')} -> "
                    f"{row.get('mid_after')}, detection {_f(row.get('detection_ms'))} ms, "
                    f"recovery {_f(row.get('recovery_ms'))} ms, lost {row.get('lost')}, "
                    f"dup {row.get('duplicated')}, relayed {row.get('relayed_bytes')} ({status})",
                    file=sys.stderr,
                    flush=True,
                )
            key = f"{setup.label}/{case}/{topology}"
            cells[key] = {
                "setup": setup.label,
                "case": case,
                "topology": topology,
                "heartbeat_s": setup.detection[0],
                "dead_after_s": setup.detection[1],
                "convergence_s": setup.convergence,
                "rate": setup.rate,
                "hold_s": setup.hold_s if case == "partition" else None,
                "starve_s": setup.starve_s if case == "starve" else None,
                "seconds": time.monotonic() - t0,
                "notes": notes,
                **provenance(),
                "summary": cell_summary(rows),
                "rows": rows,
            }
    return cells


def _f(x: float | None, digits: int = 0) -> str:
    return "-" if x is None else f"{x:,.{digits}f}"


CASE_TITLES = {
    "kill": "relay killed",
    "crash": "mso node crashed, router alive",
    "partition": "relay partitioned, healed",
    "starve": "route starved",
}


def render(result: dict[str, Any]) -> str:
    """The Markdown table of every cell (and what went wrong, if anything)."""
    lines = [
        f"### Faults under `src -> mid -> sink` at {result.get('rate', RATE):g} events/s "
        "(`bench/failure.py`)",
        "",
        "| setup | fault | topology | runs ok | detection ms p50 / max "
        "| recovery ms p50 / p99 / max | not recovered in 12 s | live node declared failed "
        "| lost | duplicated | relayed B p50 | mid moved |",
        "|---|---|---|---:|---|---|---:|---:|---:|---:|---:|---|",
    ]
    order = {c: i for i, c in enumerate(CASES)}
    cells = sorted(
        result["cells"].values(), key=lambda c: (c["setup"], order.get(c["case"], 9), c["topology"])
    )
    for c in cells:
        s = c["summary"]
        d, r = s["detection_ms"], s["recovery_ms"]
        moves = ", ".join(f"{k} ({v})" for k, v in sorted(s["mid_moves"].items()))
        what = CASE_TITLES.get(c["case"], c["case"])
        if c.get("starve_s"):
            what += f" {c['starve_s']:g} s"
        if c.get("hold_s"):
            what += f" ({c['hold_s']:g} s)"
        lines.append(
            f"| {c['setup']} (hb {c['heartbeat_s']:g} s, dead {c['dead_after_s']:g} s) | {what} "
            f"| {c['topology']} | {s['ok']}/{s['runs']} | {_f(d['p50'])} / {_f(d['max'])} "
            f"| {_f(r['p50'])} / {_f(r['p99'])} / {_f(r['max'])} | {s['unrecovered']} "
            f"| {s['false_declarations']} "
            f"| {s['lost_total']:,} of {s['emitted_total']:,} | {s['duplicated_total']:,} "
            f"| {_f(s['relayed_bytes_p50'])} | {moves} |"
        )
    lines += [
        "",
        "- detection: the earliest survivor's failure record minus the fault time; recovery: "
        "the largest gap between sink arrivals that ends after the fault (for a starved route: "
        "during the starvation); lost/duplicated: over all runs, counted after the drain (and "
        "after the heal for a partition); relayed: bytes the nodes forwarded at the overlay "
        "(on netns the kernel forwards, so anything here went through the overlay relay); "
        "detection and recovery cover every run that measured them, runs ok are those with "
        "no error at all (a live node declared failed is one)",
    ]
    for c in cells:
        for note in c.get("notes", []):
            lines.append(f"- {c['setup']}/{c['case']}/{c['topology']}: {note}")
        for err in c["summary"]["errors"]:
            n = sum(1 for r in c["rows"] if r["error"] == err)
            lines.append(f"- {c['setup']}/{c['case']}/{c['topology']}: {n} run(s) failed: {err}")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=(__doc__ or "").split("\n")[0])
    ap.add_argument("--runs", type=int, default=20, help="runs per cell (default 20)")
    ap.add_argument("--quick", action="store_true", help="3 runs per cell")
    ap.add_argument("--backend", choices=("user", "netns"), default="user")
    ap.add_argument("--routing", choices=("babeld", "batmand"), default="babeld",
                    help="the routing daemon on netns")  # fmt: skip
    ap.add_argument("--case", default="kill,crash,partition", help=f"of {','.join(CASES)}")
    ap.add_argument("--topology", default="mesh", help="comma-separated: mesh,line")
    ap.add_argument("--convergence", type=float, default=0.0, help="routing convergence, s")
    ap.add_argument("--rate", type=float, default=RATE, help="source events/s (default 200)")
    ap.add_argument("--heartbeat", type=float, help="heartbeat period, s (0.1; netns 0.2)")
    ap.add_argument("--dead-after", type=float, help="failure timeout, s (0.5; netns 3)")
    ap.add_argument("--hold", type=float, help="partition length, s (2 x dead-after, >= 2)")
    ap.add_argument("--starve-s", type=float, default=60.0, help="starvation length, s (60)")
    ap.add_argument("--json", type=Path, help="where to write (default bench/results/failure)")
    args = ap.parse_args(argv)
    runs = 3 if args.quick else args.runs
    cases = [c for c in args.case.split(",") if c]
    topologies = [t for t in args.topology.split(",") if t]
    if not 1 <= runs <= 100:
        ap.error("--runs: 1..100")
    if not 0.0 <= args.convergence <= 10.0:
        ap.error("--convergence: 0..10 s")
    if not 1.0 <= args.rate <= 5000.0:
        ap.error("--rate: 1..5000 events/s")
    if not 1.0 <= args.starve_s <= 300.0:
        ap.error("--starve-s: 1..300 s")
    if unknown := [t for t in topologies if t not in TOPOLOGIES]:
        ap.error(f"unknown topology {unknown}; known: {', '.join(TOPOLOGIES)}")
    if unknown := [c for c in cases if c not in CASES]:
        ap.error(f"unknown case {unknown}; known: {', '.join(CASES)}")
    if "starve" in cases and args.backend != "netns":
        ap.error("--case starve needs --backend netns (the kernel's routes)")
    hb, dead = (0.1, 0.5) if args.backend == "user" else NETNS_DETECTION
    detection = (args.heartbeat or hb, args.dead_after or dead)
    hold = args.hold if args.hold is not None else max(2.0, 2 * detection[1])
    if not 0.5 <= hold <= 60.0:
        ap.error("--hold: 0.5..60 s")
    setup = Setup(args.backend, args.routing, args.convergence, args.rate, detection, hold,
                  args.starve_s)  # fmt: skip
    out: Path = args.json or RESULTS / "failure.json"
    t0 = time.monotonic()
    with tempfile.TemporaryDirectory(prefix="mso-bench-failure-") as tmp:
        cells = asyncio.run(run(setup, cases, topologies, runs, Path(tmp)))
    old: dict[str, Any] = {}
    if out.exists():
        try:
            old = json.loads(out.read_text())
        except ValueError:
            old = {}
    merged = dict(old.get("cells", {})) | cells
    for cell in merged.values():  # the summary as this version computes it, from the rows
        cell["summary"] = cell_summary(cell["rows"])
    result = {
        "benchmark": "failure",
        "rate": args.rate,
        "steady_s": STEADY_S,
        "recover_s": RECOVER_S,
        "cells": merged,
        "seconds": time.monotonic() - t0,
    } | provenance()
    write_results(out, result, render(result))
    return 0


if __name__ == "__main__":
    sys.exit(main())
