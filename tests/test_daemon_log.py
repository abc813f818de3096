"""``mso node`` on a fleet: what the core reports as ``Happened`` (every move with who asked and
how long it took, deploys, failures), the logfmt lines the daemon writes from it, and a config
file that holds every option, the rule settings included."""

from __future__ import annotations

import logging
import math
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path
from types import SimpleNamespace

import pytest

from mso.daemon.config import NodeFlags, settle
from mso.daemon.logs import LogfmtFormatter, logfmt
from mso.errors import MsoError
from mso.protocol import messages as m
from mso.protocol.events import Happened
from mso.sim.runner import Simulation
from test_runtime_sim import PIPE, deploy, line
from waits import patience


def test_the_core_reports_deploys_moves_and_failures_for_its_driver_to_log() -> None:
    sim = Simulation(line(4))
    for core in sim.cores.values():
        core.drain_happened()
    assert deploy(sim, PIPE).ok
    seen = {n: core.drain_happened() for n, core in sim.cores.items()}
    # the app's holders (its origin and hosts) log its deploy; a node that takes no part in
    # it holds none of it and logs nothing of it (issue 24.1)
    holders = {n for n, core in sim.cores.items() if "pipe" in core.apps}
    assert {"N1", "N4"} <= holders, holders  # the origin and src's host, and sink's
    assert all(Happened("deploy", "pipe", by="N1") in seen[n] for n in holders), seen
    assert not any(hs for n, hs in seen.items() if n not in holders), seen
    old = next(n for n, c in sim.cores.items() if "mid" in c.instances("pipe"))
    target = "N3" if old != "N3" else "N2"
    sim.request("N1", m.RelocateRequest("pipe", "mid", target=target), client=5)
    sim.run_until(sim.now + 1.0)
    (move,) = [h for h in sim.cores["N1"].drain_happened() if h.what == "relocation"]
    assert (move.app, move.subject, move.detail, move.by) == (
        "pipe",
        "mid",
        f"{old} -> {target}",
        "operator",
    )
    assert move.took_ms is not None and move.took_ms > 0 and not move.error
    hosted = [h for h in sim.cores[target].drain_happened() if h.what == "hosted"]
    assert [h.subject for h in hosted] == ["mid"]
    sim.crash("N4")  # its daemon: silent with a route, declared (out of reach only, it would
    sim.run_until(sim.now + 3.0)  # be held unreachable: the sink pinned there cannot move)
    failed = [h for h in sim.cores["N3"].drain_happened() if h.what == "peer_failed"]
    assert [h.subject for h in failed] == ["N4"]
    assert sim.cores["N3"].drain_happened() == []  # drained: each is logged once


def test_a_log_record_is_one_logfmt_line() -> None:
    assert logfmt({"a": 1, "b": "two words", "c": None, "d": "", "e": 'say "hi"'}) == (
        'a=1 b="two words" e="say \\"hi\\""'
    )
    record = logging.LogRecord("mso.node", logging.WARNING, "", 0, "x\ny", None, None)
    line_ = LogfmtFormatter("N1").format(record)
    assert "\n" not in line_ and line_.endswith('level=warning node=N1 msg="x\\ny"')


@pytest.mark.usefixtures("keep_allowlist")
def test_a_config_file_holds_every_option_rules_included(tmp_path: Path) -> None:
    cfg = tmp_path / "n1.yaml"
    cfg.write_text(
        "id: N1\nlisten: 127.0.0.1:7100\nheartbeat: 0.2\ndead_after: 1.0\n"
        "metrics: 127.0.0.1:9100\nverbose: true\n"
        "rules: {vertex_interval_s: 10, margin: 0.05, warmup_s: 5}\n"
    )
    s = settle(NodeFlags(config_file=cfg, rules=("margin=0.2",)))
    assert (s.heartbeat_s, s.dead_after_s, s.metrics_at, s.verbose) == (
        0.2,
        1.0,
        ("127.0.0.1", 9100),
        True,
    )
    assert s.rules is not None
    assert (s.rules.vertex_interval_s, s.rules.margin, s.rules.warmup_s) == (10, 0.2, 5)
    assert settle(NodeFlags(node_id="N1")).rules is None  # the defaults
    cfg.write_text("id: N1\nrules: {vertex_interval: 10}\n")
    with pytest.raises(MsoError, match="unknown setting 'vertex_interval'"):
        settle(NodeFlags(config_file=cfg))
    with pytest.raises(MsoError, match="margin: expected a number >= 0"):
        settle(NodeFlags(node_id="N1", rules=("margin=-1",)))
    with pytest.raises(MsoError, match="--rule warmup_s: expected a float"):
        settle(NodeFlags(node_id="N1", rules=("warmup_s=soon",)))


def test_mso_node_logs_start_deploy_a_move_and_its_stop_on_sigterm(tmp_path: Path) -> None:
    """Two real nodes with fixed peers: N1's log says where it listens and how it routes, the
    deployment, an operator's relocation with its duration, and on SIGTERM one stop line."""
    from mso.api import Overlay

    ports = []
    for _ in range(2):
        with socket.socket() as s:
            s.bind(("127.0.0.1", 0))
            ports.append(s.getsockname()[1])
    tests = Path(__file__).resolve().parent
    env = {k: v for k, v in os.environ.items() if k not in ("MSO_KEY", "MSO_ENCRYPT")}
    env["PYTHONPATH"] = os.pathsep.join(p for p in (str(tests), env.get("PYTHONPATH")) if p)
    env["MSO_ALLOW_CODE"] = "runtime_vertices"
    logs = [tmp_path / "N1.log", tmp_path / "N2.log"]
    nodes = []
    for i, (me, other) in enumerate(((1, 2), (2, 1))):
        cmd = [sys.executable, "-m", "mso", "node", "--id", f"N{me}",
               "--listen", f"127.0.0.1:{ports[me - 1]}",
               "--peer", f"N{other}=127.0.0.1:{ports[other - 1]}", "--no-manage"]  # fmt: skip
        with logs[i].open("w") as out:
            nodes.append(subprocess.Popen(cmd, env=env, stdout=out, stderr=subprocess.STDOUT))
    app = tmp_path / "pipe.yaml"
    app.write_text(PIPE.replace("pinned: N4", "pinned: N2"))
    try:
        overlay = Overlay(f"127.0.0.1:{ports[0]}", timeout=30.0)
        deadline = time.monotonic() + patience(60.0)
        while True:  # until both listen and N1 has its peer (a loaded machine: seconds)
            try:
                if "N2" in overlay.status(everywhere=True):
                    break
            except MsoError:
                pass
            assert time.monotonic() < deadline, logs[0].read_text()
            time.sleep(0.1)
        assert overlay.deploy(app).ok
        where = overlay.status()
        host = next(n for n, st in where.items() if "mid" in st["apps"]["pipe"]["vertices"])
        to = "N2" if host == "N1" else "N1"
        overlay.relocate("pipe", "mid", target=to)
    finally:
        for p in nodes:
            p.send_signal(signal.SIGTERM)
        codes = [p.wait(20) for p in nodes]
    text = logs[0].read_text()
    lines = [ln for ln in text.splitlines() if ln.startswith("ts=")]
    assert f"event=start listen=127.0.0.1:{ports[0]} routes=static:N2 " in lines[0], text
    assert "operator_keys=off" in lines[0]
    assert any("event=deploy app=pipe by=N1" in ln for ln in lines), text
    (move,) = [ln for ln in lines if "event=relocation" in ln]
    assert f'vertex=mid move="{host} -> {to}" by=operator took_ms=' in move, move
    # the stop line is the last event (a reconnect to the peer stopping beside it may still log)
    (stop,) = [ln for ln in lines if "event=stop" in ln]
    assert [ln for ln in lines if " event=" in ln][-1] == stop, text
    assert "event=stop reason=SIGTERM" in stop and "relocation:1" in stop, text
    assert codes == [0, 0]


@pytest.mark.usefixtures("keep_allowlist")
def test_a_device_says_its_link_rate_in_its_config(tmp_path: Path) -> None:
    # configured, not measured: the routing view's shape of a link (the emulator's) wins
    from mso.net.base import LinkShape, Neighbour
    from mso.node.core import NodeCore
    from mso.node.driver import NodeDriver

    cfg = tmp_path / "n1.yaml"
    cfg.write_text("id: N1\nlink_mbps: 6.5\n")
    assert settle(NodeFlags(config_file=cfg)).link_mbps == {"*": 6.5}
    flags = ("2", "N2=54")  # the flags win; one peer's rate beside every other link's
    assert settle(NodeFlags(config_file=cfg, link_mbps=flags)).link_mbps == {"*": 2, "N2": 54}
    assert settle(NodeFlags(node_id="N1")).link_mbps == {}
    cfg.write_text("id: N1\nlink_mbps: {N2: 54, '*': 6.5}\n")
    assert settle(NodeFlags(config_file=cfg)).link_mbps == {"N2": 54.0, "*": 6.5}
    for bad in ("fast", "0", "{N2: -1}", "[1]"):
        cfg.write_text(f"id: N1\nlink_mbps: {bad}\n")
        with pytest.raises(MsoError, match="link_mbps: expected a rate in Mb/s > 0"):
            settle(NodeFlags(config_file=cfg))
    for bad in ("fast", "N2=", "=5", "N2=-1", "N2=nan"):
        with pytest.raises(MsoError, match="--link-mbps: expected RATE or PEER=RATE"):
            settle(NodeFlags(node_id="N1", link_mbps=(bad,)))
    shaped = {"N2": Neighbour("h", 1, LinkShape(11.0)), "N3": Neighbour("h", 2)}
    view = SimpleNamespace(neighbours=lambda: shaped)
    driver = SimpleNamespace(view=view, link_mbps={"*": 6.5, "N4": 2.0})
    rate = NodeDriver._link_rate
    got = [rate(driver, n) for n in ("N2", "N3", "N4", "N9")]  # type: ignore[arg-type]
    assert got == [11.0, 6.5, 2.0, 6.5]
    assert rate(SimpleNamespace(view=view, link_mbps={}), "N3") is None  # type: ignore[arg-type]
    core = NodeCore("N1", link_rates=lambda n: {"N2": 11.0, "N3": math.nan}.get(n))
    assert [core.link_rate(n) for n in ("N2", "N3", "N4")] == [11.0, None, None]
