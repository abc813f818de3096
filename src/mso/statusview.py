"""The overlay's status as plain-text tables: what ``mso status`` prints.

Plain text rather than rich's tables: ``mso status`` must answer within 150 ms of being typed,
and importing rich's console costs about 35 ms of that; the columns align the same in a
terminal, a pipe and a log file.
"""

from __future__ import annotations

from typing import Any


class Table:
    """Columns aligned under a title; numbers right-aligned; a caption under the rows."""

    def __init__(self, title: str) -> None:
        self.title = title
        self.caption = ""
        self.columns: list[tuple[str, str]] = []  # (header, "left" | "right")
        self.rows: list[tuple[str, ...]] = []

    def add_column(self, header: str, justify: str = "left") -> None:
        self.columns.append((header, justify))

    def add_row(self, *cells: str) -> None:
        self.rows.append(cells)

    def __str__(self) -> str:
        widths = [
            max([len(h), *(len(r[i]) for r in self.rows)]) for i, (h, _) in enumerate(self.columns)
        ]

        def line(cells: tuple[str, ...]) -> str:
            return "  ".join(
                c.rjust(w) if j == "right" else c.ljust(w)
                for c, w, (_, j) in zip(cells, widths, self.columns, strict=True)
            ).rstrip()

        rule = "  ".join("-" * w for w in widths)
        lines = [self.title, line(tuple(h for h, _ in self.columns)), rule]
        lines += [line(r) for r in self.rows]
        if self.caption:
            lines.append(self.caption)
        return "\n".join(lines) + "\n"


def _energy_cells(mon: dict[str, Any]) -> tuple[str, str, str, str]:
    frac, life = mon.get("battery_fraction"), mon.get("lifetime_s")
    battery = "wall" if frac is None else f"{frac * 100:.1f}%"
    lifetime = "-" if life is None else f"{life / 3600:.1f} h"
    measured = mon.get("measured", {})
    drain = measured.get("battery_power_w")
    watts = f"{mon.get('drain_w', 0.0):.2f}" if drain is None else f"{drain:.2f}"
    return battery, watts, lifetime, _measured_cell(mon)


def _measured_cell(mon: dict[str, Any]) -> str:
    """Which of the node's figures the OS measured (the rest come from the power model)."""
    sources, measured = mon.get("sources", {}), mon.get("measured", {})
    out = []
    if str(sources.get("battery", "")).startswith("measured"):
        out.append("battery" + (" (charging)" if measured.get("charging") else ""))
    if sources.get("drain") == "measured":
        out.append("W")
    if "cpu_load" in measured:
        out.append(f"cpu {measured['cpu_load'] * 100:.0f}%")
    if "iface_tx_bytes" in measured:
        tx, rx = _size(measured["iface_tx_bytes"]), _size(measured["iface_rx_bytes"])
        out.append(f"radio {tx}/{rx}")
    return ", ".join(out) or "-"


def _size(n: float) -> str:
    for unit in ("B", "kB", "MB", "GB"):
        if abs(n) < 1000 or unit == "GB":
            return f"{n:.0f} {unit}" if unit == "B" else f"{n:.1f} {unit}"
        n /= 1000
    return f"{n:.1f} GB"


def _clip(text: str, width: int) -> str:
    text = " ".join(str(text).split())  # one line, whatever the vertex wrote
    return text if len(text) <= width else text[: width - 1] + "…"


def _stats_cell(stats: Any) -> str:
    """A vertex's own ``stats()``, compactly: ``k=v`` pairs (numbers rounded), clipped."""
    if stats is None or stats == {}:
        return ""
    if isinstance(stats, dict):
        parts = [f"{k}={v:.4g}" if isinstance(v, float) else f"{k}={v}" for k, v in stats.items()]
        return _clip(" ".join(parts), 48)
    return _clip(str(stats), 48)


def _aged(line: str, clock: Any) -> str:
    """A rule's "time action" line with its time as an age ("12.3 s ago"): the node's clock
    reads nothing a person knows (seconds since the host booted)."""
    head, _, rest = line.partition(" ")
    try:
        at = float(head)
    except ValueError:
        return line
    if not isinstance(clock, int | float) or clock <= 0:
        return rest
    return f"{max(0.0, clock - at):.1f} s ago, {rest}"


def recovered_from(rec: dict[str, Any]) -> str:
    """What a recovery record recovered from: the nodes declared failed, or those whose
    instances were gone with an old incarnation (a restart; no node declared)."""
    if rec.get("failed"):
        return f"{', '.join(rec['failed'])} failed"
    if rec.get("vanished_on"):
        return f"{', '.join(rec['vanished_on'])} restarted (its instances gone)"
    return "instances gone"


def move_line(rec: dict[str, Any]) -> str:
    """One move a node coordinated (its status' ``moves``), with who asked and how long."""
    what, app = rec.get("what", "move"), rec.get("app", "")
    where = rec.get("detail", "")
    head = f"{app}: {rec['vertex']} {where}" if rec.get("vertex") else f"{app}: {what} {where}"
    kind = f" ({what})" if rec.get("vertex") and what != "relocation" else ""
    took = rec.get("took_ms")
    line = f"{head}{kind}" + (f" in {took:.0f} ms" if isinstance(took, int | float) else "")
    line += f", asked by {rec.get('asked') or rec.get('by') or 'nobody said'}"
    return line + (f": failed: {rec['error']}" if rec.get("error") else "")


def status_text(nodes: dict[str, Any]) -> str:
    """Nodes with their traffic; per app, vertices (where, events, CPU) and edges."""
    out: list[str] = []
    table = Table("nodes")
    cols = (
        "node",
        "neighbours",
        "in B",
        "out B",
        "fwd B",
        "rejected",
        "battery",
        "W",
        "life",
        "measured",
    )
    table.caption = (
        "battery, W and life come from the power model unless 'measured' names them; "
        "radio: the interfaces' tx/rx bytes"
    )
    for col in cols:
        table.add_column(col, justify="left" if col in ("node", "neighbours") else "right")
    apps: dict[str, dict[str, Any]] = {}
    failed: set[str] = set()
    # out of some node's reach, declared failed by nobody: its instances presumed running
    unreachable: dict[str, list[str]] = {}  # node -> the nodes that cannot reach it
    rejoined: dict[str, int] = {}  # node -> latest incarnation it came back as
    decisions: list[str] = []
    moves: list[str] = []
    for nid in sorted(nodes):
        st = nodes[nid]
        failed.update(st.get("failed_nodes", []))
        for n in st.get("unreachable_nodes", []):
            unreachable.setdefault(n, []).append(nid)
        for r in st.get("rejoins", []):
            rejoined[r["node"]] = max(rejoined.get(r["node"], 0), int(r["incarnation"]))
        clock = st.get("clock")
        done = st.get("management", {}).get("done", [])[-3:]
        decisions += [f"{nid}: {_aged(d, clock)}" for d in done]
        moves += [
            f"{nid}: {rec['ago_s']:.1f} s ago, {move_line(rec)}" for rec in st.get("moves", [])[-5:]
        ]
        traffic = st.get("traffic", {})
        table.add_row(
            nid,
            ", ".join(st.get("neighbours", [])) or "-",
            str(traffic.get("bytes_in", 0)),
            str(traffic.get("bytes_out", 0)),
            str(traffic.get("bytes_forwarded", 0)),
            str(traffic.get("frames_rejected", 0)),
            *_energy_cells(st.get("monitor", {})),
        )
        for name, app in st.get("apps", {}).items():
            agg = apps.setdefault(
                name,
                {"vertices": {}, "edges": {}, "chains": app["chains"], "delay": {}, "notes": []},
            )
            agg["delay"].update(app.get("chain_delay_ms", {}))
            agg["parked"] = app.get("parked", {}) or agg.get("parked", {})
            for rec in app.get("recoveries", []):
                agg["notes"].append(
                    f"{nid} recovered from {recovered_from(rec)}: {rec['remap']} remap of "
                    f"{', '.join(rec['chains'])} "
                    + (
                        f"in {rec['took_ms']:.1f} ms"
                        if rec.get("ok")
                        else f"failed: {rec['error']}"
                        if rec.get("error")
                        else "(in progress)"
                    )
                    + (f"; re-sent: {', '.join(rec['retried'])}" if rec.get("retried") else "")
                )
            for v, vs in app["vertices"].items():
                agg["vertices"][v] = (nid, vs)
            for e, c in app["edges"].items():
                merged = agg["edges"].setdefault(e, {})
                for k, val in c.items():
                    if val or k not in merged:
                        merged[k] = val
    out.append(str(table))
    if failed:
        out.append(f"failed nodes: {', '.join(sorted(failed))}")
    if cut := {n: by for n, by in unreachable.items() if n not in failed}:
        held = ", ".join(f"{n} (from {', '.join(by)})" for n, by in sorted(cut.items()))
        out.append(
            "unreachable nodes (out of reach, not failed: instances presumed running, edges "
            f"buffering): {held}"
        )
    if rejoined:
        out.append(
            "rejoined (restarted or back from a partition, as a new incarnation): "
            + ", ".join(f"{n} ({inc})" for n, inc in sorted(rejoined.items()))
        )
    for line in decisions:
        out.append(f"rule: {line}")
    for line in moves:
        out.append(f"move: {line}")
    for name, app in apps.items():
        if app.get("chains"):
            out.append(
                f"app {name}: chains "
                + "  ".join(f"[{i}] {'-'.join(c)}" for i, c in enumerate(app["chains"]))
            )
        if app.get("delay"):
            out.append(
                f"app {name}: end-to-end delay "
                + "  ".join(f"{c} {ms:.2f} ms" for c, ms in sorted(app["delay"].items()))
            )
        for chain, why in sorted(app.get("parked", {}).items()):
            out.append(f"app {name}: chain {chain} parked: {why}")
        for note in app.get("notes", []):
            out.append(f"app {name}: {note}")
        vt = Table(f"app {name}: vertices")
        numbers = ("events", "cpu ms", "errors", "crashes")
        for col in ("vertex", "node", "kind", *numbers, "stats"):
            vt.add_column(col, justify="right" if col in numbers else "left")
        problems = []
        for v, (nid, vs) in app["vertices"].items():
            events = vs["emitted"] if vs["kind"] == "source" else vs["processed"]
            vt.add_row(
                v, nid, vs["kind"], str(events), f"{vs['cpu_s'] * 1e3:.1f}", str(vs["errors"]),
                str(vs.get("crashes", 0)), _stats_cell(vs.get("stats")),
            )  # fmt: skip
            if vs.get("last_error"):
                problems.append(f"  {v}: last error: {_clip(vs['last_error'], 160)}")
            if vs.get("last_crash"):
                problems.append(f"  {v}: last crash: {_clip(vs['last_crash'], 160)}")
        out.append(str(vt))
        out.extend(problems)
        et = Table(f"app {name}: edges")
        for col in ("edge", "sent", "delivered", "duplicates", "events/s"):
            et.add_column(col, justify="left" if col == "edge" else "right")
        for e, c in app["edges"].items():
            et.add_row(
                e,
                str(c.get("sent", 0)),
                str(c.get("delivered", 0)),
                str(c.get("duplicates", 0)),
                f"{c.get('events_per_s', 0.0):.1f}",
            )
        out.append(str(et))
    return "\n".join(out)


ERROR_ALARM = 5  # errors a vertex may add between two looks before the console flags it


def error_alarms(
    seen: dict[str, int], nodes: dict[str, Any], app: str, threshold: int = ERROR_ALARM
) -> list[str]:
    """The vertices of ``app`` whose error count grew by ``threshold`` or more since the last
    call (``seen`` keeps the counts between calls): one line each, with its last error, so a
    vertex failing on every event is not buried in a summary."""
    lines = []
    for nid in sorted(nodes):
        vertices = nodes[nid].get("apps", {}).get(app, {}).get("vertices", {})
        for v, vs in sorted(vertices.items()):
            errors = int(vs.get("errors", 0))
            grew = errors - seen.get(v, 0)
            seen[v] = errors
            if grew >= threshold:
                last = _clip(vs.get("last_error", ""), 120)
                lines.append(f"vertex {v} on {nid}: {grew} new errors ({errors} in all): {last}")
    return lines
