"""Each running emulator is an overlay with its own name and state file, so two on one machine
never answer for each other; `mso emulate --no-manage` reaches every node."""

from __future__ import annotations

import asyncio
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import pytest
from click.testing import CliRunner

from mso.cli import main
from mso.emu.controller import Emulator
from mso.emu.overlays import (
    _claim,
    find_overlay,
    overlays_dir,
    running_overlays,
    state_file,
)
from mso.errors import MsoError
from mso.scenario import loads_scenario

PAIR = """
name: pair
nodes: {N1: {}, N2: {}}
links: [[N1, N2]]
"""


@pytest.fixture(autouse=True)
def private_tmp(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Overlays of other tests (and of a user's own emulator) stay out of sight."""
    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))
    monkeypatch.setenv("TMPDIR", str(tmp_path))
    monkeypatch.setenv("MSO_RUN_DIR", str(tmp_path))  # where overlays_dir() looks


def cli(*args: str) -> tuple[int, str, str]:
    result = CliRunner().invoke(main, list(args))
    return result.exit_code, result.stdout, result.stderr


def dead_pid() -> int:
    proc = subprocess.Popen([sys.executable, "-c", "pass"])
    proc.wait()
    return proc.pid


def write(name: str, pid: int, nodes: dict[str, str]) -> None:
    overlays_dir().mkdir(parents=True, exist_ok=True)
    state_file(name).write_text(json.dumps({"name": name, "pid": pid, "nodes": nodes}))


def test_names_are_claimed_once_and_stale_state_is_cleared() -> None:
    write("line", os.getpid(), {"N1": "127.0.1.1:1"})  # a live emulator holds "line"
    write("ghost", dead_pid(), {"N1": "127.0.1.1:2"})  # one killed without cleaning up
    assert _claim(None, "line") == "line-2"
    assert _claim(None, "my line!") == "my-line"
    with pytest.raises(MsoError, match="'line' is already running; choose another --name"):
        _claim("line", "whatever")
    with pytest.raises(MsoError, match="--name: expected letters"):
        _claim("a/b", "x")
    assert sorted(running_overlays()) == ["line", "line-2", "my-line"]
    assert not state_file("ghost").exists()
    # claimed but not started yet (no nodes): not a candidate for a command
    assert find_overlay(None) == ("line", json.loads(state_file("line").read_text()))
    with pytest.raises(MsoError, match=r"no running overlay named 'ghost' \(running: line\)"):
        find_overlay("ghost")


def test_two_emulators_side_by_side() -> None:
    async def run() -> None:
        managed = Emulator(loads_scenario(PAIR))
        frozen = Emulator(loads_scenario(PAIR), manage=False)
        await managed.start()
        try:
            await frozen.start()
            try:
                assert (managed.name, frozen.name) == ("pair", "pair-2")
                code, _, err = await asyncio.to_thread(cli, "status")
                assert code == 2 and "2 overlays are running (pair, pair-2)" in err
                code, _, err = await asyncio.to_thread(cli, "status", "--via", "N1")
                assert code == 2 and "'N1' is in 2 running overlays" in err
                for emu, manage in ((managed, True), (frozen, False)):
                    code, out, err = await asyncio.to_thread(
                        cli, "status", "--json", "--overlay", str(emu.name), "--via", "N2"
                    )
                    assert code == 0, err
                    nodes = json.loads(out)
                    assert sorted(nodes) == ["N1", "N2"]
                    assert {st["management"]["enabled"] for st in nodes.values()} == {manage}
                code, out, err = await asyncio.to_thread(
                    cli, "status", "--json", "--watch", "0.2", "--count", "2", "--overlay", "pair"
                )
                assert code == 0, err
                assert [sorted(json.loads(line)) for line in out.splitlines()] == [["N1", "N2"]] * 2
                code, out, _ = await asyncio.to_thread(cli, "overlays", "--json")
                listed = json.loads(out)
                assert listed["pair-2"]["nodes"] == {n: frozen.address(n) for n in frozen.nodes}
                assert "key" not in json.dumps(listed)
            finally:
                await frozen.stop()
            assert not state_file("pair-2").exists()
            code, out, err = await asyncio.to_thread(cli, "status", "--json")  # the one left
            assert code == 0, err
            assert sorted(json.loads(out)) == ["N1", "N2"]
        finally:
            await managed.stop()
        code, _, err = await asyncio.to_thread(cli, "status")
        assert code == 2 and "no emulator running" in err

    asyncio.run(run())


def test_log_folders_of_dead_emulators_are_cleaned_and_kept_ones_after_a_day(
    tmp_path: Path,
) -> None:
    from mso.emu.overlays import KEPT_FILE, OWNER_FILE, clean_stale_logs, make_log_dir

    def folder(name: str, pid: int | None, kept_s_ago: float | None = None) -> Path:
        d = tmp_path / name
        d.mkdir()
        if pid is not None:
            (d / OWNER_FILE).write_text(f"{pid}\n")
        if kept_s_ago is not None:
            (d / KEPT_FILE).write_text("a node crashed\n")
            t = time.time() - kept_s_ago
            os.utime(d / KEPT_FILE, (t, t))
        return d

    dead = dead_pid()
    gone = folder("mso-emu-gone", dead)
    running = folder("mso-emu-running", os.getpid())
    fresh = folder("mso-emu-kept", dead, kept_s_ago=60)
    old = folder("mso-netns-old", dead, kept_s_ago=2 * 86400)
    other = folder("mso-emu-other", None)  # no owner file: not known to be an emulator's
    assert sorted(clean_stale_logs(tmp_path)) == sorted([gone, old])
    assert running.exists() and fresh.exists() and other.exists()
    made = make_log_dir("mso-emu-")  # under $TMPDIR (this test's), marked as this process's
    assert made.parent == tmp_path and (made / OWNER_FILE).read_text().strip() == str(os.getpid())


def test_overlays_are_found_whatever_the_tmpdir_and_in_other_users_folders_one_may_read(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    from mso.emu.overlays import folder_of

    write("mine", os.getpid(), {"N1": "127.0.1.1:1"})
    theirs = tmp_path / "mso-54321" / "overlays"  # another user's (this test may read it)
    theirs.mkdir(parents=True)
    (theirs / "theirs.json").write_text(json.dumps({"pid": os.getpid(), "nodes": {"A": "x:1"}}))
    (theirs / "gone.json").write_text(json.dumps({"pid": dead_pid(), "nodes": {"B": "x:2"}}))
    monkeypatch.setenv("TMPDIR", str(tmp_path / "elsewhere"))  # another shell's TMPDIR
    assert sorted(running_overlays(everyone=True)) == ["mine", "theirs"]
    assert sorted(running_overlays()) == ["mine"]  # this user's own, by default
    assert find_overlay("theirs")[1]["nodes"] == {"A": "x:1"} and folder_of("theirs") == theirs
    assert (theirs / "gone.json").exists()  # another user's leftovers are theirs to clean
    code, out, _ = cli("overlays")
    assert code == 0 and "mine:" in out and "theirs:" in out
