"""One inter-node hop of the data plane: mso against a bare msgspec-over-TCP baseline.

mso: a 2-node emulated scenario (N1 - N2, unshaped link), an app ``src -> sink`` with ``src``
(``mso.benchmarks.vertices.dataplane:StampSource``) pinned on N1 and ``sink``
(``LatencySink``) pinned on N2.
Saturated rows: the source has no ``rate`` and emits as fast as the send window allows.
Paced rows: ``rate: 1000`` (one event per ms), so latency is the path's, not the queue's.

Baseline: two processes, asyncio at both ends, the sender writing length-prefixed msgspec
msgpack frames (one frame per event, 256 frames coalesced into one write, ``drain()`` with the
same 1 MiB write-buffer limit as mso's driver for flow control), the receiver parsing frames
and calling the very same ``LatencySink``.

Both are measured with every process pinned to CPU 0 and with the sender on CPU 0 and the
receiver on CPU 1 (the controller stays on CPU 0). The sink measures per-event latency
(``perf_counter`` at the receiver minus the source's stamp; CLOCK_MONOTONIC, shared by the
processes) and events/s over a window that opens after a warm-up.

Usage: .venv/bin/python bench/dataplane.py [--quick] [--profile SIZE@CPUS ...]
  --profile 3000@0,1[@RATE]: one extra mso run (saturated, or paced at RATE events/s; that
             size, sender/receiver on those CPUs)
             with cProfile in both node processes, enabled by a sitecustomize.py written to the
             temp dir (every thread profiled); own time by stage per event and the top functions
             go to bench/results/dataplane-profile-SIZE-CPUS[-pacedRATE].txt. The
             profiler slows the nodes down (its events/s are not comparable). Repeatable.
  --only-profile: skip the measurements, run the --profile runs only.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import io
import json
import math
import os
import pstats
import struct
import sys
import tempfile
import time
from collections.abc import Awaitable, Callable
from pathlib import Path
from typing import Any

import msgspec

from mso.benchmarks.common import cpu_seconds, src_digest
from mso.benchmarks.vertices.dataplane import LatencySink, Stamped, pad_len
from mso.errors import MsoError

HERE = Path(__file__).resolve().parent
RESULTS = HERE / "results"
VERTICES = "mso.benchmarks.vertices.dataplane"  # the vertex code the nodes import

SIZES = (38, 967, 3000)
PACED_RATE = 1000.0
BATCH = 256  # baseline frames per write; mso's rate-less source emits 256 events per turn
PLACEMENTS = {"same CPU (0/0)": (0, 0), "different CPUs (0/1)": (0, 1)}
TARGET_RATIO = 0.5
TARGET_38B_EPS = 200_000
HIGH_WATER = 1 << 20  # the baseline's transport write buffer limit: mso.node.driver's
_LEN = struct.Struct(">I")

SCENARIO = """\
name: dataplane-pair
nodes: {N1: {}, N2: {}}
links: [[N1, N2]]
"""


def app_yaml(name: str, size: int, rate: float | None, warmup: float, window: float) -> str:
    rate_attr = f", rate: {rate:g}" if rate else ""
    return f"""\
name: {name}
vertices:
  src: {{code: {VERTICES}:StampSource, pinned: N1, params: {{size: {size}}},
        output: {VERTICES}:Stamped{rate_attr}}}
  sink: {{code: {VERTICES}:LatencySink, pinned: N2, input: {VERTICES}:Stamped,
         params: {{warmup_s: {warmup}, window_s: {window}}}}}
edges:
  - {{from: src, to: sink, size: {size}}}
"""


# -- process helpers ----------------------------------------------------------------------------
def pin(pid: int, cpu: int) -> None:
    """Pin every thread of ``pid`` to ``cpu``."""
    try:
        tids = [int(t) for t in os.listdir(f"/proc/{pid}/task")]
    except OSError:
        tids = [pid]
    for tid in tids:
        with contextlib.suppress(ProcessLookupError):
            os.sched_setaffinity(tid, {cpu})


def kill_tree(procs: list[asyncio.subprocess.Process]) -> None:
    for p in procs:
        if p.returncode is None:
            with contextlib.suppress(ProcessLookupError):
                p.kill()


# -- the baseline's two roles (run as child processes) ------------------------------------------
class _Receiver(asyncio.Protocol):
    def __init__(self, sink: LatencySink, finished: asyncio.Future[None]) -> None:
        self.sink = sink
        self.buf = bytearray()
        self.decoder = msgspec.msgpack.Decoder(Stamped)
        self.finished = finished
        self.transport: asyncio.Transport | None = None

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        assert isinstance(transport, asyncio.Transport)
        self.transport = transport

    def data_received(self, data: bytes) -> None:
        buf = self.buf
        buf += data
        pos, n = 0, len(buf)
        decode, sink = self.decoder.decode, self.sink
        while n - pos >= 4:
            (length,) = _LEN.unpack_from(buf, pos)
            end = pos + 4 + length
            if end > n:
                break
            sink(decode(buf[pos + 4 : end]))
            pos = end
        if pos:
            del buf[:pos]
        if sink.done() and not self.finished.done():
            self.finished.set_result(None)
            assert self.transport is not None
            self.transport.close()

    def connection_lost(self, exc: Exception | None) -> None:
        if not self.finished.done():
            self.finished.set_result(None)


async def _recv_role(args: argparse.Namespace) -> None:
    loop = asyncio.get_running_loop()
    sink = LatencySink(warmup_s=args.warmup, window_s=args.window)
    finished: asyncio.Future[None] = loop.create_future()
    server = await loop.create_server(lambda: _Receiver(sink, finished), "127.0.0.1", 0)
    port = server.sockets[0].getsockname()[1]
    print(json.dumps({"port": port}), flush=True)
    with contextlib.suppress(TimeoutError):
        await asyncio.wait_for(finished, args.warmup + args.window + 30.0)
    server.close()
    print(json.dumps(sink.stats()), flush=True)


async def _send_role(args: argparse.Namespace) -> None:
    _, writer = await asyncio.open_connection("127.0.0.1", args.port)
    transport = writer.transport
    assert isinstance(transport, asyncio.WriteTransport)
    transport.set_write_buffer_limits(high=HIGH_WATER)  # as mso's driver does
    encoder = msgspec.msgpack.Encoder()
    pad = bytes(pad_len(args.size))
    loop = asyncio.get_running_loop()
    deadline = loop.time() + args.duration
    clock = time.perf_counter
    print(json.dumps({"connected": True}), flush=True)
    try:
        if args.rate > 0:  # paced: one frame per tick
            period = 1.0 / args.rate
            nxt = loop.time()
            while loop.time() < deadline:
                payload = encoder.encode(Stamped(clock(), pad))
                writer.write(_LEN.pack(len(payload)) + payload)
                await writer.drain()
                nxt += period
                await asyncio.sleep(max(0.0, nxt - loop.time()))
        else:  # saturated: BATCH frames coalesced into one write
            buf = bytearray()
            while loop.time() < deadline:
                buf.clear()
                for _ in range(BATCH):
                    start = len(buf)
                    buf += b"\0\0\0\0"
                    encoder.encode_into(Stamped(clock(), pad), buf, -1)
                    _LEN.pack_into(buf, start, len(buf) - start - 4)
                writer.write(bytes(buf))
                await writer.drain()
    except (ConnectionError, OSError):
        pass  # the receiver closed: its window is over
    finally:
        writer.close()
        with contextlib.suppress(Exception):
            await writer.wait_closed()


def child_main(args: argparse.Namespace) -> None:
    os.sched_setaffinity(0, {args.cpu})
    asyncio.run(_recv_role(args) if args.role == "recv" else _send_role(args))


# -- baseline driver ----------------------------------------------------------------------------
async def _readline(proc: asyncio.subprocess.Process, timeout: float) -> dict[str, Any]:
    assert proc.stdout is not None
    line = await asyncio.wait_for(proc.stdout.readline(), timeout)
    if not line:
        raise RuntimeError("baseline process exited without output")
    result: dict[str, Any] = json.loads(line)
    return result


async def run_baseline(
    size: int, rate: float, cpus: tuple[int, int], warmup: float, window: float
) -> dict[str, Any]:
    load = os.getloadavg()[0]
    me = [sys.executable, str(Path(__file__).resolve())]
    common = ["--size", str(size), "--warmup", str(warmup), "--window", str(window)]
    procs: list[asyncio.subprocess.Process] = []
    try:
        recv = await asyncio.create_subprocess_exec(
            *me, "--role", "recv", "--cpu", str(cpus[1]), *common,
            stdout=asyncio.subprocess.PIPE,
        )  # fmt: skip
        procs.append(recv)
        port = (await _readline(recv, 20.0))["port"]
        send = await asyncio.create_subprocess_exec(
            *me, "--role", "send", "--cpu", str(cpus[0]), "--port", str(port),
            "--rate", str(rate), "--duration", str(warmup + window + 10.0), *common,
            stdout=asyncio.subprocess.PIPE,
        )  # fmt: skip
        procs.append(send)
        await _readline(send, 20.0)  # connected: events flow from now on
        await asyncio.sleep(warmup)
        c0 = {"sender": cpu_seconds(send.pid), "receiver": cpu_seconds(recv.pid)}
        t0 = time.perf_counter()
        await asyncio.sleep(window)
        wall = time.perf_counter() - t0
        cpu = {
            "sender": cpu_seconds(send.pid) - c0["sender"],
            "receiver": cpu_seconds(recv.pid) - c0["receiver"],
        }
        stats = await _readline(recv, warmup + window + 40.0)
        with contextlib.suppress(TimeoutError):
            await asyncio.wait_for(send.wait(), 5.0)
        with contextlib.suppress(TimeoutError):
            await asyncio.wait_for(recv.wait(), 5.0)
        return {
            "system": "baseline",
            "size": size,
            "rate": rate or None,
            "loadavg_before": load,
            "sink": stats,
            "cpu_util": {k: v / wall for k, v in cpu.items()},
        }
    finally:
        kill_tree(procs)
        for p in procs:
            with contextlib.suppress(Exception):
                await asyncio.wait_for(p.wait(), 5.0)


# -- mso driver ---------------------------------------------------------------------------------
STATUS_S = 30.0  # how long a status read waits for every node's part (and the app's) in it


class StatusMissing(Exception):
    """The overlay's status did not list a node or the case's app in time."""


async def status_of(emu: Any, app: str | None = None, timeout: float = STATUS_S) -> dict[str, Any]:
    """Both nodes' status, once one reply lists both (and ``app`` on each): a reply gathered
    by one node lacks a node whose part did not come in time (a bench run at load 16 read
    ``KeyError: 'N2'``). Asked again every 0.2 s until ``timeout``; then StatusMissing
    says what was missing."""
    loop = asyncio.get_running_loop()
    deadline = loop.time() + timeout
    while True:
        try:
            nodes: dict[str, Any] = await emu.status()
        except MsoError as exc:
            nodes, missing = {}, [str(exc)]
        else:
            missing = [n for n in ("N1", "N2") if n not in nodes]
            missing += [
                f"{app} on {n}"
                for n in ("N1", "N2")
                if app and app not in nodes.get(n, {}).get("apps", {})
            ]
        if not missing:
            return nodes
        if loop.time() > deadline:
            raise StatusMissing(f"the status lacked {', '.join(missing)} after {timeout:g} s")
        await asyncio.sleep(0.2)  # (a poll period)


async def run_mso(
    cpus: tuple[int, int],
    cases: list[tuple[int, float]],
    warmup: float,
    window: float,
    tmp: Path,
    env_extra: dict[str, str] | None = None,
    after_case: Callable[[int, float], Awaitable[dict[str, Any]]] | None = None,
) -> list[dict[str, Any]]:
    """Run every case on one emulated pair; ``after_case(size, rate)`` runs right after each
    (the baseline of the same case, so both see the same background load)."""
    from mso.emu.controller import Emulator
    from mso.scenario import load_scenario

    scen_file = tmp / "dataplane-pair.yaml"
    scen_file.write_text(SCENARIO)
    saved = dict(os.environ)
    if env_extra:  # profiling: the nodes pick up the sitecustomize.py written to tmp
        path = os.environ.get("PYTHONPATH", "")
        os.environ["PYTHONPATH"] = os.pathsep.join([str(tmp), *([path] if path else [])])
    os.environ.update(env_extra or {})
    emu = Emulator(load_scenario(scen_file), log_dir=tmp)
    out: list[dict[str, Any]] = []
    try:
        await emu.start()
        pids = {}
        for node, cpu in zip(("N1", "N2"), cpus, strict=True):
            proc = emu.nodes[node].process
            assert proc is not None
            pids[node] = proc.pid
            pin(proc.pid, cpu)
        for k, (size, rate) in enumerate(cases):
            name = f"dp{k}x{size}{'paced' if rate else ''}"
            doc = app_yaml(name, size, rate or None, warmup, window)
            (tmp / f"{name}.yaml").write_text(doc)
            row: dict[str, Any] = {
                "system": "mso",
                "size": size,
                "rate": rate or None,
                "loadavg_before": os.getloadavg()[0],
            }
            try:
                before = await status_of(emu)
            except StatusMissing as exc:
                out.append(row | {"error": str(exc)})
                continue
            reply = await emu.deploy(doc, str(tmp / f"{name}.yaml"), "N1")
            if not reply.ok:
                row["error"] = reply.error
                out.append(row)
                continue
            # CPU use over (about) the sink's window: it opens `warmup` after the first event
            await asyncio.sleep(warmup)
            c0 = {n: cpu_seconds(p) for n, p in pids.items()}
            t0 = time.perf_counter()
            await asyncio.sleep(window)
            wall = time.perf_counter() - t0
            row["cpu_util"] = {
                "sender": (cpu_seconds(pids["N1"]) - c0["N1"]) / wall,
                "receiver": (cpu_seconds(pids["N2"]) - c0["N2"]) / wall,
            }
            loop = asyncio.get_running_loop()
            deadline = loop.time() + 20.0
            sink: dict[str, Any] = {}
            nodes: dict[str, Any] = {}
            try:
                for _ in range(1000):
                    nodes = await status_of(emu, name)
                    sink = nodes["N2"]["apps"][name]["vertices"]["sink"]["stats"] or {}
                    if sink.get("done") or loop.time() > deadline:
                        break
                    await asyncio.sleep(0.1)
            except StatusMissing as exc:
                row["error"] = str(exc)
                out.append(row)
                await emu.undeploy(name, "N1")
                continue
            row["sink"] = sink
            src = nodes["N1"]["apps"][name]
            row["source_emitted"] = src["vertices"]["src"]["emitted"]
            row["edge"] = src["edges"].get("src->sink", {})
            got = nodes["N2"]["traffic"]["bytes_in"] - before["N2"]["traffic"]["bytes_in"]
            if sink.get("count"):
                row["wire_bytes_in_per_event"] = got / sink["count"]
            row["dropped_messages"] = {n: nodes[n]["dropped_messages"] for n in ("N1", "N2")}
            if not sink.get("done"):
                row["error"] = "the sink's window did not close in time"
            out.append(row)
            await emu.undeploy(name, "N1")
            await asyncio.sleep(0.2)
            if after_case is not None:
                out.append(await after_case(size, rate))
    finally:
        await emu.stop()
        os.environ.clear()
        os.environ.update(saved)
    return out


# -- profiling (optional) -----------------------------------------------------------------------
SITECUSTOMIZE = """\
import os

_dir = os.environ.get("MSO_BENCH_PROFILE_DIR")
if _dir:
    import atexit
    import cProfile

    _prof = cProfile.Profile()
    _prof.enable()

    def _dump():
        _prof.disable()
        _prof.dump_stats(os.path.join(_dir, f"profile-{os.getpid()}.prof"))

    atexit.register(_dump)

    import threading

    import itertools

    _run = threading.Thread.run
    _threads = itertools.count()

    def _profiled_run(self):
        # worker threads (vertex calls) get a profile of their own, dumped when they end
        prof = cProfile.Profile()
        prof.enable()
        try:
            _run(self)
        finally:
            prof.disable()
            name = f"profile-{os.getpid()}-t{next(_threads)}.prof"
            prof.dump_stats(os.path.join(_dir, name))

    threading.Thread.run = _profiled_run
"""


# where a function's own time goes: (stage, substrings of "file:function" or of a builtin's
# name), first match wins; any other builtin (msgspec, hashing) goes where its callers go
STAGES: list[tuple[str, tuple[str, ...]]] = [
    ("idle", ("'poll' of 'select.epoll", "'get' of '_queue.SimpleQueue", "'acquire' of '_thread")),
    (
        "ack",
        (
            "channel.py:on_ack",
            "dataplane.py:on_ack",
            "dataplane.py:ack",
            "ack_due",
            "dataplane.py:release",
            "channel.py:release",
            "channel.py:record",
        ),
    ),
    (
        "hand-off (queue, wake-up, results)",
        (
            "executor.py:",
            "driver.py:_vertex_result",
            "driver.py:_drain_results",
            "call_soon_threadsafe",
            "_write_to_self",
            "_read_from_self",
            "_process_self_data",
            "'put' of '_queue.SimpleQueue",
            "threading.py:",
        ),
    ),
    (
        "vertex call (decode, user code, encode)",
        ("worker.py:", "vertices/dataplane.py:", "instance.py:"),
    ),
    (
        "read, authenticate, decode",
        (
            "tcp.py:data_received",
            "framing.py:feed",
            "framing.py:_open",
            "framing.py:_confirm",
            "'recv' of '_socket",
            "tcp.py:on_envelope",
            "base.py:decode",
        ),
    ),
    ("encode, seal", ("base.py:encode", "framing.py:seal", "framing.py:_seal")),
    (
        "write",
        (
            "'send' of '_socket",
            "selector_events.py:write",
            "tcp.py:write_frame",
            "tcp.py:send",
            "tcp.py:_send_toward",
            "tcp.py:send_message",
        ),
    ),
    (
        "channel, data plane, core",
        (
            "channel.py:",
            "dataplane.py:",
            "core.py:",
            "state.py:",
            "context.py:",
            "driver.py:",
            "effects.py:",
            "messages.py:",
            "procedures/",
            "protocol/events.py:",
        ),
    ),
    ("event loop", ("base_events.py:", "events.py:", "selectors.py:", "selector_events.py:")),
    (
        "start-up",
        (
            "importlib",
            "compile",
            "marshal",
            "exec",
            "__build_class__",
            "_imp.",
            "/re/",
            "sre_",
            "yaml",
            "click",
            "frozen",
        ),
    ),
]


def _stage_of(func: tuple[str, int, str]) -> str | None:
    label = f"{func[0]}:{func[2]}"
    for stage, keys in STAGES:
        if any(k in label for k in keys):
            return stage
    return None


def stage_breakdown(paths: list[Path], other: dict[str, float] | None = None) -> dict[str, float]:
    """Own time (s) per stage over the given profiles of one process (its threads); what
    fits no stage is added up per function into ``other``."""
    out: dict[str, float] = {}
    other = {} if other is None else other
    for path in paths:
        raw: dict[Any, Any] = pstats.Stats(str(path)).stats  # type: ignore[attr-defined]
        for func, (_, _, tt, _, callers) in raw.items():
            stage = _stage_of(func)
            if stage is None and func[0] == "~" and callers:
                total = sum(c[2] for c in callers.values()) or 1.0
                for caller, c in callers.items():
                    st = _stage_of(caller) or "other"
                    out[st] = out.get(st, 0.0) + tt * c[2] / total
                    if st == "other":
                        key = f"{func[2]} from {caller[0]}:{caller[2]}"
                        other[key] = other.get(key, 0.0) + tt * c[2] / total
                continue
            out[stage or "other"] = out.get(stage or "other", 0.0) + tt
            if stage is None:
                key = f"{func[0]}:{func[2]}"
                other[key] = other.get(key, 0.0) + tt
    return out


async def run_profile(
    size: int, rate: float, cpus: tuple[int, int], warmup: float, window: float, tmp: Path
) -> str:
    (tmp / "sitecustomize.py").write_text(SITECUSTOMIZE)
    rows = await run_mso(
        cpus, [(size, rate)], warmup, window, tmp, {"MSO_BENCH_PROFILE_DIR": str(tmp)}
    )
    text = io.StringIO()
    row = rows[0]
    eps = row.get("sink", {}).get("events_per_s", 0.0)
    events = int(row.get("source_emitted") or 0)
    how = f"paced at {rate:g} events/s" if rate else "saturated"
    text.write(
        f"mso {size} B {how}, sender CPU {cpus[0]}, receiver CPU {cpus[1]}, under cProfile: "
        f"{eps:,.0f} events/s; CPU use {json.dumps(row.get('cpu_util'))}; "
        f"{events:,} events emitted\n"
        "profile-<pid>.prof: the lower pid is N1 (the source's node), the higher N2 (the sink's); "
        "profile-<pid>-t<thread>.prof: that node's other threads (vertex workers)\n"
    )
    mains = sorted(
        (p for p in tmp.glob("profile-*.prof") if "-t" not in p.stem),
        key=lambda p: int(p.stem.split("-")[1]),
    )
    if not mains:
        text.write("no profile was written (did the nodes exit normally?)\n")
    for prof, node in zip(mains, ("N1 (sender)", "N2 (receiver)"), strict=False):
        pid = prof.stem.split("-")[1]
        threads = sorted(tmp.glob(f"profile-{pid}-t*.prof"))
        other: dict[str, float] = {}
        stages = stage_breakdown([prof, *threads], other)
        busy = {k: v for k, v in stages.items() if k not in ("idle", "start-up")}
        total = sum(busy.values())
        text.write(f"\n=== {node}: own time by stage, µs per event (of {events:,}) ===\n")
        text.write("| stage | µs per event | share |\n|---|---:|---:|\n")
        for k, v in sorted(busy.items(), key=lambda kv: -kv[1]):
            per = v / events * 1e6 if events else 0.0
            text.write(f"| {k} | {per:.2f} | {v / total if total else 0:.0%} |\n")
        text.write(f"| total | {total / events * 1e6 if events else 0:.2f} | 100% |\n")
        text.write("\nother, the largest:\n")
        for k, v in sorted(other.items(), key=lambda kv: -kv[1])[:15]:
            text.write(f"  {v / events * 1e6 if events else 0:8.2f} µs/event  {k}\n")
        for name, path in [(prof.name, prof)] + [(t.name, t) for t in threads]:
            stats = pstats.Stats(str(path), stream=text)
            text.write(f"\n=== {node}, {name}: top 25 by own time ===\n")
            stats.sort_stats("tottime").print_stats(25)
    return text.getvalue()


# -- report -------------------------------------------------------------------------------------
def _fmt(x: Any, spec: str) -> str:
    if x is None or (isinstance(x, float) and math.isnan(x)):
        return "-"
    return format(x, spec)


def _eps(row: dict[str, Any]) -> float:
    return float(row.get("sink", {}).get("events_per_s") or 0.0)


def best_rows(rows: list[dict[str, Any]]) -> dict[tuple[Any, ...], dict[str, Any]]:
    """Per (placement, size, rate, system): the repetition with the most events/s, with the
    spread of all repetitions attached as ``_all``."""
    groups: dict[tuple[Any, ...], list[dict[str, Any]]] = {}
    for r in rows:
        groups.setdefault((r["placement"], r["size"], r["rate"], r["system"]), []).append(r)
    out = {}
    for key, rs in groups.items():
        best = max(rs, key=_eps)
        out[key] = {**best, "_all": [_eps(r) for r in rs]}
    return out


def render(rows: list[dict[str, Any]]) -> str:
    best = best_rows(rows)
    out: list[str] = []
    for paced in (False, True):
        title = (
            f"Paced at {PACED_RATE:g} events/s (latency of the path, not of a queue); one run"
            if paced
            else "Saturated (source emits as fast as flow control allows); best of the reps, "
            "mso and baseline alternating"
        )
        out += [
            f"**{title}**",
            "",
            "| placement | size B | system | events/s | all reps, events/s | MB/s | p50 µs "
            "| p99 µs | send CPU | recv CPU | mso/baseline |",
            "|---|---:|---|---:|---:|---:|---:|---:|---:|---:|---:|",
        ]
        for (placement, size, rate, system), r in best.items():
            if bool(rate) != paced:
                continue
            s = r.get("sink", {})
            eps = s.get("events_per_s")
            ratio = ""
            base = best.get((placement, size, rate, "baseline"))
            if system == "mso" and base and eps and _eps(base) and not paced:
                ratio = f"{eps / _eps(base):.2f}"
            cpu = r.get("cpu_util", {})
            mbs = eps * size / 1e6 if eps else None
            err = f" ({r['error']})" if r.get("error") else ""
            spread = " / ".join(f"{x / 1e3:,.0f}k" for x in r["_all"]) if not paced else ""
            out.append(
                f"| {placement} | {size} | {system}{err} | {_fmt(eps, ',.0f')} | {spread} "
                f"| {_fmt(mbs, '.1f')} | {_fmt(s.get('latency_p50_us'), ',.0f')} "
                f"| {_fmt(s.get('latency_p99_us'), ',.0f')} "
                f"| {_fmt(cpu.get('sender'), '.0%')} | {_fmt(cpu.get('receiver'), '.0%')} "
                f"| {ratio} |"
            )
        out.append("")
    for (placement, size, rate, system), r in best.items():
        if system != "mso" or rate:
            continue
        eps = _eps(r)
        base = best.get((placement, size, rate, "baseline"))
        beps = _eps(base) if base else 0.0
        verdict = "met" if beps and eps >= TARGET_RATIO * beps else "MISSED"
        line = (
            f"- {placement}, {size} B: mso {eps:,.0f} events/s = "
            f"{(eps / beps if beps else 0):.0%} of the baseline (target >= 50%): {verdict}"
        )
        if size == 38:
            ok = "met" if eps >= TARGET_38B_EPS else "MISSED"
            line += f"; >= {TARGET_38B_EPS:,} events/s at 38 B: {ok}"
        out.append(line)
    out.append(
        "- CPU columns: each process's CPU time (utime+stime from /proc) over a window of the "
        "same length sampled by the driver right after the warm-up, divided by its length; "
        "100% = one full vCPU."
    )
    loads = [r.get("loadavg_before", 0.0) for r in rows]
    if loads:
        out.append(
            f"- 1-min load average before each case: {min(loads):.2f} to {max(loads):.2f} "
            "(the machine is shared; other sessions' processes add noise)"
        )
    return "\n".join(out) + "\n"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="smoke run: short windows, 1 rep")
    ap.add_argument(
        "--reps",
        type=int,
        default=2,
        help="repetitions of each saturated case (mso then baseline, alternating); the table "
        "shows the best of them for both systems, the JSON every one",
    )
    ap.add_argument(
        "--profile",
        action="append",
        default=[],
        metavar="SIZE@CPUS",
        help="add a cProfile'd mso run, e.g. 38@0,0 or 3000@0,1 (repeatable)",
    )
    ap.add_argument("--only-profile", action="store_true", help="run only the --profile runs")
    ap.add_argument("--warmup", type=float, default=None, help="seconds before the window")
    ap.add_argument("--window", type=float, default=None, help="measurement window, seconds")
    # the baseline's child processes
    ap.add_argument("--role", choices=("recv", "send"), help=argparse.SUPPRESS)
    ap.add_argument("--cpu", type=int, default=0, help=argparse.SUPPRESS)
    ap.add_argument("--port", type=int, default=0, help=argparse.SUPPRESS)
    ap.add_argument("--size", type=int, default=38, help=argparse.SUPPRESS)
    ap.add_argument("--rate", type=float, default=0.0, help=argparse.SUPPRESS)
    ap.add_argument("--duration", type=float, default=10.0, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.role:
        args.warmup = 1.0 if args.warmup is None else args.warmup
        args.window = 2.0 if args.window is None else args.window
        child_main(args)
        return 0
    warmup = args.warmup if args.warmup is not None else (0.3 if args.quick else 0.75)
    window = args.window if args.window is not None else (0.5 if args.quick else 1.5)
    if not (0 < warmup <= 30 and 0 < window <= 60):
        ap.error("--warmup must be in (0, 30] and --window in (0, 60]")
    reps = 1 if args.quick else args.reps
    if not 1 <= reps <= 5:
        ap.error("--reps: 1..5")
    cases = [(size, 0.0) for size in SIZES for _ in range(reps)]
    cases += [(size, PACED_RATE) for size in SIZES]
    profiles: list[tuple[int, tuple[int, int], float]] = []
    for spec in args.profile:
        try:
            size_text, cpu_text, *rate_text = spec.split("@")
            a, b = (int(c) for c in cpu_text.split(","))
            profiles.append((int(size_text), (a, b), float(rate_text[0]) if rate_text else 0.0))
        except (ValueError, IndexError):
            ap.error(f"--profile: expected SIZE@CPU,CPU[@RATE] such as 3000@0,1, got {spec!r}")
    original = os.sched_getaffinity(0)
    rows: list[dict[str, Any]] = []
    profile_text: dict[str, str] = {}
    t_start = time.monotonic()
    try:
        with tempfile.TemporaryDirectory(prefix="mso-bench-dataplane-") as tmpdir:
            tmp = Path(tmpdir)
            for placement, cpus in PLACEMENTS.items():
                if args.only_profile:
                    break
                os.sched_setaffinity(0, {cpus[0]})  # the controller beside the sender

                async def baseline(size: int, rate: float, cpus: tuple[int, int] = cpus) -> Any:
                    return await run_baseline(size, rate, cpus, warmup, window)

                for r in asyncio.run(run_mso(cpus, cases, warmup, window, tmp, None, baseline)):
                    rows.append({"placement": placement, **r})
            for size, cpus, rate in profiles:
                os.sched_setaffinity(0, {cpus[0]})
                tag = f"{size}-{cpus[0]}{cpus[1]}" + (f"-paced{rate:g}" if rate else "")
                ptmp = tmp / f"profile-{tag}"
                ptmp.mkdir()
                profile_text[tag] = asyncio.run(
                    run_profile(size, rate, cpus, warmup, max(window, 2.0), ptmp)
                )
    finally:
        os.sched_setaffinity(0, original)
    RESULTS.mkdir(parents=True, exist_ok=True)
    for tag, text in profile_text.items():
        path = RESULTS / f"dataplane-profile-{tag}.txt"
        path.write_text(text)
        print(f"profile written to {path}")
    if args.only_profile:
        return 0
    table = render(rows)
    name = "dataplane-quick" if args.quick else "dataplane"
    out = {
        "benchmark": "dataplane",
        "src_digest": src_digest(),
        "measured_at": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
        "quick": args.quick,
        "warmup_s": warmup,
        "window_s": window,
        "paced_rate": PACED_RATE,
        "baseline_batch": BATCH,
        "reps": reps,
        "loadavg_end": os.getloadavg(),
        "elapsed_s": time.monotonic() - t_start,
        "targets": {"ratio_to_baseline": TARGET_RATIO, "events_per_s_38B": TARGET_38B_EPS},
        "rows": rows,
    }
    (RESULTS / f"{name}.json").write_text(json.dumps(out, indent=2) + "\n")
    (RESULTS / f"{name}.md").write_text(table)
    print(table)
    errors = [r for r in rows if r.get("error")]
    return 1 if errors else 0


if __name__ == "__main__":
    sys.exit(main())
