"""Rich renderings that more than one command prints: a plan, a simulation's report, a sink's
progress line."""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from mso.statusview import recovered_from

if TYPE_CHECKING:
    from rich.console import Console

    from mso.model.app import App
    from mso.model.capabilities import Needs
    from mso.planning.placement import Plan
    from mso.scenario import Scenario


def constraint_json(n: Needs) -> dict[str, Any]:
    out: dict[str, Any] = {"requires": dict(n.requires)}
    if n.near is not None:
        out["near"] = n.near
    if n.apart_from is not None:
        out["apart_from"] = n.apart_from
    return out


def constraint_text(n: Needs) -> str:
    from mso.model.capabilities import describe

    parts = [f"requires {describe(n.requires)}" if n.requires else "any node"]
    if n.near is not None:
        parts.append(f"near {n.near}")
    if n.apart_from is not None:
        parts.append(f"apart from {n.apart_from}")
    return ", ".join(parts)


def render_plan(console: Console, app: App, scenario: Scenario, result: Plan) -> None:
    """Chains with their placement, then the load each node carries."""
    from rich.table import Table

    net = scenario.network
    table = Table(title=f"{app.name} on {scenario.name}: chains in placement order")
    table.add_column("step", justify="right")
    table.add_column("chain, head first: vertex@node")
    table.add_column("probed route")
    for step, ci in enumerate(result.order, start=1):
        c = result.chains[ci]
        placed = " → ".join(f"{v}@{result.placement[v]}" for v in c.vertices)
        table.add_row(str(step), placed, "-".join(result.routes.get(ci, [])))
    console.print(table)
    for v, capable in result.capable.items():
        n = next(x for x in app.needs() if x.vertex == v)
        console.print(
            f"{v}: placed by capability on {result.placement[v]} ({constraint_text(n)}; "
            f"capable, best first: {', '.join(capable)})"
        )
    nodes = Table(title="nodes")
    nodes.add_column("node")
    nodes.add_column("cpu", justify="right")
    nodes.add_column("load (ms/event)", justify="right")
    nodes.add_column("vertices")
    for nid, spec in net.nodes.items():
        here = [v for v, n in result.placement.items() if n == nid]
        load = sum(app.vertices[v].cost for v in here) / spec.cpu
        nodes.add_row(nid, f"{spec.cpu:g}", f"{load:.2f}", ", ".join(here) or "-")
    console.print(nodes)


def sink_line(nodes: dict[str, Any], app: str) -> str:
    """The sinks' progress, one line; or why there is none (the app stopped, undeployed)."""
    parts = []
    held = False
    for st in nodes.values():
        a = st.get("apps", {}).get(app)
        if a is None:
            continue
        held = True
        for v, s in a["vertices"].items():
            if s["kind"] == "sink":
                parts.append(f"{v}@{st['node']}: {s['processed']} events")
    if not held:
        running = sorted({a for st in nodes.values() for a in st.get("apps", {})})
        return f"{app} runs nowhere (undeployed?); running: {', '.join(running) or 'none'}"
    return ", ".join(parts) or "no sink yet"


def render_simulation(console: Console, r: dict[str, Any]) -> None:
    """The report of ``mso simulate``: events, reconfigurations, failures, energy."""
    from rich.table import Table

    dep = r["deploy"]
    console.print(
        f"simulated {r['app']} on {r['scenario']} for {r['duration_s']:g} s (seed {r['seed']}): "
        + (
            f"deployed in {dep['elapsed_ms']:.1f} ms"
            if dep["ok"]
            else f"deploy failed: {dep['error']}"
        )
    )
    for t, what in r["timeline"]:
        console.print(f"  t={t:7.3f}s  {what}")
    ev = r["events"]
    et = Table(title="events")
    for col in ("vertex", "kind", "events"):
        et.add_column(col, justify="right" if col == "events" else "left")
    for v, n in ev["emitted"].items():
        et.add_row(v, "emitted", str(n))
    for v, n in ev["delivered"].items():
        et.add_row(v, "delivered", str(n))
    console.print(et)
    if ev.get("skipped"):
        skips = ", ".join(f"{v} {n}" for v, n in ev["skipped"].items())
        console.print(
            f"sequence numbers a restarted source skipped (never used, not counted as "
            f"emitted): {skips}"
        )
    console.print(
        f"given up by edge bounds and QoS: {ev['given_up']}, "
        f"frames lost on lossy links (resent): {ev['frames_lost_on_links']}"
    )
    rc = r["reconfigurations"]
    console.print(
        f"reconfigurations: {len(rc['moves'])} vertex moves, {len(rc['recoveries'])} recoveries, "
        f"{len(rc['rejoins'])} rejoins, {len(rc['management'])} rule actions"
    )
    for mv in rc["moves"]:
        console.print(f"  t={mv['at']:7.3f}s  {mv['vertex']}: {mv['from']} -> {mv['to']}")
    for rec in rc["recoveries"]:
        state = "ok" if rec.get("ok") else (rec.get("error") or "in progress")
        console.print(
            f"  recovery from {recovered_from(rec)}: {rec['remap']} remap of "
            f"{', '.join(rec['chains'])}: {state}"
        )
    for rj in rc["rejoins"]:
        console.print(
            f"  t={rj['at']:7.3f}s  {rj['node']} rejoined as incarnation {rj['incarnation']}"
        )
    for d in rc["management"]:
        console.print(f"  rule: {d}")
    ft = Table(title="failures detected")
    for col in ("node", "detector", "at s"):
        ft.add_column(col, justify="right" if col == "at s" else "left")
    for f in r["failures"]:
        ft.add_row(f["node"], f["detector"], f"{f['at']:.3f}")
    if r["failures"]:
        console.print(ft)
    nt = Table(title="energy per node")
    for col in (
        "node",
        "alive",
        "incarnation",
        "energy J",
        "W",
        "battery",
        "bytes out",
        "bytes in",
    ):
        nt.add_column(col, justify="left" if col in ("node", "alive") else "right")
    for n, e in r["energy"].items():
        frac = e["battery_fraction"]
        nt.add_row(
            n, "yes" if e["alive"] else "no", str(e["incarnation"]), f"{e['energy_j']:.2f}",
            f"{e['drain_w']:.2f}",
            "empty" if e.get("battery_empty") else "wall" if frac is None else f"{frac:.1%}",
            str(e["bytes_sent"]), str(e["bytes_received"]),
        )  # fmt: skip
    console.print(nt)
    console.print(
        "final placement: " + ", ".join(f"{v}@{n}" for v, n in r["placement"].items()) or "-"
    )
