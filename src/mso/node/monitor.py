"""The per-node monitor (paper §3.5): energy, load, traffic, neighbours and routes. Sans-IO.

Fed cumulative counters with the time they were read; keeps the energy spent under the node's
power model (docs/architecture.md, "Energy model"), a smoothed drain, the expected lifetime
(remaining energy / recent drain), and the history of neighbour and route changes.

On a device (``mso node`` outside an emulator) the driver also hands it what the OS measures
(:mod:`mso.node.device`): a battery's charge, charging state and drain replace the modelled
remaining energy and drain, the process's CPU time gives the measured node load, and the
interface counters the radio's bytes. ``status().sources`` says which figure is which.

CPU energy is charged, by default, for the *modelled* work of the vertices that ran here: a
vertex of cost c processing one event is c ms of CPU on a node of ``cpu: 1.0``, so c / cpu ms
here (stand-in code is cheap, yet the experiment must drain the robot that would do the work).
With ``cpu_energy: measured`` it is charged for the CPU time the vertex code really took,
divided by the node's cpu (the host is the reference node): real code drains whichever robot
runs it, by what it costs.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import msgspec

from mso.model.network import PowerModel
from mso.node.device import Battery

# drain and load are means over the last few samples: steady enough for a camera at 0.5
# frames/s (three frames in the window), quick enough that work moved here is fully seen 6 s
# later (the management rules weigh moves with them). The means are weighted by each sample's
# length: a status request samples in between the periodic samples, and a burst (a vertex's
# start-up) caught in such a sliver must count for the sliver's time, not for a whole sample
WINDOW = 6


class MonitorStatus(msgspec.Struct, frozen=True, kw_only=True):
    """The monitor's figures for status: energy, load, changes seen, and which figures the OS
    measured (``measured``, ``sources``: free-form, as the device reports them)."""

    energy_j: float
    cpu_energy_j: float
    radio_energy_j: float
    battery_j: float | None  # None: wall-powered
    remaining_j: float | None
    battery_fraction: float | None
    drain_w: float
    load: float
    lifetime_s: float | None  # None: wall-powered, charging or not yet known
    route_changes: int
    neighbour_changes: int
    last_route_change: float | None
    last_start: float | None
    recent: list[str]  # the last few events, "time what"
    measured: dict[str, Any]
    sources: dict[str, str]
    work_ms: float  # the data plane's counters as last sampled: what energy was charged for
    cpu_ms: float


@dataclass
class Monitor:
    power: PowerModel = field(default_factory=PowerModel)
    battery_wh: float | None = None  # None: wall-powered
    cpu_speed: float = 1.0
    started_at: float = 0.0
    energy_j: float = 0.0
    cpu_energy_j: float = 0.0
    radio_energy_j: float = 0.0
    drain_w: float = 0.0
    load: float = 0.0  # modelled CPU utilisation, recent mean (1.0 = a fully busy CPU)
    route_changes: int = 0
    neighbour_changes: int = 0
    last_route_change: float | None = None
    last_start: float | None = None  # when a vertex instance last started here (note_start)
    events: list[tuple[float, str]] = field(default_factory=list)  # recent, bounded
    # the cumulative modelled vertex work and measured vertex CPU time last sampled
    work_ms: float = 0.0
    cpu_ms: float = 0.0
    _last: tuple[float, float, int, int] | None = None  # now, work_ms, bytes_out, bytes_in
    _neighbours: frozenset[str] = frozenset()
    # the routing view last noted: the core's own table, which it replaces and never changes
    # (not a copy: an N-entry table per node was 30 KB of each node's memory at 1,000 nodes)
    _routes: Mapping[str, tuple[str, int]] = field(default_factory=dict)
    # (seconds, CPU-busy seconds) and (seconds, joules) of each recent sample
    _busy: deque[tuple[float, float]] = field(default_factory=lambda: deque(maxlen=WINDOW))
    _spent: deque[tuple[float, float]] = field(default_factory=lambda: deque(maxlen=WINDOW))
    battery: Battery | None = None  # measured by the OS, when the device reports one
    device: dict[str, Any] = field(default_factory=dict)  # last device reading (measured)
    _cpu: tuple[float, float] | None = None  # (now, process cpu_s) of the last reading
    _cpu_load: deque[float] = field(default_factory=lambda: deque(maxlen=WINDOW))

    def observe(self, now: float, reading: dict[str, Any]) -> None:
        """Take a device reading (:meth:`mso.node.device.DeviceProbe.read`)."""
        b = reading.get("battery")
        self.battery = b if isinstance(b, Battery) else None
        cpu = reading.get("cpu_s")
        if isinstance(cpu, float):
            if self._cpu is not None and now > self._cpu[0]:
                self._cpu_load.append(max(0.0, cpu - self._cpu[1]) / (now - self._cpu[0]))
            self._cpu = (now, cpu)
        self.device = {k: v for k, v in reading.items() if k != "battery"}
        if self._cpu_load:
            self.device["cpu_load"] = sum(self._cpu_load) / len(self._cpu_load)

    @property
    def measured_drain_w(self) -> float | None:
        b = self.battery
        return None if b is None or b.charging or b.power_w is None else b.power_w

    @property
    def capacity_j(self) -> float | None:
        if self.battery is not None and self.battery.full_j is not None:
            return self.battery.full_j
        return None if self.battery_wh is None else self.battery_wh * 3600.0

    @property
    def remaining_j(self) -> float | None:
        cap = self.capacity_j
        if cap is not None and self.battery is not None:
            return cap * self.battery.fraction
        return None if cap is None else max(0.0, cap - self.energy_j)

    @property
    def empty(self) -> bool:
        """The modelled battery is spent (an OS-measured one is the device's own business):
        an emulated or simulated robot stops here, fail-stop."""
        rem = self.remaining_j
        return self.battery is None and rem is not None and rem <= 0

    @property
    def lifetime_s(self) -> float | None:
        """Expected lifetime at the recent drain; None when wall-powered, charging or not yet
        known. A measured drain is preferred to the model's."""
        if self.battery is not None and self.battery.charging:
            return None
        rem = self.remaining_j
        drain = self.measured_drain_w or self.drain_w
        if rem is None or drain <= 0:
            return None
        return rem / drain

    def sources(self) -> dict[str, str]:
        """Which figures the OS measured and which the energy model gives."""
        b = self.battery
        if b is not None:
            battery = f"measured ({b.source})" + (", charging" if b.charging else "")
            if b.full_j is None and self.battery_wh is not None:
                battery += "; capacity modelled"
        else:
            battery = "modelled" if self.battery_wh is not None else "none (wall power)"
        return {
            "battery": battery,
            "drain": "measured" if self.measured_drain_w is not None else "modelled",
            "energy": "modelled (power model: idle, "
            + ("measured vertex CPU time" if self.power.cpu_energy == "measured" else "vertex cost")
            + ", bytes)",
            "load": "modelled (vertex cost / cpu); node CPU time measured"
            if "cpu_load" in self.device
            else "modelled (vertex cost / cpu)",
            "vertex_cpu": "measured (thread CPU time per vertex)",
            "bytes": "measured (sockets)"
            + ("; interfaces measured" if "iface_tx_bytes" in self.device else ""),
        }

    def sample(
        self, now: float, work_ms: float, bytes_out: int, bytes_in: int, cpu_ms: float = 0.0
    ) -> None:
        """Charge the energy spent since the last sample (counters are cumulative; ``cpu_ms``
        is the measured CPU time of the vertex code, used with ``cpu_energy: measured``)."""
        self.work_ms, self.cpu_ms = work_ms, cpu_ms
        if self.power.cpu_energy == "measured":
            work_ms = cpu_ms
        if self._last is None:
            self._last = (now, work_ms, bytes_out, bytes_in)
            self.started_at = now
            return
        t0, w0, o0, i0 = self._last
        dt = now - t0
        if dt <= 0:
            return
        cpu_j = self.power.cpu_w * max(0.0, work_ms - w0) / 1e3 / self.cpu_speed
        radio_j = (
            self.power.tx_uj_per_byte * max(0, bytes_out - o0)
            + self.power.rx_uj_per_byte * max(0, bytes_in - i0)
        ) * 1e-6
        spent = self.power.idle_w * dt + cpu_j + radio_j
        self.energy_j += spent
        self.cpu_energy_j += cpu_j
        self.radio_energy_j += radio_j
        self._spent.append((dt, spent))
        self.drain_w = _rate(self._spent)
        self._busy.append((dt, max(0.0, work_ms - w0) / 1e3 / self.cpu_speed))
        self.load = _rate(self._busy)
        self._last = (now, work_ms, bytes_out, bytes_in)

    def note_routes(self, now: float, routes: Mapping[str, tuple[str, int]]) -> None:
        """Record neighbour and route changes seen in the routing view (a next hop that
        changed; a hop count alone is no change). ``routes`` is kept, not copied: the caller
        gives a new table each time."""
        old = self._routes
        neighbours = frozenset(d for d, r in routes.items() if r[0] == d)
        if old:
            changed = [d for d, r in routes.items() if (o := old.get(d)) is None or o[0] != r[0]]
            changed += [d for d in old if d not in routes]
            if changed:
                self.route_changes += 1
                self.last_route_change = now
                self.note_event(now, "routes changed: " + ", ".join(sorted(changed)))
        if neighbours != self._neighbours and (self._neighbours or self._routes):
            self.neighbour_changes += 1
            gone, new = self._neighbours - neighbours, neighbours - self._neighbours
            self.note_event(now, f"neighbours: +{sorted(new)} -{sorted(gone)}")
        self._routes, self._neighbours = routes, neighbours

    def note_start(self, now: float) -> None:
        """A vertex instance started here (its ``open()`` returned). Its construction (imports,
        a database, a map) and first calls are charged like any work, so for a while the drain
        says more about starting than about running: the rules wait (``RuleSettings.warmup_s``)
        before judging this node by it."""
        self.last_start = now

    def note_event(self, now: float, what: str) -> None:
        """Keep a line for the recent-events list in status."""
        self.events.append((now, what))
        del self.events[:-20]

    def status(self) -> MonitorStatus:
        """The figures as last sampled (the core samples before it asks)."""
        life = self.lifetime_s
        return MonitorStatus(
            energy_j=self.energy_j,
            cpu_energy_j=self.cpu_energy_j,
            radio_energy_j=self.radio_energy_j,
            battery_j=self.capacity_j,
            remaining_j=self.remaining_j,
            battery_fraction=None
            if self.capacity_j is None
            else (self.remaining_j or 0.0) / self.capacity_j,
            drain_w=self.drain_w,
            load=self.load,
            lifetime_s=None if life is None or math.isinf(life) else life,
            route_changes=self.route_changes,
            neighbour_changes=self.neighbour_changes,
            last_route_change=self.last_route_change,
            last_start=self.last_start,
            recent=[f"{t:.3f} {w}" for t, w in self.events[-5:]],
            measured=self._measured(),
            sources=self.sources(),
            work_ms=self.work_ms,
            cpu_ms=self.cpu_ms,
        )

    def _measured(self) -> dict[str, Any]:
        out = dict(self.device)
        b = self.battery
        if b is not None:
            out["battery_fraction"] = b.fraction
            out["charging"] = b.charging
            if b.power_w is not None:
                out["battery_power_w"] = b.power_w
        return out


def _rate(samples: deque[tuple[float, float]]) -> float:
    """Amount per second over the window: the total over the total time, so that each sample
    counts for as long as it lasted (a 50 ms sliver with a burst does not weigh like 1 s)."""
    return sum(x for _, x in samples) / sum(dt for dt, _ in samples)
