"""The emulator never gives up: nodes killed by hand are told and can be restarted, scripted
and operator faults in any order, commands from the API over the emulator's socket, and a
seeded random fault sequence that ends with every node in the summary."""

from __future__ import annotations

import asyncio
import os
import signal
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from click.testing import CliRunner

from mso.api import CommandFailed, EmulatorControl
from mso.cli import main
from mso.emu.commands import Commands, ControlSocket
from mso.emu.controller import Emulator
from mso.emu.faultplay import random_sequence
from mso.errors import MsoError
from mso.scenario import loads_scenario
from runtime_vertices import pipe_app
from terminal import ctrl_c_as_in_a_terminal
from waits import patience

TESTS = Path(__file__).resolve().parent

MESH = """
name: mesh
link_defaults: {delay_ms: 0.5}
nodes: {N1: {}, N2: {}, N3: {}, N4: {}}
links: [[N1, N2], [N2, N4], [N1, N3], [N3, N4]]
"""


@pytest.fixture(autouse=True)
def node_pythonpath(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> Iterator[None]:
    path = os.environ.get("PYTHONPATH", "")
    monkeypatch.setenv("PYTHONPATH", f"{TESTS}{os.pathsep}{path}" if path else str(TESTS))
    monkeypatch.setenv("MSO_RUN_DIR", str(tmp_path))
    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))  # node logs kept: the test's
    yield


class Told:
    """What the emulator tells, with a wait for a sentence (an event, not a sleep)."""

    def __init__(self) -> None:
        self.lines: list[str] = []
        self._changed = asyncio.Event()

    def __call__(self, at: float, text: str) -> None:
        self.lines.append(text)
        self._changed.set()

    async def wait_for(self, words: str, timeout: float = 20.0) -> str:
        async def seen() -> str:
            while True:
                for line in self.lines:
                    if words in line:
                        return line
                self._changed.clear()
                await self._changed.wait()

        return await asyncio.wait_for(seen(), patience(timeout))


async def answering(emu: Emulator, timeout: float = 20.0) -> dict[str, Any]:
    """The status once every node answers it (nodes that restarted rejoin in a moment)."""
    loop = asyncio.get_running_loop()
    deadline = loop.time() + patience(timeout)
    while True:
        nodes = await emu.status()
        if sorted(nodes) == sorted(emu.nodes) or loop.time() > deadline:
            return nodes
        await asyncio.sleep(0.2)  # membership converging: nothing to wait on from outside


def test_a_node_killed_by_hand_is_told_and_comes_back_by_command() -> None:
    async def run() -> tuple[list[str], dict[str, Any]]:
        emu = Emulator(loads_scenario(MESH))
        told = Told()
        emu.tell = told
        await emu.start()
        try:
            proc = emu.nodes["N2"].process
            assert proc is not None
            os.kill(proc.pid, signal.SIGKILL)  # a user's kill -9, no command
            await told.wait_for("N2 died (killed by hand")
            assert emu.scenario.network.neighbours("N2") == []
            with pytest.raises(MsoError, match="N2 is not running"):
                await emu.fail("N2")
            said = await emu.restart("N2")
            assert "N2 restarted" in said
            assert sorted(emu.scenario.network.neighbours("N2")) == ["N1", "N4"]
            with pytest.raises(MsoError, match="still running"):
                await emu.restart("N2")
            return told.lines, await answering(emu)
        finally:
            await emu.stop()

    lines, nodes = asyncio.run(run())
    assert sorted(nodes) == ["N1", "N2", "N3", "N4"]
    assert any("N2 died" in line for line in lines)


def test_a_scripted_restart_brings_back_a_node_killed_by_hand() -> None:
    """The repro of issue 23: a scripted fail and restart of one node and a kill -9 of
    another; the run goes on and its status has every node it should."""
    changes = "changes:\n  - {at: 1.0, fail: N3}\n  - {at: 3.0, restart: N3}\n"
    scenario = loads_scenario(MESH + changes)

    async def run() -> dict[str, Any]:
        emu = Emulator(scenario)
        told = Told()
        emu.tell = told
        await emu.start()
        try:
            # the script's times from now, not from the start (a loaded machine starts slowly)
            playing = asyncio.create_task(emu.play(asyncio.get_running_loop().time()))
            proc = emu.nodes["N2"].process
            assert proc is not None
            os.kill(proc.pid, signal.SIGKILL)
            await told.wait_for("N2 died")
            await told.wait_for("N3 restarts (scripted)")
            await asyncio.wait_for(playing, patience(30.0))
            assert emu.running("N3") and not emu.running("N2")
            await emu.restart("N2")
            return await answering(emu, 40.0)
        finally:
            await emu.stop()

    assert sorted(asyncio.run(run())) == ["N1", "N2", "N3", "N4"]


def test_commands_reach_a_running_emulator_through_the_api_and_the_cli() -> None:
    async def run() -> None:
        emu = Emulator(loads_scenario(MESH), name="meshy")
        await emu.start()
        commands = Commands(emu)
        control = ControlSocket(commands, "meshy")
        await control.start()
        try:
            api = EmulatorControl("meshy")
            assert await asyncio.to_thread(api.cut, "N1", "N2") == "cut N1-N2"
            assert emu.scenario.network.link("N1", "N2") is None
            with pytest.raises(CommandFailed, match="N2-N1 is already cut"):
                await asyncio.to_thread(api.cut, "N2", "N1")
            with pytest.raises(CommandFailed, match="unknown node 'N9'"):
                await asyncio.to_thread(api.fail, "N9")
            with pytest.raises(CommandFailed, match="unknown command 'jump'"):
                await asyncio.to_thread(api.command, "jump N1")
            result = await asyncio.to_thread(
                CliRunner().invoke, main, ["emulator", "heal", "N1", "N2", "--overlay", "meshy"]
            )
            assert result.exit_code == 0, result.output
            assert "healed N1-N2" in result.stdout
            assert emu.scenario.network.link("N1", "N2") is not None
            result = await asyncio.to_thread(
                CliRunner().invoke, main, ["emulator", "fail", "N9", "--overlay", "meshy"]
            )
            assert result.exit_code == 2 and "unknown node 'N9'" in result.stderr
            assert await asyncio.to_thread(api.stop) and commands.done.is_set()
        finally:
            await control.stop()
            await emu.stop()

    asyncio.run(run())
    result = CliRunner().invoke(main, ["emulator", "cut", "N1", "N2", "--overlay", "gone"])
    assert result.exit_code == 2 and "no running overlay named 'gone'" in result.stderr


def test_a_seeded_random_fault_sequence_ends_with_every_node_in_the_summary() -> None:
    scenario = loads_scenario(MESH)
    links = sorted(scenario.network.links)
    steps = random_sequence(7, list(scenario.network.nodes), links, 10, keep=("N1",))
    assert {s.kind for s in steps} >= {"fail", "restart", "cut"}

    async def run() -> tuple[dict[str, Any], list[str]]:
        emu = Emulator(scenario)
        told = Told()
        emu.tell = told
        await emu.start()
        commands = Commands(emu)
        try:
            reply = await emu.deploy(pipe_app(50), "pipe.yaml", "N1")
            assert reply.ok, reply.error
            for step in steps:
                if step.kind == "kill":
                    proc = emu.nodes[step.node].process
                    assert proc is not None
                    os.kill(proc.pid, signal.SIGKILL)
                    await asyncio.to_thread(proc.wait, 10)
                    continue
                answer = await commands.reply(step.line)
                assert answer["ok"], (step, answer)
                await asyncio.sleep(0.3)  # the pace of the faults, not a synchronisation
            return await answering(emu, 30.0), told.lines
        finally:
            await emu.stop()

    nodes, lines = asyncio.run(run())
    assert sorted(nodes) == ["N1", "N2", "N3", "N4"], lines
    assert not [line for line in lines if "did not come back" in line]


def test_an_empty_battery_stops_an_emulated_robot_and_a_restart_replaces_it() -> None:
    scenario = loads_scenario(MESH.replace("N2: {}", "N2: {battery_wh: 0.0005}"))  # about 2 s

    async def run() -> tuple[str, str, set[str]]:
        emu = Emulator(scenario)
        told = Told()
        emu.tell = told
        await emu.start()
        try:
            line = await told.wait_for("battery is empty", timeout=30.0)
            emptied = set(emu.emptied)
            assert emu.scenario.network.neighbours("N2") == []
            return line, await emu.restart("N2"), emptied
        finally:
            await emu.stop()

    line, restarted, emptied = asyncio.run(run())
    assert line == "N2's battery is empty: it stopped (fail-stop)" and emptied == {"N2"}
    assert restarted.startswith("N2 restarted with a full battery")


def test_a_move_is_told_once_with_who_asked_and_how_long_it_took() -> None:
    from mso.cli.story import MoveWatch

    async def run() -> tuple[list[tuple[float, str]], list[tuple[float, str]]]:
        emu = Emulator(loads_scenario(MESH), manage=False)
        await emu.start()
        try:
            reply = await emu.deploy(pipe_app(50), "pipe.yaml", "N1")
            assert reply.ok, reply.error
            watch = MoveWatch()
            watch.placed("pipe", dict(reply.placement))
            to = "N3" if reply.placement["mid"] == "N2" else "N2"
            moved = await emu.relocate("pipe", "mid", target=to)
            assert moved.ok, moved.error
            first = watch.moves(await answering(emu), "pipe", emu.now())
            return first, watch.moves(await answering(emu), "pipe", emu.now())
        finally:
            await emu.stop()

    first, again = asyncio.run(run())
    ((_, line),) = first
    assert "pipe: mid " in line and " ms, asked by an operator (mso relocate)" in line, line
    assert again == []  # told once


def test_ctrl_c_prints_the_summary_and_stops_every_node(tmp_path: Path) -> None:
    """`mso emulate` with no --duration: Ctrl-C (SIGINT) ends the run with its summary (what
    happened, then every node's figures), as the README says; a piped console command is
    carried out first."""
    import subprocess
    import sys

    scenario = tmp_path / "mesh.yaml"
    scenario.write_text(MESH)
    env = dict(os.environ, TMPDIR=str(tmp_path))
    proc = subprocess.Popen(
        [sys.executable, "-m", "mso", "emulate", str(scenario), "--name", "ctrlc"],
        env=env, stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
        text=True, preexec_fn=ctrl_c_as_in_a_terminal,
    )  # fmt: skip
    assert proc.stdin is not None and proc.stdout is not None
    try:
        proc.stdin.write("cut N1 N2\n")
        proc.stdin.flush()
        for line in proc.stdout:  # bounded: the emulator says so, or exits
            if "cut N1-N2" in line:
                break
        proc.send_signal(signal.SIGINT)
        out, _ = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(10)
    assert proc.returncode == 0, out
    assert "summary (stopped early: Ctrl-C or SIGTERM)" in out, out
    assert "command 'cut N1 N2': cut N1-N2" in out and "N4 " in out.split("nodes\n", 1)[1], out


def test_a_node_that_does_not_answer_is_passed_over_not_fatal() -> None:
    async def run() -> dict[str, Any]:
        emu = Emulator(loads_scenario(MESH))
        await emu.start()
        proc = emu.nodes["N1"].process
        assert proc is not None
        try:
            os.kill(proc.pid, signal.SIGSTOP)  # alive, silent: every request to it times out
            return await emu.status(timeout=2.0)  # asked through N2 instead
        finally:
            os.kill(proc.pid, signal.SIGCONT)
            await emu.stop()

    nodes = asyncio.run(run())
    assert "N2" in nodes and "N1" not in nodes  # the next live node answered for the overlay
