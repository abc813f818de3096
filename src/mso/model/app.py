"""The application model (paper §3.1): a directed flow graph of vertices joined by typed edges.

A vertex names its code by import path (``package.module:attr``) or is given a callable directly;
it has a relative ``cost`` (work units per event, 1 unit = 1 ms of CPU on a node of ``cpu: 1.0``),
an optional ``pinned`` node, and optional state hooks used when it moves. Every edge carries a
format: a ``msgspec.Struct`` type. Sources and sinks are not declared, they follow from the graph.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, field
from typing import Any

import msgspec

from mso.errors import AppError, with_code_hint
from mso.model.capabilities import Needs, parse_capabilities
from mso.model.graph import topological_order
from mso.model.imports import ImportPathError, resolve
from mso.model.qos import DEFAULT_BUFFER_AGE_S, DEFAULT_BUFFER_BYTES, QOS_KEYS, check_edge_qos
from mso.model.yamlfile import Located

Code = str | Callable[..., Any]


@dataclass
class Vertex:
    """One vertex of the flow graph: a source, an operator or a sink."""

    id: str
    code: Code | None = None
    cost: float = 1.0
    pinned: str | None = None
    input: type[msgspec.Struct] | str | None = None
    output: type[msgspec.Struct] | str | None = None
    rate: float | None = None
    params: dict[str, Any] = field(default_factory=dict)
    get_state: Code | None = None
    set_state: Code | None = None
    # where its code runs on a node: ``auto`` (its thread, or the node's loop while its calls
    # take microseconds), always a thread of the node's process, or a process of its own (a
    # CPU-bound pure-Python vertex gets a core and a GIL to itself; import paths only)
    isolation: str = "auto"
    # instead of ``pinned``: what its node must offer, and where it must (not) be relative to
    # another vertex (mso.model.capabilities); resolved to one node before chains are placed
    requires: dict[str, float] = field(default_factory=dict)
    near: str | None = None
    apart_from: str | None = None
    # chain replication of its state (docs/architecture.md): how many other nodes hold a
    # snapshot of it (None: 1 if the vertex has state, else 0), taken every ``snapshot_events``
    # events processed or ``snapshot_s`` seconds, whichever comes first
    replicas: int | None = None
    snapshot_events: int = 100
    snapshot_s: float = 5.0

    @property
    def constrained(self) -> bool:
        """Its node is chosen by capability (it is not pinned and says what it needs)."""
        return self.pinned is None and bool(self.requires or self.near or self.apart_from)


ISOLATIONS = ("auto", "thread", "process")
MAX_REPLICAS = 2
MAX_SNAPSHOT_EVENTS = 1_000_000
MAX_SNAPSHOT_S = 3600.0

PLANNERS = ("paper", "bytes")
"""How Algorithm 1 splits a chain along its probed route (``mso.planning.placement``):
``paper`` -- in proportion to cost and capacity, as the paper does; ``bytes`` -- the split
cheapest in energy per event, computing weighed against carrying each edge's bytes."""


@dataclass
class Edge:
    """A directed edge ``src -> dst``; ``format`` is the Struct type of its events."""

    src: str
    dst: str
    format: type[msgspec.Struct] | str | None = None
    size: int | None = None  # bytes per event, an estimate for planning and energy
    # delivery settings (mso.model.qos): reliability, history, deadline, lifespan, and the
    # store-and-forward bound (bytes, age) with what happens past it
    qos: str = "reliable"
    keep_last: int | None = None
    deadline_ms: float | None = None
    lifespan_ms: float | None = None
    buffer_bytes: int = DEFAULT_BUFFER_BYTES
    buffer_age_s: float = DEFAULT_BUFFER_AGE_S
    overflow: str = "buffer"


@dataclass
class App:
    """A validated-on-demand application graph, built in Python or loaded from YAML.

    >>> app = App("fig2")
    >>> _ = app.vertex("A", pinned="N1"); _ = app.vertex("B"); _ = app.edge("A", "B")
    >>> app.validate().sinks()
    ['B']
    """

    name: str
    vertices: dict[str, Vertex] = field(default_factory=dict)
    edges: list[Edge] = field(default_factory=list)
    slo_ms: float | None = None
    # the management policy: a shipped name, an import path, or {name|code, params}
    policy: str | dict[str, Any] | None = None
    # how chains are split along their routes (PLANNERS); None: the planner's default
    planner: str | None = None
    located: Located | None = field(default=None, compare=False, repr=False)

    # -- builder -------------------------------------------------------------------------
    def vertex(
        self,
        id: str,
        code: Code | None = None,
        *,
        cost: float = 1.0,
        pinned: str | None = None,
        input: type[msgspec.Struct] | str | None = None,
        output: type[msgspec.Struct] | str | None = None,
        rate: float | None = None,
        params: dict[str, Any] | None = None,
        get_state: Code | None = None,
        set_state: Code | None = None,
        isolation: str = "auto",
        requires: Any = None,
        near: str | None = None,
        apart_from: str | None = None,
        replicas: int | None = None,
        snapshot_events: int = 100,
        snapshot_s: float = 5.0,
    ) -> Vertex:
        """Add a vertex; a duplicate id or a bad value is an AppError at once."""
        if not isinstance(id, str) or not id:
            raise AppError(f"expected a non-empty string vertex id, got {id!r}", field="vertices")
        if id in self.vertices:
            raise AppError(f"duplicate vertex id {id!r}", field=f"vertices.{id}")
        if params is not None and not isinstance(params, dict):
            raise self._error(
                f"expected a mapping of parameters, got {params!r}",
                f"vertices.{id}.params",
                ("vertices", id, "params"),
            )
        v = Vertex(
            id=id,
            code=code,
            cost=cost,
            pinned=pinned,
            input=input,
            output=output,
            rate=rate,
            params=dict(params or {}),
            get_state=get_state,
            set_state=set_state,
            isolation=isolation,
            near=near,
            apart_from=apart_from,
            replicas=replicas,
            snapshot_events=snapshot_events,
            snapshot_s=snapshot_s,
        )
        try:
            v.requires = parse_capabilities(requires, f"vertices.{id}.requires")
        except AppError as exc:
            where = f"vertices.{id}.requires"
            raise self._error(exc.message, where, ("vertices", id, "requires")) from None
        _check_vertex_values(v, self._error)
        self.vertices[id] = v
        return v

    def edge(
        self,
        src: str,
        dst: str,
        *,
        format: type[msgspec.Struct] | str | None = None,
        size: int | None = None,
        **qos: Any,
    ) -> Edge:
        """Add an edge ``src -> dst``; endpoints are checked by :meth:`validate`; ``qos``:
        the keys of :data:`mso.model.qos.QOS_KEYS`."""
        unknown = sorted(set(qos) - set(QOS_KEYS))
        if unknown:
            raise AppError(f"unknown edge setting {unknown[0]!r}", field="edges")
        e = Edge(src=src, dst=dst, format=format, size=size, **qos)
        self.edges.append(e)
        return e

    # -- graph queries -------------------------------------------------------------------
    def successors(self) -> dict[str, list[str]]:
        out: dict[str, list[str]] = {v: [] for v in self.vertices}
        for e in self.edges:
            out[e.src].append(e.dst)
        return out

    def predecessors(self) -> dict[str, list[str]]:
        inc: dict[str, list[str]] = {v: [] for v in self.vertices}
        for e in self.edges:
            inc[e.dst].append(e.src)
        return inc

    def sources(self) -> list[str]:
        has_in = {e.dst for e in self.edges}
        return [v for v in self.vertices if v not in has_in]

    def sinks(self) -> list[str]:
        has_out = {e.src for e in self.edges}
        return [v for v in self.vertices if v not in has_out]

    def kinds(self) -> dict[str, str]:
        """``source``, ``sink``, ``operator`` or ``isolated`` for every vertex, from the edges."""
        has_in, has_out = {e.dst for e in self.edges}, {e.src for e in self.edges}
        names = {(False, True): "source", (True, False): "sink", (True, True): "operator"}
        return {v: names.get((v in has_in, v in has_out), "isolated") for v in self.vertices}

    def replicas(self, vertex: str, kind: str | None = None) -> int:
        """How many replicas of ``vertex``'s state are kept: its ``replicas``, or by default 1
        for a vertex with state (state hooks, or a class with ``get_state``) and 0 otherwise.
        A source keeps none (it has no input to replay after a snapshot). ``kind``: the
        vertex's, if known (saves a pass over the edges)."""
        v = self.vertices[vertex]
        if (kind or self.kind(vertex)) == "source":
            return 0
        if v.replicas is not None:
            return v.replicas
        return 1 if has_state(v) else 0

    def kind(self, vertex: str) -> str:
        return self.kinds()[vertex]

    def topological_order(self) -> list[str]:
        """Vertices so that every edge goes forward; the app must be acyclic."""
        order = _kahn(self.vertices, self.edges)
        if len(order) != len(self.vertices):
            raise AppError(f"the graph has a cycle: {' -> '.join(self.find_cycle())}")
        return order

    def find_cycle(self) -> list[str]:
        """One cycle as ``[a, b, ..., a]``, or ``[]`` if the graph is acyclic."""
        succ = self.successors()
        color: dict[str, int] = {}
        for start in self.vertices:
            if color.get(start):
                continue
            stack: list[tuple[str, Iterator[str]]] = [(start, iter(succ[start]))]
            path = [start]
            color[start] = 1
            while stack:
                node, it = stack[-1]
                nxt = next(it, None)
                if nxt is None:
                    stack.pop()
                    path.pop()
                    color[node] = 2
                elif color.get(nxt) == 1:
                    return [*path[path.index(nxt) :], nxt]
                elif not color.get(nxt):
                    color[nxt] = 1
                    path.append(nxt)
                    stack.append((nxt, iter(succ[nxt])))
        return []

    def edge_format(self, edge: Edge) -> type[msgspec.Struct] | None:
        """The edge's format: declared on the edge, else the producer's output format, else the
        consumer's input format (validation makes sure they agree when several are given)."""
        fmt = edge.format if edge.format is not None else self.vertices[edge.src].output
        if fmt is None:
            fmt = self.vertices[edge.dst].input
        return fmt if isinstance(fmt, type) else None

    # -- validation ----------------------------------------------------------------------
    def _error(self, message: str, field: str, path: tuple[str | int, ...] = ()) -> AppError:
        loc = self.located
        line = loc.line(path) if loc is not None and path else None
        return AppError(
            message, file=loc.file if loc else None, line=line, field=field, path=path or None
        )

    def validate(self, *, resolve_code: bool = True) -> App:
        """Check the whole graph; raise the first problem found as an AppError.

        With ``resolve_code`` the import paths of code, state hooks and formats are imported
        and replaced by what they name; planning-only commands may skip it.
        """
        if not isinstance(self.name, str) or not self.name:
            raise self._error("expected a non-empty string", "name", ("name",))
        if self.slo_ms is not None and (not _is_number(self.slo_ms) or self.slo_ms <= 0):
            raise self._error(
                f"expected a positive number of milliseconds, got {self.slo_ms!r}",
                "slo_ms",
                ("slo_ms",),
            )
        if self.planner is not None and self.planner not in PLANNERS:
            raise self._error(
                f"expected one of {', '.join(PLANNERS)}, got {self.planner!r}",
                "planner",
                ("planner",),
            )
        for v in self.vertices.values():
            _check_vertex_values(v, self._error)
            if resolve_code:
                self._resolve_vertex(v)
        seen: set[tuple[str, str]] = set()
        for i, e in enumerate(self.edges):
            where, path = f"edges[{i}]", ("edges", i)
            for end in (e.src, e.dst):
                if end not in self.vertices:
                    raise self._error(
                        f"unknown vertex {end!r} in edge {e.src} -> {e.dst} "
                        f"(known: {', '.join(sorted(self.vertices)) or 'none'})",
                        where,
                        path,
                    )
            if (e.src, e.dst) in seen:
                raise self._error(f"duplicate edge {e.src} -> {e.dst}", where, path)
            seen.add((e.src, e.dst))
            if e.size is not None and (
                isinstance(e.size, bool)
                or not isinstance(e.size, int)
                or not 0 <= e.size <= MAX_EDGE_SIZE
            ):
                raise self._error(
                    f"expected a non-negative integer byte count up to {MAX_EDGE_SIZE} "
                    f"(16 MiB), got {e.size!r}",
                    f"{where}.size",
                    (*path, "size"),
                )
            check_edge_qos(e, self._error, where, path)
            if e.format is not None and not isinstance(e.format, str) and not _is_struct(e.format):
                raise self._error(
                    f"expected an import path 'package.module:Struct' or a msgspec.Struct type, "
                    f"got {e.format!r}",
                    f"{where}.format",
                    (*path, "format"),
                )
            if resolve_code and isinstance(e.format, str):
                e.format = self._resolve_format(e.format, f"{where}.format", (*path, "format"))
        cycle = self.find_cycle()
        if cycle:
            raise self._error(f"the graph has a cycle: {' -> '.join(cycle)}", "edges", ("edges",))
        kinds = self.kinds()
        for v in self.vertices.values():
            if v.replicas and kinds[v.id] == "source":
                raise self._error(
                    "a source keeps no replica (there is no input to replay after its "
                    "snapshot); give replicas to the stateful vertices it feeds",
                    f"vertices.{v.id}.replicas",
                    ("vertices", v.id, "replicas"),
                )
        for i, e in enumerate(self.edges):
            self._check_formats(i, e)
        self.needs()
        return self

    def needs(self) -> list[Needs]:
        """The vertices whose node is chosen by capability, in the order they are resolved (a
        ``near``/``apart_from`` vertex before those that name it). AppError if one names an
        unknown vertex, itself, or one placed only later by Algorithm 1 (neither pinned nor
        constrained), or if they name each other in a cycle."""
        todo: dict[str, Vertex] = {v.id: v for v in self.vertices.values() if v.constrained}
        for v in todo.values():
            for attr in ("near", "apart_from"):
                other = getattr(v, attr)
                if other is None:
                    continue
                where, loc = f"vertices.{v.id}.{attr}", ("vertices", v.id, attr)
                if other not in self.vertices or other == v.id:
                    raise self._error(
                        f"expected another vertex of the app, got {other!r}", where, loc
                    )
                if self.vertices[other].pinned is None and other not in todo:
                    raise self._error(
                        f"{other!r} is placed by Algorithm 1 after the constrained vertices are "
                        f"chosen: pin it, or give it requires:",
                        where,
                        loc,
                    )
        out: list[Needs] = []
        done: set[str] = set()
        while todo:
            ready = [
                v
                for v in todo.values()
                if all(o is None or o not in todo for o in (v.near, v.apart_from))
            ]
            if not ready:
                names = ", ".join(sorted(todo))
                raise self._error(
                    f"near/apart_from name each other in a cycle ({names})",
                    f"vertices.{min(todo)}",
                    ("vertices", min(todo)),
                )
            for v in ready:
                out.append(Needs(v.id, dict(v.requires), v.near, v.apart_from))
                done.add(v.id)
                del todo[v.id]
        return out

    def _resolve_vertex(self, v: Vertex) -> None:
        base = ("vertices", v.id)
        for attr in ("code", "get_state", "set_state"):
            value = getattr(v, attr)
            if isinstance(value, str):
                try:
                    obj = resolve(value)
                except ImportPathError as exc:
                    why = with_code_hint(str(exc))
                    raise self._error(why, f"vertices.{v.id}.{attr}", (*base, attr)) from None
                if not callable(obj):
                    raise self._error(
                        f"expected {value!r} to name a callable, got {type(obj).__name__}",
                        f"vertices.{v.id}.{attr}",
                        (*base, attr),
                    )
        for attr in ("input", "output"):
            value = getattr(v, attr)
            if isinstance(value, str):
                setattr(
                    v, attr, self._resolve_format(value, f"vertices.{v.id}.{attr}", (*base, attr))
                )
            elif value is not None and not _is_struct(value):
                raise self._error(
                    f"expected a msgspec.Struct type, got {value!r}",
                    f"vertices.{v.id}.{attr}",
                    (*base, attr),
                )

    def _resolve_format(
        self, path: str, field: str, loc: tuple[str | int, ...]
    ) -> type[msgspec.Struct]:
        try:
            obj = resolve(path)
        except ImportPathError as exc:
            raise self._error(with_code_hint(str(exc)), field, loc) from None
        if not _is_struct(obj):
            raise self._error(
                f"expected {path!r} to name a msgspec.Struct type, got {obj!r}", field, loc
            )
        return obj  # type: ignore[no-any-return]

    def _check_formats(self, i: int, e: Edge) -> None:
        produced = e.format if e.format is not None else self.vertices[e.src].output
        out = self.vertices[e.src].output
        consumed = self.vertices[e.dst].input
        where, path = f"edges[{i}]", ("edges", i)
        if e.format is not None and out is not None and _fmt_name(out) != _fmt_name(e.format):
            raise self._error(
                f"format mismatch on {e.src} -> {e.dst}: {e.src} produces {_fmt_name(out)} "
                f"but the edge carries {_fmt_name(e.format)}",
                f"{where}.format",
                (*path, "format"),
            )
        if (
            produced is not None
            and consumed is not None
            and _fmt_name(produced) != _fmt_name(consumed)
        ):
            raise self._error(
                f"format mismatch on {e.src} -> {e.dst}: {e.src} produces "
                f"{_fmt_name(produced)} but {e.dst} consumes {_fmt_name(consumed)}",
                where,
                path,
            )


def _is_struct(obj: object) -> bool:
    return isinstance(obj, type) and issubclass(obj, msgspec.Struct)


def _fmt_name(fmt: type | str) -> str:
    if isinstance(fmt, str):
        return fmt
    return f"{fmt.__module__}:{fmt.__qualname__}"


def _is_number(x: object) -> bool:
    return isinstance(x, int | float) and not isinstance(x, bool) and math.isfinite(x)


MAX_COST = 1e9  # work units per event: beyond it sums and objectives would overflow
MAX_RATE = 1e7  # events per second of a source
# bytes per event of an edge: no event larger than a frame (mso.protocol.framing.MAX_FRAME)
# can travel, and 10**29 bytes made the planners' and energy model's sums meaningless
MAX_EDGE_SIZE = 16 * 1024 * 1024


def _check_vertex_values(v: Vertex, error: Callable[..., AppError]) -> None:
    base = ("vertices", v.id)
    if not _is_number(v.cost) or v.cost < 0 or v.cost > MAX_COST:
        bound = f"up to {MAX_COST:g}" if _is_number(v.cost) and v.cost > MAX_COST else ""
        raise error(
            f"expected a non-negative number{' ' + bound if bound else ''}, got {v.cost!r}",
            f"vertices.{v.id}.cost",
            (*base, "cost"),
        )
    if v.pinned is not None and (not isinstance(v.pinned, str) or not v.pinned):
        raise error(
            f"expected a node id (string), got {v.pinned!r}",
            f"vertices.{v.id}.pinned",
            (*base, "pinned"),
        )
    if v.rate is not None and (not _is_number(v.rate) or v.rate <= 0 or v.rate > MAX_RATE):
        raise error(
            f"expected a positive number of events per second up to {MAX_RATE:g}, got {v.rate!r}",
            f"vertices.{v.id}.rate",
            (*base, "rate"),
        )
    if v.pinned is not None and (v.requires or v.near or v.apart_from):
        raise error(
            "give pinned: or requires/near/apart_from, not both: a pinned vertex's node is set",
            f"vertices.{v.id}.pinned",
            (*base, "pinned"),
        )
    for attr in ("near", "apart_from"):
        other = getattr(v, attr)
        if other is not None and (not isinstance(other, str) or not other):
            raise error(f"expected a vertex id, got {other!r}", f"vertices.{v.id}.{attr}",
                        (*base, attr))  # fmt: skip
    if v.near is not None and v.near == v.apart_from:
        raise error(
            f"near and apart_from both name {v.near!r}", f"vertices.{v.id}.near", (*base, "near")
        )
    if v.isolation not in ISOLATIONS:
        raise error(
            f"expected one of {', '.join(ISOLATIONS)}, got {v.isolation!r}",
            f"vertices.{v.id}.isolation",
            (*base, "isolation"),
        )
    if not isinstance(v.params, dict):
        raise error(
            f"expected a mapping of parameters, got {type(v.params).__name__}",
            f"vertices.{v.id}.params",
            (*base, "params"),
        )
    for attr in ("input", "output"):
        value = getattr(v, attr)
        if value is not None and not isinstance(value, str) and not _is_struct(value):
            raise error(
                f"expected an import path 'package.module:Struct' or a msgspec.Struct type, "
                f"got {value!r}",
                f"vertices.{v.id}.{attr}",
                (*base, attr),
            )
    _check_replication(v, error)
    for attr in ("code", "get_state", "set_state"):
        value = getattr(v, attr)
        if value is not None and not (isinstance(value, str) or callable(value)):
            raise error(
                f"expected an import path 'package.module:attr' or a callable, got {value!r}",
                f"vertices.{v.id}.{attr}",
                (*base, attr),
            )


def _check_replication(v: Vertex, error: Callable[..., AppError]) -> None:
    base = ("vertices", v.id)
    r = v.replicas
    if r is not None and (
        isinstance(r, bool) or not isinstance(r, int) or not 0 <= r <= MAX_REPLICAS
    ):
        raise error(
            f"expected 0, 1 or {MAX_REPLICAS} replicas, got {r!r}",
            f"vertices.{v.id}.replicas",
            (*base, "replicas"),
        )
    n = v.snapshot_events
    if isinstance(n, bool) or not isinstance(n, int) or not 1 <= n <= MAX_SNAPSHOT_EVENTS:
        raise error(
            f"expected a whole number of events from 1 to {MAX_SNAPSHOT_EVENTS}, got {n!r}",
            f"vertices.{v.id}.snapshot_events",
            (*base, "snapshot_events"),
        )
    t = v.snapshot_s
    if not _is_number(t) or not 0.01 <= t <= MAX_SNAPSHOT_S:
        raise error(
            f"expected a number of seconds from 0.01 to {MAX_SNAPSHOT_S:g}, got {t!r}",
            f"vertices.{v.id}.snapshot_s",
            (*base, "snapshot_s"),
        )


def has_state(v: Vertex) -> bool:
    """The vertex keeps state across events: it names state hooks, or its code is a class
    with a ``get_state`` method (an import path is looked up; one that does not resolve
    has no state here: validation reports it)."""
    if v.get_state is not None:
        return True
    code: Any = v.code
    if isinstance(code, str):
        try:
            code = resolve(code)
        except ImportPathError:
            return False
    return isinstance(code, type) and callable(getattr(code, "get_state", None))


def _kahn(vertices: Iterable[str], edges: list[Edge]) -> list[str]:
    names = list(vertices)
    succ: dict[str, list[str]] = {v: [] for v in names}
    for e in edges:
        if e.src in succ and e.dst in succ:
            succ[e.src].append(e.dst)
    return topological_order(names, succ)
