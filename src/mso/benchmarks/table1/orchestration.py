"""Table 1's orchestration: start the emulated line (user-space or netns), deploy the convoy and
the measurement app, run every phase in turn within a time budget, and gather the figures.
"""

from __future__ import annotations

import asyncio
import statistics
import tempfile
import time
from pathlib import Path
from typing import Any

from mso.benchmarks.common import Progress, percentile, provenance
from mso.benchmarks.table1.phases import (
    APP_FILE,
    CONVOY,
    PERIOD_MS,
    SCENARIO_FILE,
    Bench,
    account,
    beats_document,
    interior,
    phase_interruption,
    phase_mapping,
    phase_relocation,
    phase_remap,
    phase_stop_redeploy,
    pick_remap_via,
)
from mso.benchmarks.table1.report import PAPER_MS, TARGET_GAP_MS, TARGET_GAP_RATIO, TARGET_P50_MS
from mso.emu.controller import Emulator
from mso.errors import MsoError
from mso.model.appfile import with_planner
from mso.model.network import LinkSpec
from mso.scenario import Scenario, load_scenario

# the navigation pipeline's three chains, by (head, tail): localization also feeds the target
# map (its poses place camera frames in the map), a chain of its own left out of "part"
NAVIGATION = (("laser", "localization"), ("odometry", "localization"), ("localization", "storage"))
STALL_MS = 50.0  # an interruption longer than this is reported as a stall
DEADLINE_S = 110.0  # per scenario: no operation starts after this
QUICK_DEADLINE_S = 45.0


def summary(values: list[float]) -> dict[str, Any]:
    if not values:
        return {
            "mean_ms": None,
            "std_ms": None,
            "p50_ms": None,
            "p99_ms": None,
            "min_ms": None,
            "max_ms": None,
            "n": 0,
        }
    return {
        "mean_ms": statistics.fmean(values),
        "std_ms": statistics.stdev(values) if len(values) > 1 else 0.0,
        "p50_ms": percentile(values, 50),
        "p99_ms": percentile(values, 99),
        "min_ms": min(values),
        "max_ms": max(values),
        "n": len(values),
    }


def unshaped(scenario: Scenario) -> Scenario:
    """The same line with neither bandwidth nor delay on its links."""
    net = scenario.network
    for (a, b), _link in list(net.links.items()):
        net.remove_link(a, b)
        net.add_link(LinkSpec(a, b))
    scenario.name += " (unshaped)"
    return scenario


def node_log_errors(emu: Emulator) -> dict[str, list[str]]:
    """The last error lines of each node's log (the logs go away with the emulator)."""
    out: dict[str, list[str]] = {}
    for name, node in emu.nodes.items():
        if node.log is None or not node.log.exists():
            continue
        lines = node.log.read_text(errors="replace").splitlines()
        hits = [ln for ln in lines if "Error" in ln or "ERROR" in ln or "Traceback" in ln]
        if hits:
            out[name] = hits[-6:]
    return out


def _first_chain(chains: list[list[str]], head: str, tail: str | None = None) -> int:
    for i, c in enumerate(chains):
        if c[0] == head and (tail is None or c[-1] == tail):
            return i
    raise MsoError(f"no chain from {head!r} in {chains}")


async def measure(
    scenario: Scenario,
    runs: int,
    budget_s: float,
    backend: str = "user",
    progress: Progress | None = None,
) -> dict[str, Any]:
    """Every measurement on one emulated line (``backend`` netns: namespaces and babeld)."""
    step = progress or Progress("table1", quiet=True)
    logs = tempfile.TemporaryDirectory(prefix="mso-bench-table1-")
    pause = Path(logs.name) / "beats.pause"
    kind: type[Emulator] = Emulator
    if backend == "netns":
        from mso.emu.netns.emulator import NetnsEmulator

        kind = NetnsEmulator
    emu = kind(scenario, log_dir=Path(logs.name), manage=False)  # operations alone
    # the paper's operations on the paper's placement (planner: paper): its relocations move a
    # vertex along a chain spread over the line, which the default bytes split keeps on fewer
    # nodes (the convoy's relocations then found nothing to time)
    convoy = with_planner(APP_FILE.read_text(encoding="utf-8"), "paper", file=str(APP_FILE))
    b = Bench(emu, runs, time.monotonic() + budget_s, pause, convoy)
    out: dict[str, Any] = {"scenario": scenario.name}
    t_start = time.monotonic()
    mapping: list[float] = []
    mapping_wall: list[float] = []
    reloc: dict[str, Any] = {"upstream": [], "downstream": [], "refused": []}
    no_remap: dict[str, Any] = {"samples": [], "moved": [], "perturb": [], "restored": 0}
    chain_r = part_r = whole_r = no_remap
    inter: dict[str, Any] = {
        "gaps": [],
        "idle": [],
        "elapsed": [],
        "by_direction": {"upstream": [], "downstream": []},
    }
    events: dict[str, Any] = {}
    sr: dict[str, Any] = {"gaps": [], "lower": [], "redeploy_ms": [], "instances": []}
    final: dict[str, Any] = {}
    try:
        step(f"starting {len(scenario.network.nodes)} node processes ({backend} backend)")
        await emu.start()
        step("cold deployment of the convoy")
        # cold deployment (imports the vertex code on every node; not in the statistics), and
        # the node that coordinates remaps
        reply = await b.deploy(b.convoy_doc, str(APP_FILE), check=True)
        out["cold_mapping_ms"] = reply.elapsed_ms
        _, chains = await b.app_view(CONVOY)
        await pick_remap_via(b, _first_chain(chains, "laser"))
        await emu.undeploy(CONVOY, "N1")
        if not await b.wait_gone(CONVOY):
            raise MsoError("the convoy did not go away")
        # the measurement app runs from here to the end
        reply = await b.deploy(beats_document(str(pause)), "beats.yaml", check=True)
        out["beats_placement"] = reply.placement
        await asyncio.sleep(0.5)

        step(f"mapping, {runs} runs")
        mapping, mapping_wall = await phase_mapping(b)

        # stays, flowing at the paper's rates
        await b.deploy(b.convoy_doc, str(APP_FILE), check=True)
        await asyncio.sleep(1.0)
        placed, chains = await b.app_view(CONVOY)
        out["convoy_placement"] = dict(placed)
        out["convoy_chains"] = chains
        laser = _first_chain(chains, "laser")
        nav = [_first_chain(chains, h, t) for h, t in NAVIGATION]
        step(f"upstream and downstream relocations, {runs} runs each")
        reloc = await phase_relocation(b, placed, chains[laser])
        chain_movers = interior(chains[laser])
        nav_movers = [v for c in nav for v in interior(chains[c])]
        all_movers = [v for c in chains for v in interior(c)]
        step(f"chain remaps, {runs} runs")
        chain_r = await phase_remap(b, "chain_remapping", placed, [laser], False, chain_movers)
        step(f"global remaps of part of the app, {runs} runs")
        part_r = await phase_remap(b, "global_remapping_part", placed, nav, False, nav_movers)
        step(f"global remaps of the whole app, {runs} runs")
        whole_r = await phase_remap(b, "global_remapping_whole", placed, [], True, all_movers)

        step("interruption of the flow by a relocation")
        inter = await phase_interruption(b)
        events = await account(b, "relocations")
        await asyncio.sleep(0.2)
        step("interruption by stop and redeploy, for comparison")
        sr = await phase_stop_redeploy(b)
        final = await account(b, "last redeployed instance")

        conv = (await b.node_status("N1"))["apps"][CONVOY]["edges"]
        out["convoy_source_rates"] = {
            e: round(d["events_per_s"], 2) for e, d in conv.items() if e.split("->")[0] in
            ("laser", "odometry", "visible_camera", "infrared_camera")
        }  # fmt: skip
    except (MsoError, TimeoutError, KeyError) as exc:  # a node unreachable, a refused deployment
        b.failures.append(f"aborted: {type(exc).__name__}: {exc}")
        step(f"aborted: {type(exc).__name__}: {exc}")
    finally:
        step("stopping the node processes")
        await emu.stop()
        out["node_log_errors"] = node_log_errors(emu)
        logs.cleanup()

    ops = {
        "mapping": mapping,
        "upstream_relocation": reloc["upstream"],
        "downstream_relocation": reloc["downstream"],
        "chain_remapping": chain_r["samples"],
        "global_remapping_part": part_r["samples"],
        "global_remapping_whole": whole_r["samples"],
    }
    out["operations"] = {k: summary(v) for k, v in ops.items()}
    for name, r in (
        ("chain_remapping", chain_r),
        ("global_remapping_part", part_r),
        ("global_remapping_whole", whole_r),
    ):
        out["operations"][name] |= {
            "runs_moved": sum(1 for k in r["moved"] if k),
            "vertices_moved_mean": statistics.fmean(r["moved"]) if r["moved"] else 0.0,
            "runs_restored": r["restored"],
        }
    out["operations"]["mapping"]["wall"] = summary(mapping_wall)
    rel = summary(inter["gaps"])
    sr_s = summary(sr["gaps"])
    out["interruption_ms"] = {
        "relocation": rel,
        "stop_and_redeploy": sr_s,
        "relocation_idle_baseline": summary(inter["idle"]),
        "stop_and_redeploy_lower_bound": summary(sr["lower"]),
        "relocation_upstream": summary(inter["by_direction"]["upstream"]),
        "relocation_downstream": summary(inter["by_direction"]["downstream"]),
        "relocation_stalls": {
            "threshold_ms": STALL_MS,
            "upstream": sum(1 for g in inter["by_direction"]["upstream"] if g > STALL_MS),
            "downstream": sum(1 for g in inter["by_direction"]["downstream"] if g > STALL_MS),
        },
        "ratio_mean": _ratio(sr_s["mean_ms"], rel["mean_ms"]),
        "ratio_p50": _ratio(sr_s["p50_ms"], rel["p50_ms"]),
        "nominal_period_ms": PERIOD_MS,
    }
    out["events"] = events
    instances = sr["instances"]
    out["events_stop_and_redeploy"] = {
        "instances_stopped": len(instances),
        "duplicated": sum(x["repeats"] for x in instances),
        "reordered": sum(x["out_of_order"] for x in instances),
        "relay_state_errors": sum(x["relay_state_errors"] for x in instances),
        "last_instance": final,
        "note": "events in flight when an instance is stopped are discarded by design",
    }
    out["extra"] = {
        "targeted_relocation_ms": summary(
            chain_r["perturb"] + part_r["perturb"] + whole_r["perturb"]
        ),
        "relay_relocation_ms": summary(inter["elapsed"]),
        "beats_redeploy_ms": summary(sr["redeploy_ms"]),
        "refused_relocations": reloc["refused"],
        "samples_ms": ops,
    }
    out["remap_via"] = b.remap_via
    out["notes"] = b.notes
    out["failures"] = b.failures
    out["seconds"] = time.monotonic() - t_start
    return out


def _ratio(num: float | None, den: float | None) -> float | None:
    if num is None or den is None:
        return None
    return num / max(den, 0.01)


async def run(
    runs: int = 30,
    quick: bool = False,
    variants: bool = True,
    netns: bool = False,
    progress: Progress | None = None,
) -> dict[str, Any]:
    """Every Table 1 operation ``runs`` times (``quick``: 5, the specified line only);
    ``netns``: the same runs again on the netns backend, in the same run."""
    if quick:
        runs = min(runs, 5)
    t0 = time.monotonic()
    budget = QUICK_DEADLINE_S if quick else DEADLINE_S
    main_result = await measure(load_scenario(SCENARIO_FILE), runs, budget, progress=progress)
    result: dict[str, Any] = {
        "benchmark": "table1",
        "operations": main_result.pop("operations"),
        "interruption_ms": main_result.pop("interruption_ms"),
        "events": main_result.pop("events"),
    }
    result |= main_result
    if variants and not quick:
        if progress:
            progress("the same on unshaped links")
        result["unshaped"] = await measure(
            unshaped(load_scenario(SCENARIO_FILE)), runs, budget, progress=progress
        )
    if netns:
        from mso.emu.netns.emulator import check_available

        check_available()
        result["netns"] = await measure(
            load_scenario(SCENARIO_FILE), runs, budget, "netns", progress=progress
        )
    result["paper_ms"] = {k: {"mean_ms": v[0], "std_ms": v[1]} for k, v in PAPER_MS.items()}
    result["ratio_to_paper"] = {
        k: (None if s["mean_ms"] is None else s["mean_ms"] / PAPER_MS[k][0])
        for k, s in result["operations"].items()
    }
    result["targets"] = {
        "p50_ms": TARGET_P50_MS,
        "relocation_interruption_ms": TARGET_GAP_MS,
        "stop_and_redeploy_over_relocation": TARGET_GAP_RATIO,
    }
    result["runs"] = runs
    result["quick"] = quick
    result |= provenance()
    result["app"] = "mso/examples/convoy.yaml"
    result["scenario_file"] = "mso/examples/convoy-line.yaml"
    result["seconds"] = time.monotonic() - t0
    return result
