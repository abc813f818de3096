"""The CLI against a running emulator, as a user drives it from a second terminal."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

from click.testing import CliRunner

from mso.cli import main
from mso.emu.overlays import running_overlays, state_file
from terminal import ctrl_c_as_in_a_terminal
from waits import patience

TESTS = Path(__file__).resolve().parent

LINE = """
name: line
nodes: {N1: {}, N2: {}, N3: {}, N4: {}}
links: [[N1, N2], [N2, N3], [N3, N4]]
"""

APP = """
name: pipe
vertices:
  src: {code: runtime_vertices:CountingSource, pinned: N1, rate: 100,
        output: runtime_vertices:Num}
  mid: {code: runtime_vertices:Counter, output: runtime_vertices:Num}
  sink: {code: runtime_vertices:Recorder, pinned: N4}
edges: [[src, mid], [mid, sink]]
"""


def cli(*args: str) -> tuple[int, str, str]:
    """The CLI as a user types it; should someone else's emulator run on this machine too
    (the default is then ambiguous, and the CLI says so), this test's is named."""
    others = set(running_overlays()) - {"line"}
    env = {"MSO_OVERLAY": "line"} if others else {}
    result = CliRunner().invoke(main, list(args), env=env)
    return result.exit_code, result.stdout, result.stderr


def test_emulate_then_drive_it_from_another_terminal(tmp_path: Path) -> None:
    (tmp_path / "line.yaml").write_text(LINE)
    (tmp_path / "pipe.yaml").write_text(APP)
    env = dict(os.environ, PYTHONPATH=f"{TESTS}{os.pathsep}{os.environ.get('PYTHONPATH', '')}")
    emu = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "mso",
            "emulate",
            "line.yaml",
            "--app",
            "pipe.yaml",
            "--duration",
            "30",
        ],
        cwd=tmp_path,
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        preexec_fn=ctrl_c_as_in_a_terminal,
    )
    try:
        assert emu.stdout is not None
        deadline = time.monotonic() + patience(20)
        seen = ""
        while "deployed pipe" not in seen and time.monotonic() < deadline:
            seen += emu.stdout.readline()
        assert "deployed pipe" in seen, seen
        assert "line" in running_overlays()  # named after its scenario
        code, out, err = cli("status", "--json")
        assert code == 0, err
        nodes = json.loads(out)
        assert sorted(nodes) == ["N1", "N2", "N3", "N4"]
        before = next(n for n, st in nodes.items() if "mid" in st["apps"]["pipe"]["vertices"])
        code, out, err = cli("relocate", "mid", "--downstream", "--json")  # --app: the only one
        assert code == 0, err
        assert json.loads(out)["node"] != before
        code, out, err = cli("relocate", "src", "--downstream")
        assert code == 2 and "end of chain" in err
        code, out, err = cli("remap", "chain", "src-mid-sink", "--json")
        assert code == 0, err
        code, out, err = cli("remap", "--all", "--via", "N3")
        assert code == 0 and "remapped in" in out, err
        deadline = time.monotonic() + patience(10.0)
        while True:  # until 50 events have passed the moves and remaps to the sink
            code, out, _ = cli("status", "--json", "--via", "N2")
            sink = json.loads(out)["N4"]["apps"]["pipe"]["vertices"]["sink"]["stats"]
            if sink["count"] > 50 or time.monotonic() > deadline:
                break
        assert sink["count"] > 50 and sink["repeats"] == 0 and sink["out_of_order"] == 0
        emu.send_signal(signal.SIGINT)  # Ctrl-C: everything stops, cleanly
        rest, _ = emu.communicate(timeout=60)  # the summary and the stop, on a loaded CI box
        assert emu.returncode == 0, rest
        assert "Traceback" not in rest
    finally:
        if emu.poll() is None:
            emu.kill()
            emu.wait()
    assert not state_file("line").exists()
