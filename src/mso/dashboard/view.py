"""What the dashboard shows, derived from successive ``status`` replies. Pure: no I/O, time is
passed in, so the timeline's bookkeeping is tested without a browser or a node.

A status reply says what is (placement, counters, batteries) and keeps short histories (rule
decisions, recoveries, failures, rejoins). The tracker turns two successive replies into rates
(events/s per chain, bytes/s and measured vertex CPU per node) and turns what is new in the
histories, and every vertex whose node changed, into timeline entries: what happened, why, how
long it took and how many events it cost.
"""

from __future__ import annotations

import re
from collections import deque
from dataclasses import dataclass, field
from typing import Any

from mso.statusview import recovered_from

# distinct colours for chains (Okabe-Ito, then Tableau): told apart by most colour-blind eyes
PALETTE = (
    "#0072B2",
    "#E69F00",
    "#009E73",
    "#CC79A7",
    "#D55E00",
    "#56B4E9",
    "#F0E442",
    "#000000",
    "#8C564B",
    "#7F7F7F",
    "#BCBD22",
    "#17BECF",
)
TIMELINE_LEN = 100
RATE_WINDOW_S = 5.0  # rates are means over this long: a 1 Hz camera does not flicker to 0
_DECISION = re.compile(r"^(?P<at>-?\d+(?:\.\d+)?) (?P<what>.*?)(?: \((?P<why>.*)\))?$")
_RELOCATE = re.compile(r"^relocate (?P<app>[^/ ]+)/(?P<vertex>\S+) -> (?P<node>\S+)$")
PENDING_S = 30.0  # a move asked for and not seen by then is not waited for any more
NOBODY_SAID = "no node said who asked"
MOVED_S = 6.0  # a vertex that moved is highlighted on the topology this long
HISTORY_LEN = 90  # points of each chain's rate and delay kept for its sparklines
ERRORS_PER_S = 1.0  # a vertex failing this often (over the rate window) is flagged on the page


def chain_colour(index: int) -> str:
    return PALETTE[index % len(PALETTE)]


@dataclass
class Entry:
    """One reconfiguration or membership change on the timeline."""

    t: float  # seconds since the dashboard started
    kind: str  # relocation, remap, recovery, rule, failure, rejoin, move
    what: str
    why: str = ""
    took_ms: float | None = None
    lost: int | None = None  # events given up (edge bounds and QoS) while it ran
    ok: bool = True

    def as_dict(self) -> dict[str, Any]:
        return {
            "t": round(self.t, 2),
            "kind": self.kind,
            "what": self.what,
            "why": self.why,
            "took_ms": None if self.took_ms is None else round(self.took_ms, 2),
            "lost": self.lost,
            "ok": self.ok,
        }


@dataclass
class Tracker:
    """Keeps what the previous replies said; ``update`` gives the next view."""

    t0: float
    timeline: list[Entry] = field(default_factory=list)
    _history: deque[tuple[float, dict[str, Any]]] = field(default_factory=deque)
    _seen: set[tuple[Any, ...]] = field(default_factory=set)
    _placement: dict[tuple[str, str], str] = field(default_factory=dict)
    _dropped: dict[str, int] = field(default_factory=dict)  # app -> given up by edge bounds and QoS
    # (app, vertex) -> (node, kind, why, took_ms, when) of a move asked for, not yet seen
    _requested: dict[tuple[str, str], tuple[str, str, str, float | None, float]] = field(
        default_factory=dict
    )
    # latest move seen of each vertex: its entry and the node it went to
    _moves: dict[tuple[str, str], tuple[Entry, str]] = field(default_factory=dict)
    # each node's last battery reported: a failed or silent node is drawn with it
    _battery: dict[str, float | None] = field(default_factory=dict)
    # (app, chain index) -> its recent (t, events/s, delay ms), for the sparklines
    _series: dict[tuple[str, int], deque[tuple[float, float | None, float | None]]] = field(
        default_factory=dict
    )

    def note(
        self,
        now: float,
        kind: str,
        what: str,
        why: str = "",
        took_ms: float | None = None,
        ok: bool = True,
    ) -> None:
        """Add an entry the dashboard itself knows of (a remap it asked for, a refusal)."""
        self._add(Entry(now - self.t0, kind, what, why, took_ms, ok=ok))

    def attribute(
        self,
        now: float,
        app: str,
        vertex: str,
        node: str,
        kind: str,
        why: str,
        took_ms: float | None,
    ) -> None:
        """A move of ``vertex`` to ``node`` was asked for (and took ``took_ms``): say so on its
        entry, the one already seen in status (a move shows in status when it ends, as its
        reply comes) if it is recent, unexplained and went there, or else the next one seen."""
        seen = self._moves.get((app, vertex))
        if (
            seen is not None
            and seen[0].kind == "move"
            and seen[1] == node
            and (now - self.t0 - seen[0].t < 5.0)
        ):
            entry = seen[0]
            entry.kind, entry.why, entry.took_ms = kind, why, took_ms
        else:
            self._requested[(app, vertex)] = (node, kind, why, took_ms, now)

    def _add(self, entry: Entry) -> None:
        self.timeline.append(entry)
        del self.timeline[:-TIMELINE_LEN]

    def update(
        self,
        nodes: dict[str, Any],
        now: float,
        positions: dict[str, tuple[float, float]] | None = None,
        expected: list[str] | None = None,
    ) -> dict[str, Any]:
        """The view of one status reply (node id -> that node's status), at loop time ``now``.

        ``expected`` lists every node of the overlay (from the emulator), so a node that did not
        answer is shown, as silent, instead of vanishing."""
        while len(self._history) > 1 and now - self._history[1][0] >= RATE_WINDOW_S:
            self._history.popleft()  # keep the newest reply at least the window old
        prev_at, prev = self._history[0] if self._history else (now, {})
        dt = now - prev_at
        failed: set[str] = set()
        unreachable: set[str] = set()  # out of some node's reach, failed by nobody
        rejoined: dict[str, int] = {}
        for nid, st in sorted(nodes.items()):
            failed.update(st.get("failed_nodes", []))
            unreachable.update(st.get("unreachable_nodes", []))
            for f in st.get("failures", []):
                self._once(("failure", f["node"]), now, "failure", f"{f['node']} failed",
                           f"detected by {f['detector']}")  # fmt: skip
            for r in st.get("rejoins", []):
                inc = int(r["incarnation"])
                rejoined[r["node"]] = max(rejoined.get(r["node"], 0), inc)
                if self._once(("rejoin", r["node"], inc), now, "rejoin",
                              f"{r['node']} rejoined", f"incarnation {inc}"):  # fmt: skip
                    self._seen.discard(("failure", r["node"]))  # it may fail again
            for d in st.get("management", {}).get("done", []):
                if ("rule", nid, d) in self._seen:
                    continue
                match = _DECISION.match(d)
                what, why = (match["what"], match["why"] or "") if match else (d, "")
                moved = _RELOCATE.match(what)
                if moved:  # told on the move's own entry, when status shows it
                    self._seen.add(("rule", nid, d))
                    self.attribute(now, moved["app"], moved["vertex"], moved["node"],
                                   "relocation", f"rule on {nid}: {why}", None)  # fmt: skip
                else:
                    self._once(("rule", nid, d), now, "rule", f"{nid}: {what}", why)
        unreachable -= failed
        nodes_out = self._nodes(nodes, prev, dt, failed, unreachable, rejoined, positions, expected)
        apps = self._apps(nodes, prev, dt, now)
        links = sorted(
            {tuple(sorted((nid, n))) for nid, st in nodes.items() for n in st.get("neighbours", [])}
        )
        self._history.append((now, nodes))
        return {
            "t": round(now - self.t0, 2),
            "nodes": nodes_out,
            "links": [list(link) for link in links],
            "routes": {nid: st.get("routes", {}) for nid, st in sorted(nodes.items())},
            "apps": apps,
            "failed": sorted(failed),
            "unreachable": sorted(unreachable),
            "rejoined": rejoined,
            "timeline": [e.as_dict() for e in reversed(self.timeline)],
        }

    def _once(self, key: tuple[Any, ...], now: float, kind: str, what: str, why: str) -> bool:
        if key in self._seen:
            return False
        self._seen.add(key)
        self._add(Entry(now - self.t0, kind, what, why))
        return True

    def _nodes(
        self,
        nodes: dict[str, Any],
        prev: dict[str, Any],
        dt: float,
        failed: set[str],
        unreachable: set[str],
        rejoined: dict[str, int],
        positions: dict[str, tuple[float, float]] | None,
        expected: list[str] | None,
    ) -> list[dict[str, Any]]:
        out = []
        parked_on: set[str] = set()
        for st in nodes.values():
            for app in st.get("apps", {}).values():
                if app.get("parked"):
                    parked_on.add(st["node"])
        for nid in sorted(set(nodes) | set(expected or [])):
            st = nodes.get(nid)
            pos = (positions or {}).get(nid)
            if st is None:
                out.append({"id": nid, "answered": False, "failed": nid in failed,
                            "unreachable": nid in unreachable,
                            "last_battery": self._battery.get(nid),
                            "pos": list(pos) if pos else None})  # fmt: skip
                continue
            mon = st.get("monitor", {})
            self._battery[nid] = mon.get("battery_fraction")
            traffic = st.get("traffic", {})
            before = prev.get(nid, {})
            rate = {
                k: _rate(traffic.get(k, 0), before.get("traffic", {}).get(k, 0), dt)
                for k in ("bytes_in", "bytes_out", "bytes_forwarded")
            }
            cpu_s = _vertex_cpu(st)
            out.append(
                {
                    "id": nid,
                    "answered": True,
                    "failed": nid in failed,
                    "unreachable": nid in unreachable,
                    "rejoined": rejoined.get(nid),
                    "parked": nid in parked_on,
                    "pos": list(pos) if pos else None,
                    "battery": mon.get("battery_fraction"),
                    "drain_w": mon.get("drain_w", 0.0),
                    "lifetime_s": mon.get("lifetime_s"),
                    "load": mon.get("load", 0.0),
                    "cpu": _rate(cpu_s, _vertex_cpu(before), dt) if before else 0.0,
                    "traffic": rate,
                    "neighbours": st.get("neighbours", []),
                    "vertices": sorted(
                        v for a in st.get("apps", {}).values() for v in a["vertices"]
                    ),
                }
            )
        return out

    def _apps(
        self, nodes: dict[str, Any], prev: dict[str, Any], dt: float, now: float
    ) -> list[dict[str, Any]]:
        merged: dict[str, dict[str, Any]] = {}
        for nid, st in sorted(nodes.items()):
            for name, app in st.get("apps", {}).items():
                agg = merged.setdefault(
                    name,
                    {"chains": app["chains"], "placement": {}, "vertices": {}, "delay": {},
                     "parked": {}, "dropped": 0, "delivered": {}, "capable": {}},
                )  # fmt: skip
                agg["capable"].update(app.get("capable", {}))  # placed by capability (§3.3)
                agg["delay"].update(app.get("chain_delay_ms", {}))
                agg["parked"].update(app.get("parked", {}))
                agg["dropped"] += sum(app.get("given_up", {}).values())
                for v, vs in app["vertices"].items():
                    agg["placement"][v] = nid
                    agg["vertices"][v] = {
                        "node": nid,
                        "kind": vs["kind"],
                        "events": vs["emitted"] if vs["kind"] == "source" else vs["processed"],
                        "state": vs.get("state", ""),
                        "errors": int(vs.get("errors", 0)),
                        "last_error": str(vs.get("last_error", ""))[:300],
                    }
                for e, c in app["edges"].items():
                    got = agg["delivered"].get(e, 0)
                    agg["delivered"][e] = max(got, c.get("delivered", 0))
                for rec in app.get("recoveries", []):
                    self._recovery(name, rec, now)
        before = {name: _delivered(prev, name) for name in merged}
        out = []
        for name, agg in sorted(merged.items()):
            dropped = agg["dropped"]
            lost = dropped - self._dropped.get(name, dropped)
            self._dropped[name] = dropped
            for v, n in sorted(agg["placement"].items()):
                old = self._placement.get((name, v))
                self._placement[(name, v)] = n
                if old is not None and old != n:
                    kind, why, took = "move", NOBODY_SAID, None
                    told = _told(nodes, name, v)  # the coordinating node's record of it
                    if told is not None:
                        why, took = told
                    asked = self._requested.pop((name, v), None)
                    if asked is not None and asked[0] == n and now - asked[4] < PENDING_S:
                        _, kind, why, asked_took, _ = asked
                        took = took if asked_took is None else asked_took  # a rule's: its record
                    entry = Entry(now - self.t0, kind, f"{v}: {old} → {n}", why, took, lost)
                    self._moves[(name, v)] = (entry, n)
                    self._add(entry)
            chains = []
            for i, c in enumerate(agg["chains"]):
                cname = "-".join(c)
                last = f"{c[-2]}->{c[-1]}" if len(c) > 1 else ""
                delivered = agg["delivered"].get(last, 0)
                prior = before[name].get(last)
                rate = _rate(delivered, prior, dt) if prior is not None else None
                series = self._series.setdefault((name, i), deque(maxlen=HISTORY_LEN))
                series.append((round(now - self.t0, 2), rate, agg["delay"].get(cname)))
                chains.append(
                    {
                        "index": i,
                        "name": cname,
                        "vertices": c,
                        "colour": chain_colour(i),
                        "nodes": [agg["placement"].get(v) for v in c],
                        "events_per_s": rate,
                        "delay_ms": agg["delay"].get(cname),
                        "parked": agg["parked"].get(cname),
                        "history": [list(point) for point in series],
                    }
                )
            out.append(
                {
                    "name": name,
                    "chains": chains,
                    "placement": agg["placement"],
                    "vertices": agg["vertices"],
                    "given_up": dropped,
                    "capable": agg["capable"],
                    "movable": movable(agg["chains"], agg["placement"]),
                    "alarms": _alarms(agg["vertices"], _errors(prev, name), dt),
                    "moved": {
                        v: round(now - self.t0 - entry.t, 2)
                        for (a, v), (entry, _) in self._moves.items()
                        if a == name and now - self.t0 - entry.t < MOVED_S
                    },
                }
            )
        return out

    def _recovery(self, app: str, rec: dict[str, Any], now: float) -> None:
        key = ("recovery", app, rec.get("at"), tuple(rec.get("failed", [])))
        done = rec.get("ok") is not None or rec.get("error")
        if key in self._seen or not done:
            return
        self._seen.add(key)
        chains = ", ".join(rec.get("chains", [])) or "-"
        failed = recovered_from(rec)
        entry = Entry(
            now - self.t0,
            "recovery",
            f"{app}: {rec.get('remap', '?')} remap of {chains}",
            failed,
            took_ms=rec.get("took_ms"),
            ok=bool(rec.get("ok")),
        )
        # its restored vertices can show in status (running at their new hosts) a poll before
        # the coordinator's record says the recovery is done: those moves are this recovery's,
        # and the timeline shows the recovery first, then what it moved
        lost = set(rec.get("lost", []))
        since = now - self.t0 - PENDING_S
        mine = [
            e
            for (a, v), (e, _) in self._moves.items()
            if a == app and v in lost and e.kind == "move" and e.t >= since and e in self.timeline
        ]
        for e in mine:
            e.kind = "recovery"
            if e.why == NOBODY_SAID:
                e.why = failed
        if mine:
            first = min(self.timeline.index(e) for e in mine)
            entry.t = self.timeline[first].t
            self.timeline.insert(first, entry)
            del self.timeline[:-TIMELINE_LEN]
        else:
            self._add(entry)


def movable(chains: list[list[str]], placement: dict[str, str]) -> dict[str, list[str]]:
    """The vertices a relocation can move (§3.4.1: a chain's interior, never its head or tail,
    which pinned sources and sinks always are), each with the ways it can go: ``upstream`` or
    ``downstream`` while the vertex before or after it in its chain runs on another node, and
    every node the app does not already run it on."""
    ends = {c[0] for c in chains if c} | {c[-1] for c in chains if c}
    out: dict[str, list[str]] = {}
    for c in chains:
        for i in range(1, len(c) - 1):
            v = c[i]
            if v in ends or v in out:
                continue
            here = placement.get(v)
            ways = []
            if placement.get(c[i - 1]) not in (None, here):
                ways.append("upstream")
            if placement.get(c[i + 1]) not in (None, here):
                ways.append("downstream")
            out[v] = ways
    return dict(sorted(out.items()))


def _errors(nodes: dict[str, Any], app: str) -> dict[str, int]:
    """Each vertex's error count in an earlier reply."""
    return {
        v: int(vs.get("errors", 0))
        for st in nodes.values()
        for v, vs in st.get("apps", {}).get(app, {}).get("vertices", {}).items()
    }


def _alarms(
    vertices: dict[str, dict[str, Any]], before: dict[str, int], dt: float
) -> list[dict[str, Any]]:
    """The vertices failing at ``ERRORS_PER_S`` or more since the earlier reply: a vertex that
    fails on every event is flagged, not buried in a column (its last error says why)."""
    out = []
    for v, vs in sorted(vertices.items()):
        rate = _rate(vs["errors"], before.get(v), dt)
        if rate >= ERRORS_PER_S:
            out.append({"vertex": v, "node": vs["node"], "errors": vs["errors"],
                        "per_s": round(rate, 1), "last_error": vs["last_error"]})  # fmt: skip
    return out


def _rate(value: float, before: float | None, dt: float) -> float:
    if before is None or dt <= 0:
        return 0.0
    return max(0.0, (value - before) / dt)


def _vertex_cpu(st: dict[str, Any]) -> float:
    return float(
        sum(
            vs.get("cpu_s", 0.0)
            for a in st.get("apps", {}).values()
            for vs in a["vertices"].values()
        )
    )


def _delivered(nodes: dict[str, Any], app: str) -> dict[str, int]:
    out: dict[str, int] = {}
    for st in nodes.values():
        a = st.get("apps", {}).get(app)
        for e, c in (a or {}).get("edges", {}).items():
            out[e] = max(out.get(e, 0), c.get("delivered", 0))
    return out


def _told(nodes: dict[str, Any], app: str, vertex: str) -> tuple[str, float | None] | None:
    """Who asked for the latest move of ``vertex`` (in words) and how long it took, from the
    nodes' records of the moves they coordinated (a remap's record names every vertex)."""
    best: tuple[float, str, float | None] | None = None
    for st in nodes.values():
        for rec in st.get("moves", []):
            if rec.get("app") != app:
                continue
            moved = rec.get("vertex") == vertex or any(
                part.split("->")[0] == vertex for part in str(rec.get("detail", "")).split()
            )
            if moved and (best is None or rec.get("ago_s", 0.0) < best[0]):
                best = (
                    rec.get("ago_s", 0.0),
                    rec.get("asked") or rec.get("by", ""),
                    rec.get("took_ms"),
                )
    return None if best is None else (best[1], best[2])
