"""How long does a CLI command take, start to answer, as a user types it?

Starts a 4-node emulated line (no app), then runs each command ``--runs`` times as a fresh
process (``.venv/bin/mso ...``, the console script a user runs) and records the wall time of each
run: Python's start-up, the imports, finding the overlay's state file, asking a node, printing.
Byte code is cached as in an installed package (one untimed run first; PYTHONDONTWRITEBYTECODE
is dropped from the environment).
Target (issue 12): ``mso status`` answers in <= 150 ms. On a shared, loaded machine the wall
time is mostly waiting for a CPU, so each run's CPU time (user + system, from ``wait4``) is
recorded too: on an idle machine the wall time is about that plus the node's answer.
The commands measured:

- ``mso status --json`` and ``mso status`` (rendered with rich) against the running overlay;
- ``mso overlays`` (no node asked) and ``mso --help``.

Usage: .venv/bin/python bench/cli_startup.py [--runs 20] [--json FILE]
"""

from __future__ import annotations

import argparse
import asyncio
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from mso.benchmarks.common import percentile, provenance, write_results
from mso.emu.controller import Emulator
from mso.scenario import loads_scenario

HERE = Path(__file__).resolve().parent
MSO = Path(sys.executable).parent / "mso"
LINE = """\
name: startup-line
nodes: {N1: {}, N2: {}, N3: {}, N4: {}}
links: [[N1, N2], [N2, N3], [N3, N4]]
"""
COMMANDS = [["status", "--json"], ["status"], ["overlays"], ["--help"]]
FLOOR = [sys.executable, "-c", "pass"]  # Python's own start-up, for scale


def time_runs(args: list[str], runs: int, env: dict[str, str]) -> tuple[list[float], list[float]]:
    """Wall time and CPU time (user + system, from wait4) of each run."""
    wall, cpu = [], []
    for i in range(runs + 1):  # the first, untimed, writes the byte code cache
        t0 = time.perf_counter()
        cmd = FLOOR if args == FLOOR else [str(MSO), *args]
        proc = subprocess.Popen(cmd, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
        _, status, usage = os.wait4(proc.pid, 0)
        proc.returncode = os.waitstatus_to_exitcode(status)
        if i:
            wall.append(time.perf_counter() - t0)
            cpu.append(usage.ru_utime + usage.ru_stime)
        if proc.returncode != 0:
            assert proc.stderr is not None
            raise SystemExit(f"mso {' '.join(args)} failed: {proc.stderr.read().decode()}")
        assert proc.stderr is not None
        proc.stderr.close()
    return wall, cpu


async def measure(runs: int) -> dict[str, Any]:
    emu = Emulator(loads_scenario(LINE))
    await emu.start()
    try:
        env = dict(os.environ)
        # as installed: byte code cached (a fresh run once writes it); a dev shell may say not to
        env.pop("PYTHONDONTWRITEBYTECODE", None)
        rows = {}
        for args in [*COMMANDS, FLOOR]:
            times, cpu = await asyncio.to_thread(time_runs, args, runs, env)
            name = "python -c pass" if args == FLOOR else "mso " + " ".join(args)
            rows[name] = {
                "runs": runs,
                "p50_ms": percentile(times, 50) * 1e3,
                "p90_ms": percentile(times, 90) * 1e3,
                "min_ms": min(times) * 1e3,
                "cpu_p50_ms": percentile(cpu, 50) * 1e3,
            }
        return rows
    finally:
        await emu.stop()


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=20)
    ap.add_argument("--json", type=Path, default=HERE / "results" / "cli_startup.json")
    a = ap.parse_args(argv)
    tempfile.tempdir = tempfile.mkdtemp(prefix="mso-bench-cli-")  # our overlay only
    os.environ["TMPDIR"] = tempfile.tempdir
    t0 = time.perf_counter()
    rows = asyncio.run(measure(a.runs))
    result = {"benchmark": "cli_startup", "target_status_ms": 150, "commands": rows}
    result |= provenance() | {"seconds": time.perf_counter() - t0}
    load = result["machine"]["load_average"]
    lines = [
        f"CLI start to answer, {a.runs} runs each (load average {load[0]:.2f} on "
        f"{result['machine']['cpus']} CPUs)",
        "",
        "| command | wall p50 ms | wall p90 ms | wall min ms | CPU p50 ms |",
        "|---|---:|---:|---:|---:|",
    ]
    for cmd, r in rows.items():
        lines.append(
            f"| `{cmd}` | {r['p50_ms']:.0f} | {r['p90_ms']:.0f} | {r['min_ms']:.0f} "
            f"| {r['cpu_p50_ms']:.0f} |"
        )
    write_results(a.json, result, "\n".join(lines) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
