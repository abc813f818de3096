"""Where the robots' radio bytes go in the energy study (app accounting): every frame the
virtual-time simulator charges, by message type and direction, per robot, for static placements
run as ``bench/lifetime_floor.py`` runs them (120 s of virtual time each): its lowest-leader-draw
placement ("floor": scan filter, blob detectors and fusion on the leader) and Algorithm 1's.

The simulator charges each hop of a frame ``len(frame)`` bytes at the sender and the receiver
(``Simulation._send``; relays count both), the frame being the msgpack
:class:`~mso.protocol.messages.Envelope` around the message; the monitor turns those counters
into radio energy (``Monitor.sample``: 1.9 µJ per byte sent, 0.5 µJ per byte received here).
This script wraps ``_send`` to attribute every hop's bytes to the message's type (a ``Data``
frame resending events already sent counts as ``Data (retransmit)``, a frame relayed for others
as ``relayed``) and splits ``Data`` frames into the events' own bytes, the ``Data`` header and
the envelope. Its totals are shown beside what the monitor charged (they agree).

It then estimates, from the frames actually sent, what each avoidable overhead would save:

- heartbeats: the monitored figures a beat carries change once per monitor period, so one full
  beat per link per period; in between a slim liveness beat (node, incarnation), and none at all
  when the sender sent another frame over that link during the heartbeat period before it
  (every frame received is proof of life: ``NodeCore.receive`` calls ``liveness.heard_from``);
- the same with compact encodings: integer message tags and node ids, no power-model list (it
  never changes: the hello beat could carry it);
- acks coalesced: one frame per link per ``COALESCE_S`` (under the retransmission timeout) with
  the latest ack of each edge;
- data frames to the same next hop within ``MERGE_S`` sent as one (one envelope and app header);
- a compact data header: integer tag, app and node ids, the timestamp as 32-bit milliseconds.

Not charged by the simulator, and reported only per frame: the real wire's stream framing
(4-byte length + 16-byte tag, which the TCP transport's counters do include), TCP/IP and 802.11
headers, and the radio's per-packet energy.

    .venv/bin/python bench/lifetime_radio.py [--seconds 120] [--placement floor|algorithm1-kept]
                                             [--out FILE.json]
"""

from __future__ import annotations

import argparse
import itertools
import tempfile
import time
from collections import defaultdict
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any
from unittest import mock

import msgspec

from mso.benchmarks import lifetime as study
from mso.benchmarks.common import provenance, write_results
from mso.protocol import framing
from mso.protocol import messages as m
from mso.protocol.dataplane import RETRANSMIT_S
from mso.protocol.procedures.membership.liveness import HEARTBEAT_S
from mso.protocol.procedures.membership.peers import MONITOR_PERIOD_S
from mso.sim.runner import Simulation

# bench/lifetime_floor.py's leader-side vertices, and the ones its lowest leader draw ("nav
# filter+matcher, odom filter off, camera blobs+fusion" since the scan matcher sends ranges,
# 2026-11-25) keeps on the leader; the others go where
# Algorithm 1 puts them, or to N2 when that is the leader
FRONT = ("scan_filter", "scan_matcher", "odom_filter", "visible_blobs", "infrared_blobs",
         "blob_fusion", "bayes_inference", "target_map")  # fmt: skip
FLOOR_ON_LEADER = ("scan_filter", "scan_matcher", "visible_blobs", "infrared_blobs", "blob_fusion")
PLACEMENTS = ("floor", "algorithm1-kept")
WIRE_FRAMING_B = 4 + framing.TAG_BYTES  # u32 length + tag per frame on the real stream
COALESCE_S = 0.1  # acks of one link gathered this long: well under RETRANSMIT_S (0.25 s)
MERGE_S = 0.005  # data frames to one next hop this close in time could leave as one
DEPLOYMENT = {"AppAnnounce", "Probe", "ProbeReply", "ChainPlaced", "BuildChain",
              "ChainPartReady", "ChainBuilt", "StartApp"}  # fmt: skip
DIRECTIONS = ("sent", "received")


# -- what the overheads would cost in other encodings (estimates only, never sent) ----------
class _SlimBeat(msgspec.Struct, tag="hb", array_like=True):
    """A liveness-only heartbeat in today's encoding: who, which incarnation."""

    node: str
    incarnation: int


class _CompactSlimBeat(msgspec.Struct, tag=1, array_like=True):
    node: int
    incarnation: int


class _CompactBeat(msgspec.Struct, tag=2, array_like=True):
    """A full heartbeat with an integer tag and node ids, without the constant power list."""

    node: int
    cpu: float
    load: float
    drain_w: float
    remaining_j: float | None
    lifetime_s: float | None
    incarnation: int
    dead: dict[int, int]
    leader: int
    hosting: int


class _LinkAcks(msgspec.Struct, tag="acks", array_like=True):
    """Several edges' acks to one node in one frame: [edge, upto, positions] each."""

    app: str
    epoch: int
    acks: list[tuple[int, int, dict[int, int]]]


class _LinkData(msgspec.Struct, tag="datas", array_like=True):
    """Several edges' events to one node in one frame: [edge, seq, events, ts, floor] each."""

    app: str
    epoch: int
    parts: list[tuple[int, int, list[bytes], float, int]]


class _CompactData(msgspec.Struct, tag=3, array_like=True):
    app: int
    edge: int
    epoch: int
    seq: int
    events: list[bytes]
    ts_ms: int  # 32-bit milliseconds (wrapping): 5 bytes
    floor: int


class _CompactLinkData(msgspec.Struct, tag=4, array_like=True):
    app: int
    epoch: int
    parts: list[tuple[int, int, list[bytes], int, int]]  # edge, seq, events, ts_ms, floor


def _ms32(ts: float) -> int:
    """A timestamp as wrapping 32-bit milliseconds, always 5 bytes of msgpack."""
    return 2**31 + int(ts * 1e3) % 2**31


def _compact_data(x: m.Data) -> _CompactData:
    return _CompactData(0, x.edge, x.epoch, x.seq, x.events, _ms32(x.ts), x.floor)


class _CompactEnvelope(msgspec.Struct, array_like=True):
    src: int
    dst: int
    ttl: int
    kind: int
    body: msgspec.Raw


_ENC = msgspec.msgpack.Encoder()


def _ids(name: str) -> int:
    return int(name.lstrip("N") or 0) if name.lstrip("N").isdigit() else 0


def _compact_frame(src: str, dst: str, kind: int, body: msgspec.Struct) -> int:
    return len(_ENC.encode(_CompactEnvelope(_ids(src), _ids(dst), 32, kind,
                                            msgspec.Raw(_ENC.encode(body)))))  # fmt: skip


@dataclass(frozen=True)
class Hop:
    at: float
    a: str  # sender of this hop
    b: str  # receiver of this hop
    what: str  # category: message type, "Data (retransmit)"
    size: int  # frame bytes charged at each end
    msg: m.Message


@dataclass
class Tally:
    """Every hop of every frame the simulator charged, and sums per node/direction/type."""

    tx_uj: float
    rx_uj: float
    frames: dict[tuple[str, str, str], int] = field(default_factory=lambda: defaultdict(int))
    bytes: dict[tuple[str, str, str], int] = field(default_factory=lambda: defaultdict(int))
    # (node, direction, part) of fresh Data frames: events, data header, envelope
    parts: dict[tuple[str, str, str], int] = field(default_factory=lambda: defaultdict(int))
    hops: list[Hop] = field(default_factory=list)
    sent_upto: dict[tuple[str, str, int, int], int] = field(default_factory=dict)

    def category(self, src: str, msg: m.Message) -> str:
        if isinstance(msg, m.Data):
            key = (src, msg.app, msg.edge, msg.epoch)
            upto = self.sent_upto.get(key, 0)
            self.sent_upto[key] = max(upto, msg.seq + len(msg.events))
            if msg.seq < upto:
                return "Data (retransmit)"
        return type(msg).__name__

    def count(self, now: float, src: str, dst: str, msg: m.Message, route: list[str]) -> None:
        frame = len(m.wrap(src, dst, msg))
        body = len(m.encode(msg))
        what = self.category(src, msg)
        parts = {}
        if what == "Data" and isinstance(msg, m.Data):  # (a resent frame is all overhead)
            events = sum(map(len, msg.events))
            parts = {"events": events, "data header": body - events, "envelope": frame - body}
        for a, b in itertools.pairwise(route):
            for node, direction in ((a, "sent"), (b, "received")):
                relay = node not in (src, dst)
                key = (node, direction, f"relayed {what}" if relay else what)
                self.frames[key] += 1
                self.bytes[key] += frame
                for part, n in parts.items():
                    self.parts[(node, direction, ("relayed " if relay else "") + part)] += n
            self.hops.append(Hop(now, a, b, what, frame, msg))

    def mw(self, direction: str, bytes_per_s: float) -> float:
        return bytes_per_s * (self.tx_uj if direction == "sent" else self.rx_uj) * 1e-3

    def of(self, node: str, direction: str, keep: Callable[[Hop], bool]) -> list[Hop]:
        """The hops ``node`` sent (or received) that ``keep`` selects."""
        return [h for h in self.hops if (h.a if direction == "sent" else h.b) == node and keep(h)]


@contextmanager
def counting(tally: Tally) -> Iterator[None]:
    """Attribute every hop of every frame the simulator sends (the bytes it charges)."""
    original = Simulation._send

    def send(self: Simulation, node: str, dst: str, msg: m.Message) -> bool:
        route = self.network.route(node, dst)
        before = {n: tuple(c) for n, c in self.bytes.items()}
        ok = original(self, node, dst, msg)
        if ok and route is not None:
            # the study's links lose nothing: the simulator charged every hop of the route
            charged = {n for n, c in self.bytes.items() if tuple(c) != before[n]}
            assert charged == set(route), (charged, route)
            tally.count(self.now, node, dst, msg, list(route))
        return ok

    with mock.patch.object(Simulation, "_send", send):
        yield


def placement(name: str) -> dict[str, str]:
    net = study.network_for("app")
    doc = study.APP_FILE.read_text(encoding="utf-8")
    alg1 = study.placement_for("algorithm1-kept", doc, net)
    assert alg1 is not None
    if name == "algorithm1-kept":
        return alg1
    p = dict(alg1)
    for v in FRONT:  # as bench/lifetime_floor.py builds it
        on = v in FLOOR_ON_LEADER
        p[v] = study.LEADER if on else (alg1[v] if alg1[v] != study.LEADER else "N2")
    return p


def _windows(hops: list[Hop], span: float) -> list[list[Hop]]:
    """Hops grouped per link (sender, receiver) into windows of ``span`` from their first."""
    out: list[list[Hop]] = []
    open_: dict[tuple[str, str], list[Hop]] = {}
    for h in sorted(hops, key=lambda h: h.at):
        w = open_.get((h.a, h.b))
        if w is None or h.at - w[0].at > span:
            open_[(h.a, h.b)] = w = []
            out.append(w)
        w.append(h)
    return out


def heartbeats(t: Tally, node: str, dur: float) -> dict[str, dict[str, float]]:
    """Heartbeat bytes/s now; with one full beat per link per monitor period and slim or no
    beats between; and that with compact encodings (see the module docstring)."""
    other: dict[tuple[str, str], list[float]] = defaultdict(list)
    for h in t.hops:
        if h.what != "Heartbeat":  # a frame from a to b tells b that a lives
            other[(h.a, h.b)].append(h.at)
    out: dict[str, dict[str, float]] = {}
    for d in DIRECTIONS:
        beats = t.of(node, d, lambda h: h.what == "Heartbeat")
        now_b = after = compact = 0
        full: set[tuple[str, str, int]] = set()
        suppressed = 0
        figures: dict[str, m.Figures] = {}  # each sender's latest (a beat may carry none)
        for h in beats:
            now_b += h.size
            msg = h.msg
            assert isinstance(msg, m.Heartbeat)
            if msg.figures is not None:
                figures[h.a] = msg.figures
            period = (h.a, h.b, int(h.at // MONITOR_PERIOD_S))
            if period not in full:  # its figures, once per monitor period
                full.add(period)
                after += h.size
                f = figures.get(h.a) or m.Figures(0.0, 0.0, 0.0, None, None, (0.0,) * 4)
                cb = _CompactBeat(_ids(msg.node), f.cpu, f.load, f.drain_w,
                                  f.remaining_j, f.lifetime_s, msg.incarnation,
                                  {_ids(k): v for k, v in msg.failed.items()}, _ids(msg.leader),
                                  msg.hosting)  # fmt: skip
                compact += _compact_frame(h.a, h.b, m.CONTROL, cb)
            elif any(h.at - HEARTBEAT_S < u <= h.at for u in other[(h.a, h.b)]):
                suppressed += 1
            else:
                after += len(m.wrap(h.a, h.b, _SlimBeat(msg.node, msg.incarnation)))  # type: ignore[arg-type]
                slim = _CompactSlimBeat(_ids(msg.node), msg.incarnation)
                compact += _compact_frame(h.a, h.b, m.CONTROL, slim)
        out[d] = {
            "beats_per_s": len(beats) / dur,
            "mean_beat_bytes": now_b / len(beats) if beats else 0.0,
            "bytes_per_s": now_b / dur,
            "mw": t.mw(d, now_b / dur),
            "suppressed_per_s": suppressed / dur,
            "full_per_s": len(full) / dur,
            "bytes_per_s_suppressed_slim": after / dur,
            "saves_mw_suppressed_slim": t.mw(d, (now_b - after) / dur),
            "bytes_per_s_also_compact": compact / dur,
            "saves_mw_also_compact": t.mw(d, (now_b - compact) / dur),
        }
    return out


def acks(t: Tally, node: str, dur: float) -> dict[str, dict[str, float]]:
    """Ack bytes/s now, and with one frame per link per ``COALESCE_S`` (the latest of each
    edge's acks in it)."""
    out: dict[str, dict[str, float]] = {}
    for d in DIRECTIONS:
        hops = t.of(node, d, lambda h: h.what == "Ack")
        now_b = sum(h.size for h in hops)
        after = 0
        windows = _windows(hops, COALESCE_S)
        for w in windows:
            if len(w) == 1:
                after += w[0].size
                continue
            latest: dict[int, m.Ack] = {}
            for h in w:
                assert isinstance(h.msg, m.Ack)
                latest[h.msg.edge] = h.msg
            first = w[0].msg
            assert isinstance(first, m.Ack)
            body = [(e, k.upto, k.positions) for e, k in sorted(latest.items())]
            after += len(m.wrap(w[0].a, w[0].b, _LinkAcks(first.app, first.epoch, body)))  # type: ignore[arg-type]
        out[d] = {
            "acks_per_s": len(hops) / dur,
            "mean_ack_bytes": now_b / len(hops) if hops else 0.0,
            "bytes_per_s": now_b / dur,
            "mw": t.mw(d, now_b / dur),
            "frames_per_s_coalesced": len(windows) / dur,
            "bytes_per_s_coalesced": after / dur,
            "saves_mw_coalesced": t.mw(d, (now_b - after) / dur),
        }
    return out


def data(t: Tally, node: str, dur: float) -> dict[str, dict[str, Any]]:
    """Data frames (fresh and resent): events, header and envelope bytes/s; merged per next
    hop within ``MERGE_S``; with a compact header and envelope."""
    out: dict[str, dict[str, Any]] = {}
    for d in DIRECTIONS:
        hops = t.of(node, d, lambda h: h.what.startswith("Data"))
        now_b = sum(h.size for h in hops)
        merged = compact = both = 0
        windows = _windows(hops, MERGE_S)
        for w in windows:
            msgs = [h.msg for h in w]
            assert all(isinstance(x, m.Data) for x in msgs)
            ds: list[m.Data] = msgs  # type: ignore[assignment]
            a, b = w[0].a, w[0].b
            if len(w) == 1:
                merged += w[0].size
                both += _compact_frame(a, b, m.DATA, _compact_data(ds[0]))
                continue
            parts = [(x.edge, x.seq, x.events, x.ts, x.floor) for x in ds]
            merged += len(m.wrap(a, b, _LinkData(ds[0].app, ds[0].epoch, parts)))  # type: ignore[arg-type]
            cparts = [(x.edge, x.seq, x.events, _ms32(x.ts), x.floor) for x in ds]
            both += _compact_frame(a, b, m.DATA, _CompactLinkData(0, ds[0].epoch, cparts))
        for h in hops:
            assert isinstance(h.msg, m.Data)
            compact += _compact_frame(h.a, h.b, m.DATA, _compact_data(h.msg))
        parts_b = {p: t.parts[(node, d, p)] / dur for p in ("events", "data header", "envelope")}
        overhead = parts_b["data header"] + parts_b["envelope"]
        own_frames = t.frames[(node, d, "Data")]
        out[d] = {
            "frames_per_s": len(hops) / dur,
            "bytes_per_s": now_b / dur,
            "own_parts_bytes_per_s": parts_b,
            "own_overhead_per_frame": overhead * dur / max(1, own_frames),
            "own_overhead_mw": t.mw(d, overhead),
            "frames_per_s_merged": len(windows) / dur,
            "saves_mw_merged": t.mw(d, (now_b - merged) / dur),
            "saves_mw_compact_header": t.mw(d, (now_b - compact) / dur),
            "saves_mw_merged_and_compact": t.mw(d, (now_b - both) / dur),
        }
    return out


def run(name: str, seconds: float, tmp: Path) -> dict[str, Any]:
    net = study.network_for("app")
    power = next(iter(net.nodes.values())).power
    t = Tally(power.tx_uj_per_byte, power.rx_uj_per_byte)
    p = placement(name)
    with counting(t):
        r = study.run(name, seconds, tmp / f"{name}.sqlite", accounting="app",
                      until_leader_dies=False, placement=p)  # fmt: skip
    dur = r["virtual_s"]
    nodes: dict[str, Any] = {}
    for node in sorted(net.nodes):
        rows = [
            {"type": cat, "direction": d, "frames_per_s": t.frames[(nd, d, cat)] / dur,
             "bytes_per_s": n / dur, "mw": t.mw(d, n / dur),
             "deployment": cat.removeprefix("relayed ") in DEPLOYMENT}
            for (nd, d, cat), n in t.bytes.items()
            if nd == node
        ]  # fmt: skip
        rows.sort(key=lambda x: -x["mw"])
        frames = {d: sum(x["frames_per_s"] for x in rows if x["direction"] == d)
                  for d in DIRECTIONS}  # fmt: skip
        hb, ak, da = heartbeats(t, node, dur), acks(t, node, dur), data(t, node, dur)
        savings = {
            "heartbeats: one full beat per monitor period, slim or none between": (
                hb, "saves_mw_suppressed_slim"),
            "heartbeats: that, and compact (int tag and ids, no power list)": (
                hb, "saves_mw_also_compact"),
            f"acks: coalesced per link per {COALESCE_S:g} s": (ak, "saves_mw_coalesced"),
            f"data: frames to one next hop within {1e3 * MERGE_S:g} ms merged": (
                da, "saves_mw_merged"),
            "data: compact header and envelope": (da, "saves_mw_compact_header"),
            "data: merged and compact": (da, "saves_mw_merged_and_compact"),
        }  # fmt: skip
        saved = {what: sum(est[d][key] for d in DIRECTIONS) for what, (est, key) in savings.items()}
        best = (  # one estimate per kind of frame: these add up
            "heartbeats: that, and compact (int tag and ids, no power list)",
            f"acks: coalesced per link per {COALESCE_S:g} s",
            "data: merged and compact",
        )
        nodes[node] = {
            "radio_mw": sum(x["mw"] for x in rows),
            "radio_mw_without_deployment": sum(x["mw"] for x in rows if not x["deployment"]),
            "monitor_radio_mw": 1e3 * r["average_cpu_radio_w"][node][1],
            "cpu_mw": 1e3 * r["average_cpu_radio_w"][node][0],
            "rows": rows,
            "frames_per_s": frames,
            "heartbeats": hb,
            "acks": ak,
            "data": da,
            "savings_mw": saved,
            "saves_mw_all": sum(saved[k] for k in best),
            "wire_framing_mw_not_charged": sum(
                t.mw(d, WIRE_FRAMING_B * frames[d]) for d in DIRECTIONS
            ),
        }
    return {
        "placement": name,
        "on_leader": sorted(v for v, n in p.items() if n == study.LEADER),
        "assignment": p,
        "virtual_s": dur,
        "uj_per_byte": {"sent": t.tx_uj, "received": t.rx_uj},
        "wall_s": r["wall_s"],
        "results_stored": r["results_stored"],
        "complete": r["complete"],
        "nodes": nodes,
    }


def _group(cat: str) -> str:
    base = cat.removeprefix("relayed ")
    return "deployment (one-off)" if base in DEPLOYMENT else base


def _frames_cell(label: str, frames: float) -> str:
    return "(the same frames)" if label == "Data: header + envelope" else f"{frames:.2f}"


def _node_table(r: dict[str, Any], d: dict[str, Any]) -> dict[tuple[str, str], list[float]]:
    """(type, direction) -> [frames/s, bytes/s, mW] of one node, fresh Data frames split
    into the events and the overhead around them, deployment messages together."""
    table: dict[tuple[str, str], list[float]] = defaultdict(lambda: [0.0, 0.0, 0.0])
    for x in d["rows"]:
        g = ("relayed " if x["type"].startswith("relayed ") else "") + _group(x["type"])
        if g == "Data":
            pb = d["data"][x["direction"]]["own_parts_bytes_per_s"]
            for label, b in (
                ("Data: events (the app's bytes)", pb["events"]),
                ("Data: header + envelope", pb["data header"] + pb["envelope"]),
            ):
                row = table[(label, x["direction"])]
                row[0] += x["frames_per_s"] if label.endswith("bytes)") else 0.0
                row[1] += b
                row[2] += b * r["uj_per_byte"][x["direction"]] * 1e-3
            continue
        row = table[(g, x["direction"])]
        row[0] += x["frames_per_s"]
        row[1] += x["bytes_per_s"]
        row[2] += x["mw"]
    return dict(sorted(table.items(), key=lambda kv: -kv[1][2]))


def markdown(runs: list[dict[str, Any]]) -> str:
    lines: list[str] = [
        "Radio by message type and direction (virtual-time simulator, app accounting: "
        "1.9 µJ/B sent, 0.5 µJ/B received; `Data` split into the events' bytes and the "
        "overhead around them: `Data` header + envelope). Relayed frames in the rows "
        "`relayed …`; deployment messages (`AppAnnounce`, probes, `ChainPlaced`, builds) "
        "are a one-off at the start, averaged over the run.",
        "",
        f"## The leader, {study.LEADER}: bytes/s and mW",
        "",
        "| message type | direction | "
        + " | ".join(f"{r['placement']} B/s | mW" for r in runs)
        + " |",
        "|---|---|" + "---:|---:|" * len(runs),
    ]
    tables = [_node_table(r, r["nodes"][study.LEADER]) for r in runs]
    keys = list(dict.fromkeys(k for t in tables for k in t))
    for k in keys:
        cells = " | ".join(f"{t[k][1]:.1f} | {t[k][2]:.3f}" if k in t else "- | -" for t in tables)
        lines.append(f"| {k[0]} | {k[1]} | {cells} |")
    leaders = [r["nodes"][study.LEADER] for r in runs]
    lines += [
        "| **radio** | | "
        + " | ".join(
            f"{sum(v[1] for v in t.values()):.1f} | **{d['radio_mw']:.2f}**"
            for t, d in zip(tables, leaders, strict=True)
        )
        + " |",
        "| of which the app's events | | "
        + " | ".join(
            f"{t[k][1]:.1f} | {t[k][2]:.2f}"
            for t in tables
            for k in [("Data: events (the app's bytes)", "sent")]
        )
        + " |",
        "| avoidable, together (estimate) | | "
        + " | ".join(f"| {d['saves_mw_all']:.2f}" for d in leaders)
        + " |",
        "| CPU | | " + " | ".join(f"| {d['cpu_mw']:.2f}" for d in leaders) + " |",
        "",
    ]
    for r in runs:
        lines += [f"## {r['placement']}: {r['virtual_s']:.0f} s virtual, on the leader: "
                  f"{', '.join(r['on_leader'])}", ""]  # fmt: skip
        for node, d in r["nodes"].items():
            table = _node_table(r, d)
            lines += [
                f"### {node}: radio {d['radio_mw']:.2f} mW (monitor charged "
                f"{d['monitor_radio_mw']:.2f}; {d['radio_mw_without_deployment']:.2f} without "
                f"the one-off deployment), CPU {d['cpu_mw']:.2f} mW",
                "",
                "| message type | direction | frames/s | bytes/s | mW |",
                "|---|---|---:|---:|---:|",
                *(
                    f"| {k[0]} | {k[1]} | {_frames_cell(k[0], v[0])} | {v[1]:.1f} | {v[2]:.3f} |"
                    for k, v in table.items()
                    if v[2] >= 0.0005
                ),
                f"| **total** | | {sum(d['frames_per_s'].values()):.2f} | "
                f"{sum(v[1] for v in table.values()):.1f} | {d['radio_mw']:.3f} |",
                "",
            ]
            if node == study.LEADER or any(v > 0.1 for v in d["savings_mw"].values()):
                lines += [
                    f"Avoidable on {node} (estimates, mW saved; not additive across rows of "
                    "the same kind):",
                    "",
                    *(f"- {k}: {v:.3f}" for k, v in d["savings_mw"].items()),
                    "- **together** (compact heartbeats as above, acks coalesced, data merged "
                    f"and compact): **{d['saves_mw_all']:.3f}**, radio "
                    f"{d['radio_mw']:.2f} → {d['radio_mw'] - d['saves_mw_all']:.2f} mW",
                    "- not charged by the simulator: the wire's framing, "
                    f"{WIRE_FRAMING_B} B/frame, would add "
                    f"{d['wire_framing_mw_not_charged']:.3f} mW",
                    "",
                ]
    return "\n".join(lines)


def main() -> int:
    ap = argparse.ArgumentParser(description=(__doc__ or "").split("\n\n")[0])
    ap.add_argument("--seconds", type=float, default=120.0, help="virtual seconds per placement")
    ap.add_argument("--placement", choices=PLACEMENTS, action="append", help="these only")
    ap.add_argument("--out", type=Path, default=study.ROOT / "bench/results/lifetime-radio.json")
    args = ap.parse_args()
    t0 = time.perf_counter()
    runs = []
    with tempfile.TemporaryDirectory(prefix="mso-radio-") as tmp:
        for name in args.placement or PLACEMENTS:
            runs.append(run(name, args.seconds, Path(tmp)))
            print(f"{name}: done in {runs[-1]['wall_s']} s", flush=True)
    result = {
        "seconds_per_placement": args.seconds,
        "heartbeat_s": HEARTBEAT_S,
        "monitor_period_s": MONITOR_PERIOD_S,
        "retransmit_s": RETRANSMIT_S,
        "coalesce_acks_s": COALESCE_S,
        "merge_data_s": MERGE_S,
        "wire_framing_bytes": WIRE_FRAMING_B,
        "runs": runs,
        "seconds": time.perf_counter() - t0,
        **provenance(),
    }
    write_results(args.out, result, markdown(runs))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
