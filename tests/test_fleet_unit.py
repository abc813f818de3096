"""The systemd unit docs/fleet.md installs says what the daemon does: it starts `mso node` from
the config file, is not restarted after the fail-stop of an empty modelled battery, and has a
writable state directory under a read-only system."""

from __future__ import annotations

from pathlib import Path

import pytest

import mso.examples
from mso.node.driver import BATTERY_EMPTY_EXIT

UNIT = Path(mso.examples.__file__).parent / "mso-node.service"


def settings() -> dict[str, str]:
    out = {}
    for line in UNIT.read_text().splitlines():
        if line and not line.startswith(("#", "[")):
            key, _, value = line.partition("=")
            out[key] = value
    return out


def test_the_unit_matches_the_daemon() -> None:
    unit = settings()
    assert unit["ExecStart"].endswith("mso node --config /etc/mso/node.yaml")
    assert unit["RestartPreventExitStatus"] == str(BATTERY_EMPTY_EXIT)
    assert unit["ProtectSystem"] == "strict" and unit["StateDirectory"] == "mso"
    assert unit["KillSignal"] == "SIGTERM" and "-HUP" in unit["ExecReload"]
    fleet = (Path(__file__).resolve().parents[1] / "docs" / "fleet.md").read_text()
    assert "state_dir: /var/lib/mso" in fleet  # the directory the unit makes writable


def test_a_node_started_without_peers_or_kernel_routes_says_it_finds_none(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    from types import SimpleNamespace
    from typing import Any

    from mso.daemon.assembly import describe_routes
    from mso.node.driver import PARENT_ENV

    by_hand: Any = SimpleNamespace(routes_from="auto", peers={})
    monkeypatch.delenv(PARENT_ENV, raising=False)
    assert describe_routes(by_hand, None) == "none"  # and the no_neighbours warning follows
    monkeypatch.setenv(PARENT_ENV, "1")
    assert describe_routes(by_hand, None) == "emulator"
    kernel: Any = SimpleNamespace(routes_from="kernel", peers={})
    assert describe_routes(kernel, None) == "kernel"
