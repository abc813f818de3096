"""Table 1 of the MSO paper (§4): the cost of mapping and remapping the convoy app, measured.

The convoy app of Fig. 6 (``mso/examples/convoy.yaml``: laser 967 B and odometry 38 B at
5 events/s, cameras ~3 KB at 0.5 events/s, sensors pinned to N1, storage to N4) runs on the
emulated four-robot line (``mso/examples/convoy-line.yaml``; one ``mso node`` process per robot
on 127.0.1.i). Every operation of Table 1 is run ``runs`` times; the figure is the coordinating
node's own measure (``elapsed_ms`` of the reply: request received -> operation complete):

* mapping: deploy the convoy via N1 (DeployReply: every chain built), then undeploy it and wait
  until no node holds it;
* upstream / downstream relocation: with the convoy flowing, move an interior vertex of the
  laser -> scan_filter -> scan_matcher -> localization chain (``scan_filter``, ``scan_matcher``)
  downstream then back upstream, alternately; the request goes to the node hosting the
  vertex's predecessor (§3.4.1: the node housing u relocates its successor v).
  Only moves that can succeed are asked for, and only successful ones are counted;
* chain remapping (§3.4.2) of the laser chain, global remapping (§3.4.3) of the navigation
  pipeline's three chains (part) and of every chain (whole): before each timed remap one
  interior vertex of the remapped chains is first relocated to another node (untimed), so the
  remap has something to move back; the runs that moved vertices are counted.

A small measurement app runs alongside the whole time (``beats``: a source at 200 events/s on N1
-> ``near`` (N2) -> ``relay`` -> ``far`` (N3) -> a sink on N4). Its
sink records the wall time of every arrival, so the benchmark can measure the interruption of
the flow (largest inter-arrival gap minus the nominal 5 ms period):

* across each relocation of ``relay`` between N2 and N3 (the gap overlapping the request; an
  "idle" window of the same length just before it gives the undisturbed jitter), versus
* across a stop-and-redeploy: undeploy ``beats``, wait until no node holds it, deploy it again
  with ``relay`` pinned to the other node; the gap runs from the last arrival the old sink
  reported just before the stop to the first arrival at the new sink.

The source numbers its events and the relay carries a counter that must move with it, so the
sink counts repeats, events arriving ahead of their turn (a skipped seq: lost or reordered) and
relay-state errors. For an exact count the source is paused (by a file it checks) until
everything emitted has arrived. Events in flight when an instance is stopped are discarded by
design; they are not counted as lost.

The same runs are repeated on the same line with unshaped links (no bandwidth, no delay) to
separate mso's own cost from the emulated links'. The node processes import the measurement
app's vertices from :mod:`mso.benchmarks.vertices.table1` (``...table1:GapSink``), part of the
package: no PYTHONPATH needed. The benchmark's code: :mod:`.phases` (each timed operation),
:mod:`.orchestration` (the emulated line, the phases in turn, the figures), :mod:`.report` (the
Markdown table); :func:`main` runs and writes them.

Usage: .venv/bin/python bench/table1.py [--runs 30] [--quick] [--json FILE]
"""

from __future__ import annotations

import argparse
import asyncio
from pathlib import Path

from mso.benchmarks.common import Progress, write_results
from mso.benchmarks.table1.orchestration import run
from mso.benchmarks.table1.report import default_json, render


def main(argv: list[str] | None = None) -> int:
    """``mso bench table1`` and ``bench/table1.py``: run, write the JSON and the table beside it;
    1 if any run recorded a failure (so a scripted series notices)."""
    ap = argparse.ArgumentParser(description=(__doc__ or "").split("\n")[0])
    ap.add_argument("--runs", type=int, default=30, help="runs of each operation (>= 30)")
    ap.add_argument("--quick", action="store_true", help="smoke run: 5 runs, no unshaped variant")
    ap.add_argument("--no-variants", action="store_true", help="skip the unshaped-links variant")
    ap.add_argument("--json", type=Path, help="where to write the JSON (a .md goes beside it)")
    ap.add_argument(
        "--netns",
        action="store_true",
        help="also run on the netns backend (root or a user namespace; babeld), in this run",
    )
    ap.add_argument("--quiet", action="store_true", help="no progress lines on stderr")
    args = ap.parse_args(argv)
    if not 1 <= args.runs <= 1000:
        ap.error("--runs: 1..1000")
    out: Path = args.json or default_json(args.quick)
    progress = Progress("table1", quiet=args.quiet)
    result = asyncio.run(
        run(
            args.runs,
            args.quick,
            variants=not args.no_variants,
            netns=args.netns,
            progress=progress,
        )
    )
    write_results(out, result, render(result))
    failures = (
        result["failures"]
        + (result.get("unshaped") or {}).get("failures", [])
        + (result.get("netns") or {}).get("failures", [])
    )
    return 1 if failures else 0
