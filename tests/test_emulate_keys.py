"""`mso emulate` overlays get a key of their own per run (none given), left for the user who
started the emulator only, so any other local user who has mso cannot join a loopback overlay
with the built-in development key; an empty key is an error, never a fall-back to it."""

from __future__ import annotations

import asyncio
import json
import os
import stat
import subprocess
import sys
import tempfile
from pathlib import Path

import pytest
from click.testing import CliRunner

from mso.cli import main
from mso.client import DEFAULT_KEY, overlay_key, request
from mso.emu.controller import Emulator
from mso.emu.overlays import key_file, key_for, overlays_dir, state_file
from mso.errors import MsoError
from mso.protocol import messages as m
from mso.scenario import loads_scenario

PAIR = "name: pair\nnodes: {N1: {}, N2: {}}\nlinks: [[N1, N2]]\n"


@pytest.fixture(autouse=True)
def private_tmp(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))
    monkeypatch.setenv("TMPDIR", str(tmp_path))
    monkeypatch.setenv("MSO_RUN_DIR", str(tmp_path))  # where overlays_dir() looks
    monkeypatch.delenv("MSO_KEY", raising=False)


def cli(*args: str) -> tuple[int, str, str]:
    result = CliRunner().invoke(main, list(args))
    return result.exit_code, result.stdout, result.stderr


def test_an_emulated_overlay_has_a_random_key_only_its_user_holds() -> None:
    async def run() -> None:
        emu, other = Emulator(loads_scenario(PAIR)), Emulator(loads_scenario(PAIR))
        await emu.start()
        try:
            await other.start()
            try:
                assert emu.key and other.key and len({emu.key, other.key, DEFAULT_KEY}) == 3
                path = key_file(str(emu.name))
                assert path.read_text().strip() == emu.key
                assert stat.S_IMODE(path.stat().st_mode) == 0o600
                assert stat.S_IMODE(overlays_dir().stat().st_mode) == 0o700
                assert emu.key not in state_file(str(emu.name)).read_text()
                # this user's commands find it, by overlay name or by a node's address
                code, out, err = await asyncio.to_thread(
                    cli, "status", "--json", "--overlay", str(emu.name)
                )
                assert code == 0, err
                assert sorted(json.loads(out)) == ["N1", "N2"]
                assert key_for(emu.address("N2")) == emu.key
                # what any local user could try: the development key is refused
                with pytest.raises(MsoError, match="wrong overlay key"):
                    await request(emu.address("N1"), m.StatusRequest(), key=DEFAULT_KEY)
            finally:
                await other.stop()
        finally:
            await emu.stop()
        assert not path.exists()

    asyncio.run(run())


def test_a_key_file_others_could_read_or_write_is_not_used() -> None:
    overlays_dir().mkdir(parents=True)
    state_file("x").write_text(json.dumps({"pid": os.getpid(), "nodes": {"N1": "127.0.1.1:9"}}))
    key_file("x").write_text("planted\n")
    key_file("x").chmod(0o644)
    assert key_for("127.0.1.1:9") is None
    key_file("x").chmod(0o600)
    assert key_for("127.0.1.1:9") == "planted"


def test_an_empty_key_is_an_error_not_the_development_key(tmp_path: Path) -> None:
    with pytest.raises(MsoError, match="empty overlay key"):
        overlay_key("")
    with pytest.raises(MsoError, match="empty overlay key"):
        Emulator(loads_scenario(PAIR), key="")
    scenario = tmp_path / "pair.yaml"
    scenario.write_text(PAIR)
    for args in (
        ["emulate", str(scenario), "--key", ""],
        ["status", "--via", "127.0.0.1:9", "--key", ""],
    ):
        code, out, err = cli(*args)
        assert code == 2, (args, out, err)
        assert err.count("\n") == 1 and "empty overlay key" in err, err


@pytest.mark.parametrize("key", [None, DEFAULT_KEY])
def test_the_development_key_is_refused_beyond_loopback(key: str | None) -> None:
    """A node never listens elsewhere with the development key (192.0.2.1 is TEST-NET: were
    the check gone, binding it would fail differently)."""
    cmd = [sys.executable, "-m", "mso", "node", "--id", "N1", "--listen", "192.0.2.1:0"]
    env = {k: v for k, v in os.environ.items() if k != "MSO_KEY"}
    if key is not None:
        cmd += ["--key", key]
    done = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=30)
    assert done.returncode == 2, done.stderr
    assert "refusing to listen beyond loopback with the built-in development key" in done.stderr
