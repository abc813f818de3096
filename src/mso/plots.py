"""PNG plots of simulation reports (``mso simulate --plot``) and benchmark results
(``bench/plots.py``), drawn with matplotlib (the ``plots`` extra; ``make`` installs it).

Each function takes the JSON a command or benchmark already writes, so a plot can be redrawn
from a kept result without running anything again. matplotlib is imported only here, and only
when a plot is asked for, with the non-interactive Agg backend (no display needed).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from mso.errors import MsoError


def _pyplot() -> Any:
    try:
        import matplotlib
    except ImportError:
        raise MsoError(
            "plots need matplotlib: pip install 'mso[plots]' (make installs it)"
        ) from None
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _save(fig: Any, out: Path) -> Path:
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.tight_layout()
    fig.savefig(out, dpi=110)
    fig.clf()
    return out


def simulation(report: dict[str, Any], out: Path) -> Path:
    """A simulation: what moved when (and failures, rejoins), and the energy each node spent."""
    plt = _pyplot()
    fig, (top, bottom) = plt.subplots(2, 1, figsize=(9, 6.5), height_ratios=[3, 2])
    moves = report["reconfigurations"]["moves"]
    vertices = sorted({m["vertex"] for m in moves})
    for m in moves:
        y = vertices.index(m["vertex"])
        top.scatter(m["at"], y, color="#0072B2", zorder=3)
        top.annotate(f"{m['from']}→{m['to']}", (m["at"], y), textcoords="offset points",
                     xytext=(4, 4), fontsize=8)  # fmt: skip
    for f in report.get("failures", []):
        top.axvline(f["at"], color="#D55E00", linestyle="--", linewidth=1)
        top.text(f["at"], len(vertices) - 0.5, f" {f['node']} failed", color="#D55E00", fontsize=8)
    for r in report["reconfigurations"].get("rejoins", []):
        top.axvline(r["at"], color="#009E73", linestyle=":", linewidth=1)
        top.text(r["at"], -0.5, f" {r['node']} rejoined", color="#009E73", fontsize=8)
    top.set_yticks(range(len(vertices)), vertices)
    top.set_ylim(-1, max(len(vertices), 1))
    top.set_xlim(0, report["duration_s"])
    top.set_xlabel("virtual time (s)")
    top.set_title(
        f"{report['app']} on {report['scenario']}: {len(moves)} vertex moves, "
        f"{len(report.get('failures', []))} failures (seed {report['seed']})"
    )
    top.grid(axis="x", alpha=0.3)
    nodes = list(report["energy"])
    energy = [report["energy"][n]["energy_j"] for n in nodes]
    bars = bottom.bar(nodes, energy, color="#56B4E9")
    for bar, n in zip(bars, nodes, strict=True):
        frac = report["energy"][n]["battery_fraction"]
        label = "wall" if frac is None else f"{frac * 100:.1f}% left"
        bottom.annotate(label, (bar.get_x() + bar.get_width() / 2, bar.get_height()),
                        ha="center", va="bottom", fontsize=8)  # fmt: skip
    bottom.set_ylabel("energy spent (J)")
    bottom.set_title("energy per node")
    return _save(fig, out)


def _paired_bars(
    before: dict[str, float], after: dict[str, float], labels: tuple[str, str], ylabel: str,
    title: str, out: Path,
) -> Path:  # fmt: skip
    """Two bars per node: a figure without and with something."""
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(7, 3.8))
    nodes = list(before)
    xs = range(len(nodes))
    ax.bar([x - 0.2 for x in xs], [before[n] for n in nodes], 0.4, label=labels[0])
    ax.bar([x + 0.2 for x in xs], [after.get(n, 0.0) for n in nodes], 0.4, label=labels[1])
    ax.set_xticks(list(xs), nodes)
    ax.set_ylabel(ylabel)
    ax.set_title(title)
    ax.legend()
    return _save(fig, out)


def dashboard(result: dict[str, Any], out: Path) -> Path:
    """bench/dashboard.py: each node's CPU with and without the dashboard at 1 update/s."""
    cpu = result["cost"]["node_cpu_pct"]
    load = result["machine"]["load_average"][0]
    return _paired_bars(
        {n: r["without"] for n, r in cpu.items()}, {n: r["with"] for n, r in cpu.items()},
        ("without", "with dashboard"), "CPU (% of one core)",
        f"node CPU, dashboard at 1 update/s (load average {load:.1f})", out,
    )  # fmt: skip


def cli_startup(result: dict[str, Any], out: Path) -> Path:
    """bench/cli_startup.py: start-to-answer time of each command, with the 150 ms target."""
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(7, 3.5))
    rows = result["commands"]
    names = list(rows)
    ax.barh(names, [rows[n]["p50_ms"] for n in names], color="#0072B2", label="wall p50")
    ax.scatter(
        [rows[n]["p90_ms"] for n in names], names, color="#D55E00", zorder=3, label="wall p90"
    )
    if all("cpu_p50_ms" in rows[n] for n in names):
        ax.scatter([rows[n]["cpu_p50_ms"] for n in names], names, color="#009E73", marker="D",
                   zorder=3, label="CPU time p50")  # fmt: skip
    ax.axvline(result["target_status_ms"], color="#000000", linestyle="--", label="target")
    ax.set_xlabel("ms, start to answer")
    load = result["machine"]["load_average"][0]
    ax.set_title(f"CLI start-up (load average {load:.1f})")
    ax.invert_yaxis()
    ax.legend()
    return _save(fig, out)


def rates(result: dict[str, Any], out: Path) -> Path:
    """bench/rates.py: the rate a source got against the rate it was asked for."""
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(6, 3.8))
    rows = result["rows"]
    asked = [r["asked"] for r in rows]
    ax.loglog(asked, asked, color="#7F7F7F", linestyle="--", label="asked")
    ax.loglog(asked, [r["got"] for r in rows], marker="o", color="#0072B2", label="got")
    for r in rows:
        ax.annotate(f"{r['error_pct']:+.2f}%", (r["asked"], r["got"]), textcoords="offset points",
                    xytext=(5, -12), fontsize=8)  # fmt: skip
    ax.set_xlabel("asked (events/s)")
    ax.set_ylabel("got at the sink (events/s)")
    ax.set_title("rated sources")
    ax.legend()
    return _save(fig, out)


def scale(result: dict[str, Any], out: Path) -> Path:
    """bench/scale.py: start-up CPU and CPU per simulated second against N, per topology."""
    plt = _pyplot()
    fig, (left, right) = plt.subplots(1, 2, figsize=(10, 4))
    by_topology: dict[str, list[dict[str, Any]]] = {}
    for r in result["sizes"]:
        if "error" not in r:
            by_topology.setdefault(r["topology"], []).append(r)
    for topology, rs in by_topology.items():
        ns = [r["nodes"] for r in rs]
        left.plot(ns, [r["startup_cpu_s"] for r in rs], marker="o", label=topology)
        right.plot(ns, [r["cpu_ms_per_node_per_sim_s"] for r in rs], marker="o", label=topology)
    left.set(xscale="log", yscale="log", xlabel="nodes", ylabel="start-up CPU (s)",
             title="start-up: build, deploy N/20 apps")  # fmt: skip
    right.axhline(1.0, color="grey", linestyle="--", linewidth=1)
    right.set(xscale="log", xlabel="nodes", ylabel="CPU ms per node per simulated s",
              title="steady state (target: 1 ms, dashed)")  # fmt: skip
    for ax in (left, right):
        if ax.get_legend_handles_labels()[0]:
            ax.legend(fontsize=8)
    return _save(fig, out)


BENCHMARKS = {
    "dashboard": dashboard,
    "cli_startup": cli_startup,
    "rates": rates,
    "scale": scale,
}  # the energy study (mso bench lifetime) draws its own plots


def _finish(fig: Any, ax: Any, out: Path, **labels: str) -> Path:
    """Label the axes, add a legend if anything is labelled, save."""
    ax.set(**labels)
    if ax.get_legend_handles_labels()[0]:  # (an empty legend only warns)
        ax.legend(fontsize=8)
    return _save(fig, out)


def sweep(rows: list[dict[str, Any]], out_dir: Path) -> list[Path]:
    """A study's four figures: energy spent over time and reconfigurations over time (one
    line per scenario and policy, the mean over seeds), the CDF of chain delays, and the
    control messages per reconfiguration against the number of nodes."""
    plt = _pyplot()
    groups: dict[str, list[dict[str, Any]]] = {}
    for r in rows:
        groups.setdefault(f"{r['scenario']} / {r['policy']}", []).append(r)
    paths = []
    fig, ax = plt.subplots(figsize=(8, 4.5))
    for label, rs in groups.items():
        ts = min((r["series"]["t"] for r in rs), key=len)
        mean = [sum(r["series"]["energy_j"][i] for r in rs) / len(rs) for i in range(len(ts))]
        ax.plot(ts, mean, label=label)
    paths.append(
        _finish(
            fig,
            ax,
            out_dir / "energy.png",
            xlabel="virtual time (s)",
            ylabel="energy spent, all nodes (J)",
            title="energy over time (mean over seeds)",
        )
    )
    fig, ax = plt.subplots(figsize=(8, 4.5))
    for label, rs in groups.items():
        times = sorted(t for r in rs for t in r["series"]["reconfigurations_at"])
        ax.step([0.0, *times], [k / len(rs) for k in range(len(times) + 1)], where="post",
                label=label)  # fmt: skip
    paths.append(
        _finish(
            fig,
            ax,
            out_dir / "reconfigurations.png",
            xlabel="virtual time (s)",
            ylabel="reconfigurations (cumulative, per run)",
            title="reconfigurations over time (mean over seeds)",
        )
    )
    fig, ax = plt.subplots(figsize=(8, 4.5))
    for label, rs in groups.items():
        delays = sorted(d for r in rs for d in r["series"]["delay_ms"])
        if delays:
            ax.step(delays, [(i + 1) / len(delays) for i in range(len(delays))], where="post",
                    label=label)  # fmt: skip
    paths.append(
        _finish(
            fig,
            ax,
            out_dir / "delay_cdf.png",
            xlabel="chain delay, as each chain's tail measures it (ms)",
            ylabel="fraction",
            title="delay CDF (samples once a simulated second)",
        )
    )
    fig, ax = plt.subplots(figsize=(8, 4.5))
    by_policy: dict[str, dict[int, list[float]]] = {}
    for r in rows:
        if r["control_per_reconfiguration"] is not None:
            per_n = by_policy.setdefault(r["policy"], {})
            per_n.setdefault(r["nodes"], []).append(r["control_per_reconfiguration"])
    for policy, per_n in sorted(by_policy.items()):
        ns = sorted(per_n)
        ax.plot(ns, [sum(per_n[n]) / len(per_n[n]) for n in ns], marker="o", label=policy)
    paths.append(
        _finish(
            fig,
            ax,
            out_dir / "control_vs_n.png",
            xlabel="nodes",
            ylabel="control messages per reconfiguration",
            title="control messages per reconfiguration against N (mean over runs)",
        )
    )
    return paths
