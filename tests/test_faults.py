"""Seeded fault schedules: random worlds and faults in virtual time, invariants checked after a
quiet period; a seed replays to the identical event log."""

from __future__ import annotations

import pytest

from mso.protocol import messages as m
from mso.sim import faults, vertices
from mso.sim.invariants import check
from mso.sim.runner import Simulation

# short phases keep 200 seeds within about a minute on two cores
CI = faults.Settings(start_s=1.0, faults_s=2.5, quiet_s=3.5, rate=10.0)
SEEDS = 200
# seeds that found bugs in the node core (not fixed here: reported to the core's owner, with
# the invariant); strict, so a fix shows up as an unexpected pass and the entry goes
KNOWN: dict[int, str] = {
    23: "placement",
    31: "dangling-edge, hosted-once, placement",
    37: "placement",
    42: "placement",
    53: "dangling-edge, hosted-once, placement",
    54: "dangling-edge, placement, stalled",
    56: "exception",
    69: "dangling-edge, placement",
    71: "dangling-edge, hosted-once, membership, parked, placement, stalled",
    73: "placement, stalled",
    75: "dangling-edge, hosted-once, placement, stalled",
    78: "dangling-edge, hosted-once, placement",
    91: "dangling-edge, hosted-once, placement",
    110: "dangling-edge, hosted-once, placement, stalled",
    133: "dangling-edge, hosted-once, placement",
    135: "dangling-edge, placement",
    160: "dangling-edge, placement, stalled",
    168: "exception",
    170: "dangling-edge, hosted-once, membership, parked, placement, stalled",
    178: "dangling-edge, hosted-once, placement",
    183: "dangling-edge, hosted-once, placement",
    196: "dangling-edge, hosted-once, membership, parked, placement, stalled",
}


def test_a_seed_replays_to_the_identical_event_log() -> None:
    seed = next(
        s for s in range(100) if {"crash", "partition"} <= set(faults.generate(s, CI).faults)
    )
    a, b = faults.run(seed, CI), faults.run(seed, CI)
    assert a.log == b.log and a.digest == b.digest
    assert len(a.log) > 500  # deliveries, changes and requests, not an empty log
    assert any("timeline fail" in line for line in a.log)
    assert any("timeline partition" in line for line in a.log)
    assert faults.run(seed + 1, CI).digest != a.digest


def test_schedules_are_seeded_and_cover_every_kind_of_fault() -> None:
    one, again = faults.generate(7), faults.generate(7)
    assert (one.app, one.changes, one.requests) == (again.app, again.changes, again.requests)
    kinds: set[str] = set()
    shapes, sizes = set(), set()
    for s in range(60):
        sched = faults.generate(s)
        kinds |= set(sched.faults)
        shapes.add(sched.topology)
        sizes.add(len(sched.network.nodes))
        assert all(sched.settings.start_s <= c.at <= sched.end for c in sched.changes)
    assert kinds == set(faults.KINDS)
    assert shapes == {"line", "mesh", "geometric"} and min(sizes) == 3 and max(sizes) == 8


def test_the_checker_catches_a_vertex_that_vanished_and_a_duplicate() -> None:
    seed = next(s for s in range(100) if not faults.generate(s, CI).faults["crash"])
    sched = faults.generate(seed, CI)
    result = faults.run(seed, CI)
    assert not result.violations, result.violations
    # replay the same world by hand, then break it the way a bug would
    sim = Simulation(sched.network, seed=seed, manage=False)

    vertices.RUNS.pop(str(seed), None)
    sim.request("N1", m.DeployRequest(sched.app, "faults.yaml"))
    sim.run_until(3.0)
    records = vertices.RUNS.pop(str(seed), [])
    assert records and all(r.streams for r in records)
    host = next(n for n, c in sim.cores.items() if "faults" in c.apps and c.apps["faults"].stones)
    stones = sim.cores[host].apps["faults"].stones
    gone = next(iter(stones))
    del stones[gone]
    stream = next(iter(records[0].streams.values()))
    stream.duplicates += 1
    found = {v.invariant for v in check(sim, sched, records)}
    assert {"hosted-once", "duplicate"} <= found, found


@pytest.mark.parametrize(
    "seed",
    [
        pytest.param(s, marks=pytest.mark.xfail(strict=True, reason=KNOWN[s])) if s in KNOWN else s
        for s in range(SEEDS)
    ],
)
def test_invariants_hold_after_a_seeded_fault_schedule(seed: int) -> None:
    result = faults.run(seed, CI)
    assert not result.violations, "\n".join(map(str, result.violations))
