"""Where one event's time goes on mso's 2-hop path at 100 events/s (issue 29.1).

The pipeline of ``bench/peer_dora.py`` (``source -> relay -> sink``, an emulated line N1-N2-N3,
unshaped loopback links, the relay on N2) with every node process stamping, on the one clock
they share (CLOCK_MONOTONIC), the points an event passes: a timer firing (the rated source's
tick), a turn of the inline (cheap) vertex jobs starting and ending, bytes arriving on a
neighbour's connection, a frame authenticated and decoded, a frame handed to a link. The hooks
are put in by a ``sitecustomize`` on the nodes' ``PYTHONPATH`` (``MSO_BENCH_TRACE_DIR``), so
the code under test is the code the project runs; they cost about a microsecond a stamp.

Per event, the stamps are chained across the three processes (N1's Data frame, the first Data
frame decoded at N2 after it, and so on) and the segments' medians reported:

* N1: the source's tick -> its inline turn starts -> ends (the source's call) -> Data handed
  to the link;
* the wire N1 -> N2: handed to the link -> bytes read at N2 (a ``send``, the kernel's
  loopback, the other process woken and its ``epoll_wait`` returning);
* N2: read -> decoded -> the relay's inline turn starts -> ends -> Data handed to the link;
* the wire N2 -> N3, and N3: read -> decoded -> the sink's turn starts -> ends.

Also per event and node: turns of the event loop, reads, frames sent (Data, acks, the rest).
``--strace`` adds a second window with ``strace -c -f`` attached to the three node processes
(they are this benchmark's own): system calls per event by name (strace slows every call, so
that window's latency is not reported).

Results: ``bench/results/path_trace.json`` and ``.md``.

``--profile`` runs every node under cProfile (dataplane.py's hook and stages): own CPU time per
event by stage (decode, channel, hand-off, vertex call, encode, ack, write, the loop).

Usage: .venv/bin/python bench/path_trace.py [--size 38] [--rate 100] [--window 10] [--strace]
                                            [--profile]
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import pstats
import shutil
import signal
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from mso.benchmarks.common import cpu_seconds, provenance, write_results

HERE = Path(__file__).resolve().parent
RESULTS = HERE / "results"
sys.path.insert(0, str(HERE))
from dataplane import SITECUSTOMIZE as PROFILE_HOOK  # noqa: E402
from dataplane import stage_breakdown  # noqa: E402
from peer_dora import LINE3, hosting, mso_app, sink_stats  # noqa: E402

NODES = ("N1", "N2", "N3")
DATA = "data"  # a frame's class as the hooks tell it: data, ack, beat, ctl (the rest)

SITECUSTOMIZE = """\
import os

_dir = os.environ.get("MSO_BENCH_TRACE_DIR")
if _dir:
    import atexit
    import time

    _t = time.perf_counter
    _rec = []
    _on = [False]
    _turns = [0]

    def _cls(b, kind):
        if kind == 3:
            return "beat"
        head = b[:48]
        return "data" if b"\\xa4data" in head else "ack" if b"\\xa3ack" in head else "ctl"

    def _dump():
        import json
        with open(os.path.join(_dir, f"trace-{os.getpid()}.json"), "w") as f:
            json.dump({"records": _rec, "turns": _turns[0]}, f)

    atexit.register(_dump)

    def _hooks():
        import asyncio.base_events as be
        from mso.net import shaping, tcp
        from mso.node import driver

        once = be.BaseEventLoop._run_once

        def run_once(self):
            _turns[0] += 1
            if _on[0]:
                _rec.append((_t(), "L", 0))
            return once(self)

        be.BaseEventLoop._run_once = run_once

        received = tcp.Connection.data_received

        def data_received(self, data):
            if _on[0] and self.peer is not None:
                _rec.append((_t(), "R", len(data)))
            return received(self, data)

        tcp.Connection.data_received = data_received

        envelope = tcp.TcpTransport.on_envelope

        def on_envelope(self, conn, env, size):
            if _on[0] and conn.peer is not None:
                _rec.append((_t(), "E", _cls(bytes(memoryview(env.body)[:48]), env.kind)))
            return envelope(self, conn, env, size)

        tcp.TcpTransport.on_envelope = on_envelope

        send = shaping.Link.send

        def link_send(self, payload, kind, via=None):
            if _on[0]:
                _rec.append((_t(), "S", _cls(payload, kind)))
            return send(self, payload, kind, via)

        shaping.Link.send = link_send

        inline = driver.NodeDriver._run_inline

        def run_inline(self):
            if _on[0]:
                _rec.append((_t(), "I", 0))
                inline(self)
                _rec.append((_t(), "i", 0))
                return
            inline(self)

        driver.NodeDriver._run_inline = run_inline

        fire = driver.NodeDriver._fire

        def fire_timer(self, key):
            if _on[0]:
                _rec.append((_t(), "T", type(key).__name__))
            return fire(self, key)

        driver.NodeDriver._fire = fire_timer

        import signal

        def toggle(*_):
            _on[0] = not _on[0]

        signal.signal(signal.SIGUSR2, toggle)

    _hooks()
"""


def after(recs: list[tuple[float, str, Any]], t: float, code: str, arg: Any = None) -> int:
    """Index of the first record at or after ``t`` with ``code`` (and ``arg``); -1 if none."""
    lo, hi = 0, len(recs)
    while lo < hi:  # records are in time order
        mid = (lo + hi) // 2
        if recs[mid][0] < t:
            lo = mid + 1
        else:
            hi = mid
    for i in range(lo, len(recs)):
        if recs[i][1] == code and (arg is None or recs[i][2] == arg):
            return i
    return -1


def before(recs: list[tuple[float, str, Any]], i: int, code: str) -> int:
    """Index of the last record before index ``i`` with ``code``; -1 if none."""
    for j in range(i - 1, -1, -1):
        if recs[j][1] == code:
            return j
    return -1


SEGMENTS = [
    ("N1: source tick -> its turn starts", "n1_tick", "n1_turn"),
    ("N1: the source's turn (call, data plane, encode, write)", "n1_turn", "n1_turn_end"),
    ("  of which: turn start -> Data handed to the link", "n1_turn", "n1_send"),
    ("wire N1 -> N2 (send, loopback, wake-up, epoll)", "n1_send", "n2_read"),
    ("N2: read -> Data decoded (auth, framing)", "n2_read", "n2_decoded"),
    ("N2: decoded -> the relay's turn starts (core, feed, call_soon)", "n2_decoded", "n2_turn"),
    ("N2: turn start -> Data handed to the link", "n2_turn", "n2_send"),
    ("wire N2 -> N3", "n2_send", "n3_read"),
    ("N3: read -> Data decoded", "n3_read", "n3_decoded"),
    ("N3: decoded -> the sink's turn starts", "n3_decoded", "n3_turn"),
    ("N3: the sink's turn (call, ack)", "n3_turn", "n3_turn_end"),
    ("**source tick -> the sink's turn ends**", "n1_tick", "n3_turn_end"),
]


def chain(traces: dict[str, list[tuple[float, str, Any]]]) -> list[dict[str, float]]:
    """One timeline per event: N1's source tick through the sink's turn at N3."""
    n1, n2, n3 = (traces[n] for n in NODES)
    out = []
    for t, code, arg in n1:
        if code != "T" or arg != "SourceTick":
            continue
        ev: dict[str, float] = {"n1_tick": t}
        i = after(n1, t, "I")
        j = after(n1, t, "S", DATA)
        if i < 0 or j < 0:
            continue
        ev["n1_turn"] = n1[i][0]
        ev["n1_turn_end"] = n1[after(n1, n1[i][0], "i")][0]
        ev["n1_send"] = n1[j][0]
        e = after(n2, ev["n1_send"], "E", DATA)
        if e < 0:
            continue
        ev["n2_decoded"] = n2[e][0]
        ev["n2_read"] = n2[before(n2, e, "R")][0]
        i = after(n2, ev["n2_decoded"], "I")
        j = after(n2, ev["n2_decoded"], "S", DATA)
        if i < 0 or j < 0:
            continue
        ev["n2_turn"], ev["n2_send"] = n2[i][0], n2[j][0]
        e = after(n3, ev["n2_send"], "E", DATA)
        if e < 0:
            continue
        ev["n3_decoded"] = n3[e][0]
        ev["n3_read"] = n3[before(n3, e, "R")][0]
        i = after(n3, ev["n3_decoded"], "I")
        if i < 0:
            continue
        ev["n3_turn"] = n3[i][0]
        ev["n3_turn_end"] = n3[after(n3, ev["n3_turn"], "i")][0]
        if ev["n3_turn_end"] - ev["n1_tick"] < 0.05:  # (a pairing across two events: none)
            out.append(ev)
    return out


def constructed(paths: list[Path], events: int) -> dict[str, float]:
    """Objects built in Python per event, from cProfile's call counts (which, unlike its times,
    the load does not change): every ``__init__``/``__new__`` written in Python (dataclasses,
    the protocol's classes; msgspec Structs and builtins are built in C and not counted), the
    most frequent first, and their sum. A process's whole life, start-up included."""
    calls: dict[str, int] = {}
    for path in paths:
        raw: dict[Any, Any] = pstats.Stats(str(path)).stats  # type: ignore[attr-defined]
        for (file, line, name), (_, ncalls, *_rest) in raw.items():
            if name in ("__init__", "__new__") and file != "~":
                key = f"{Path(file).parent.name}/{Path(file).name}:{line}"
                calls[key] = calls.get(key, 0) + ncalls
    top = sorted(calls.items(), key=lambda kv: -kv[1])[:8]
    out = {k: round(v / max(1, events), 2) for k, v in top}
    out["all"] = round(sum(calls.values()) / max(1, events), 2)
    return out


def counts(recs: list[tuple[float, str, Any]], events: int) -> dict[str, float]:
    """Per event: loop turns, reads, timers, inline turns, frames handed to links by kind."""
    c: dict[str, int] = {}
    for _, code, arg in recs:
        key = {"L": "turns", "R": "reads", "T": "timers", "I": "inline turns"}.get(code)
        if code in ("S", "E"):
            key = f"{arg} frames {'sent' if code == 'S' else 'read'}"
        if key:
            c[key] = c.get(key, 0) + 1
    return {k: round(v / max(1, events), 2) for k, v in sorted(c.items())}


def strace_counts(path: Path, events: int) -> dict[str, float]:
    """``strace -c`` output: calls per event by system call (the most frequent first)."""
    out: dict[str, float] = {}
    for line in path.read_text().splitlines():
        parts = line.split()
        if len(parts) >= 5 and parts[0][0].isdigit() and parts[-1] != "total":
            out[parts[-1]] = int(parts[3]) / max(1, events)
    return dict(sorted(out.items(), key=lambda kv: -kv[1]))


async def run(args: argparse.Namespace, tmp: Path) -> dict[str, Any]:
    from mso.emu.controller import Emulator
    from mso.scenario import loads_scenario

    (tmp / "sitecustomize.py").write_text(SITECUSTOMIZE + (PROFILE_HOOK if args.profile else ""))
    saved = dict(os.environ)
    if args.profile:
        os.environ["MSO_BENCH_PROFILE_DIR"] = str(tmp)
    os.environ["PYTHONPATH"] = os.pathsep.join(
        [str(tmp), *filter(None, [os.environ.get("PYTHONPATH")])]
    )
    os.environ["MSO_BENCH_TRACE_DIR"] = str(tmp)
    emu = Emulator(loads_scenario(LINE3), manage=False, log_dir=tmp)
    result: dict[str, Any] = {}
    try:
        await emu.start()
        name = "trace"
        doc = mso_app(name, args.size, args.rate, args.warmup, args.window, "N3")
        reply = await emu.deploy(doc, str(tmp / "trace.yaml"), "N1")
        if not reply.ok or reply.placement.get("relay") != "N2":
            raise SystemExit(f"deployment: {reply.error or reply.placement}")
        first = await sink_stats(emu, name, "count", 30.0)
        await asyncio.sleep(max(0.0, first["first"] + args.warmup - time.monotonic()))
        procs = {n: emu.nodes[n].process for n in NODES}
        pids = {n: p.pid for n, p in procs.items() if p is not None}
        c0 = {n: cpu_seconds(p) for n, p in pids.items()}
        for p in pids.values():
            os.kill(p, signal.SIGUSR2)
        await asyncio.sleep(args.window)
        for p in pids.values():
            os.kill(p, signal.SIGUSR2)
        result["cpu_s"] = {n: cpu_seconds(p) - c0[n] for n, p in pids.items()}
        stats = await sink_stats(emu, name, "done", 20.0)
        result["sink"] = {k: stats.get(k) for k in ("window_events", "p50_us", "p99_us")}
        if args.strace and shutil.which("strace"):
            tracers = [
                subprocess.Popen(
                    ["strace", "-c", "-f", "-p", str(p), "-o", str(tmp / f"strace-{n}.txt")],
                    stderr=subprocess.DEVNULL,
                )
                for n, p in pids.items()
            ]
            _, src0 = hosting(await emu.status(), name, "src")
            await asyncio.sleep(args.window)
            _, src1 = hosting(await emu.status(), name, "src")
            for t in tracers:
                t.send_signal(signal.SIGINT)
            for t in tracers:
                t.wait(timeout=30)
            n_ev = src1.get("emitted", 0) - src0.get("emitted", 0)
            result["strace_events"] = n_ev
            result["strace"] = {n: strace_counts(tmp / f"strace-{n}.txt", n_ev) for n in NODES}
        _, src = hosting(await emu.status(), name, "src")
        emitted = int(src.get("emitted", 0))
        await emu.undeploy(name, "N1")
    finally:
        await emu.stop()
        os.environ.clear()
        os.environ.update(saved)
    traces = {}
    for n, p in pids.items():
        f = tmp / f"trace-{p}.json"
        doc_ = json.loads(f.read_text()) if f.exists() else {"records": []}
        traces[n] = [tuple(r) for r in doc_["records"]]
    events = chain(traces)
    result["events_traced"] = len(events)
    seg = {}
    for label, a, b in SEGMENTS:
        xs = sorted((ev[b] - ev[a]) * 1e6 for ev in events)
        if xs:
            seg[label] = {"p50_us": statistics.median(xs), "p90_us": xs[int(0.9 * (len(xs) - 1))]}
    result["segments"] = seg
    n_win = result["sink"].get("window_events") or len(events)
    result["per_event"] = {n: counts(traces[n], n_win) for n in NODES}
    result["cpu_us_per_event"] = {n: v / max(1, n_win) * 1e6 for n, v in result["cpu_s"].items()}
    if args.profile:  # the whole life of each process, over every event its source emitted
        result["profile_events"] = emitted
        result["profile_us_per_event"] = {}
        result["objects_per_event"] = {}
        for n, p in pids.items():
            paths = [tmp / f"profile-{p}.prof", *sorted(tmp.glob(f"profile-{p}-t*.prof"))]
            stages = stage_breakdown([x for x in paths if x.exists()])
            result["objects_per_event"][n] = constructed([x for x in paths if x.exists()], emitted)
            result["profile_us_per_event"][n] = {
                k: round(v / max(1, emitted) * 1e6, 1)
                for k, v in sorted(stages.items(), key=lambda kv: -kv[1])
                if k not in ("idle", "start-up")
            }
    return result


def per_node(title: str, what: str, rows: dict[str, dict[str, float]], fmt: str) -> list[str]:
    """A titled table of one figure per node per row."""
    out = ["", title, "", f"| {what} | " + " | ".join(NODES) + " |", "|---|" + "---:|" * len(NODES)]
    for k, v in rows.items():
        out.append(f"| {k} | " + " | ".join(fmt.format(v.get(n, 0)) for n in NODES) + " |")
    return out


def table(r: dict[str, Any]) -> str:
    s = r["sink"]
    lines = [
        f"### Where a 2-hop event's time goes: mso, {r['size']} B at {r['rate']:g} events/s "
        f"(`bench/path_trace.py`)",
        "",
        f"{r['events_traced']} events chained across the three node processes; the sink's own "
        f"figure over the window: p50 {s['p50_us'] or 0:.0f} µs, p99 {s['p99_us'] or 0:.0f} µs "
        f"(stamped, so a little slower than `peer_dora.py`'s). Load average "
        f"{r['provenance']['machine']['load_average'][0]:.1f}.",
        "",
        "| segment | p50 µs | p90 µs |",
        "|---|---:|---:|",
    ]
    for label, v in r["segments"].items():
        lines.append(f"| {label} | {v['p50_us']:.0f} | {v['p90_us']:.0f} |")
    keys = sorted({k for n in NODES for k in r["per_event"][n]})
    rows = {k: {n: r["per_event"][n].get(k, 0) for n in NODES} for k in keys}
    lines += per_node("Per event, at each node:", "per event", rows, "{:.2f}")
    lines.append(
        "| CPU µs | " + " | ".join(f"{r['cpu_us_per_event'][n]:.0f}" for n in NODES) + " |"
    )
    if r.get("strace"):
        names = sorted(
            {k for n in NODES for k in list(r["strace"][n])[:8]},
            key=lambda k: -sum(r["strace"][n].get(k, 0) for n in NODES),
        )
        tot = {n: sum(r["strace"][n].values()) for n in NODES}
        lines += per_node(
            f"System calls per event (`strace -c -f`, {r['strace_events']} events, a window "
            "of its own):",
            "system call",
            {k: {n: r["strace"][n].get(k, 0) for n in NODES} for k in names} | {"**all**": tot},
            "{:.2f}",
        )
    if r.get("profile_us_per_event"):
        prof = r["profile_us_per_event"]
        stages = sorted({k for n in NODES for k in prof[n]}, key=lambda k: -prof["N2"].get(k, 0))
        rows = {k: {n: prof[n].get(k, 0) for n in NODES} for k in stages}
        rows["**total**"] = {n: sum(prof[n].values()) for n in NODES}
        lines += per_node(
            f"CPU by stage under cProfile, µs per event (each process's whole life over the "
            f"{r['profile_events']} events its source emitted; cProfile inflates Python calls: "
            "compare stages, not absolutes):",
            "stage",
            rows,
            "{:.0f}",
        )
        objs = r.get("objects_per_event") or {}
        names = list(dict.fromkeys(k for n in NODES for k in objs.get(n, {}) if k != "all"))
        rows = {k: {n: objs.get(n, {}).get(k, 0) for n in NODES} for k in names}
        rows["**all**"] = {n: objs.get(n, {}).get("all", 0) for n in NODES}
        lines += per_node(
            "Objects built in Python per event (`__init__`/`__new__` calls counted by cProfile, "
            "the most frequent; msgspec and builtin objects are built in C, not counted):",
            "constructor",
            rows,
            "{:.2f}",
        )
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=(__doc__ or "").split("\n")[0])
    ap.add_argument("--size", type=int, default=38)
    ap.add_argument("--rate", type=float, default=100.0)
    ap.add_argument("--warmup", type=float, default=2.0)
    ap.add_argument("--window", type=float, default=10.0)
    ap.add_argument("--strace", action="store_true", help="a second window under strace -c")
    ap.add_argument("--profile", action="store_true", help="cProfile in every node (slower)")
    ap.add_argument("--json", type=Path, default=RESULTS / "path_trace.json")
    args = ap.parse_args(argv)
    if args.window <= 0 or args.rate <= 0 or args.warmup < 0:
        ap.error("--window and --rate must be positive, --warmup not negative")
    t0 = time.monotonic()
    with tempfile.TemporaryDirectory(prefix="mso-bench-trace-") as tmp:
        result = asyncio.run(run(args, Path(tmp)))
    result |= {"size": args.size, "rate": args.rate, "window_s": args.window}
    result["provenance"] = provenance()
    result["seconds"] = time.monotonic() - t0
    write_results(args.json, result, table(result))
    return 0


if __name__ == "__main__":
    sys.exit(main())
