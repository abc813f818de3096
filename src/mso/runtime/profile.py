"""Measuring an app's vertex costs and edge sizes instead of guessing them (``mso profile``).

The app runs in this process, sequentially, for ``seconds`` of simulated time: every source is
called at its rate in time order (a rate-less source once a simulated second), and each event is
pushed through the graph at once, encoded and decoded with msgspec exactly as on the wire. Each
call's thread CPU time (less what ran inside ``not_charged``: a simulated sensor's world) is
charged to its vertex, each encoded event's size to its edge. A vertex's cost is then its mean
CPU time per event (per call for a source) in ms, scaled by ``speed`` — how fast this host is
relative to a node of ``cpu: 1.0`` — which is the app's unit (docs/app-format.md).
``write_back`` puts the figures into the YAML file in place, on the lines that hold them, so
the file's layout and comments stay.
"""

from __future__ import annotations

import heapq
import re
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import msgspec

from mso.errors import MsoError
from mso.model.app import App
from mso.model.yamlfile import load_yaml_file
from mso.runtime.instance import Instance
from mso.runtime.worker import charged_thread_time


@dataclass
class VertexProfile:
    calls: int = 0
    cpu_s: float = 0.0
    errors: int = 0
    last_error: str = ""

    def cost(self, speed: float) -> float | None:
        return None if not self.calls else self.cpu_s / self.calls * 1e3 * speed


@dataclass
class Profile:
    seconds: float
    speed: float
    vertices: dict[str, VertexProfile] = field(default_factory=dict)
    edge_bytes: dict[tuple[str, str], list[int]] = field(default_factory=dict)

    def costs(self) -> dict[str, float]:
        out = {}
        for v, p in self.vertices.items():
            c = p.cost(self.speed)
            if c is not None:
                out[v] = c
        return out

    def sizes(self) -> dict[tuple[str, str], int]:
        return {e: round(sum(b) / len(b)) for e, b in self.edge_bytes.items() if b}


def profile(app: App, seconds: float = 30.0, speed: float = 1.0) -> Profile:
    """Run ``app`` here for ``seconds`` of simulated time and measure it (see module doc)."""
    app.validate()
    if seconds <= 0 or speed <= 0:
        raise MsoError("profile: seconds and speed must be > 0")
    kinds = app.kinds()
    prof = Profile(seconds, speed, {v: VertexProfile() for v in app.vertices})
    out_edges: dict[str, list[tuple[str, str]]] = {v: [] for v in app.vertices}
    decoders: dict[tuple[str, str], msgspec.msgpack.Decoder[Any]] = {}
    for e in app.edges:
        out_edges[e.src].append((e.src, e.dst))
        fmt = e.format or app.vertices[e.src].output or app.vertices[e.dst].input
        decoders[(e.src, e.dst)] = msgspec.msgpack.Decoder(fmt if isinstance(fmt, type) else Any)
        prof.edge_bytes[(e.src, e.dst)] = []
    old_tmp = tempfile.tempdir
    with tempfile.TemporaryDirectory(prefix="mso-profile-") as tmp:
        tempfile.tempdir = tmp  # a sink that writes files writes them here
        try:
            instances = {v: Instance(app.vertices[v], kinds[v]) for v in app.topological_order()}
            for inst in instances.values():
                opener = inst.hook("open")
                if opener is not None:
                    opener()
            _run(app, instances, prof, out_edges, decoders, seconds)
            for inst in instances.values():
                closer = inst.hook("close")
                if closer is not None:
                    closer()
        finally:
            tempfile.tempdir = old_tmp
    return prof


def _run(
    app: App,
    instances: dict[str, Instance],
    prof: Profile,
    out_edges: dict[str, list[tuple[str, str]]],
    decoders: dict[tuple[str, str], msgspec.msgpack.Decoder[Any]],
    seconds: float,
) -> None:
    ticks: list[tuple[float, str, int]] = []
    for v, inst in instances.items():
        if inst.kind == "source":
            period = 1.0 / (inst.rate or 1.0)
            ticks.extend((k * period, v, k) for k in range(int(seconds / period)))
    heapq.heapify(ticks)
    encode = msgspec.msgpack.encode

    def call(v: str, *args: Any) -> list[Any]:
        p = prof.vertices[v]
        inst = instances[v]
        t0 = charged_thread_time()
        try:
            it = inst.iterator
            result = next(it, None) if it is not None else inst.fn(*args)
        except Exception as exc:  # user code: counted, as the runtime does
            p.errors += 1
            p.last_error = f"{type(exc).__name__}: {exc}"
            result = None
        p.cpu_s += charged_thread_time() - t0
        p.calls += 1
        if result is None:
            return []
        return result if isinstance(result, list) else [result]

    while ticks:
        at, src, seq = heapq.heappop(ticks)
        queue = [(src, ev) for ev in call(src, seq, at)]
        while queue:
            v, ev = queue.pop(0)
            payload = encode(ev)
            for edge in out_edges[v]:
                prof.edge_bytes[edge].append(len(payload))
                event = decoders[edge].decode(payload)
                queue.extend((edge[1], out) for out in call(edge[1], event))


_NUMBER = r"-?\d+(?:\.\d*)?(?:[eE][-+]?\d+)?"


def write_back(path: Path, costs: dict[str, float], sizes: dict[tuple[str, str], int]) -> list[str]:
    """Replace the ``cost:`` of each vertex and the ``size:`` of each edge in the YAML file,
    on the line the key is on. Returns what could not be written (no such key in the file)."""
    doc = load_yaml_file(path)
    lines = path.read_text(encoding="utf-8").splitlines(keepends=True)
    missing = []

    def put(keypath: tuple[Any, ...], key: str, value: str) -> bool:
        line = doc.lines.get(keypath)
        if line is None:
            return False
        text = lines[line - 1]
        new, n = re.subn(rf"(\b{key}:\s*){_NUMBER}", rf"\g<1>{value}", text, count=1)
        if n != 1:
            return False
        lines[line - 1] = new
        return True

    for v, c in costs.items():
        if not put(("vertices", v, "cost"), "cost", f"{c:.3g}"):
            missing.append(f"vertex {v}: no cost: in the file")
    edges = doc.data.get("edges") or [] if isinstance(doc.data, dict) else []
    for i, e in enumerate(edges):
        if not isinstance(e, dict):
            continue
        size = sizes.get((str(e.get("from")), str(e.get("to"))))
        if size is not None and not put(("edges", i, "size"), "size", str(size)):
            missing.append(f"edge {e.get('from')} -> {e.get('to')}: no size: in the file")
    path.write_text("".join(lines), encoding="utf-8")
    return missing
