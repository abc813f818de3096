"""ROS 2 through mso: the bridge's cost and what per-edge QoS does for a camera (issue 26).

Everything goes through a Zenoh router in this process on 127.0.0.1 (``rmw_zenohd``'s role;
one of its own for each phase of part 1 and each throughput run); talkers and listeners are
rmw_zenoh-style sessions (:mod:`mso.benchmarks.rmwpeers`: peers of the router) publishing CDR
with the 33-byte attachment on the keys rmw_zenoh uses. Each talker stamps ``header.stamp``
with the wall clock at publication; listeners read it back from the CDR bytes without
decoding the rest. Parts:

1. **The bridge in one process** (no mso node): a ``sensor_msgs/LaserScan`` (1,081 beams,
   intensities too: 8.7 KB) at 40 Hz and a ``sensor_msgs/Image`` (640x480 rgb8: 900 KiB) at
   30 Hz, (a) talker -> raw listener (Zenoh alone, the baseline: a plain zenoh-python
   subscriber in a client session of the router, where the Subscriber sits), (b) talker ->
   ``mso.ros2:Subscriber`` -> the vertex's ``next()`` (a worker thread, as mso's executor
   calls it), (c) ``mso.ros2:Publisher`` -> raw listener. The latency each hop adds over the
   baseline (p50, p99) and the CPU it adds per message (this process's CPU time over the phase,
   less the baseline's). Then throughput: Images as fast as the talker can put them into a
   Subscriber (reliable, keep_all: nothing dropped), and out of a Publisher.
2. **Into mso and back out** on two emulated node processes: talker -> Subscriber (N1) ->
   Publisher (N2) -> listener, the Image and the LaserScan streams side by side for
   ``--duration``: delivered/sent, end to end latency p50/p99 (through the router twice and
   mso's edge once), each vertex's CPU per message (mso status).
3. **keep_last: 1 against reliable**: a 10 Hz camera (Image) -> Subscriber (N1) -> a 2 Hz
   consumer (N2, 0.5 s a frame): how old the frames it processes are, over the run.
4. **A 10,000-message bag replayed at 10x**: LaserScans recorded at 40 Hz (250 s) ->
   ``mso.ros2:BagSource`` (rate 10, N1) -> a sink (N2) timing each arrival against the
   recording: count, span (25 s expected), lateness p50/p99/max.

Usage: .venv/bin/python bench/ros2.py [--quick] [--duration 30] [--only 1,2,3,4] [--json FILE]
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import multiprocessing
import shutil
import tempfile
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import zenoh
from rosbags.rosbag2 import StoragePlugin, Writer

from mso.benchmarks import rmwpeers
from mso.benchmarks.common import provenance, write_results
from mso.benchmarks.rmwpeers import config, stamp_of, wait_until
from mso.emu.controller import Emulator
from mso.errors import MsoError
from mso.ros2 import Publisher, Subscriber, wire
from mso.ros2.types import type_map
from mso.scenario import loads_scenario

HERE = Path(__file__).resolve().parent
RESULTS = HERE / "results"
TYPES = type_map("jazzy")
STORE = TYPES.store
IMAGE, SCAN = "sensor_msgs/msg/Image", "sensor_msgs/msg/LaserScan"
BEAMS = 1081  # a Hokuyo UTM-30LX: 1,081 beams at 40 Hz
VERTICES = "mso.benchmarks.vertices.ros2"
HEARTBEAT_S, DEAD_S = 0.5, 3.0  # the nodes' failure detection here (see emulated())
LINE2 = """\
name: ros2bench
nodes: {N1: {}, N2: {}}
links: [[N1, N2]]
"""


# -- Zenoh, as rmw_zenoh uses it -------------------------------------------------------------
def key(topic: str, ros_type: str) -> str:
    return wire.topic_key(0, topic, ros_type, TYPES.rihs01(ros_type))


def make(ros_type: str) -> Callable[[int], Any]:
    """A message of ``ros_type`` stamped ``ns`` (the payload made once)."""
    Header, Time = STORE.types["std_msgs/msg/Header"], STORE.types["builtin_interfaces/msg/Time"]
    if ros_type == IMAGE:
        data = np.random.default_rng(1).integers(0, 255, 640 * 480 * 3, dtype=np.uint8)
        cls = STORE.types[IMAGE]

        def image(ns: int) -> Any:
            header = Header(stamp=Time(sec=ns // 10**9, nanosec=ns % 10**9), frame_id="camera")
            return cls(
                header=header,
                height=480,
                width=640,
                encoding="rgb8",
                is_bigendian=0,
                step=1920,
                data=data,
            )

        return image
    ranges = np.random.default_rng(2).uniform(0.1, 30.0, BEAMS).astype(np.float32)
    cls = STORE.types[SCAN]

    def scan(ns: int) -> Any:
        header = Header(stamp=Time(sec=ns // 10**9, nanosec=ns % 10**9), frame_id="laser")
        return cls(
            header=header,
            angle_min=-2.356,
            angle_max=2.356,
            angle_increment=0.00436,
            time_increment=1.7e-5,
            scan_time=0.025,
            range_min=0.1,
            range_max=30.0,
            ranges=ranges,
            intensities=ranges,
        )

    return scan


class Talker:
    """Publishes ``ros_type`` on ``topic`` as an rmw_zenoh publisher does."""

    def __init__(self, session: Any, topic: str, ros_type: str) -> None:
        self.pub = session.declare_publisher(
            key(topic, ros_type),
            reliability=zenoh.Reliability.RELIABLE,
            congestion_control=zenoh.CongestionControl.BLOCK,
        )
        self.make, self.ros_type, self.seq = make(ros_type), ros_type, 0
        self.gid = bytes(range(16))

    def put(self, payload: bytes | None = None) -> None:
        """Publish a message stamped now (or ``payload`` as it is: a throughput run, where
        the talker's own serializing would be the bottleneck)."""
        self.seq += 1
        ns = time.time_ns()
        if payload is None:
            payload = bytes(STORE.serialize_cdr(self.make(ns), self.ros_type))
        self.pub.put(payload, attachment=rmwpeers.attachment(self.seq, ns, self.gid))

    def run(self, hz: float, n: int) -> None:
        t0 = time.monotonic()
        for i in range(n):
            wait = t0 + i / hz - time.monotonic()
            if wait > 0:
                time.sleep(wait)
            self.put()

    def close(self) -> None:
        self.pub.undeclare()


class Listener:
    """Counts messages on a key and how long after their stamp each arrived (ms)."""

    def __init__(self, session: Any, topic: str, ros_type: str) -> None:
        self.lat: list[float] = []
        self.lock = threading.Lock()
        self.sub = session.declare_subscriber(key(topic, ros_type), self._on)

    def _on(self, sample: Any) -> None:
        now = time.time_ns()
        ms = (now - stamp_of(sample.payload.to_bytes())) / 1e6
        with self.lock:
            self.lat.append(ms)

    def count(self) -> int:
        with self.lock:
            return len(self.lat)

    def close(self) -> None:
        self.sub.undeclare()


def q(values: list[float], p: float) -> float:
    if not values:
        return float("nan")
    ordered = sorted(values)
    return round(ordered[min(len(ordered) - 1, int(p * len(ordered)))], 3)


def lat(values: list[float]) -> dict[str, float]:
    return {"p50": q(values, 0.5), "p99": q(values, 0.99), "max": q(values, 1.0)}


# -- 1: the bridge in one process ------------------------------------------------------------
def drain(sub: Subscriber, n: int, timeout: float) -> tuple[list[float], list[float]]:
    """Call the Subscriber's next() as mso's worker does, until ``n`` messages; returns each
    one's latency from its stamp (ms) and when it came (monotonic s)."""
    got: list[float] = []
    when: list[float] = []
    end = time.monotonic() + timeout
    while len(got) < n and time.monotonic() < end:
        event = next(sub)
        if event is None:
            continue
        now = time.time_ns()
        st = event.header.stamp
        got.append((now - (st.sec * 10**9 + st.nanosec)) / 1e6)
        when.append(time.monotonic())
    return got, when


def bridge_phases(ros_type: str, hz: float, n: int) -> dict[str, Any]:
    """Zenoh alone, into a Subscriber, out of a Publisher: each through a router of its own
    (with a peer session of its own for the talker and the listener)."""
    name = ros_type.rsplit("/", 1)[1].lower()
    out: dict[str, Any] = {"type": ros_type, "hz": hz, "messages": n}
    # (a) Zenoh alone: a raw listener where the Subscriber will be, a client of the router
    router, endpoint = rmwpeers.router()
    peer: Any = zenoh.open(config("peer", connect=endpoint))
    client: Any = zenoh.open(config("client", connect=endpoint))
    listener = Listener(client, f"/{name}_a", ros_type)
    talker = Talker(peer, f"/{name}_a", ros_type)
    time.sleep(0.5)
    cpu = time.process_time()
    talker.run(hz, n)
    wait_until(lambda: listener.count() >= n, 10)
    base_cpu = (time.process_time() - cpu) / n
    out["zenoh"] = {
        "delivered": listener.count(),
        "latency_ms": lat(listener.lat),
        "cpu_ms_per_msg": round(base_cpu * 1e3, 3),
    }
    talker.close()
    listener.close()
    client.close()
    peer.close()
    router.close()
    # (b) talker -> Subscriber -> next()
    router, endpoint = rmwpeers.router()
    peer = zenoh.open(config("peer", connect=endpoint))
    sub = Subscriber(f"/{name}_b", ros_type, router=endpoint, qos={"history": "keep_all"})
    sub.open()
    talker = Talker(peer, f"/{name}_b", ros_type)
    time.sleep(0.5)
    cpu = time.process_time()
    result: list[Any] = []
    reader = threading.Thread(target=lambda: result.append(drain(sub, n, n / hz + 15)))
    reader.start()
    talker.run(hz, n)
    reader.join()
    got = result[0][0]
    cpu_b = (time.process_time() - cpu) / n
    stats = sub.stats()
    talker.close()
    sub.close()
    out["into_mso"] = {
        "delivered": len(got),
        "latency_ms": lat(got),
        "added_p50_ms": round(q(got, 0.5) - out["zenoh"]["latency_ms"]["p50"], 3),
        "added_p99_ms": round(q(got, 0.99) - out["zenoh"]["latency_ms"]["p99"], 3),
        "cpu_ms_per_msg": round(cpu_b * 1e3, 3),
        "added_cpu_ms_per_msg": round((cpu_b - base_cpu) * 1e3, 3),
        "undecodable": stats["undecodable"],
    }
    peer.close()
    router.close()
    # (c) Publisher -> listener
    router, endpoint = rmwpeers.router()
    peer = zenoh.open(config("peer", connect=endpoint))
    pub = Publisher(f"/{name}_c", ros_type, router=endpoint)
    pub.open()
    listener = Listener(peer, f"/{name}_c", ros_type)
    time.sleep(0.5)
    build = make(ros_type)
    events = []  # the Structs an upstream vertex would hand it (made before the clock runs)
    for _ in range(min(n, 50)):
        events.append(TYPES.to_struct(ros_type, build(0)))
    cpu = time.process_time()
    t0 = time.monotonic()
    for i in range(n):
        wait = t0 + i / hz - time.monotonic()
        if wait > 0:
            time.sleep(wait)
        ev = events[i % len(events)]
        ns = time.time_ns()
        ev.header.stamp.sec, ev.header.stamp.nanosec = ns // 10**9, ns % 10**9
        pub(ev)
    wait_until(lambda: listener.count() >= n, 10)
    cpu_c = (time.process_time() - cpu) / n
    out["out_of_mso"] = {
        "delivered": listener.count(),
        "latency_ms": lat(listener.lat),
        "added_p50_ms": round(q(listener.lat, 0.5) - out["zenoh"]["latency_ms"]["p50"], 3),
        "added_p99_ms": round(q(listener.lat, 0.99) - out["zenoh"]["latency_ms"]["p99"], 3),
        "cpu_ms_per_msg": round(cpu_c * 1e3, 3),
        "added_cpu_ms_per_msg": round((cpu_c - base_cpu) * 1e3, 3),
    }
    listener.close()
    pub.close()
    peer.close()
    router.close()
    return out


def talk_images(endpoint: str, n: int, done: Any) -> None:
    """A talker process: ``n`` Images (one payload, made once) as fast as Zenoh takes them."""
    session: Any = zenoh.open(config("peer", connect=endpoint))
    talker = Talker(session, "/image_t", IMAGE)
    time.sleep(1.0)  # (its declarations reach the router and the Subscriber)
    payload = bytes(STORE.serialize_cdr(make(IMAGE)(time.time_ns()), IMAGE))
    t0 = time.monotonic()
    for _ in range(n):
        talker.put(payload)
    done.put(round(n / (time.monotonic() - t0), 1))
    time.sleep(1.0)
    talker.close()
    session.close()


def listen_images(endpoint: str, n: int, ready: Any, counted: Any) -> None:
    """A listener process: counts Images on /image_o until ``n`` or 60 s of none."""
    session: Any = zenoh.open(config("peer", connect=endpoint))
    times: list[float] = []
    sub = session.declare_subscriber(
        key("/image_o", IMAGE), lambda s: times.append(time.monotonic())
    )
    ready.put(True)
    last = time.monotonic()
    while len(times) < n and time.monotonic() - last < 60:
        seen = len(times)
        time.sleep(0.1)
        if len(times) > seen:
            last = time.monotonic()
    counted.put((len(times), times[-1] - times[0] if len(times) > 1 else 0.0))
    sub.undeclare()
    session.close()


def throughput(n: int) -> dict[str, Any]:
    """Images as fast as they go, into a Subscriber (reliable, keep_all; the talker in another
    process) and out of a Publisher (the listener in another process), each through a router
    of its own."""
    router, endpoint = rmwpeers.router()
    sub = Subscriber("/image_t", IMAGE, router=endpoint, qos={"history": "keep_all"})
    sub.open()
    time.sleep(0.5)
    result: list[Any] = []
    reader = threading.Thread(target=lambda: result.append(drain(sub, n, 120)))
    reader.start()
    # the talker in a process of its own: in this one it would share the GIL with the bridge
    ctx = multiprocessing.get_context("spawn")
    done = ctx.Queue()
    child = ctx.Process(target=talk_images, args=(endpoint, n, done))
    child.start()
    put_per_s = done.get(timeout=180)
    child.join(30)
    reader.join()
    got, when = result[0]
    sub.close()
    router.close()
    into = {
        "sent": n,
        "received": len(got),
        "talker_put_per_s": put_per_s,
        "per_s": round((len(when) - 1) / (when[-1] - when[0]), 1) if len(when) > 1 else 0.0,
    }
    router, endpoint = rmwpeers.router()
    ready, counted = ctx.Queue(), ctx.Queue()
    child = ctx.Process(target=listen_images, args=(endpoint, n, ready, counted))
    child.start()
    ready.get(timeout=60)
    pub = Publisher("/image_o", IMAGE, router=endpoint)
    pub.open()
    time.sleep(1.0)
    event = TYPES.to_struct(IMAGE, make(IMAGE)(time.time_ns()))
    t0 = time.monotonic()
    for _ in range(n):
        pub(event)
    calls_s = time.monotonic() - t0
    received, span = counted.get(timeout=120)
    child.join(30)
    pub.close()
    router.close()
    out = {
        "sent": n,
        "received": received,
        "calls_per_s": round(n / calls_s, 1),
        "per_s": round((received - 1) / span, 1) if span > 0 else 0.0,
    }
    return {"into_subscriber": into, "out_of_publisher": out}


# -- 2-4: on emulated node processes ---------------------------------------------------------
def through_app(endpoint: str) -> str:
    def pair(name: str, ros_type: str) -> str:
        fmt = f"mso.ros2.types:{ros_type.replace('/', '__')}"
        return (
            f'  {name}_in: {{code: "mso.ros2:Subscriber", pinned: N1, output: "{fmt}",\n'
            f'    params: {{topic: /{name}, type: {ros_type}, router: "{endpoint}",\n'
            f"             qos: {{history: keep_all}}}}}}\n"
            f'  {name}_out: {{code: "mso.ros2:Publisher", pinned: N2,\n'
            f'    params: {{topic: /{name}_out, type: {ros_type}, router: "{endpoint}"}}}}\n'
        )

    return (
        "name: bridge\nvertices:\n"
        + pair("camera", IMAGE)
        + pair("scan", SCAN)
        + "edges: [[camera_in, camera_out], [scan_in, scan_out]]\n"
    )


def stale_app(endpoint: str, name: str, qos: str) -> str:
    fmt = f"mso.ros2.types:{IMAGE.replace('/', '__')}"
    return f"""\
name: {name}
vertices:
  cam: {{code: "mso.ros2:Subscriber", pinned: N1, output: "{fmt}",
        params: {{topic: /{name}, type: {IMAGE}, router: "{endpoint}"}}}}
  slow: {{code: "{VERTICES}:Stale", pinned: N2, params: {{delay_s: 0.5}}}}
edges: [{{from: cam, to: slow{qos}}}]
"""


def bag_app(path: Path) -> str:
    fmt = f"mso.ros2.types:{SCAN.replace('/', '__')}"
    return f"""\
name: replay
vertices:
  play: {{code: "mso.ros2:BagSource", pinned: N1, output: "{fmt}",
         params: {{path: "{path}", rate: 10}}}}
  time: {{code: "{VERTICES}:Arrivals", pinned: N2, params: {{rate: 10}}}}
edges: [[play, time]]
"""


def make_bag(path: Path, n: int, hz: float) -> None:
    writer = Writer(path, version=9, storage_plugin=StoragePlugin.MCAP)
    writer.open()
    conn = writer.add_connection("/scan", SCAN, typestore=STORE)
    build = make(SCAN)
    t0 = 1_700_000_000 * 10**9
    for i in range(n):
        ns = t0 + int(i * 1e9 / hz)
        writer.write(conn, ns, bytes(STORE.serialize_cdr(build(ns), SCAN)))
    writer.close()


def vstat(nodes: dict[str, Any], node: str, app: str, vertex: str) -> dict[str, Any]:
    found: dict[str, Any] = nodes[node]["apps"][app]["vertices"][vertex]
    return found


async def emulated(
    endpoint: str, peer: Any, duration: float, parts: set[int], bag_n: int
) -> dict[str, Any]:
    out: dict[str, Any] = {}
    # failure detection at 0.5 s beats / 3 s (the default 0.1 / 0.5 s declared these nodes
    # failed again and again at a load of 15 on this box, under the reliable camera's backlog)
    emu = Emulator(
        loads_scenario(LINE2), manage=False, heartbeat_s=HEARTBEAT_S, dead_after_s=DEAD_S
    )
    await emu.start()
    try:
        if 2 in parts:
            out["through_mso"] = await _through(emu, endpoint, peer, duration)
        if 4 in parts:
            out["bag_replay"] = await _replay(emu, bag_n)
        if 3 in parts:
            out["slow_consumer"] = {
                "keep_last_1": await _stale(
                    emu, endpoint, peer, "stale_kl", ", keep_last: 1", duration
                ),
                "reliable": await _stale(emu, endpoint, peer, "stale_rel", "", duration),
            }
    finally:
        await emu.stop()
    return out


async def _ready(peer: Any, n: int) -> None:
    def tokens() -> int:
        return sum("/MS/" in t or "/MP/" in t for t in rmwpeers.tokens(peer))

    if not await asyncio.to_thread(wait_until, lambda: tokens() >= n, 30):
        raise RuntimeError("the mso ROS vertices did not show up on the router")


async def _through(emu: Emulator, endpoint: str, peer: Any, duration: float) -> dict[str, Any]:
    await emu.deploy(through_app(endpoint), "bridge.yaml", "N1", check=True)
    await _ready(peer, 4)
    listeners = {
        "camera": Listener(peer, "/camera_out", IMAGE),
        "scan": Listener(peer, "/scan_out", SCAN),
    }
    talkers = {"camera": Talker(peer, "/camera", IMAGE), "scan": Talker(peer, "/scan", SCAN)}
    await asyncio.sleep(0.5)
    sent = {"camera": int(30 * duration), "scan": int(40 * duration)}
    await asyncio.gather(
        asyncio.to_thread(talkers["camera"].run, 30.0, sent["camera"]),
        asyncio.to_thread(talkers["scan"].run, 40.0, sent["scan"]),
    )
    await asyncio.to_thread(
        wait_until, lambda: all(listeners[k].count() >= sent[k] for k in sent), 15
    )
    nodes = await emu.status()
    out: dict[str, Any] = {}
    for k, ros_type in (("camera", IMAGE), ("scan", SCAN)):
        vin, vout = (
            vstat(nodes, "N1", "bridge", f"{k}_in"),
            vstat(nodes, "N2", "bridge", f"{k}_out"),
        )
        out[k] = {
            "type": ros_type,
            "sent": sent[k],
            "delivered": listeners[k].count(),
            "latency_ms": lat(listeners[k].lat),
            "subscriber_cpu_ms_per_msg": round(vin["cpu_s"] * 1e3 / max(1, vin["emitted"]), 3),
            # its decoding, on Zenoh's threads (not in the vertex's CPU)
            "subscriber_decode_ms_per_msg": round(
                vin["stats"].get("decode_ms", 0.0) / max(1, vin["emitted"]), 3
            ),
            "publisher_cpu_ms_per_msg": round(vout["cpu_s"] * 1e3 / max(1, vout["processed"]), 3),
            "subscriber_stats": vin["stats"],
        }
        talkers[k].close()
        listeners[k].close()
    await emu.undeploy("bridge")
    return out


async def _undeploy(emu: Emulator, name: str) -> None:
    """Undeploy ``name``, asking again while a loaded node does not answer (for 60 s)."""
    for _ in range(12):
        try:
            await emu.undeploy(name)
            return
        except (MsoError, OSError):
            await asyncio.sleep(5.0)
    await emu.undeploy(name)


async def _stale(
    emu: Emulator, endpoint: str, peer: Any, name: str, qos: str, duration: float
) -> dict[str, Any]:
    await emu.deploy(stale_app(endpoint, name, qos), f"{name}.yaml", "N1", check=True)
    await _ready(peer, 1)
    talker = Talker(peer, f"/{name}", IMAGE)
    await asyncio.sleep(0.5)
    await asyncio.to_thread(talker.run, 10.0, int(10 * duration))
    app: dict[str, Any] = {}
    for _ in range(10):  # (a status may miss a node under load: ask again)
        with contextlib.suppress(MsoError, OSError):
            nodes = await emu.status()
            app = nodes.get("N2", {}).get("apps", {}).get(name, {})
        if "slow" in app.get("vertices", {}):
            break
        await asyncio.sleep(1.0)
    else:
        talker.close()
        return {"error": f"N2 does not report the consumer: {json.dumps(app)[:2000]}"}
    stats = app["vertices"]["slow"]["stats"]
    edge = app["edges"]["cam->slow"]
    talker.close()
    await _undeploy(emu, name)
    ages = [a for _, a in stats["ages"]]
    half = ages[len(ages) // 2 :]
    return {
        "frames_sent": int(10 * duration),
        "processed": stats["count"],
        "superseded": edge.get("superseded", 0),
        "age_s": {
            "p50_second_half": q(half, 0.5),
            "max": q(ages, 1.0),
            "last": round(ages[-1], 3) if ages else None,
        },
        "ages": [[round(t, 2), a] for t, a in stats["ages"]][::2],
    }


async def _replay(emu: Emulator, n: int) -> dict[str, Any]:
    folder = Path(tempfile.mkdtemp(prefix="mso-ros2bench-"))
    try:
        bag = folder / "scans"
        await asyncio.to_thread(make_bag, bag, n, 40.0)
        size = sum(p.stat().st_size for p in bag.iterdir())
        await emu.deploy(bag_app(bag), "replay.yaml", "N1", check=True)
        expected = n / 40.0 / 10
        loop = asyncio.get_running_loop()
        end = loop.time() + expected + 60
        stats: dict[str, Any] = {}
        while loop.time() < end:
            await asyncio.sleep(1.0)
            stats = vstat(await emu.status(), "N2", "replay", "time")["stats"]
            if stats["count"] >= n:
                break
        await emu.undeploy("replay")
        return {
            "messages": n,
            "recorded_hz": 40.0,
            "rate": 10,
            "bag_bytes": size,
            "expected_s": expected,
            **stats,
        }
    finally:
        shutil.rmtree(folder, ignore_errors=True)


# -- report ----------------------------------------------------------------------------------
def table(r: dict[str, Any]) -> str:
    lines = [
        f"### ROS 2 through mso (bench/ros2.py{' --quick' if r['quick'] else ''})",
        "",
        f"Machine: {r['machine']['cpus']} vCPUs, load average at the end "
        f"{', '.join(f'{x:.1f}' for x in r['machine']['load_average'])} (shared). Zenoh "
        "routers in the benchmark's process on 127.0.0.1 (one of its own for each phase of "
        "part 1 and each throughput run); talkers and listeners rmw_zenoh-style peers of them; "
        "Zenoh alone is a plain subscriber in a client session, where the Subscriber sits.",
        "",
    ]
    for b in r.get("bridge", []):
        z, i, o = b["zenoh"], b["into_mso"], b["out_of_mso"]
        lines += [
            f"**{b['type']}** at {b['hz']:g} Hz, {b['messages']} messages, in one process:",
            "",
            "| hop | delivered | latency p50 / p99 ms | added p50 / p99 ms | CPU ms/msg (added) |",
            "|---|---:|---:|---:|---:|",
            f"| talker -> listener (Zenoh alone) | {z['delivered']} | "
            f"{z['latency_ms']['p50']} / {z['latency_ms']['p99']} | - | "
            f"{z['cpu_ms_per_msg']} |",
            f"| talker -> Subscriber -> next() | {i['delivered']} | "
            f"{i['latency_ms']['p50']} / {i['latency_ms']['p99']} | "
            f"{i['added_p50_ms']} / {i['added_p99_ms']} | {i['cpu_ms_per_msg']} "
            f"({i['added_cpu_ms_per_msg']:+}) |",
            f"| Publisher -> listener | {o['delivered']} | "
            f"{o['latency_ms']['p50']} / {o['latency_ms']['p99']} | "
            f"{o['added_p50_ms']} / {o['added_p99_ms']} | {o['cpu_ms_per_msg']} "
            f"({o['added_cpu_ms_per_msg']:+}) |",
            "",
        ]
    if "throughput" in r:
        t = r["throughput"]
        a, b = t["into_subscriber"], t["out_of_publisher"]
        lines += [
            f"Images (900 KiB) as fast as they go: into a Subscriber {a['per_s']}/s "
            f"({a['received']} of {a['sent']}; the talker put {a['talker_put_per_s']}/s), "
            f"out of a Publisher {b['per_s']}/s ({b['received']} of {b['sent']}, a listener "
            f"in another process; {b['calls_per_s']} calls/s).",
            "",
        ]
    if "through_mso" in r:
        lines += [
            "Into mso and back out on two node processes (talker -> Subscriber N1 -> "
            f"Publisher N2 -> listener), both streams at once for {r['duration']:g} s:",
            "",
            "| stream | delivered / sent | end to end p50 / p99 / max ms | "
            "Subscriber CPU ms/msg | Publisher CPU ms/msg |",
            "|---|---:|---:|---:|---:|",
        ]
        for k, s in r["through_mso"].items():
            L = s["latency_ms"]
            lines.append(
                f"| {k} ({s['type']}) | {s['delivered']} / {s['sent']} | "
                f"{L['p50']} / {L['p99']} / {L['max']} | "
                f"{s['subscriber_cpu_ms_per_msg']} | {s['publisher_cpu_ms_per_msg']} |"
            )
        lines.append("")
    if "slow_consumer" in r:
        lines += [
            "A 10 Hz camera behind a 2 Hz consumer (0.5 s a frame), "
            f"{r['duration']:g} s: how old the frames it processes are",
            "",
            "| edge QoS | frames sent | processed | superseded | age p50 (2nd half) s | "
            "age max s | last s |",
            "|---|---:|---:|---:|---:|---:|---:|",
        ]
        for k, s in r["slow_consumer"].items():
            if "error" in s:
                lines.append(f"| {k.replace('_', ' ')} | {s['error'][:200]} | | | | | |")
                continue
            a = s["age_s"]
            lines.append(
                f"| {k.replace('_', ' ')} | {s['frames_sent']} | {s['processed']} | "
                f"{s['superseded']} | {a['p50_second_half']} | {a['max']} | "
                f"{a['last']} |"
            )
        lines.append("")
    if "bag_replay" in r:
        b = r["bag_replay"]
        L = b.get("late_ms", {})
        lines += [
            f"A bag of {b['messages']:,} LaserScans recorded at 40 Hz "
            f"({b['bag_bytes'] / 1e6:.1f} MB MCAP) replayed at 10x by BagSource (N1) to "
            f"a sink (N2): {b.get('count', 0):,} arrived over {b.get('span_s', 0)} s "
            f"(expected {b['expected_s']:g} s); lateness against the recording p50 "
            f"{L.get('p50')} ms, p99 {L.get('p99')} ms, max {L.get('max')} ms.",
            "",
        ]
    return "\n".join(lines) + "\n"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true", help="short phases (a smoke run)")
    ap.add_argument("--duration", type=float, default=30.0, help="seconds of parts 1-3")
    ap.add_argument("--only", default="1,2,3,4", help="which parts, e.g. 1,3")
    ap.add_argument("--json", type=Path, default=RESULTS / "ros2.json")
    args = ap.parse_args()
    parts = {int(p) for p in args.only.split(",") if p.strip()}
    duration = 6.0 if args.quick else args.duration
    bag_n = 1000 if args.quick else 10_000
    started = time.monotonic()
    router, endpoint = rmwpeers.router()
    peer: Any = rmwpeers.ros_peer(endpoint)
    result: dict[str, Any] = {"quick": args.quick, "duration": duration}
    try:
        if 1 in parts:
            result["bridge"] = [
                bridge_phases(SCAN, 40.0, int(40 * duration)),
                bridge_phases(IMAGE, 30.0, int(30 * duration)),
            ]
            result["throughput"] = throughput(300 if args.quick else 2000)
        if parts & {2, 3, 4}:
            result |= asyncio.run(emulated(endpoint, peer, duration, parts, bag_n))
    finally:
        peer.close()
        router.close()
    result |= provenance()
    result["seconds"] = round(time.monotonic() - started, 1)
    write_results(args.json, result, table(result))


if __name__ == "__main__":
    main()
