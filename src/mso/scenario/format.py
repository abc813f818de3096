"""Scenario files: the network an app runs on (nodes, capacities, energy model, links) and
what happens to it over time (scripted changes, mobility).

See docs/scenario-format.md. Links are listed explicitly, or derived from node positions and a
radio range. This module only parses; :mod:`mso.scenario.timeline` plays the changes.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

from mso.errors import AppError, ScenarioError
from mso.model.capabilities import parse_capabilities
from mso.model.mobility import GaussMarkov, GroupMobility, Mobility, RandomWaypoint, Trace
from mso.model.network import LinkSpec, Network, NodeSpec, PowerModel
from mso.model.propagation import MODELS, Propagation
from mso.model.yamlfile import Located, load_yaml, load_yaml_file
from mso.scenario.mobility_import import FORMATS, load_trace

SCENARIO_KEYS = {
    "name",
    "nodes",
    "links",
    "radio_range",
    "node_defaults",
    "link_defaults",
    "changes",
    "mobility",
    "propagation",
}
PROPAGATION_KEYS = {
    "model", "tx_dbm", "ref_loss_db", "ref_distance_m", "exponent", "sensitivity_dbm",
    "width_db", "shadowing_db", "seed", "max_loss", "retry_delay_ms", "curve",
}  # fmt: skip
MOBILITY_KEYS = {  # per model
    "random_waypoint": {"model", "area", "speed", "pause_s", "seed", "fixed", "step_s"},
    "gauss_markov": {"model", "area", "speed", "alpha", "interval_s", "seed", "fixed", "step_s"},
    "group": {
        "model", "area", "speed", "pause_s", "groups", "radius", "interval_s", "seed", "step_s",
    },
}  # fmt: skip
TRACE_KEYS = {"model", "file", "nodes", "dim", "step_s"}
MOBILITY_MODELS = (*MOBILITY_KEYS, *FORMATS)
CHANGE_KEYS = {"at", "down", "up", "fail", "restart", "partition", "heal", "loss", "between"}
CHANGE_KINDS = ("up", "down", "fail", "restart", "partition", "heal", "loss")
MAX_NUMBER = 1e12  # capacities, powers, delays: larger ones only overflow the objectives
NODE_KEYS = {"cpu", "battery_wh", "power", "pos", "capabilities"}
POWER_KEYS = {"idle_w", "cpu_w", "tx_uj_per_byte", "rx_uj_per_byte", "cpu_energy"}
CPU_ENERGY = ("modelled", "measured")
LINK_KEYS = {"between", "bandwidth_mbps", "delay_ms", "loss"}
LINK_ATTRS = LINK_KEYS - {"between"}


@dataclass(frozen=True)
class LinkChange:
    """A scripted link change: at ``at`` seconds the link between ``a`` and ``b`` goes up/down."""

    at: float
    a: str
    b: str
    up: bool
    link: LinkSpec | None = None


@dataclass(frozen=True)
class NodeFailure:
    """A scripted fail-stop failure: at ``at`` seconds node ``node`` dies (SIGKILL)."""

    at: float
    node: str


@dataclass(frozen=True)
class NodeRestart:
    """A scripted restart: at ``at`` seconds a failed ``node`` starts again, as a new process
    (a new incarnation with no apps); its links come back."""

    at: float
    node: str


@dataclass(frozen=True)
class Partition:
    """At ``at`` seconds the network splits: links between different ``groups`` go down
    (nodes in no group form one more group together). Replaces an earlier partition."""

    at: float
    groups: tuple[frozenset[str], ...]


@dataclass(frozen=True)
class Heal:
    """At ``at`` seconds a partition ends: the links it cut come back."""

    at: float


@dataclass(frozen=True)
class LossChange:
    """At ``at`` seconds the loss probability of one link (``ends``), or of every link if
    ``ends`` is None, becomes ``loss``."""

    at: float
    loss: float
    ends: tuple[str, str] | None = None


Change = LinkChange | NodeFailure | NodeRestart | Partition | Heal | LossChange


@dataclass
class Scenario:
    """A named network, loaded from a file, with its scripted link changes."""

    name: str
    network: Network
    radio_range: float | None = None
    file: str | None = None
    changes: list[Change] = field(default_factory=list)
    mobility: Mobility | None = None
    mobility_step_s: float = 0.5
    link_template: LinkSpec | None = None
    propagation: Propagation | None = None


class _Reader:
    def __init__(self, doc: Located) -> None:
        self.doc = doc

    def err(self, message: str, path: tuple[str | int, ...]) -> ScenarioError:
        field = ""
        for p in path:
            field += f"[{p}]" if isinstance(p, int) else (f".{p}" if field else str(p))
        return ScenarioError(
            message, file=self.doc.file, line=self.doc.line(path), field=field or None
        )

    def mapping(self, value: Any, allowed: set[str], path: tuple[str | int, ...]) -> dict[str, Any]:
        if value is None:
            return {}
        if not isinstance(value, dict):
            raise self.err(f"expected a mapping, got {value!r}", path)
        for key in value:
            if key not in allowed:
                raise self.err(
                    f"unknown attribute {key!r} (expected one of: {', '.join(sorted(allowed))})",
                    (*path, key),
                )
        return value

    def number(
        self, value: Any, path: tuple[str | int, ...], *, low: float = 0.0, strict: bool = False
    ) -> float:
        ok = isinstance(value, int | float) and not isinstance(value, bool) and math.isfinite(value)
        if not ok or value < low or (strict and value == low) or value > MAX_NUMBER:
            bound = f"> {low:g}" if strict else f">= {low:g}"
            if ok and value > MAX_NUMBER:
                bound = f"<= {MAX_NUMBER:g}"
            raise self.err(f"expected a number {bound}, got {value!r}", path)
        return float(value)


def scenario_from_document(doc: Located) -> Scenario:
    """Build a Scenario from a parsed YAML document, with located errors."""
    r = _Reader(doc)
    data = r.mapping(doc.data, SCENARIO_KEYS, ())
    if not data:
        raise r.err("expected a mapping with 'name' and 'nodes'", ())
    name = data.get("name", Path(doc.file).stem if doc.file else "scenario")
    if not isinstance(name, str) or not name:
        raise r.err(f"expected a non-empty string, got {name!r}", ("name",))
    node_defaults = r.mapping(data.get("node_defaults"), NODE_KEYS - {"pos"}, ("node_defaults",))
    link_defaults = r.mapping(data.get("link_defaults"), LINK_ATTRS, ("link_defaults",))
    if node_defaults:  # check the defaults where they are written, not at the first node
        _node(r, "defaults", node_defaults, ("node_defaults",))
    raw_nodes = data.get("nodes")
    if not isinstance(raw_nodes, dict) or not raw_nodes:
        raise r.err("expected a non-empty mapping of node id to attributes", ("nodes",))
    nodes = []
    for nid, attrs in raw_nodes.items():
        own = r.mapping(attrs, NODE_KEYS, ("nodes", nid))
        merged = {**node_defaults, **own}
        if "power" in own and "power" in node_defaults:  # a node's power refines the default
            base = r.mapping(node_defaults["power"], POWER_KEYS, ("node_defaults", "power"))
            merged["power"] = {
                **base,
                **r.mapping(own["power"], POWER_KEYS, ("nodes", nid, "power")),
            }
        nodes.append(_node(r, nid, merged, ("nodes", nid)))
    radio_range = None
    if "radio_range" in data:
        radio_range = r.number(data["radio_range"], ("radio_range",), strict=True)
    propagation = None
    if "propagation" in data:
        propagation = _propagation(r, data["propagation"])
        if "links" in data:
            raise r.err("'propagation' shapes links from positions, not listed 'links'",
                        ("propagation",))  # fmt: skip
        if radio_range is None:
            radio_range = propagation.range_m()
            if radio_range <= 0:
                raise r.err("this propagation model links no pair of nodes at any distance",
                            ("propagation",))  # fmt: skip
    trace: Trace | None = None
    if "mobility" in data:
        if radio_range is None:
            raise r.err("mobility needs node positions and a 'radio_range'", ("mobility",))
        trace = _trace(r, data["mobility"], [n.id for n in nodes])
    if trace is not None:  # a trace gives the start positions of the nodes it moves
        starts = trace.start_positions()
        nodes = [replace(n, pos=starts[n.id]) if n.id in starts else n for n in nodes]
    network = Network(nodes)
    links = data.get("links")
    if links is not None and radio_range is not None:
        raise r.err("give either 'links' or 'radio_range', not both", ("radio_range",))
    template = _link_attrs(r, "", "", link_defaults, ("link_defaults",))
    if radio_range is not None:
        for n in nodes:
            if n.pos is None:
                raise r.err(
                    "a node needs 'pos: [x, y]' when the scenario has a radio_range",
                    ("nodes", n.id),
                )
        network.links_from_positions(radio_range, template, propagation)
    elif links is not None:
        if not isinstance(links, list):
            raise r.err("expected a list of links", ("links",))
        for i, item in enumerate(links):
            path: tuple[str | int, ...] = ("links", i)
            ends: Any
            if isinstance(item, list):
                ends, attrs = item, {}
            else:
                attrs = r.mapping(item, LINK_KEYS, path)
                ends = attrs.get("between")
                path = (*path, "between")
            if not (
                isinstance(ends, list) and len(ends) == 2 and all(isinstance(e, str) for e in ends)
            ):
                raise r.err(f"expected a pair of node ids like [N1, N2], got {ends!r}", path)
            for end in ends:
                if end not in network.nodes:
                    raise r.err(f"unknown node {end!r} (known: {', '.join(network.nodes)})", path)
            if ends[0] == ends[1]:
                raise r.err(f"a link joins two different nodes, got {ends!r}", path)
            if network.link(ends[0], ends[1]) is not None:
                raise r.err(f"duplicate link {ends[0]}-{ends[1]}", path)
            merged = {**link_defaults, **{k: v for k, v in attrs.items() if k != "between"}}
            network.add_link(_link_attrs(r, ends[0], ends[1], merged, ("links", i)))
    changes = _changes(r, data.get("changes"), network, template)
    scenario = Scenario(
        name=name,
        network=network,
        radio_range=radio_range,
        file=doc.file,
        changes=changes,
        link_template=template,
        propagation=propagation,
    )
    if trace is not None:
        scenario.mobility = trace
        scenario.mobility_step_s = _step(r, data["mobility"])
    elif "mobility" in data:
        scenario.mobility, scenario.mobility_step_s = _mobility(r, data["mobility"], network)
    return scenario


def _propagation(r: _Reader, raw: Any) -> Propagation:
    """The ``propagation:`` block: a link model (:mod:`mso.model.propagation`), checked."""
    path: tuple[str | int, ...] = ("propagation",)
    attrs = r.mapping(raw, PROPAGATION_KEYS, path)
    if not attrs:
        raise r.err(f"expected a mapping with 'model' ({', '.join(MODELS)})", path)
    model = attrs.get("model", "log_distance")
    if model not in MODELS:
        raise r.err(f"unknown model {model!r} (expected one of: {', '.join(MODELS)})",
                    (*path, "model"))  # fmt: skip
    values: dict[str, Any] = {"model": model}
    for key in ("tx_dbm", "ref_loss_db", "sensitivity_dbm"):  # signed decibels
        if key in attrs:
            values[key] = r.number(attrs[key], (*path, key), low=-MAX_NUMBER)
    for key in ("ref_distance_m", "exponent", "width_db"):
        if key in attrs:
            values[key] = r.number(attrs[key], (*path, key), strict=True)
    for key in ("shadowing_db", "retry_delay_ms"):
        if key in attrs:
            values[key] = r.number(attrs[key], (*path, key))
    if "max_loss" in attrs:
        values["max_loss"] = r.number(attrs["max_loss"], (*path, "max_loss"), strict=True)
        if values["max_loss"] >= 1.0:
            raise r.err(f"expected a loss in (0, 1), got {attrs['max_loss']!r}",
                        (*path, "max_loss"))  # fmt: skip
    if "seed" in attrs:
        seed = attrs["seed"]
        if not isinstance(seed, int) or isinstance(seed, bool):
            raise r.err(f"expected an integer seed, got {seed!r}", (*path, "seed"))
        values["seed"] = seed
    if model == "curve":
        values["curve"] = _curve(r, attrs.get("curve"), (*path, "curve"))
    elif "curve" in attrs:
        raise r.err("'curve' goes with 'model: curve'", (*path, "curve"))
    return Propagation(**values)


def _curve(r: _Reader, raw: Any, path: tuple[str | int, ...]) -> tuple[tuple[float, float], ...]:
    """``[[distance_m, loss], ...]``, distances increasing, losses in [0, 1]."""
    if not isinstance(raw, list) or not raw:
        raise r.err("expected a list of [distance_m, loss] points", path)
    points: list[tuple[float, float]] = []
    for i, point in enumerate(raw):
        if not (isinstance(point, list) and len(point) == 2):
            raise r.err(f"expected [distance_m, loss], got {point!r}", (*path, i))
        d = r.number(point[0], (*path, i))
        p = r.number(point[1], (*path, i))
        if p > 1.0:
            raise r.err(f"expected a loss in [0, 1], got {point[1]!r}", (*path, i))
        if points and d <= points[-1][0]:
            raise r.err(f"distances must increase, got {d:g} after {points[-1][0]:g}", (*path, i))
        points.append((d, p))
    return tuple(points)


def _step(r: _Reader, attrs: dict[str, Any]) -> float:
    return r.number(attrs.get("step_s", 0.5), ("mobility", "step_s"), strict=True)


def _trace(r: _Reader, raw: Any, ids: list[str]) -> Trace | None:
    """The movement file a ``model: ns2`` or ``model: bonnmotion`` mobility names, or None for
    another model. Its path is relative to the scenario file."""
    path: tuple[str | int, ...] = ("mobility",)
    if not isinstance(raw, dict) or raw.get("model") not in FORMATS:
        return None
    attrs = r.mapping(raw, TRACE_KEYS, path)
    file = attrs.get("file")
    if not isinstance(file, str) or not file:
        raise r.err(f"expected the path of a movement file, got {file!r}", (*path, "file"))
    order = attrs.get("nodes", ids)
    if not (
        isinstance(order, list) and order and all(isinstance(n, str) and n in ids for n in order)
    ):
        raise r.err(
            f"expected a list of node ids (known: {', '.join(ids)}), got {order!r}",
            (*path, "nodes"),
        )
    if len(set(order)) != len(order):
        raise r.err(f"a node id is listed twice in {order!r}", (*path, "nodes"))
    dim = attrs.get("dim", 2)
    if attrs["model"] != "bonnmotion" and "dim" in attrs:
        raise r.err("'dim' goes with model: bonnmotion only", (*path, "dim"))
    if dim not in (2, 3) or isinstance(dim, bool):
        raise r.err(f"expected dim 2 or 3, got {dim!r}", (*path, "dim"))
    base = Path(r.doc.file).parent if r.doc.file else Path.cwd()
    return load_trace(base / file, attrs["model"], list(order), dim=dim)


def _mobility(r: _Reader, raw: Any, network: Network) -> tuple[Mobility, float]:
    path: tuple[str | int, ...] = ("mobility",)
    model = raw.get("model") if isinstance(raw, dict) else None
    if model not in MOBILITY_KEYS:
        raise r.err(
            f"expected model: one of {', '.join(MOBILITY_MODELS)}, got {model!r}",
            (*path, "model"),
        )
    attrs = r.mapping(raw, MOBILITY_KEYS[model], path)

    def pair(key: str) -> tuple[float, float]:
        v = attrs.get(key)
        if not (isinstance(v, list) and len(v) == 2):
            raise r.err(f"expected two numbers [a, b], got {v!r}", (*path, key))
        return (r.number(v[0], (*path, key)), r.number(v[1], (*path, key)))

    def positive(key: str, default: float) -> float:
        return r.number(attrs.get(key, default), (*path, key), strict=True)

    area, speed = pair("area"), pair("speed")
    if speed[1] < speed[0] or speed[1] <= 0:
        raise r.err(f"expected [min, max] speeds with max > 0, got {list(speed)}", (*path, "speed"))
    fixed = attrs.get("fixed", [])
    if not (isinstance(fixed, list) and all(f in network.nodes for f in fixed)):
        raise r.err(f"expected a list of node ids, got {fixed!r}", (*path, "fixed"))
    seed = attrs.get("seed", 0)
    if isinstance(seed, bool) or not isinstance(seed, int):
        raise r.err(f"expected an integer seed, got {seed!r}", (*path, "seed"))
    pause = r.number(attrs.get("pause_s", 0.0), (*path, "pause_s"))
    step = positive("step_s", 0.5)
    if model == "gauss_markov":
        alpha = r.number(attrs.get("alpha", 0.75), (*path, "alpha"))
        if alpha > 1:
            raise r.err(f"expected alpha in [0, 1], got {alpha!r}", (*path, "alpha"))
        interval = positive("interval_s", 1.0)
        return GaussMarkov(area, speed, alpha, interval, seed, frozenset(fixed)), step
    if model == "group":
        groups = _node_groups(r, attrs.get("groups"), network, (*path, "groups"))
        radius = r.number(attrs.get("radius", 10.0), (*path, "radius"))
        interval = positive("interval_s", 1.0)
        return GroupMobility(area, speed, groups, radius, pause, interval, seed), step
    return RandomWaypoint(area, speed, pause, seed, frozenset(fixed)), step


def _node_groups(
    r: _Reader, raw: Any, network: Network, path: tuple[str | int, ...]
) -> tuple[tuple[str, ...], ...]:
    """Groups of nodes (a partition's, group mobility's): lists of known node ids, each node
    in one group at most."""
    if not (isinstance(raw, list) and raw and all(isinstance(g, list) and g for g in raw)):
        raise r.err(f"expected a list of node groups like [[N1, N2], [N3]], got {raw!r}", path)
    seen: set[str] = set()
    for j, group in enumerate(raw):
        for n in group:
            if not isinstance(n, str) or n not in network.nodes:
                raise r.err(f"unknown node {n!r} (known: {', '.join(network.nodes)})", (*path, j))
            if n in seen:
                raise r.err(f"node {n!r} is in two groups", (*path, j))
            seen.add(n)
    return tuple(tuple(g) for g in raw)


def _changes(r: _Reader, raw: Any, network: Network, template: LinkSpec) -> list[Change]:
    if raw is None:
        return []
    if not isinstance(raw, list):
        raise r.err(
            "expected a list of {at: SECONDS, down: [A, B]}, {at, up: [A, B]}, {at, fail: N}, "
            "{at, restart: N}, {at, partition: [[A, ...], [B, ...]]}, {at, heal: true} or "
            "{at, loss: P, between: [A, B]}",
            ("changes",),
        )
    known = ", ".join(network.nodes)
    out: list[Change] = []
    for i, item in enumerate(raw):
        path: tuple[str | int, ...] = ("changes", i)
        attrs = r.mapping(item, CHANGE_KEYS, path)
        if not attrs:
            raise r.err("expected a change like {at: 5.0, down: [N1, N2]}", path)
        at = r.number(attrs.get("at"), (*path, "at"))
        kinds = [k for k in CHANGE_KINDS if k in attrs]
        if len(kinds) != 1:
            raise r.err(f"expected exactly one of {', '.join(map(repr, CHANGE_KINDS))}", path)
        kind = kinds[0]
        field_path = (*path, kind)
        if "between" in attrs and kind != "loss":
            raise r.err("'between' goes with 'loss' only", (*path, "between"))
        value = attrs[kind]
        if kind in ("fail", "restart"):
            if not isinstance(value, str) or value not in network.nodes:
                raise r.err(f"unknown node {value!r} (known: {known})", field_path)
            out.append(NodeFailure(at, value) if kind == "fail" else NodeRestart(at, value))
        elif kind == "heal":
            if value is not True:
                raise r.err(f"expected 'heal: true', got {value!r}", field_path)
            out.append(Heal(at))
        elif kind == "partition":
            out.append(Partition(at, _groups(r, value, network, field_path)))
        elif kind == "loss":
            loss = r.number(value, field_path)
            if loss >= 1.0:
                raise r.err(f"expected a loss probability in [0, 1), got {loss!r}", field_path)
            ends = None
            if "between" in attrs:
                a, b = _pair(r, attrs["between"], network, (*path, "between"))
                ends = (a, b)
            out.append(LossChange(at, loss, ends))
        else:
            up = kind == "up"
            a, b = _pair(r, value, network, field_path)
            link = network.link(a, b) or LinkSpec(
                a, b, template.bandwidth_mbps, template.delay_ms, template.loss
            )
            out.append(LinkChange(at=at, a=a, b=b, up=up, link=link))
    return sorted(out, key=lambda c: c.at)  # stable: changes at one time keep file order


def _pair(r: _Reader, ends: Any, network: Network, path: tuple[str | int, ...]) -> tuple[str, str]:
    if not (isinstance(ends, list) and len(ends) == 2 and all(isinstance(e, str) for e in ends)):
        raise r.err(f"expected a pair of node ids like [N1, N2], got {ends!r}", path)
    for end in ends:
        if end not in network.nodes:
            raise r.err(f"unknown node {end!r} (known: {', '.join(network.nodes)})", path)
    if ends[0] == ends[1]:
        raise r.err(f"a link joins two different nodes, got {ends!r}", path)
    return ends[0], ends[1]


def _groups(
    r: _Reader, raw: Any, network: Network, path: tuple[str | int, ...]
) -> tuple[frozenset[str], ...]:
    groups = _node_groups(r, raw, network, path)
    if len(groups) < 2 and sum(map(len, groups)) == len(network.nodes):
        raise r.err("a partition needs at least two groups", path)
    return tuple(frozenset(g) for g in groups)


def _node(r: _Reader, nid: Any, attrs: dict[str, Any], path: tuple[str | int, ...]) -> NodeSpec:
    if not isinstance(nid, str) or not nid:
        raise r.err(f"expected a string node id, got {nid!r}", path)
    cpu = r.number(attrs.get("cpu", 1.0), (*path, "cpu"), strict=True)
    battery = attrs.get("battery_wh")
    if battery is not None:
        battery = r.number(battery, (*path, "battery_wh"), strict=True)
    p = r.mapping(attrs.get("power"), POWER_KEYS, (*path, "power"))
    if p.get("cpu_energy", "modelled") not in CPU_ENERGY:
        raise r.err(
            f"expected one of {', '.join(CPU_ENERGY)}, got {p['cpu_energy']!r}",
            (*path, "power", "cpu_energy"),
        )
    kw: dict[str, Any] = {
        k: v if k == "cpu_energy" else r.number(v, (*path, "power", k)) for k, v in p.items()
    }
    power = PowerModel(**kw)
    pos = attrs.get("pos")
    if pos is not None:
        if not (isinstance(pos, list) and len(pos) == 2):
            raise r.err(f"expected a position [x, y], got {pos!r}", (*path, "pos"))
        pos = (
            r.number(pos[0], (*path, "pos"), low=-math.inf),
            r.number(pos[1], (*path, "pos"), low=-math.inf),
        )
    try:
        caps = parse_capabilities(attrs.get("capabilities"), "capabilities")
    except AppError as exc:
        raise r.err(exc.message, (*path, "capabilities")) from None
    return NodeSpec(id=nid, cpu=cpu, battery_wh=battery, power=power, pos=pos, capabilities=caps)


def _link_attrs(
    r: _Reader, a: str, b: str, attrs: dict[str, Any], path: tuple[str | int, ...]
) -> LinkSpec:
    bw = attrs.get("bandwidth_mbps")
    loss = r.number(attrs.get("loss", 0.0), (*path, "loss"))
    if loss >= 1.0:
        raise r.err(f"expected a loss probability in [0, 1), got {loss!r}", (*path, "loss"))
    return LinkSpec(
        a,
        b,
        bandwidth_mbps=None if bw is None else r.number(bw, (*path, "bandwidth_mbps"), strict=True),
        delay_ms=r.number(attrs.get("delay_ms", 0.0), (*path, "delay_ms")),
        loss=loss,
    )


def load_scenario(path: str | Path) -> Scenario:
    """Load a scenario YAML file."""
    return scenario_from_document(load_yaml_file(path))


def loads_scenario(text: str, *, file: str | None = None) -> Scenario:
    """Load a scenario from YAML text."""
    return scenario_from_document(load_yaml(text, file))
