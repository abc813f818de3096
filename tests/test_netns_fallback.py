"""Where namespaces cannot be made, ``mso emulate --backend netns`` says why and runs the
user-space backend; ``--cleanup`` with nothing to clean says so. Runs everywhere (no root)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from click.testing import CliRunner

import mso.emu.netns.emulator as netns_emulator
import mso.emu.netns.testbed as testbed
from mso.cli import main

EXAMPLES = Path(__file__).resolve().parent.parent / "src" / "mso" / "examples"


@pytest.mark.slow
def test_netns_backend_falls_back_with_the_reason(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(netns_emulator, "unavailable", lambda: "no namespaces for you (test)")
    monkeypatch.setenv("MSO_NETNS_USERNS", "1")  # as if already re-run in a user namespace
    result = CliRunner().invoke(
        main,
        ["emulate", "--backend", "netns", str(EXAMPLES / "line4.yaml"), "--duration", "1",
         "--json"],
    )  # fmt: skip
    assert result.exit_code == 0, result.output
    said = " ".join(result.output.split())  # the console wraps long lines
    assert "the netns backend cannot run here: no namespaces for you (test)" in said
    assert "using the user-space backend instead" in said
    summary = json.loads(result.output.strip().splitlines()[-1])
    assert sorted(summary) == ["N1", "N2", "N3", "N4"]  # the user-space nodes ran


def test_cleanup_without_namespaces_says_so(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(testbed, "unavailable", lambda: "not root (test)")
    result = CliRunner().invoke(main, ["emulate", "--cleanup"])
    assert result.exit_code == 0
    assert "nothing to clean: not root (test)" in result.output


def test_emulate_needs_a_scenario_unless_cleaning() -> None:
    result = CliRunner().invoke(main, ["emulate"])
    assert result.exit_code == 2 and "give a SCENARIO_FILE" in result.output
