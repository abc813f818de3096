"""A study: many seeds × policies × scenarios, each a simulation, run in parallel and gathered
into one table (``mso sweep``).

Each run is :func:`mso.sim.play.simulate` on one scenario with one node policy and one seed
(the seed drives the simulator's loss and, when the scenario has a seeded mobility model, the
movement). Runs go to Ray when it is installed (``pip install 'mso[sweep]'``: local worker
processes by default, an existing cluster given its address), else to local processes with the
same interface. A job carries the scenario and app texts, not paths, so a cluster's workers
need no shared files (a trace-driven mobility's movement file excepted). Nothing here draws or
writes files: :mod:`mso.cli.sweep` does.
"""

from __future__ import annotations

import os
import statistics
import time
from collections.abc import Callable, Iterator
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import dataclass, replace
from multiprocessing import get_context
from typing import Any

from mso.errors import MsoError
from mso.model.mobility import Trace

BACKENDS = ("auto", "ray", "processes")
INSTALL = "pip install 'mso[sweep]'"
MAX_RUNS = 100_000  # a study bigger than this is a typo


@dataclass(frozen=True)
class Job:
    """One run: where the scenario and app came from (for the table) and their texts."""

    scenario_file: str
    scenario_text: str
    app_file: str
    app_text: str
    policy: str
    seed: int
    duration_s: float


def jobs(
    scenarios: list[tuple[str, str]],
    app: tuple[str, str],
    policies: list[str],
    seeds: list[int],
    duration_s: float,
) -> list[Job]:
    """Every combination, scenario-major (the table's order)."""
    out = [
        Job(sf, st, app[0], app[1], p, seed, duration_s)
        for sf, st in scenarios
        for p in policies
        for seed in seeds
    ]
    if len(out) > MAX_RUNS:
        raise MsoError(f"a study of {len(out)} runs: at most {MAX_RUNS}")
    return out


def run(job: Job) -> dict[str, Any]:
    """One run, reduced to its table row and the series the plots need (picklable both ways:
    it runs in a worker process)."""
    from mso.scenario.format import loads_scenario
    from mso.sim.play import simulate

    t0, cpu0 = time.perf_counter(), time.process_time()
    scenario = loads_scenario(job.scenario_text, file=job.scenario_file)
    if scenario.mobility is not None and not isinstance(scenario.mobility, Trace):
        scenario.mobility = replace(scenario.mobility, seed=job.seed)
    report = simulate(
        scenario, job.app_text, job.app_file, seed=job.seed, duration=job.duration_s,
        policy=job.policy, series=True,
    )  # fmt: skip
    return summarize(job, scenario.name, len(scenario.network.nodes), report) | {
        "wall_s": round(time.perf_counter() - t0, 3),
        "cpu_s": round(time.process_time() - cpu0, 3),
    }


def summarize(job: Job, name: str, nodes: int, report: dict[str, Any]) -> dict[str, Any]:
    """A run's row (scalars) and its ``series`` (for the plots)."""
    ev = report["events"]
    emitted, delivered = sum(ev["emitted"].values()), sum(ev["delivered"].values())
    rec = report["reconfigurations"]
    episodes = [e for e in rec.get("episodes", [])[1:]]  # the first is the deployment
    control = [e["control_messages"] for e in episodes]
    involved = [e["nodes_involved"] for e in episodes]
    energy = report["energy"]
    batteries = [
        e["battery_fraction"] for e in energy.values() if e["battery_fraction"] is not None
    ]
    moves = [m["at"] for m in rec["moves"]]
    return {
        "scenario": name,
        "scenario_file": job.scenario_file,
        "nodes": nodes,
        "policy": job.policy,
        "seed": job.seed,
        "duration_s": job.duration_s,
        "deploy_ok": report["deploy"]["ok"],
        "emitted": emitted,
        "delivered": delivered,
        "moves": len(moves),
        "decisions": len(rec["management"]),
        "recoveries": len(rec["recoveries"]),
        "failures": len(report["failures"]),
        "energy_j": round(sum(e["energy_j"] for e in energy.values()), 3),
        "min_battery": round(min(batteries), 4) if batteries else None,
        "messages": report.get("messages", {}).get("total", 0),
        "reconfigurations": len(episodes),
        "control_per_reconfiguration": round(statistics.fmean(control), 2) if control else None,
        "nodes_per_reconfiguration": round(statistics.fmean(involved), 2) if involved else None,
        "series": {
            **report.get("series", {}),
            "moves_at": moves,
            "reconfigurations_at": [e["at"] for e in episodes],
        },
    }


def backend_for(backend: str, address: str | None) -> str:
    """The backend to use: Ray when asked for or (``auto``) installed, else local processes.
    MsoError when Ray is asked for (by name or an address) and missing."""
    if backend not in BACKENDS:
        raise MsoError(f"--backend: expected one of {', '.join(BACKENDS)}, got {backend!r}")
    if backend == "processes":
        if address is not None:
            raise MsoError("--address names a Ray cluster: it goes with --backend ray or auto")
        return "processes"
    try:
        import ray  # noqa: F401
    except ImportError:
        if backend == "ray" or address is not None:
            raise MsoError(f"Ray is not installed: {INSTALL}") from None
        return "processes"
    return "ray"


def execute(
    all_jobs: list[Job],
    *,
    workers: int,
    backend: str = "processes",
    address: str | None = None,
    done: Callable[[dict[str, Any]], None] | None = None,
) -> list[dict[str, Any]]:
    """Run every job on ``workers`` processes (Ray: local workers, or the cluster's at
    ``address``); rows in the jobs' order. ``done`` sees each row as it arrives."""
    if workers < 1:
        raise MsoError(f"--workers: expected at least 1, got {workers}")
    rows: list[dict[str, Any] | None] = [None] * len(all_jobs)
    runner = _ray if backend == "ray" else _processes
    for i, row in runner(all_jobs, workers, address):
        rows[i] = row
        if done is not None:
            done(row)
    return [r for r in rows if r is not None]


def _processes(
    all_jobs: list[Job], workers: int, address: str | None
) -> Iterator[tuple[int, dict[str, Any]]]:
    if workers == 1:  # in this process: no start-up, and a traceback if a run breaks
        for i, job in enumerate(all_jobs):
            yield i, run(job)
        return
    # spawn, not fork: a fresh interpreter per worker whatever threads this one runs
    with ProcessPoolExecutor(workers, mp_context=get_context("spawn")) as pool:
        futures = {pool.submit(run, job): i for i, job in enumerate(all_jobs)}
        for fut in as_completed(futures):
            yield futures[fut], fut.result()


def _ray(
    all_jobs: list[Job], workers: int, address: str | None
) -> Iterator[tuple[int, dict[str, Any]]]:
    import ray

    started = not ray.is_initialized()
    if started:
        kwargs: dict[str, Any] = {"include_dashboard": False, "log_to_driver": False}
        if address is None:
            kwargs["num_cpus"] = workers  # local: this many worker processes at once
        else:
            kwargs["address"] = address
        os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")  # never phones home
        ray.init(**kwargs)
    try:
        remote = ray.remote(num_cpus=1, max_retries=0)(run)
        refs = {remote.remote(job): i for i, job in enumerate(all_jobs)}
        pending = list(refs)
        while pending:
            ready, pending = ray.wait(pending, num_returns=1)
            for ref in ready:
                yield refs[ref], ray.get(ref)
    finally:
        if started:
            ray.shutdown()


# -- the study's table -------------------------------------------------------------------------
COLUMNS = (
    "scenario", "nodes", "policy", "seed", "deploy_ok", "emitted", "delivered", "moves",
    "decisions", "recoveries", "failures", "energy_j", "min_battery", "messages",
    "reconfigurations", "control_per_reconfiguration", "nodes_per_reconfiguration", "wall_s",
    "cpu_s",
)  # fmt: skip
SUMMED = ("delivered", "moves", "recoveries", "failures", "energy_j", "messages",
          "control_per_reconfiguration", "cpu_s")  # fmt: skip


def summary(rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """Per scenario and policy: runs, deployments that succeeded, and the mean and standard
    deviation over seeds of the figures in :data:`SUMMED`."""
    groups: dict[tuple[str, int, str], list[dict[str, Any]]] = {}
    for r in rows:
        groups.setdefault((r["scenario"], r["nodes"], r["policy"]), []).append(r)
    out = []
    for (name, nodes, policy), rs in groups.items():
        deployed = sum(bool(r["deploy_ok"]) for r in rs)
        line: dict[str, Any] = {
            "scenario": name, "nodes": nodes, "policy": policy, "runs": len(rs),
            "deployed": deployed,
        }  # fmt: skip
        for col in SUMMED:
            vals = [float(r[col]) for r in rs if r.get(col) is not None]
            if not vals:
                line[col] = None  # (no run had it: no reconfiguration, say)
                continue
            sd = statistics.stdev(vals) if len(vals) > 1 else 0.0
            line[col] = (round(statistics.fmean(vals), 3), round(sd, 3))
        out.append(line)
    return out


def markdown(lines: list[dict[str, Any]]) -> str:
    """The summary as a Markdown table (mean ± sd over seeds)."""
    head = ["scenario", "N", "policy", "runs", "deployed", *SUMMED]
    out = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for ln in lines:
        cells = [
            ln["scenario"],
            str(ln["nodes"]),
            ln["policy"],
            str(ln["runs"]),
            str(ln["deployed"]),
        ]
        for col in SUMMED:
            cells.append("—" if ln[col] is None else f"{ln[col][0]:g} ± {ln[col][1]:g}")
        out.append("| " + " | ".join(cells) + " |")
    return "\n".join(out) + "\n"


__all__ = [
    "BACKENDS", "COLUMNS", "INSTALL", "Job", "backend_for", "execute", "jobs", "markdown", "run",
    "summarize", "summary",
]  # fmt: skip
