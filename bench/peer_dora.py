"""mso side by side with dora-rs: the same 3-process pipeline, runs alternating, one table.

The pipeline is ``source -> relay -> sink``, three processes, two hops, on loopback:

* **dora-rs** (``dora run``, local mode: its daemon in the ``dora`` process, three Python nodes
  spawned by it) with the relay's and the sink's inputs on dora's default queue (10 events,
  drop oldest) and, as a second configuration, ``queue_policy: backpressure``. dora-rs is
  installed from the package registry into a virtual environment of its own under the cache
  directory (``--cache``, default ``~/.cache/mso-bench``), never into the project's; if it
  cannot be installed the error is recorded and the mso half runs alone.
* **mso**: an emulated line N1-N2-N3 (unshaped links), one ``mso node`` process per node, the
  app of ``mso.benchmarks.vertices.peer``: ``ProbeSource`` pinned on N1 with ``rate``,
  ``Relay`` (unpinned: Algorithm 1 puts it on N2), ``ProbeSink`` pinned on N3; one emulator
  per run, the sizes deployed on it in turn.

An event carries a sequence number and the source's ``perf_counter()`` stamp (CLOCK_MONOTONIC,
shared by the processes) padded to the size; the sinks do the same work on both sides.

Figures, per size and system (median of ``--runs``, alternating the systems' order each run):

* 2-hop latency p50 / p99 over a ``--window`` (default 10 s, 1,000 events at 100 events/s)
  that opens ``--warmup`` after the first arrival;
* CPU per event: utime+stime of the processes over that window (from /proc, 10 ms ticks)
  divided by the events in it: for mso the three node processes; for dora-rs its three node
  processes, and with its daemon (``dora run``) beside;
* cold start: dora-rs from ``dora run`` to the sink's first event; mso from the deploy request
  (nodes already up) to the sink's first event;
* ``--gaps``: the relay moved and killed while 38 B events flow at 100 events/s, ``--gap-after``
  s before and after. mso, on an emulated square N1-N2-N3-N4 (the relay on N2 or N4): *move*
  is a live relocation downstream (``Emulator.relocate``), *kill* the SIGKILL of the relay's
  node (detection, 0.5 s by default, and the restore elsewhere). dora-rs, with its coordinator
  (``dora up``, ``dora start``): *move* is what it offers on one machine, ``dora node restart
  relay`` (stop and respawn); *kill* is the SIGKILL of the relay's process, which the daemon
  respawns (``restart_policy: always``). The gap is the largest inter-arrival at the sink that
  ended after the action; lost, the holes in the sink's numbering.

``--floor`` adds a fourth system to each run, the same pipeline in bare asyncio over TCP
(``bench/bare_pipeline.py``): what Python and the loopback cost, mso's floor.

Results: ``bench/results/peer_dora.json`` and ``.md``.

Usage: .venv/bin/python bench/peer_dora.py [--quick] [--runs 3] [--sizes 38,967,3000]
          [--rate 100] [--warmup 1] [--window 10] [--gaps] [--no-dora] [--floor] [--cache DIR]
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import os
import signal
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from mso.benchmarks.common import Progress, cpu_seconds, provenance, write_results
from mso.benchmarks.vertices.peer import probe_pad

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bare_pipeline import run_bare, wait_file

HERE = Path(__file__).resolve().parent
RESULTS = HERE / "results"
VERTICES = "mso.benchmarks.vertices.peer"
DORA_VERSION = "1.1.0"
APP = "peer"

SQUARE = """\
name: peer-square
nodes: {N1: {}, N2: {}, N3: {}, N4: {}}
links: [[N1, N2], [N2, N3], [N3, N4], [N4, N1]]
"""

# -- the dora-rs side -------------------------------------------------------------------------
# One script for the three nodes (argv[1] is the role); it runs in dora's own environment, so
# it imports only what dora-rs brings (pyarrow). Payload: <seq f64><perf_counter f64><pad>.
DORA_NODE = r"""
import json, os, struct, sys, time
import pyarrow as pa
from dora import Node

ROLE = sys.argv[1]
SIZE = int(os.environ["PEER_SIZE"])
OUT = os.environ["PEER_OUT"]
WARMUP = float(os.environ["PEER_WARMUP"])
WINDOW = float(os.environ["PEER_WINDOW"])
HEAD = struct.Struct("<dd")


def dump(path, doc):
    with open(path + ".tmp", "w") as f:
        json.dump(doc, f)
    os.replace(path + ".tmp", path)


def pct(s, q):
    pos = (len(s) - 1) * q / 100.0
    lo = int(pos)
    hi = min(lo + 1, len(s) - 1)
    return s[lo] + (s[hi] - s[lo]) * (pos - lo)


node = Node()
if ROLE == "source":
    pad = bytes(max(0, SIZE - HEAD.size))
    seq = 0
    for ev in node:
        if ev["type"] == "INPUT":
            buf = pa.py_buffer(HEAD.pack(seq, time.perf_counter()) + pad)
            node.send_output("out", pa.Array.from_buffers(pa.uint8(), len(buf), [None, buf]))
            seq += 1
        elif ev["type"] == "STOP":
            break
    dump(OUT + ".source", {"sent": seq})
elif ROLE == "relay":
    for ev in node:
        if ev["type"] == "INPUT":
            node.send_output("out", ev["value"], ev["metadata"])
        elif ev["type"] == "STOP":
            break
else:
    count = nxt = missing = repeats = 0
    lat = []
    opens = closes = float("inf")
    last = 0.0
    gaps = []
    written = False
    for ev in node:
        if ev["type"] == "STOP":
            break
        if ev["type"] != "INPUT":
            continue
        now = time.perf_counter()
        mono = time.monotonic()
        v = ev["value"]
        seq, t = HEAD.unpack_from(memoryview(v.buffers()[1]), v.offset)
        seq = int(seq)
        if count == 0:
            opens = now + WARMUP
            closes = opens + WINDOW
            dump(OUT + ".first", {"at": mono})
        elif len(gaps) < 8 or mono - last > gaps[-1][0]:
            gaps = sorted(gaps + [(mono - last, mono)], reverse=True)[:8]
        last = mono
        count += 1
        if seq < nxt:
            repeats += 1
        else:
            missing += seq - nxt
            nxt = seq + 1
        if opens <= now < closes:
            lat.append(now - t)
        elif now >= closes and not written:
            s = sorted(lat)
            dump(OUT, {"window_events": len(s), "p50_us": pct(s, 50) * 1e6,
                       "p99_us": pct(s, 99) * 1e6, "missing": missing})
            written = True
    dump(OUT + ".end", {"count": count, "next": nxt, "missing": missing, "repeats": repeats,
                        "gaps": [[g * 1e3, at] for g, at in gaps]})
"""


def dora_yaml(python: Path, node_py: Path, policy: str, restart: bool, env: str) -> str:
    """The dataflow: a 10 ms timer drives the source (100 events/s). The interpreter and the
    nodes' settings are explicit: a daemon started by ``dora up`` does not pass on ours."""
    queue = "{source: %s, queue_size: 10, queue_policy: backpressure}" if policy else "%s"
    again = "\n    restart_policy: always" if restart else ""
    common = f"path: {python}\n    env: {env}"
    return f"""\
nodes:
  - id: source
    {common}
    args: {node_py} source
    inputs:
      tick: dora/timer/millis/10
    outputs: [out]
  - id: relay
    {common}
    args: {node_py} relay{again}
    inputs:
      x: {queue % "source/out"}
    outputs: [out]
  - id: sink
    {common}
    args: {node_py} sink
    inputs:
      x: {queue % "relay/out"}
"""


def dora_env(cache: Path, progress: Progress) -> tuple[Path | None, str | None]:
    """dora-rs's own virtual environment (made once, reused): its bin directory, or why not."""
    venv = cache / f"dora-rs-{DORA_VERSION}"
    bin_dir = venv / "bin"
    check = [str(bin_dir / "python"), "-c", "import dora, pyarrow"]
    if (bin_dir / "dora").exists() and subprocess.run(check, capture_output=True).returncode == 0:
        return bin_dir, None
    progress(f"installing dora-rs {DORA_VERSION} into {venv}")
    steps = [
        [sys.executable, "-m", "venv", "--clear", str(venv)],
        [
            str(bin_dir / "python"), "-m", "pip", "install", "-q", "--disable-pip-version-check",
            f"dora-rs=={DORA_VERSION}", f"dora-rs-cli=={DORA_VERSION}",
        ],
    ]  # fmt: skip
    for cmd in steps:
        try:
            r = subprocess.run(cmd, capture_output=True, text=True, timeout=900)
        except (OSError, subprocess.TimeoutExpired) as e:
            return None, f"{cmd[2:5]}: {e}"
        if r.returncode != 0:
            tail = (r.stderr or r.stdout).strip().splitlines()[-3:]
            return None, f"{' '.join(cmd[-2:])}: exit {r.returncode}: {' | '.join(tail)}"
    if subprocess.run(check, capture_output=True).returncode != 0:
        return None, "dora-rs installed but does not import"
    return bin_dir, None


def children(pid: int) -> list[int]:
    """Every descendant of ``pid`` (from /proc; those gone meanwhile are skipped)."""
    parent: dict[int, int] = {}
    for entry in os.listdir("/proc"):
        if entry.isdigit():
            with contextlib.suppress(OSError, IndexError, ValueError):
                stat = Path(f"/proc/{entry}/stat").read_text()
                parent[int(entry)] = int(stat.rsplit(")", 1)[1].split()[1])
    out, todo = [], [pid]
    while todo:
        p = todo.pop()
        kids = [c for c, pp in parent.items() if pp == p]
        out += kids
        todo += kids
    return out


def cmdline(pid: int) -> str:
    try:
        return Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").decode()
    except OSError:
        return ""


def dora_files(tmp: Path, name: str, size: int, policy: str, restart: bool, warmup: float,
               window: float, bin_dir: Path) -> tuple[Path, Path, dict[str, str]]:  # fmt: skip
    """A run's directory: its dataflow, where its sink writes, the CLI's environment."""
    work = tmp / name
    work.mkdir()
    flow = work / "dataflow.yml"
    out = work / "sink.json"
    settings = {
        "PEER_SIZE": str(size), "PEER_OUT": str(out), "PEER_WARMUP": str(warmup),
        "PEER_WINDOW": str(window),
    }  # fmt: skip
    flow.write_text(
        dora_yaml(bin_dir / "python", tmp / "node.py", policy, restart, json.dumps(settings))
    )
    env = dict(os.environ)
    env.pop("VIRTUAL_ENV", None)
    env["PATH"] = f"{bin_dir}{os.pathsep}{env.get('PATH', '')}"
    return flow, out, env


def role_of(pid: int) -> str:
    """``source``, ``relay`` or ``sink`` for a dora node process of ours (else "")."""
    args = cmdline(pid).split()
    return args[-1] if args and args[-1] in ROLES and "node.py" in " ".join(args) else ""


async def run_dora(
    bin_dir: Path, tmp: Path, size: int, policy: str, warmup: float, window: float
) -> dict[str, Any]:
    """One ``dora run`` of the pipeline: cold start, latency and CPU over the window."""
    name = f"dora-{size}-{policy or 'default'}-{time.monotonic_ns()}"
    flow, out, env = dora_files(tmp, name, size, policy, False, warmup, window, bin_dir)
    row: dict[str, Any] = {"system": f"dora-rs ({policy or 'default queue'})", "size": size}
    t0 = time.monotonic()
    with (flow.parent / "dora.log").open("wb") as log:
        proc = await asyncio.create_subprocess_exec(
            str(bin_dir / "dora"), "run", str(flow), "--log-level", "warn",
            cwd=flow.parent, env=env, stdout=log, stderr=subprocess.STDOUT,
            start_new_session=True,
        )  # fmt: skip
    try:
        first = await wait_file(Path(f"{out}.first"), 60.0)
        if first is None:
            row["error"] = "no event reached the sink within 60 s"
            return row
        row["cold_start_s"] = first["at"] - t0
        await asyncio.sleep(warmup)
        nodes = [p for p in children(proc.pid) if role_of(p)]
        c0 = {p: cpu_seconds(p) for p in [proc.pid, *nodes]}
        await asyncio.sleep(window)
        used = {p: cpu_seconds(p) - c for p, c in c0.items()}
        stats = await wait_file(out, 10.0)
        if stats is None:
            row["error"] = "the sink's window did not close in time"
            return row
        row.update(stats)
        n = max(1, stats["window_events"])
        row["node_processes"] = len(nodes)
        row["cpu_nodes_s"] = sum(used[p] for p in nodes)
        row["cpu_daemon_s"] = used[proc.pid]
        row["cpu_us_per_event"] = row["cpu_nodes_s"] / n * 1e6
        row["cpu_us_per_event_with_daemon"] = (row["cpu_nodes_s"] + used[proc.pid]) / n * 1e6
    finally:
        await stop_dora(proc)
    return row


async def stop_dora(proc: asyncio.subprocess.Process) -> None:
    """A graceful stop (SIGINT, as Ctrl-C: the nodes get STOP), then SIGKILL to its group."""
    if proc.returncode is None:
        with contextlib.suppress(ProcessLookupError):
            proc.send_signal(signal.SIGINT)
        try:
            await asyncio.wait_for(proc.wait(), 15.0)
        except TimeoutError:
            with contextlib.suppress(ProcessLookupError):
                os.killpg(proc.pid, signal.SIGKILL)
            await proc.wait()


ROLES = ("source", "relay", "sink")


def ours(tmp: Path) -> dict[int, str]:
    """Our dora node processes by pid, with their role (whoever spawned them)."""
    mark = str(tmp / "node.py")
    out = {}
    for entry in os.listdir("/proc"):
        if entry.isdigit() and mark in cmdline(int(entry)):
            role = role_of(int(entry))
            if role:
                out[int(entry)] = role
    return out


def gap_after(gaps: list[list[float]], at: float) -> float | None:
    """The largest gap (ms) among a sink's largest that ended after ``at`` (None: none did)."""
    after = [gap for gap, ended in gaps if ended > at]
    return max(after) if after else None


def dora_cli(bin_dir: Path, env: dict[str, str], cwd: Path, *args: str) -> str:
    """A dora command (it writes its logs under ``cwd``); an error raises."""
    r = subprocess.run(
        [str(bin_dir / "dora"), *args], env=env, cwd=cwd, capture_output=True, text=True,
        timeout=60,
    )  # fmt: skip
    if r.returncode != 0:
        raise RuntimeError(f"dora {' '.join(args)}: exit {r.returncode}: {r.stderr[-300:]}")
    return r.stdout


async def dora_gap(bin_dir: Path, tmp: Path, what: str, after: float) -> dict[str, Any]:
    """dora-rs with its coordinator (``dora up``): 38 B at 100 events/s, the relay restarted
    (``move``: ``dora node restart``) or its process killed (``kill``: the daemon respawns it,
    ``restart_policy: always``) ``after`` s after the first event; the flow runs ``after`` s
    more."""
    name = f"peer{time.monotonic_ns()}"
    flow, out, env = dora_files(tmp, name, 38, "", True, 0.0, 3600.0, bin_dir)
    row: dict[str, Any] = {"system": "dora-rs", "what": what}
    dora_cli(bin_dir, env, flow.parent, "up")
    try:
        dora_cli(bin_dir, env, flow.parent, "start", str(flow), "--detach", "--name", name)
        if await wait_file(Path(f"{out}.first"), 60.0) is None:
            row["error"] = "no event reached the sink within 60 s"
            return row
        await asyncio.sleep(after)
        row["at"] = time.monotonic()
        if what == "move":
            dora_cli(bin_dir, env, flow.parent, "node", "restart", "relay", "--dataflow", name)
        else:
            for pid, role in ours(tmp).items():
                if role == "relay":
                    with contextlib.suppress(ProcessLookupError):
                        os.kill(pid, signal.SIGKILL)
        await asyncio.sleep(after)
        dora_cli(bin_dir, env, flow.parent, "stop", "--name", name)
        end = await wait_file(Path(f"{out}.end"), 15.0)
        if end is None:
            row["error"] = "the sink did not stop in time"
            return row
        row.update(gap_ms=gap_after(end["gaps"], row["at"]), lost=end["missing"])
        row["repeats"] = end["repeats"]
    finally:
        with contextlib.suppress(RuntimeError, subprocess.TimeoutExpired):
            dora_cli(bin_dir, env, flow.parent, "down")
        for pid in ours(tmp):  # anything the daemon left behind
            with contextlib.suppress(ProcessLookupError):
                os.kill(pid, signal.SIGKILL)
    return row


# -- the mso side ---------------------------------------------------------------------------
LINE3 = """\
name: peer-line
nodes: {N1: {}, N2: {}, N3: {}}
links: [[N1, N2], [N2, N3]]
"""


def mso_app(name: str, size: int, rate: float, warmup: float, window: float, sink: str) -> str:
    fmt = f"{VERTICES}:Probe"
    return f"""\
name: {name}
planner: paper  # the relay on N2: two hops, as dora's (bytes: on the source's node)
vertices:
  src:   {{code: {VERTICES}:ProbeSource, pinned: N1, rate: {rate:g}, params: {{size: {size}}},
          output: {fmt}}}
  relay: {{code: {VERTICES}:Relay, input: {fmt}, output: {fmt}}}
  sink:  {{code: {VERTICES}:ProbeSink, pinned: {sink}, input: {fmt},
          params: {{warmup_s: {warmup}, window_s: {window}}}}}
edges:
  - {{from: src, to: relay, size: {size}}}
  - {{from: relay, to: sink, size: {size}}}
"""


def hosting(nodes: dict[str, Any], app: str, vertex: str) -> tuple[str, dict[str, Any]]:
    """(node, status entry) of the node hosting ``vertex`` ("", {} if none)."""
    for n, st in nodes.items():
        v = st.get("apps", {}).get(app, {}).get("vertices", {}).get(vertex)
        if v:
            return n, v
    return "", {}


async def sink_stats(emu: Any, app: str, until: str, timeout: float) -> dict[str, Any]:
    """Poll the sink's node until its stats say ``until`` (``count``: an event arrived;
    ``done``: its window closed); {} if not within ``timeout``."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        with contextlib.suppress(Exception):
            _, sink = hosting(await emu.status(timeout=2.0), app, "sink")
            stats: dict[str, Any] = sink.get("stats") or {}
            if stats.get(until):
                return stats
        await asyncio.sleep(0.02)
    return {}


async def run_mso(
    emu: Any, tmp: Path, size: int, rate: float, warmup: float, window: float
) -> dict[str, Any]:
    """One deployment of the pipeline on the running line: cold start, latency, CPU."""
    name = f"{APP}{size}x{time.monotonic_ns() % 100000}"
    doc = mso_app(name, size, rate, warmup, window, "N3")
    row: dict[str, Any] = {"system": "mso", "size": size}
    t0 = time.monotonic()
    reply = await emu.deploy(doc, str(tmp / f"{name}.yaml"), "N1")
    if not reply.ok:
        row["error"] = reply.error
        return row
    try:
        first = await sink_stats(emu, name, "count", 30.0)
        if not first:
            row["error"] = "no event reached the sink within 30 s"
            return row
        row["cold_start_s"] = first["first"] - t0
        row["placement"] = reply.placement
        if reply.placement.get("relay") != "N2":
            row["error"] = f"the relay landed on {reply.placement.get('relay')}, not N2"
            return row
        await asyncio.sleep(max(0.0, first["first"] + warmup - time.monotonic()))
        pids = [emu.nodes[n].process.pid for n in ("N1", "N2", "N3")]
        c0 = {p: cpu_seconds(p) for p in pids}
        await asyncio.sleep(window)
        used = sum(cpu_seconds(p) - c for p, c in c0.items())
        stats = await sink_stats(emu, name, "done", 20.0)
        if not stats:
            row["error"] = "the sink's window did not close in time"
            return row
        row.update({k: stats[k] for k in ("window_events", "p50_us", "p99_us", "missing")})
        row["node_processes"] = len(pids)
        row["cpu_nodes_s"] = used
        row["cpu_us_per_event"] = used / max(1, stats["window_events"]) * 1e6
    finally:
        await emu.undeploy(name, "N1")
    return row


async def mso_gap(tmp: Path, what: str, after: float) -> dict[str, Any]:
    """mso on a square N1-N2-N3-N4: 38 B at 100 events/s from N1 to N3, the relay (on N2 or
    N4) relocated downstream (``move``) or its node killed (``kill``) ``after`` s after the
    first event; the flow runs ``after`` s more (a kill: detection and restore included)."""
    from mso.emu.controller import Emulator
    from mso.scenario import loads_scenario

    row: dict[str, Any] = {"system": "mso", "what": what}
    emu = Emulator(loads_scenario(SQUARE), manage=False, log_dir=tmp)
    name = f"{APP}gap{what}"
    try:
        await emu.start()
        reply = await emu.deploy(mso_app(name, 38, 100.0, 0.0, 3600.0, "N3"), "g.yaml", "N1")
        if not reply.ok or not await sink_stats(emu, name, "count", 30.0):
            row["error"] = reply.error or "no event reached the sink within 30 s"
            return row
        await asyncio.sleep(after)
        host, _ = hosting(await emu.status(), name, "relay")
        row["at"] = time.monotonic()
        if what == "move":
            r = await emu.relocate(name, "relay", direction="downstream")
            row.update(moved_from=host, moved_to=r.node, elapsed_ms=r.elapsed_ms)
            if not r.ok:
                row["error"] = f"relocation refused: {r.error}"
                return row
        else:
            await emu.fail(host)
            row["killed"] = host
        await asyncio.sleep(after)
        _, src = hosting(await emu.status(), name, "src")
        stats = await sink_stats(emu, name, "count", 5.0)
        row.update(gap_ms=gap_after(stats.get("gaps", []), row["at"]), lost=stats.get("missing"))
        row.update(repeats=stats.get("repeats"), emitted=src.get("emitted"))
    finally:
        await emu.stop()
    return row


# -- the run and its table ------------------------------------------------------------------
def med(rows: list[dict[str, Any]], key: str) -> float | None:
    vals = [r[key] for r in rows if r.get(key) is not None and "error" not in r]
    return statistics.median(vals) if vals else None


def fmt(v: float | None, scale: float = 1.0, digits: int = 2) -> str:
    return "—" if v is None else f"{v * scale:,.{digits}f}"


def table(result: dict[str, Any]) -> str:
    rows = result["rows"]
    systems = list(dict.fromkeys(r["system"] for r in rows))
    lines = [
        f"# mso side by side with dora-rs {DORA_VERSION} (`bench/peer_dora.py`)",
        "",
        f"source -> relay -> sink, 3 processes, 2 hops, loopback, {result['rate']:g} events/s; "
        f"median of {result['runs']} runs, alternating; load average before "
        f"{result['provenance']['machine']['load_average'][0]:.2f}.",
        "",
    ]
    if result.get("dora_error"):
        lines += [f"dora-rs could not be installed: {result['dora_error']}", ""]
    lines += [
        "| size | " + " | ".join(systems) + " |",
        "|---|" + "---|" * len(systems),
    ]
    for label, p50, p99 in [("2-hop latency p50 / p99 (ms)", "p50_us", "p99_us")]:
        lines.append(f"| **{label}** |" + " |" * len(systems))
        for size in result["sizes"]:
            cells = []
            for s in systems:
                sel = [r for r in rows if r["system"] == s and r["size"] == size]
                cells.append(f"{fmt(med(sel, p50), 1e-3)} / {fmt(med(sel, p99), 1e-3)}")
            lines.append(f"| {size} B | " + " | ".join(cells) + " |")
    for label, key, scale, digits in [
        ("CPU µs per event, the 3 node processes", "cpu_us_per_event", 1.0, 0),
        ("... with dora's daemon", "cpu_us_per_event_with_daemon", 1.0, 0),
        ("cold start (s)", "cold_start_s", 1.0, 2),
        ("events lost in the window", "missing", 1.0, 0),
    ]:
        lines.append(f"| **{label}** |" + " |" * len(systems))
        for size in result["sizes"]:
            cells = []
            for s in systems:
                sel = [r for r in rows if r["system"] == s and r["size"] == size]
                cells.append(fmt(med(sel, key), scale, digits))
            lines.append(f"| {size} B | " + " | ".join(cells) + " |")
    errors = [r for r in rows if "error" in r]
    if errors:
        lines += ["", "Errors: " + "; ".join(f"{r['system']} {r['size']} B: {r['error']}"
                                              for r in errors)]  # fmt: skip
    ratios = []
    for size in result["sizes"]:
        m = [r for r in rows if r["system"] == "mso" and r["size"] == size]
        for s in systems:
            if s == "mso":
                continue
            d = [r for r in rows if r["system"] == s and r["size"] == size]
            a, b = med(m, "p50_us"), med(d, "p50_us")
            c, e = med(m, "p99_us"), med(d, "p99_us")
            if a and b and c and e:
                ratios.append(f"{size} B vs {s}: p50 {a / b:.2f}x, p99 {c / e:.2f}x")
    if ratios:
        lines += ["", "mso / dora-rs: " + "; ".join(ratios) + "."]
    gaps = result.get("gaps") or []
    if gaps:
        lines += ["", "| move / kill of the relay (38 B) | gap ms | lost | repeats |"]
        lines.append("|---|---:|---:|---:|")
        for g in gaps:
            what = f"{g['system']} {g['what']}"
            if "error" in g:
                lines.append(f"| {what} | error: {g['error']} | | |")
            else:
                lines.append(f"| {what} | {fmt(g.get('gap_ms'), 1.0, 0)} | {g.get('lost')} | "
                             f"{g.get('repeats')} |")  # fmt: skip
    return "\n".join(lines) + "\n"


async def main_async(args: argparse.Namespace, progress: Progress) -> dict[str, Any]:
    from mso.emu.controller import Emulator
    from mso.scenario import loads_scenario

    result: dict[str, Any] = {
        "rate": args.rate, "runs": args.runs, "sizes": args.sizes, "warmup_s": args.warmup,
        "window_s": args.window, "dora_version": DORA_VERSION, "provenance": provenance(),
    }  # fmt: skip
    bin_dir: Path | None = None
    if not args.no_dora:
        bin_dir, err = dora_env(Path(args.cache).expanduser(), progress)
        result["dora_error"] = err
    rows: list[dict[str, Any]] = []
    with tempfile.TemporaryDirectory(prefix="mso-bench-peer-") as tmp_s:
        tmp = Path(tmp_s)
        (tmp / "node.py").write_text(DORA_NODE)
        for run in range(args.runs):
            emu = Emulator(loads_scenario(LINE3), manage=False, log_dir=tmp)
            await emu.start()
            try:
                for size in args.sizes:
                    order = ["mso", "default", "backpressure"] if bin_dir else ["mso"]
                    order += ["bare"] if args.floor else []
                    k = run % len(order)
                    for system in order[k:] + order[:k]:
                        progress(f"run {run + 1}/{args.runs}, {size} B, {system}")
                        if system == "mso":
                            row = await run_mso(emu, tmp, size, args.rate, args.warmup, args.window)
                        elif system == "bare":
                            row = await run_bare(size, args.rate, args.warmup, args.window, tmp)
                        else:
                            assert bin_dir is not None
                            policy = "" if system == "default" else "backpressure"
                            row = await run_dora(
                                bin_dir, tmp, size, policy, args.warmup, args.window
                            )
                        row["run"] = run
                        row["loadavg"] = os.getloadavg()[0]
                        rows.append(row)
            finally:
                await emu.stop()
        result["rows"] = rows
        if args.gaps:
            gaps = []
            for what in ("move", "kill"):
                progress(f"gaps: mso {what}")
                gaps.append(await mso_gap(tmp, what, args.gap_after))
                if bin_dir is not None:
                    progress(f"gaps: dora-rs {what}")
                    gaps.append(await dora_gap(bin_dir, tmp, what, args.gap_after))
            result["gaps"] = gaps
    return result


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true", help="1 run, 2 s window, 38 B only")
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--sizes", default="38,967,3000", help="event sizes in bytes, comma-separated")
    ap.add_argument("--rate", type=float, default=100.0, help="events/s (dora: a 10 ms timer)")
    ap.add_argument("--warmup", type=float, default=1.0)
    ap.add_argument("--window", type=float, default=10.0)
    ap.add_argument("--gaps", action="store_true", help="also move and kill the relay")
    ap.add_argument("--gap-after", type=float, default=2.0, help="s of flow before and after")
    ap.add_argument("--no-dora", action="store_true", help="the mso half only")
    ap.add_argument("--floor", action="store_true", help="also bench/bare_pipeline.py (asyncio)")
    ap.add_argument("--cache", default="~/.cache/mso-bench", help="where dora-rs's venv lives")
    ap.add_argument("--json", type=Path, default=None, help="write elsewhere")
    args = ap.parse_args(argv)
    try:
        args.sizes = [int(s) for s in args.sizes.split(",") if s.strip()]
        for s in args.sizes:
            probe_pad(s)
    except ValueError as e:
        ap.error(f"--sizes: {e}")
    if args.rate != 100.0 and not args.no_dora:
        ap.error("--rate: dora-rs's source runs on a 10 ms timer; other rates need --no-dora")
    if args.runs < 1 or args.window <= 0 or args.warmup < 0 or args.gap_after <= 0:
        ap.error("--runs must be >= 1, --window and --gap-after > 0, --warmup >= 0")
    if args.quick:
        args.runs, args.window, args.sizes = 1, 2.0, [38]
    progress = Progress("peer_dora")
    t0 = time.monotonic()
    result = asyncio.run(main_async(args, progress))
    result["seconds"] = time.monotonic() - t0
    name = "peer_dora-quick" if args.quick else "peer_dora"
    write_results(args.json or RESULTS / f"{name}.json", result, table(result))
    return 0


if __name__ == "__main__":
    sys.exit(main())
