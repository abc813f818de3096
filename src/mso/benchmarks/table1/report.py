"""Table 1's report: the Markdown table of a result beside the paper's figures and the targets,
with the interruption, event and remap lines under it.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from mso.benchmarks.table1.phases import BEAT_RATE, PERIOD_MS

OPERATIONS = (
    "mapping",
    "upstream_relocation",
    "downstream_relocation",
    "chain_remapping",
    "global_remapping_part",
    "global_remapping_whole",
)
LABELS = {
    "mapping": "Mapping",
    "upstream_relocation": "Upstream relocation",
    "downstream_relocation": "Downstream relocation",
    "chain_remapping": "Chain remapping",
    "global_remapping_part": "Global remapping (part)",
    "global_remapping_whole": "Global remapping (whole)",
}
PAPER_MS = {  # Table 1: mean, sigma (350 MHz Xeons, gSOAP control plane, 100 Mbit/s Ethernet)
    "mapping": (1390.0, 77.7),
    "upstream_relocation": (94.3, 6.4),
    "downstream_relocation": (56.3, 3.3),
    "chain_remapping": (2759.1, 217.0),
    "global_remapping_part": (2943.1, 265.8),
    "global_remapping_whole": (3327.2, 335.2),
}
TARGET_P50_MS = {
    "upstream_relocation": 2.0,
    "downstream_relocation": 2.0,
    "chain_remapping": 10.0,
    "global_remapping_part": 20.0,
    "global_remapping_whole": 30.0,
}
TARGET_GAP_MS = 5.0
TARGET_GAP_RATIO = 100.0


def _f(x: float | None, digits: int = 1) -> str:
    return "-" if x is None else f"{x:,.{digits}f}"


def render(result: dict[str, Any]) -> str:
    ops = result["operations"]
    lines = [
        "| Operation (convoy, 4-node line) | mean ms | σ ms | p50 ms | p99 ms | n "
        "| paper mean ms | paper σ ms | ratio mean/paper | target p50 |",
        "|---|---:|---:|---:|---:|---:|---:|---:|---:|---|",
    ]
    for op in OPERATIONS:
        s = ops[op]
        pm, ps = PAPER_MS[op]
        ratio = "-" if s["mean_ms"] is None else f"{s['mean_ms'] / pm:.4f}"
        tgt = TARGET_P50_MS.get(op)
        verdict = "-"
        if tgt is not None and s["p50_ms"] is not None:
            verdict = f"<= {tgt:g} ms: {'met' if s['p50_ms'] <= tgt else 'MISSED'}"
        lines.append(
            f"| {LABELS[op]} | {_f(s['mean_ms'], 2)} | {_f(s['std_ms'], 2)} "
            f"| {_f(s['p50_ms'], 2)} | {_f(s['p99_ms'], 2)} | {s['n']} | {pm:,.1f} | {ps} "
            f"| {ratio} | {verdict} |"
        )
    un = result.get("unshaped")
    ns = result.get("netns")
    titles = {
        "unshaped": "(mso's own cost, no link emulation)",
        "netns": "on the netns backend (a namespace per node, babeld routes, the kernel "
        "forwards; tbf 100 Mbit/s, no delay: no netem here)",
    }
    for key, other in (("unshaped", un), ("netns", ns)):
        if not other:
            continue
        lines += ["", f"Same runs, {other['scenario']} {titles[key]}:", ""]
        lines += [
            "| Operation | mean ms | σ ms | p50 ms | p99 ms | n | ratio mean/paper |",
            "|---|---:|---:|---:|---:|---:|---:|",
        ]
        for op in OPERATIONS:
            s = other["operations"][op]
            ratio = "-" if s["mean_ms"] is None else f"{s['mean_ms'] / PAPER_MS[op][0]:.4f}"
            lines.append(
                f"| {LABELS[op]} | {_f(s['mean_ms'], 2)} | {_f(s['std_ms'], 2)} "
                f"| {_f(s['p50_ms'], 2)} | {_f(s['p99_ms'], 2)} | {s['n']} | {ratio} |"
            )
    lines += [
        "",
        f"Interruption of a {BEAT_RATE:g} events/s flow at its sink (largest inter-arrival gap "
        f"minus the nominal {PERIOD_MS:g} ms):",
        "",
        "| Interruption | mean ms | σ ms | p50 ms | p99 ms | max ms | n |",
        "|---|---:|---:|---:|---:|---:|---:|",
    ]
    variants = (
        [("", result)] + ([(" (unshaped)", un)] if un else []) + ([(" (netns)", ns)] if ns else [])
    )
    for suffix, r in variants:
        it = r["interruption_ms"]
        for key, label in (
            ("relocation", "relocation of the relay"),
            ("relocation_upstream", "- upstream moves (onto its producer's node)"),
            ("relocation_downstream", "- downstream moves"),
            ("relocation_idle_baseline", "no operation (same-length window before it)"),
            ("stop_and_redeploy", "stop and redeploy"),
            ("stop_and_redeploy_lower_bound", "stop and redeploy, from the stop request"),
        ):
            s = it[key]
            lines.append(
                f"| {label}{suffix} | {_f(s['mean_ms'], 2)} | {_f(s['std_ms'], 2)} "
                f"| {_f(s['p50_ms'], 2)} | {_f(s['p99_ms'], 2)} | {_f(s['max_ms'], 2)} "
                f"| {s['n']} |"
            )
    lines.append("")
    for suffix, r in variants:
        it = r["interruption_ms"]
        rel, sr = it["relocation"], it["stop_and_redeploy"]
        if rel["p50_ms"] is not None and sr["p50_ms"] is not None:
            ok_gap = rel["p50_ms"] <= TARGET_GAP_MS
            ok_ratio = (it["ratio_p50"] or 0) >= TARGET_GAP_RATIO
            lines.append(
                f"- interruption{suffix}: relocation p50 {rel['p50_ms']:.2f} ms (target <= "
                f"{TARGET_GAP_MS:g} ms: {'met' if ok_gap else 'MISSED'}); stop-and-redeploy / "
                f"relocation = {it['ratio_p50']:.0f}x at p50, {it['ratio_mean']:.0f}x at the mean "
                f"(target >= {TARGET_GAP_RATIO:g}x: {'met' if ok_ratio else 'MISSED'})"
            )
        st = it["relocation_stalls"]
        lines.append(
            f"- interruption{suffix}: relocations that stalled the flow for more than "
            f"{st['threshold_ms']:g} ms: {st['upstream']} upstream, {st['downstream']} downstream "
            f"(of {it['relocation_upstream']['n']} and {it['relocation_downstream']['n']})"
        )
        ev = r["events"]
        if ev:
            lines.append(
                f"- events{suffix} (measurement app, through every operation but "
                f"stop-and-redeploy): emitted {ev['emitted']}, delivered {ev['delivered']}, lost "
                f"{ev['lost']}, duplicated {ev['duplicated']}, reordered {ev['reordered']}, relay "
                f"state errors {ev['relay_state_errors']}"
            )
        es = r["events_stop_and_redeploy"]
        lines.append(
            f"- events{suffix} over {es['instances_stopped']} stop-and-redeploys: duplicated "
            f"{es['duplicated']}, reordered {es['reordered']}, relay state errors "
            f"{es['relay_state_errors']} (in-flight events of a stopped instance are discarded "
            "by design)"
        )
        for name in ("chain_remapping", "global_remapping_part", "global_remapping_whole"):
            s = r["operations"][name]
            lines.append(
                f"- {LABELS[name]}{suffix}: {s['runs_moved']}/{s['n']} runs moved vertices "
                f"(mean {s['vertices_moved_mean']:.2f}), {s['runs_restored']} restored the "
                "placement before the perturbation"
            )
        lines.append(f"- remaps{suffix} coordinated by {r['remap_via']}")
        for note in r["notes"]:
            lines.append(f"- note{suffix}: {note}")
        for fail in r["failures"]:
            lines.append(f"- FAILURE{suffix}: {fail}")
    lines.append(
        "- paper: 350 MHz Xeons, gSOAP control plane, 100 Mbit/s Ethernet; ratio = ours / paper"
    )
    return "\n".join(lines) + "\n"


def default_json(quick: bool) -> Path:
    """bench/results/table1[.quick].json in a checkout, else the working directory."""
    root = Path(__file__).resolve().parents[4]
    results = root / "bench" / "results"
    name = "table1.quick.json" if quick else "table1.json"
    return results / name if results.parent.is_dir() else Path(name)
