"""Device figures from the OS (a sysfs tree written here) and how the monitor uses them:
measured battery and drain replace the model's, status says which figure is which."""

from __future__ import annotations

from pathlib import Path

import msgspec

from mso.model.network import PowerModel
from mso.node.device import DeviceProbe, read_battery, read_interfaces
from mso.node.monitor import Monitor
from mso.statusview import _measured_cell


def _write(root: Path, rel: str, text: str) -> None:
    p = root / rel
    p.parent.mkdir(parents=True, exist_ok=True)
    p.write_text(text + "\n")


def _laptop(root: Path, *, status: str = "Discharging") -> None:
    ps = "class/power_supply"
    _write(root, f"{ps}/AC/type", "Mains")
    _write(root, f"{ps}/AC/online", "1")
    _write(root, f"{ps}/BAT0/type", "Battery")
    _write(root, f"{ps}/BAT0/capacity", "80")
    _write(root, f"{ps}/BAT0/status", status)
    _write(root, f"{ps}/BAT0/energy_full", "50000000")  # 50 Wh in µWh
    _write(root, f"{ps}/BAT0/power_now", "10000000")  # 10 W in µW
    for dev, rx, tx in (("lo", 999, 999), ("wlan0", 1000, 250), ("eth0", 24, 6)):
        _write(root, f"class/net/{dev}/statistics/rx_bytes", str(rx))
        _write(root, f"class/net/{dev}/statistics/tx_bytes", str(tx))


def test_battery_and_interfaces_from_sysfs(tmp_path: Path) -> None:
    _laptop(tmp_path)
    b = read_battery(tmp_path)
    assert b is not None and b.source == "BAT0" and not b.charging
    assert b.fraction == 0.8 and b.full_j == 50 * 3600 and b.power_w == 10.0
    assert read_interfaces(tmp_path) == (1024, 256)  # loopback left out
    assert read_battery(tmp_path / "nothing") is None  # a VM, wall power


def test_charge_based_batteries_add_up(tmp_path: Path) -> None:
    ps = "class/power_supply"
    for name, cap in (("BAT0", "100"), ("BAT1", "50")):
        _write(tmp_path, f"{ps}/{name}/type", "Battery")
        _write(tmp_path, f"{ps}/{name}/capacity", cap)
        _write(tmp_path, f"{ps}/{name}/status", "Charging" if name == "BAT1" else "Full")
        _write(tmp_path, f"{ps}/{name}/charge_full", "2000000")  # 2 Ah
        _write(tmp_path, f"{ps}/{name}/voltage_min_design", "10000000")  # 10 V
        _write(tmp_path, f"{ps}/{name}/current_now", "500000")  # 0.5 A
        _write(tmp_path, f"{ps}/{name}/voltage_now", "10000000")
    b = read_battery(tmp_path)
    assert b is not None and b.charging
    assert b.full_j == 2 * 20 * 3600  # two 20 Wh packs
    assert b.fraction == 0.75 and b.power_w == 10.0


def test_monitor_prefers_measured_figures(tmp_path: Path) -> None:
    _laptop(tmp_path)
    mon = Monitor(PowerModel(idle_w=1.0), battery_wh=5.0)
    modelled = mon.status()
    assert modelled.sources["battery"] == "modelled"
    assert modelled.remaining_j == 5.0 * 3600
    probe = DeviceProbe(sys_root=tmp_path)
    mon.observe(0.0, probe.read())
    mon.observe(1.0, probe.read())
    snap = mon.status()
    assert snap.sources["battery"] == "measured (BAT0)"
    assert snap.sources["drain"] == "measured"
    assert snap.remaining_j == 0.8 * 50 * 3600
    assert snap.lifetime_s == 0.8 * 50 * 3600 / 10.0  # at the measured 10 W
    assert snap.measured["iface_tx_bytes"] == 256 and "cpu_load" in snap.measured
    cell = _measured_cell(msgspec.to_builtins(snap))  # as status carries it
    assert cell.startswith("battery, W, cpu ") and cell.endswith("radio 256 B/1.0 kB")
    _laptop(tmp_path, status="Charging")
    mon.observe(2.0, probe.read())
    assert mon.lifetime_s is None  # on the charger: no end in sight
    assert "charging" in mon.status().sources["battery"]


def test_model_only_when_the_os_reports_nothing(tmp_path: Path) -> None:
    mon = Monitor(PowerModel(idle_w=2.0), battery_wh=1.0)
    mon.observe(0.0, DeviceProbe(battery=False, interfaces=False, sys_root=tmp_path).read())
    mon.sample(0.0, 0.0, 0, 0)
    mon.sample(10.0, 0.0, 0, 0)
    snap = mon.status()
    assert snap.sources["battery"] == "modelled" and snap.sources["drain"] == "modelled"
    assert snap.remaining_j == 3600 - 20.0 and snap.lifetime_s == (3600 - 20.0) / 2.0
    assert _measured_cell(msgspec.to_builtins(snap)) == "-"
