"""Issue 22's "Why", rerun: the four cases a new user met, each as that user would run it.

The issue opened on four findings, each from a command a user would type; this reruns them on
the code of the day, in one command, so the figures of a closing note come from a run anyone
can repeat. The scenario and app files are small YAML written into a temporary directory:

* **partition**: five robots by random waypoint in 300 x 300 m, radio 130 m, a 10 Hz camera
  of 50 KB events pinned on R1 and a logger pinned on R5 (`mso simulate`): how long R1 and R5
  were out of each other's reach (the scenario's own timeline, stepped), emitted, delivered,
  given up (the issue: 1,206 emitted, 80 delivered, 1,120 dropped).
* **numbering**: the convoy on a 5-node mesh whose N1 (the sources' robot) fails at 10 s and
  restarts at 16 s, in the simulator and on the user-space emulator: the storage log's rows,
  distinct sequence numbers, whether the numbering ever went back (the issue: 825 rows, 484
  distinct, the camera's `seq` back to 0).
* **unreachable**: the camera and logger on a line R1-R5 whose R3 fails at 8 s (`mso emulate`),
  `mso status --json` via R5 and via R1 while it runs: who is held failed, who unreachable
  (the issue: R4 and R5 reported failed).
* **state**: a stateful counter's host SIGKILLed on real processes (`bench/replication.py
  --kill-emulated`), replicas 1 and 0: the counter's output continuous or reset.

Usage: .venv/bin/python bench/why.py [--only partition,numbering,unreachable,state]
                                     [--kills 3] [--json FILE]
Writes bench/results/why.json and why.md.
"""

from __future__ import annotations

import argparse
import itertools
import json
import os
import sqlite3
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from mso.benchmarks.common import provenance, write_results
from mso.scenario.format import load_scenario
from mso.scenario.timeline import Timeline

HERE = Path(__file__).resolve().parent
RESULTS = HERE / "results"
MSO = [sys.executable, "-m", "mso"]
CASES = ("partition", "numbering", "unreachable", "state")

RWP5 = """\
name: rwp5
radio_range: 130
link_defaults: {bandwidth_mbps: 11, delay_ms: 1.0}
nodes:
  R1: {pos: [20, 20]}
  R2: {pos: [100, 80]}
  R3: {pos: [150, 150]}
  R4: {pos: [220, 200]}
  R5: {pos: [280, 280]}
mobility: {model: random_waypoint, area: [300, 300], speed: [1, 5], pause_s: 2, seed: 3,
           step_s: 0.5}
"""
CAMLOG = """\
name: camlog
vertices:
  camera: {pinned: R1, rate: 10, cost: 2}
  detect: {cost: 5}
  logger: {pinned: R5, cost: 1}
edges:
  - {from: camera, to: detect, size: 50000}
  - {from: detect, to: logger, size: 50000}
"""
MESH_RESTART = """\
name: mesh-restart
link_defaults: {bandwidth_mbps: 100, delay_ms: 0.5}
nodes: {N1: {}, N2: {}, N3: {}, N4: {}, N5: {}}
links: [[N1, N2], [N1, N3], [N2, N3], [N2, N4], [N3, N5], [N4, N5], [N3, N4]]
changes:
  - {at: 10.0, fail: N1}
  - {at: 16.0, restart: N1}
"""
LINE_R3 = """\
name: line-r3
link_defaults: {bandwidth_mbps: 11, delay_ms: 1.0}
nodes: {R1: {}, R2: {}, R3: {}, R4: {}, R5: {}}
links: [[R1, R2], [R2, R3], [R3, R4], [R4, R5]]
changes:
  - {at: 8.0, fail: R3}
"""


def out_of_reach_s(scenario: Path, a: str, b: str, duration: float) -> tuple[float, list[str]]:
    """How long ``a`` and ``b`` had no route between them, stepping the scenario's timeline as
    the simulator plays it, and the spans (start-end, seconds)."""
    sc = load_scenario(scenario)
    tl = Timeline(sc)
    apart, spans, since = 0.0, [], None
    t = 0.0
    while t <= duration:
        tl.advance(t)
        cut = tl.network.route(a, b) is None
        if cut and since is None:
            since = t
        elif not cut and since is not None:
            apart += t - since
            spans.append(f"{since:g}-{t:g}")
            since = None
        t = round(t + sc.mobility_step_s, 6)
    if since is not None:
        apart += duration - since
        spans.append(f"{since:g}-{duration:g}")
    return apart, spans


def partition(work: Path) -> dict[str, Any]:
    (work / "rwp5.yaml").write_text(RWP5)
    (work / "camlog.yaml").write_text(CAMLOG)
    duration = 150.0
    cmd = [*MSO, "simulate", "rwp5.yaml", "--app", "camlog.yaml", "--duration", str(duration)]
    report = json.loads(_run([*cmd, "--json"], work))
    apart, spans = out_of_reach_s(work / "rwp5.yaml", "R1", "R5", duration)
    ev = report["events"]
    return {
        "command": "mso simulate rwp5.yaml --app camlog.yaml --duration 150",
        "apart_s": apart,
        "apart_spans": spans,
        "emitted": ev["emitted"].get("camera", 0),
        "delivered": ev["delivered"].get("logger", 0),
        "given_up": ev.get("given_up", 0),
    }


def _log_figures(db: Path) -> dict[str, Any]:
    """Rows, distinct sequence numbers and whether the numbering went back, from the
    convoy's storage log (its trajectory table, in the order rows were stored)."""
    with sqlite3.connect(db) as conn:
        seqs = [s for (s,) in conn.execute("SELECT seq FROM trajectory ORDER BY id")]
    back = sum(1 for x, y in itertools.pairwise(seqs) if y < x)
    jump = max((y - x for x, y in itertools.pairwise(seqs)), default=0)
    return {"rows": len(seqs), "distinct": len(set(seqs)), "went_back": back, "largest_jump": jump}


def numbering(work: Path) -> dict[str, Any]:
    (work / "mesh-restart.yaml").write_text(MESH_RESTART)
    app = HERE.parent / "src" / "mso" / "examples" / "convoy.yaml"
    out: dict[str, Any] = {}
    for how in ("simulate", "emulate"):
        db = work / f"convoy-{how}.sqlite"
        cmd = [*MSO, how, "mesh-restart.yaml", "--app", str(app), "--duration", "40"]
        _run(cmd, work, env={"MSO_CONVOY_DB": str(db)})
        out[how] = {
            "command": f"MSO_CONVOY_DB=... mso {how} mesh-restart.yaml --app convoy.yaml "
            "--duration 40",
            **_log_figures(db),
        }
    return out


def _status(overlay: str, via: str, work: Path) -> dict[str, Any] | None:
    cmd = [*MSO, "status", "--overlay", overlay, "--via", via, "--json"]
    r = subprocess.run(cmd, cwd=work, capture_output=True, text=True, timeout=30)
    if r.returncode != 0:
        return None
    nodes: dict[str, Any] = json.loads(r.stdout)
    return nodes


def _held(nodes: dict[str, Any]) -> dict[str, list[str]]:
    failed: set[str] = set()
    unreachable: set[str] = set()
    for st in nodes.values():
        failed.update(st.get("failed_nodes", []))
        unreachable.update(st.get("unreachable_nodes", []))
    return {"failed": sorted(failed), "unreachable": sorted(unreachable - failed)}


def unreachable(work: Path) -> dict[str, Any]:
    """R3 dies on a line: R4 and R5 (seen from R1), R1 and R2 (from R5) are out of reach, not
    failed. Polled until both ends no longer hear R3, then read again 6 s later."""
    (work / "line-r3.yaml").write_text(LINE_R3)
    (work / "camlog.yaml").write_text(CAMLOG)
    overlay = f"why-{os.getpid()}"
    cmd = [*MSO, "emulate", "line-r3.yaml", "--app", "camlog.yaml", "--duration", "30"]
    proc = subprocess.Popen(
        [*cmd, "--name", overlay, "--json"],
        cwd=work,
        stdout=subprocess.PIPE,
        stderr=subprocess.DEVNULL,
        text=True,
    )
    seen: dict[str, Any] = {}
    try:
        deadline = time.monotonic() + 28
        first = None
        while time.monotonic() < deadline and proc.poll() is None:
            views = {v: _status(overlay, v, work) for v in ("R1", "R5")}
            if all(views.values()):
                held = {v: _held(n) for v, n in views.items() if n}
                gone = all("R3" in h["failed"] + h["unreachable"] for h in held.values())
                if gone and first is None:
                    first = time.monotonic()
                    seen["at_detection"] = held
                if first is not None and time.monotonic() - first >= 6:
                    seen["six_s_later"] = held
                    break
            time.sleep(0.5)  # a poll of a live emulation, not synchronisation
        summary, _ = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    final = json.loads(summary) if summary.strip().startswith("{") else {}
    return {
        "command": "mso emulate line-r3.yaml --app camlog.yaml --duration 30; "
        "mso status --via R5 / --via R1 --json",
        **seen,
        "emulator_exit": proc.returncode,
        "events": final.get("events", {}),
    }


def state(work: Path, kills: int) -> dict[str, Any]:
    out = work / "replication.json"
    cmd = [
        sys.executable,
        str(HERE / "replication.py"),
        "--runs",
        "1",
        "--convoy-s",
        "5",
        "--emulate-s",
        "0",
        "--kill-emulated",
        str(kills),
        "--json",
        str(out),
    ]
    _run(cmd, work)
    rep = json.loads(out.read_text())
    by: dict[str, dict[str, Any]] = {}
    for r in rep.get("kill_emulated", []):
        agg = by.setdefault(
            str(r["replicas"]),
            {"runs": 0, "continuous": 0, "errors": 0, "repeats": 0, "lost": 0, "restored_s": []},
        )
        agg["runs"] += 1
        if "error" in r:
            agg["errors"] += 1
            continue
        agg["continuous"] += int(bool(r["continuous"]))
        agg["repeats"] += r["repeats"]
        agg["lost"] += r["lost"]
        agg["restored_s"].append(round(r["restored_s"], 2))
    return {"command": f"bench/replication.py --kill-emulated {kills}", "by_replicas": by}


def _run(cmd: list[str], cwd: Path, env: dict[str, str] | None = None) -> str:
    r = subprocess.run(
        cmd,
        cwd=cwd,
        capture_output=True,
        text=True,
        timeout=900,
        env={**os.environ, **(env or {})},
    )
    if r.returncode != 0:
        raise SystemExit(f"{' '.join(cmd)} failed ({r.returncode}):\n{r.stderr[-2000:]}")
    return r.stdout


def render(result: dict[str, Any]) -> str:
    lines = [
        '### Issue 22\'s "Why", rerun',
        "",
        "| case (the issue's figure) | command | now |",
        "|---|---|---|",
    ]
    c = result["cases"]
    if p := c.get("partition"):
        lines.append(
            f"| a partition drops the source's events (1,206 emitted, 80 delivered) | "
            f"`{p['command']}` | R1 and R5 out of "
            f"reach {p['apart_s']:.1f} s ({', '.join(p['apart_spans'])}); camera emitted "
            f"{p['emitted']:,}, logger delivered {p['delivered']:,}, {p['given_up']} given up |"
        )
    if n := c.get("numbering"):
        for how, f in n.items():
            lines.append(
                f"| a restarted source numbers from 0 again ({how}; 825 rows, 484 distinct) | "
                f"`{f['command']}` | "
                f"{f['rows']} rows, {f['distinct']} distinct, went back {f['went_back']} "
                f"times, largest jump {f['largest_jump']} |"
            )
    if u := c.get("unreachable"):
        cells = []
        for when in ("at_detection", "six_s_later"):
            for via, h in u.get(when, {}).items():
                cells.append(
                    f"{when.replace('_', ' ')} via {via}: failed {h['failed'] or 'none'}, "
                    f"unreachable {h['unreachable'] or 'none'}"
                )
        lines.append(
            f"| out of reach is reported failed (R4, R5 failed) | `{u['command']}` | "
            f"{'; '.join(cells)} |"
        )
    if s := c.get("state"):
        cells = [
            f"replicas {r}: continuous {a['continuous']} of {a['runs']}, {a['repeats']} "
            f"repeats, {a['lost']} lost, restored in {a['restored_s']} s"
            + (f", {a['errors']} errors" if a["errors"] else "")
            for r, a in sorted(s["by_replicas"].items(), reverse=True)
        ]
        lines.append(
            f"| a stateful vertex loses its state with its node (a counter back to 1) | "
            f"`{s['command']}` | "
            f"{'; '.join(cells)} |"
        )
    return "\n".join(lines) + "\n"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--only", default=",".join(CASES), help="cases, comma-separated")
    ap.add_argument("--kills", type=int, default=3, help="SIGKILLs per setting (state)")
    ap.add_argument("--json", type=Path, default=RESULTS / "why.json")
    args = ap.parse_args()
    only = [c for c in args.only.split(",") if c]
    if bad := [c for c in only if c not in CASES]:
        ap.error(f"--only: unknown case {', '.join(bad)} (expected {', '.join(CASES)})")
    t0 = time.monotonic()
    cases: dict[str, Any] = {}
    with tempfile.TemporaryDirectory(prefix="mso-why-") as tmp:
        work = Path(tmp)
        for case in only:
            print(f"{case} ...", flush=True)
            if case == "state":
                cases[case] = state(work, args.kills)
            else:
                cases[case] = {"partition": partition, "numbering": numbering,
                               "unreachable": unreachable}[case](work)  # fmt: skip
    result = {"cases": cases, "seconds": time.monotonic() - t0, **provenance()}
    write_results(args.json, result, render(result))
    print(render(result))


if __name__ == "__main__":
    main()
