"""The monitor: energy under the power model, drain, lifetime, neighbour and route changes."""

from __future__ import annotations

from dataclasses import replace

import pytest

from mso.model.network import LinkSpec, Network, NodeSpec, PowerModel
from mso.node.monitor import Monitor
from mso.protocol import messages as m
from mso.sim.runner import Simulation

POWER = PowerModel(idle_w=2.0, cpu_w=10.0, tx_uj_per_byte=3.0, rx_uj_per_byte=1.0)


def test_energy_follows_the_power_model() -> None:
    mon = Monitor(POWER, battery_wh=1.0, cpu_speed=2.0)
    mon.sample(0.0, work_ms=0.0, bytes_out=0, bytes_in=0)
    mon.sample(10.0, work_ms=4000.0, bytes_out=1_000_000, bytes_in=500_000)
    # idle 2 W x 10 s + CPU 10 W x (4 s / speed 2) + radio 3 J + 0.5 J
    assert mon.energy_j == pytest.approx(20.0 + 20.0 + 3.0 + 0.5)
    assert mon.drain_w == pytest.approx(4.35)
    assert mon.remaining_j == pytest.approx(3600.0 - 43.5)
    assert mon.lifetime_s == pytest.approx((3600.0 - 43.5) / 4.35)
    assert Monitor(POWER, battery_wh=None).lifetime_s is None  # wall power


def test_a_short_sample_counts_for_its_length_only() -> None:
    """A status request samples between the periodic samples: a burst (a vertex's start-up)
    caught in a 50 ms sliver is spread over the window's time, not weighed as a whole sample
    (the sliver alone reads 101 W; as one sample of six it made the drain 17.7 W)."""
    mon = Monitor(PowerModel(idle_w=1.0, cpu_w=10.0), battery_wh=1.0)
    for t in range(6):
        mon.sample(float(t), 0.0, 0, 0)
    mon.sample(5.05, 500.0, 0, 0)  # 0.5 s of CPU lands in the sliver
    mon.sample(6.0, 500.0, 0, 0)
    # the window (six samples) spans 1 s .. 6 s: 5 s idle at 1 W plus 5 J of CPU
    assert mon.drain_w == pytest.approx(10.0 / 5.0)
    assert mon.load == pytest.approx(0.5 / 5.0)


def test_route_and_neighbour_changes_are_recorded() -> None:
    mon = Monitor()
    mon.note_routes(0.0, {"B": ("B", 1), "C": ("B", 2)})
    assert mon.route_changes == 0
    mon.note_routes(5.0, {"B": ("B", 1), "C": ("C", 1)})
    assert mon.route_changes == 1 and mon.last_route_change == 5.0
    assert mon.neighbour_changes == 1
    assert any("C" in e for _, e in mon.events)


APP = """
name: pipe
vertices:
  src: {code: runtime_vertices:CountingSource, pinned: N1, rate: 200, cost: 0.1,
        output: runtime_vertices:Num, params: {size: 200}}
  work: {code: runtime_vertices:Double, cost: 5.0, pinned: N2}
  sink: {code: runtime_vertices:Recorder, pinned: N3}
edges: [[src, work], [work, sink]]
"""


def test_hosting_work_and_relaying_drain_the_battery() -> None:
    nodes = [NodeSpec(n, battery_wh=1.0, power=POWER) for n in ("N1", "N2", "N3", "N4")]
    links = [LinkSpec("N1", "N2"), LinkSpec("N2", "N3"), LinkSpec("N3", "N4")]
    sim = Simulation(Network(nodes, links))
    sim.request("N1", m.DeployRequest(APP, "pipe.yaml"))
    sim.run_until(10.0)
    mon = {n: c.status(sim.now)["monitor"] for n, c in sim.cores.items()}
    # N2 does the heavy work; N4 only idles; N1 and N3 send/receive the events
    assert mon["N2"]["cpu_energy_j"] > 10 * mon["N1"]["cpu_energy_j"] > 0
    assert (
        mon["N4"]["cpu_energy_j"] == 0 and mon["N4"]["radio_energy_j"] < mon["N3"]["radio_energy_j"]
    )
    assert mon["N2"]["drain_w"] > mon["N4"]["drain_w"] >= POWER.idle_w * 0.99
    assert mon["N2"]["lifetime_s"] < mon["N4"]["lifetime_s"]
    assert 0 < mon["N2"]["battery_fraction"] < mon["N4"]["battery_fraction"] <= 1


def test_measured_cpu_energy_follows_the_cpu_time_the_code_took() -> None:
    """With cpu_energy: measured the declared costs do not matter: the CPU time measured here,
    scaled by the node's speed, is what drains the battery."""
    power = PowerModel(idle_w=0.0, cpu_w=5.0, tx_uj_per_byte=0.0, rx_uj_per_byte=0.0)
    measured = Monitor(replace(power, cpu_energy="measured"), battery_wh=1.0, cpu_speed=0.5)
    modelled = Monitor(power, battery_wh=1.0, cpu_speed=0.5)
    for mon in (measured, modelled):
        mon.sample(0.0, 0.0, 0, 0, 0.0)
        mon.sample(1.0, 1000.0, 0, 0, 200.0)  # declared 1000 ms of work, measured 200 ms
    assert measured.cpu_energy_j == pytest.approx(5.0 * 0.2 / 0.5)
    assert modelled.cpu_energy_j == pytest.approx(5.0 * 1.0 / 0.5)
