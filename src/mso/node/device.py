"""What the device itself reports: battery, CPU time, interface bytes (Linux sysfs, no extra
dependency). The monitor prefers these figures to its model where they exist.

- **battery**: ``/sys/class/power_supply/*`` of ``type`` Battery: ``capacity`` (percent),
  ``status`` (Charging / Discharging / Full / Not charging), ``energy_full`` (µWh) or
  ``charge_full`` (µAh) × ``voltage_min_design`` (µV), and ``power_now`` (µW) or
  ``current_now`` × ``voltage_now`` for the present drain. Several batteries add up.
- **CPU**: this process's CPU time (user + system), so the node's measured load; vertices'
  CPU time is measured per vertex by the executor already.
- **bytes**: the kernel's counters of every interface but loopback: what the radio really sent
  and received, relayed traffic and headers included (the sockets' counters stay beside it).

Every reader takes the sysfs root so tests can point it at a directory they write.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

SYS = Path("/sys")


@dataclass(frozen=True)
class Battery:
    """A battery reading: charge fraction in [0, 1], charging or not, full energy and present
    drain (None where the OS does not say)."""

    fraction: float
    charging: bool
    full_j: float | None = None
    power_w: float | None = None
    source: str = ""


def _num(path: Path) -> float | None:
    try:
        return float(path.read_text().strip())
    except (OSError, ValueError):
        return None


def read_battery(sys_root: Path = SYS) -> Battery | None:
    """The device's batteries together; None when it reports none (wall power, a VM)."""
    root = sys_root / "class" / "power_supply"
    try:
        supplies = sorted(p for p in root.iterdir() if p.is_dir() or p.is_symlink())
    except OSError:
        return None
    found: list[tuple[float, bool, float | None, float | None, str]] = []
    for p in supplies:
        try:
            if (p / "type").read_text().strip() != "Battery":
                continue
            if (p / "present").exists() and (p / "present").read_text().strip() == "0":
                continue
        except OSError:
            continue
        capacity = _num(p / "capacity")
        if capacity is None:
            continue
        try:
            status = (p / "status").read_text().strip()
        except OSError:
            status = "Unknown"
        full = _num(p / "energy_full")
        full_j: float | None
        if full is not None:
            full_j = full * 3600e-6  # µWh -> J
        else:
            charge, volts = _num(p / "charge_full"), _num(p / "voltage_min_design")
            full_j = charge * volts * 3600e-12 if charge and volts else None
        power = _num(p / "power_now")
        if power is None:
            amps, volts = _num(p / "current_now"), _num(p / "voltage_now")
            power = amps * volts * 1e-6 if amps is not None and volts is not None else None
        power_w = None if power is None else abs(power) * 1e-6
        found.append((max(0.0, min(1.0, capacity / 100)), status == "Charging", full_j, power_w,
                      p.name))  # fmt: skip
    if not found:
        return None
    fulls = [f[2] for f in found]
    total = sum(f for f in fulls if f is not None) if all(f is not None for f in fulls) else None
    if total:
        fraction = sum(f[0] * (f[2] or 0.0) for f in found) / total
    else:
        fraction = sum(f[0] for f in found) / len(found)
    powers = [f[3] for f in found if f[3] is not None]
    return Battery(
        fraction=fraction,
        charging=any(f[1] for f in found),
        full_j=total,
        power_w=sum(powers) if powers else None,
        source=",".join(f[4] for f in found),
    )


def read_interfaces(sys_root: Path = SYS) -> tuple[int, int] | None:
    """``(rx_bytes, tx_bytes)`` summed over every interface but loopback; None if unreadable."""
    root = sys_root / "class" / "net"
    rx = tx = 0
    try:
        names = sorted(p.name for p in root.iterdir())
    except OSError:
        return None
    for name in names:
        if name == "lo":
            continue
        r = _num(root / name / "statistics" / "rx_bytes")
        t = _num(root / name / "statistics" / "tx_bytes")
        if r is None or t is None:
            continue
        rx, tx = rx + int(r), tx + int(t)
    return rx, tx


def process_cpu_s() -> float:
    """CPU seconds this process has used (user + system, every thread)."""
    t = os.times()
    return t.user + t.system


@dataclass
class DeviceProbe:
    """Reads the device each time it is asked; ``battery`` off keeps the model (emulation)."""

    battery: bool = True
    interfaces: bool = True
    sys_root: Path = SYS

    def read(self) -> dict[str, Any]:
        out: dict[str, Any] = {"cpu_s": process_cpu_s()}
        if self.battery:
            b = read_battery(self.sys_root)
            if b is not None:
                out["battery"] = b
        if self.interfaces:
            io = read_interfaces(self.sys_root)
            if io is not None:
                out["iface_rx_bytes"], out["iface_tx_bytes"] = io
        return out
