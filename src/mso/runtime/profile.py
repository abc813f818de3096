"""Measuring an app's vertex costs and edge sizes instead of guessing them (``mso profile``).

The app runs in this process, sequentially, for ``seconds`` of simulated time: every source is
called at its rate in time order (a rate-less source once a simulated second), and each event is
pushed through the graph at once, encoded and decoded with msgspec exactly as on the wire. Each
call's thread CPU time (less what ran inside ``not_charged``: a simulated sensor's world) is
charged to its vertex, each encoded event's size to its edge. A vertex's cost is then its mean
CPU time per event (per call for a source) in ms, scaled by ``speed`` — how fast this host is
relative to a node of ``cpu: 1.0`` — which is the app's unit (docs/app-format.md).
``write_back`` puts the figures into the YAML file in place, on the lines that hold them (and
adds a ``cost:`` or ``size:`` the file does not have, short edge forms included), so the file's
layout and comments stay.

Profiling has no side effects outside a scratch directory: the run's working and temporary
directories are the scratch one, a vertex parameter naming a file (or a file to be, in an
existing directory) is given a scratch copy of it instead, and a vertex whose code writes
elsewhere (a path from the environment, say) can declare a ``dry_run(scratch_dir)`` hook,
called before ``open()``, to point itself there. So a sink logging to the user's SQLite file
is measured against a copy, and the file is left as it was.
"""

from __future__ import annotations

import heapq
import os
import re
import shutil
import tempfile
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import msgspec

from mso.errors import MsoError
from mso.model.app import App, Vertex
from mso.model.appfile import load_app
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
    scratch: list[str] = field(default_factory=list)  # what was pointed at a scratch copy

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
    old_tmp, old_cwd = tempfile.tempdir, os.getcwd()
    with tempfile.TemporaryDirectory(prefix="mso-profile-") as tmp:
        scratch = Path(tmp)
        vertices = {v: _scratch_vertex(app.vertices[v], scratch, prof) for v in app.vertices}
        tempfile.tempdir = tmp  # a vertex that writes temporary files writes them here
        os.chdir(tmp)  # and relative paths land here too
        try:
            instances = {v: Instance(vertices[v], kinds[v]) for v in app.topological_order()}
            for v, inst in instances.items():
                dry_run = getattr(inst.fn, "dry_run", None)
                if callable(dry_run):
                    dry_run(tmp)
                    prof.scratch.append(f"{v}: dry_run({tmp})")
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
            os.chdir(old_cwd)
    return prof


MAX_SCRATCH_COPY = 256 * 1024 * 1024  # bytes of a file or directory profiling will copy


def _scratch_vertex(vertex: Vertex, scratch: Path, prof: Profile) -> Vertex:
    """``vertex`` with every parameter that names a file or directory (or a file to be, in an
    existing directory) pointed at a scratch copy of it."""
    params = dict(vertex.params)
    for key, value in vertex.params.items():
        if not isinstance(value, str) or not value or "\n" in value:
            continue
        path = Path(value).expanduser()
        exists = path.exists()
        if not exists and not (os.sep in value and path.parent.is_dir() and path.suffix):
            continue
        copy = scratch / "params" / f"{vertex.id}.{key}" / (path.name or "copy")
        copy.parent.mkdir(parents=True, exist_ok=True)
        if exists:
            size = _size(path)
            if size > MAX_SCRATCH_COPY:
                raise MsoError(
                    f"profile: vertex {vertex.id!r}: parameter {key}: {value} holds {size:,} "
                    f"bytes, more than the {MAX_SCRATCH_COPY:,} profiling copies to keep it "
                    "unchanged; give the vertex a dry_run(scratch_dir) hook instead"
                )
            if path.is_dir():
                shutil.copytree(path, copy)
            else:
                shutil.copy2(path, copy)
        params[key] = str(copy)
        prof.scratch.append(f"{vertex.id}.{key}: {value} -> a scratch copy")
    return replace(vertex, params=params) if params != vertex.params else vertex


def _size(path: Path) -> int:
    if not path.is_dir():
        return path.stat().st_size
    return sum(p.stat().st_size for p in path.rglob("*") if p.is_file())


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
_COMMENT = re.compile(r"(\s+#.*)?$")


def write_back(path: Path, costs: dict[str, float], sizes: dict[tuple[str, str], int]) -> list[str]:
    """Put each vertex's ``cost:`` and each edge's ``size:`` into the YAML file, on the line
    that holds it, or added where the vertex or edge is written: into a one-line ``{...}``, as
    a new line of a block mapping, and a short ``[from, to]`` edge becomes ``{from, to, size}``.
    The file is read back to check it; if it does not give the figures, it is left as it was
    and :class:`MsoError` says so. Returns what could not be written (a form not handled)."""
    original = path.read_text(encoding="utf-8")
    doc = load_yaml_file(path)
    data = doc.data if isinstance(doc.data, dict) else {}
    lines = original.splitlines(keepends=True)
    inserts: list[tuple[int, str]] = []  # (after this 0-based line, the new line)
    missing = []

    def put(keypath: tuple[Any, ...], key: str, value: str) -> bool:
        line = doc.lines.get(keypath)
        if line is None:
            return False
        new, n = re.subn(rf"(\b{key}:\s*){_NUMBER}", rf"\g<1>{value}", lines[line - 1], count=1)
        lines[line - 1] = new
        return n == 1

    def add(keypath: tuple[Any, ...], mapping: Any, key: str, value: str) -> bool:
        """Add ``key: value`` to the mapping at ``keypath``, written on line ``doc.lines``."""
        line = doc.lines.get(keypath)
        if line is None:
            return False
        text = lines[line - 1]
        body, end = text.rstrip("\r\n"), text[len(text.rstrip("\r\n")) :]
        m = _COMMENT.search(body)
        comment = m.group(0) if m else ""
        code = body[: len(body) - len(comment)]
        if code.endswith("}") and code.count("{") == code.count("}") >= 1:
            inner = code[code.index("{") + 1 : -1].strip()
            pair = f"{key}: {value}"
            code = code[: code.index("{") + 1] + (f"{inner}, {pair}" if inner else pair) + "}"
        elif keypath[0] == "edges" and code.endswith("]") and code.count("[") == 1:
            ends = [x.strip() for x in code[code.index("[") + 1 : -1].split(",")]
            if len(ends) != 2:
                return False
            mapping_text = f"{{from: {ends[0]}, to: {ends[1]}, {key}: {value}}}"
            code = code[: code.index("[")] + mapping_text
        elif isinstance(mapping, dict) and mapping and keypath[0] == "vertices":
            first = doc.lines.get((*keypath, next(iter(mapping))))
            if first is None or first == line:
                return False
            indent = lines[first - 1][: len(lines[first - 1]) - len(lines[first - 1].lstrip())]
            inserts.append((line - 1, f"{indent}{key}: {value}{end or chr(10)}"))
            return True
        elif isinstance(mapping, dict) and mapping and keypath[0] == "edges":
            column = len(code) - len(code.lstrip(" -"))  # the first key's, after "- "
            inserts.append((line - 1, f"{' ' * column}{key}: {value}{end or chr(10)}"))
            return True
        elif mapping is None and code.rstrip().endswith(":"):
            code = code.rstrip() + f" {{{key}: {value}}}"
        else:
            return False
        lines[line - 1] = code + comment + end
        return True

    vertices = data.get("vertices")
    vertices = vertices if isinstance(vertices, dict) else {}
    for v, c in costs.items():
        attrs = vertices.get(v)
        value = f"{c:.3g}"
        if isinstance(attrs, dict) and "cost" in attrs:
            ok = put(("vertices", v, "cost"), "cost", value)
        else:
            ok = add(("vertices", v), attrs, "cost", value)
        if not ok:
            missing.append(f"vertex {v}: its cost: could not be written in this form")
            costs = {k: x for k, x in costs.items() if k != v}
    edges = data.get("edges")
    edges = edges if isinstance(edges, list) else []
    for i, e in enumerate(edges):
        ends = (e.get("from"), e.get("to")) if isinstance(e, dict) else tuple(e or ())
        size = sizes.get((str(ends[0]), str(ends[1]))) if len(ends) == 2 else None
        if size is None:
            continue
        if isinstance(e, dict) and "size" in e:
            ok = put(("edges", i, "size"), "size", str(size))
        else:
            ok = add(("edges", i), e, "size", str(size))
        if not ok:
            missing.append(f"edge {ends[0]} -> {ends[1]}: its size: could not be written")
            sizes = {k: n for k, n in sizes.items() if k != (str(ends[0]), str(ends[1]))}
    for after, text in sorted(inserts, reverse=True):
        lines.insert(after + 1, text)
    written = "".join(lines)
    path.write_text(written, encoding="utf-8")
    _check_written(path, original, costs, sizes)
    return missing


def _check_written(
    path: Path, original: str, costs: dict[str, float], sizes: dict[tuple[str, str], int]
) -> None:
    """The file just written gives back every figure (to the 3 digits written), or the
    original is put back."""
    try:
        app = load_app(path, resolve_code=False)
        bad = [v for v, c in costs.items() if abs(app.vertices[v].cost - float(f"{c:.3g}")) > 1e-9]
        got = {(e.src, e.dst): e.size for e in app.edges}
        bad += [f"{a}->{b}" for (a, b), n in sizes.items() if got.get((a, b)) != n]
    except MsoError as exc:
        bad = [str(exc)]
    if bad:
        path.write_text(original, encoding="utf-8")
        raise MsoError(
            f"profile --write: {path} did not read back as written ({', '.join(bad[:5])}); "
            "it was left unchanged"
        )
