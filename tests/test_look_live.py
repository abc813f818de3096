"""``mso echo``, ``mso hz``, ``mso logs`` and ``mso record`` on a running emulator, typed as a
user types them in a second terminal: a pipe app (src N1 -> mid -> sink N4) and a ROS app
replaying the shipped chatter bag (BagSource -> shout -> a sink) run side by side."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
from click.testing import CliRunner

from mso.cli import main
from test_cli_live import APP as PIPE
from test_cli_live import LINE as CLI_LINE
from waits import patience

pytest.importorskip("rosbags")
pytestmark = pytest.mark.slow

TESTS = Path(__file__).resolve().parent
NAME = "lookline"
LINE = CLI_LINE.replace("name: line", f"name: {NAME}")
STRING = "mso.ros2.types:std_msgs__msg__String"
CHATTER = f"""
name: chat
vertices:
  play: {{code: "mso.ros2:BagSource", pinned: N1, output: "{STRING}",
         params: {{path: "{TESTS / "data" / "ros2_chatter"}", rate: 0.5}}}}
  shout: {{code: "ros2_vertices:shout", output: "{STRING}"}}
  rec: {{code: "runtime_vertices:Recorder", pinned: N3}}
edges: [[play, shout], [shout, rec]]
"""


def cli(*args: str) -> tuple[int, str, str]:
    result = CliRunner().invoke(main, list(args), env={"MSO_OVERLAY": NAME})
    return result.exit_code, result.stdout, result.stderr


@pytest.fixture(scope="module")
def emulator(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Path]:
    tmp = tmp_path_factory.mktemp("look")
    (tmp / "line.yaml").write_text(LINE)
    (tmp / "pipe.yaml").write_text(PIPE)
    (tmp / "chat.yaml").write_text(CHATTER)
    path = os.environ.get("PYTHONPATH", "")
    env = dict(os.environ, PYTHONPATH=f"{TESTS}{os.pathsep}{path}" if path else str(TESTS))
    emu = subprocess.Popen(
        [sys.executable, "-m", "mso", "emulate", "line.yaml", "--app", "pipe.yaml",
         "--name", NAME, "--duration", "120"],
        cwd=tmp, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
    )  # fmt: skip
    try:
        assert emu.stdout is not None
        deadline = time.monotonic() + patience(30)
        seen = ""
        while "deployed pipe" not in seen and time.monotonic() < deadline:
            seen += emu.stdout.readline()
        assert "deployed pipe" in seen, seen
        yield tmp
    finally:
        emu.terminate()
        try:
            emu.wait(timeout=patience(20))
        except subprocess.TimeoutExpired:
            emu.kill()
            emu.wait()


def test_echo_prints_decoded_events_rate_limited(emulator: Path) -> None:
    code, out, err = cli("echo", "pipe", "mid->sink", "--count", "5", "--json", "--rate", "5")
    assert code == 0, err
    lines = [json.loads(line) for line in out.splitlines()]
    assert len(lines) == 5 and all(ln["node"] == "N4" for ln in lines), lines
    seqs = [ln["seq"] for ln in lines]
    assert seqs == sorted(seqs) and seqs[-1] - seqs[0] >= 4 * 10, seqs  # ~1 in 20 at 100/s
    assert all(ln["event"]["seq"] == ln["seq"] for ln in lines), lines  # decoded, field names
    code, out, err = cli("echo", "pipe", "src:mid", "--count", "3")
    assert code == 0, err
    assert [line.split(" ", 1)[0][0] for line in out.splitlines()] == ["#"] * 3, out
    assert '"seq":' in out and "events while looking" in err, (out, err)
    code, out, err = cli("echo", "pipe", "sink->src", "--count", "1")
    assert code == 2 and "no edge 'sink->src'" in err, (code, err)


def test_hz_reports_the_rate_and_delay(emulator: Path) -> None:
    code, out, err = cli("hz", "pipe", "mid", "--count", "3", "--every", "1", "--json")
    assert code == 0, err
    reports = [json.loads(line) for line in out.splitlines()]
    assert len(reports) == 3, reports
    last = reports[-1]
    assert 80 <= last["rate"] <= 120, last  # the source makes 100 a second
    assert 0 < last["delay_ms"]["p50"] <= last["delay_ms"]["p99"] < 1000, last


def test_logs_prints_a_nodes_structured_lines(emulator: Path) -> None:
    code, out, err = cli("logs", "N1", "-n", "50")
    assert code == 0, err
    assert "node=N1" in out and "event=deploy" in out, out
    code, out, err = cli("logs", "N4", "--json", "-n", "50")
    assert code == 0, err
    records = [json.loads(line) for line in out.splitlines()]
    assert records and all(r.get("node") == "N4" for r in records if "level" in r), records
    code, _, err = cli("logs", "N9")
    assert code == 2 and "no running emulator has a node 'N9'" in err, err


def test_logs_follow_prints_lines_as_the_node_writes_them(emulator: Path) -> None:
    """``mso logs N1 --follow`` in a second terminal, while an app is deployed and stopped
    (N1, the app's origin: only the nodes that take part in an app hold it and log its deploy)."""
    (emulator / "chat2.yaml").write_text(CHATTER.replace("name: chat", "name: chat2"))
    env = dict(os.environ, MSO_OVERLAY=NAME)
    follower = subprocess.Popen(
        [sys.executable, "-m", "mso", "logs", "N1", "--follow", "-n", "1"],
        env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
    )  # fmt: skip
    try:
        assert follower.stdout is not None
        seen: list[str] = []
        reader = threading.Thread(target=lambda: seen.extend(follower.stdout or ()), daemon=True)
        reader.start()
        deadline = time.monotonic() + patience(20)
        while not seen and time.monotonic() < deadline:  # its last line: it has the log open
            time.sleep(0.05)
        assert seen, "mso logs printed nothing"
        assert cli("deploy", str(emulator / "chat2.yaml"))[0] == 0
        assert cli("undeploy", "chat2")[0] == 0
        deadline = time.monotonic() + patience(20)
        while time.monotonic() < deadline and not any("app=chat2" in ln for ln in list(seen)):
            time.sleep(0.1)  # polls what the reader thread collected; bounded by the deadline
        assert any("event=deploy" in ln and "app=chat2" in ln for ln in seen), seen
        assert all("node=N1" in ln for ln in seen if "level=" in ln), seen
    finally:
        follower.terminate()
        follower.wait(timeout=patience(10))


def test_record_to_a_bag_that_bagsource_replays(emulator: Path, tmp_path: Path) -> None:
    code, out, err = cli("deploy", str(emulator / "chat.yaml"))
    assert code == 0, err
    bag = tmp_path / "shout.mcap"
    code, out, err = cli("record", "chat", "shout", "-o", str(bag), "--count", "4")
    assert code == 0, err
    assert "/chat/shout/rec: 4 messages" in out and f"wrote {tmp_path / 'shout'}" in out, out
    from mso.ros2 import BagSource

    src = BagSource(str(tmp_path / "shout"))
    src.open()
    got = [e for e in src if e is not None]
    src.close()
    texts = [e.data for e in got]
    assert len(texts) == 4 and all(t.startswith("HELLO WORLD ") for t in texts), texts
    numbers = [int(t.rsplit(" ", 1)[1]) for t in texts]
    assert numbers == list(range(numbers[0], numbers[0] + 4)), numbers  # in order, none missed
    code, _, err = cli("record", "pipe", "mid", "-o", str(tmp_path / "num"), "--count", "1")
    assert code == 2 and "not a ROS message" in err, err
