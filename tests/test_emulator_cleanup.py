"""No node process outlives its emulator, even one killed outright (SIGKILL: no cleanup code
runs): each node watches the process that started it and stops when it is gone."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

from waits import patience

LINE = "name: orphans\nnodes: {N1: {}, N2: {}, N3: {}}\nlinks: [[N1, N2], [N2, N3]]\n"


def _children(pid: int) -> list[int]:
    kids = []
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                stat = (entry / "stat").read_text()
            except OSError:
                continue
            if int(stat.rsplit(")", 1)[1].split()[1]) == pid:
                kids.append(int(entry.name))
    return kids


def _running(pid: int) -> bool:
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except OSError:
        return False
    return state != "Z"  # a zombie has exited; only its parent's wait is missing


def test_nodes_stop_when_their_emulator_is_killed(tmp_path: Path) -> None:
    scenario = tmp_path / "line.yaml"
    scenario.write_text(LINE)
    env = dict(os.environ, TMPDIR=str(tmp_path), MSO_RUN_DIR=str(tmp_path))
    emu = subprocess.Popen(
        [sys.executable, "-m", "mso", "emulate", str(scenario), "--duration", "120"],
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )
    nodes: list[int] = []
    try:
        assert emu.stdout is not None
        for line in emu.stdout:  # the emulator says when its nodes run (bounded: it exits)
            if line.startswith("emulating"):
                break
        nodes = _children(emu.pid)
        assert len(nodes) == 3, nodes
        emu.send_signal(signal.SIGKILL)
        emu.wait(10)
        deadline = time.monotonic() + patience(15.0)
        while any(map(_running, nodes)) and time.monotonic() < deadline:
            time.sleep(0.1)  # polling processes: there is no event to wait on
        assert not [p for p in nodes if _running(p)]
    finally:
        for pid in [emu.pid, *nodes]:  # whatever is left: ours, by pid
            if _running(pid):
                os.kill(pid, signal.SIGKILL)
        emu.wait(10)
