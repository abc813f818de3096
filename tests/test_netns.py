"""The netns backend: one network namespace per node, babeld routing, the kernel forwarding,
each node on the kernel routing view. A 4-node line whose links move, a 6-node mesh that loses
a relay; the line again with batmand, whose routes live in table 66 behind policy rules.
Skipped, with the reason, only where namespaces (or babeld) are unavailable; in CI (root,
CI=true) the test setup installs babeld, batmand and nftables from Debian's packages."""

from __future__ import annotations

import asyncio
import os
import shutil
import subprocess
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from mso.emu.netns.testbed import namespaces, prefix
from mso.scenario import loads_scenario
from runtime_vertices import pipe_app
from waits import until

TESTS = Path(__file__).resolve().parent
APP = pipe_app(100)  # mid declares its output: the sink gets Num events and checks their order


def _install_in_ci() -> None:
    """CI runs as root on a fresh machine: the feature's Debian packages come from here."""
    if os.environ.get("CI") != "true" or os.geteuid() != 0 or shutil.which("apt-get") is None:
        return
    if shutil.which("babeld") and shutil.which("batmand") and shutil.which("nft"):
        return
    env = {**os.environ, "DEBIAN_FRONTEND": "noninteractive"}
    subprocess.run(["apt-get", "update", "-qq"], env=env, capture_output=True, timeout=300)
    subprocess.run(
        ["apt-get", "install", "-y", "-qq", "babeld", "batmand", "nftables"],
        env=env,
        capture_output=True,
        timeout=300,
    )


def _reason() -> str | None:
    from mso.emu.netns.emulator import NamespacesUnavailable, check_available

    _install_in_ci()
    try:
        check_available()
    except NamespacesUnavailable as exc:
        return str(exc)
    return None


REASON = _reason()
pytestmark = pytest.mark.skipif(REASON is not None, reason=REASON or "")


@pytest.fixture(autouse=True)
def node_pythonpath(monkeypatch: pytest.MonkeyPatch) -> Iterator[None]:
    """Node processes import the test vertices from this directory; no namespace outlives
    a test."""
    path = os.environ.get("PYTHONPATH", "")
    monkeypatch.setenv("PYTHONPATH", f"{TESTS}{os.pathsep}{path}" if path else str(TESTS))
    yield
    mine = [ns for ns in namespaces() if ns.startswith(prefix(os.getpid()))]
    assert mine == [], f"namespaces left behind: {mine}"


LINE = """
name: line
link_defaults: {bandwidth_mbps: 100}
nodes: {N1: {}, N2: {}, N3: {}, N4: {}}
links: [[N1, N2], [N2, N3], [N3, N4]]
"""

MESH = """
name: mesh
link_defaults: {bandwidth_mbps: 100}
nodes: {N1: {}, N2: {}, N3: {}, N4: {}, N5: {}, N6: {}}
links: [[N1, N2], [N2, N3], [N3, N6], [N1, N4], [N4, N5], [N5, N6], [N2, N5], [N3, N5]]
"""


def sink_errors(status: dict[str, Any], node: str) -> int:
    vertices = status[node]["apps"]["pipe"]["vertices"]
    return int(vertices["sink"]["errors"])


def sink_at(status: dict[str, Any], node: str) -> dict[str, int]:
    """The sink's counters; zeros while it is not (yet, or for a moment during a remap)
    running there."""
    vertex = status.get(node, {}).get("apps", {}).get("pipe", {}).get("vertices", {})
    stats: dict[str, int] | None = vertex.get("sink", {}).get("stats")
    return stats or {"count": 0, "repeats": 0, "out_of_order": 0}


def test_line_routes_and_overlay_follow_links_that_move() -> None:
    from mso.emu.netns.emulator import NetnsEmulator

    app = APP

    async def run() -> None:
        emu = NetnsEmulator(loads_scenario(LINE))
        await emu.start()
        try:
            # what `mso status` in another terminal does: the overlay's address of a node
            # names its namespace (NETNS@127.0.0.1:PORT)
            from mso.client import request
            from mso.protocol import messages as m

            reply = await request(emu.address("N3"), m.StatusRequest(), key=emu.key)
            assert isinstance(reply, m.StatusReply) and list(reply.nodes) == ["N3"]
            status = await emu.status("N1")
            # babeld's routes, named by the nodes' announcements: N4 is three hops via N2
            assert status["N1"]["routes"]["N2"] == ["N2", 1]
            assert status["N1"]["routes"]["N4"][0] == "N2"
            reply = await emu.deploy(app, "pipe.yaml", "N2")
            assert reply.ok, reply.error
            assert reply.placement["src"] == "N1" and reply.placement["sink"] == "N4"
            await until(emu.status, lambda s: sink_at(s, "N4")["count"] >= 100, 10, "events arrive")
            before = {n: emu.counters(n) for n in ("N2", "N3")}
            # a shortcut appears: babeld routes N1 -> N3 directly, and mso sees it
            await emu.set_link("N1", "N3", True)
            s = await until(
                lambda: emu.status("N1"),
                lambda s: (
                    s["N1"]["routes"]["N3"] == ["N3", 1] and s["N1"]["routes"]["N4"] == ["N3", 2]
                ),
                10,
                "N1 routes to N4 through the new link",
            )
            # ... and goes again: back through N2
            await emu.set_link("N1", "N3", False)
            s = await until(
                lambda: emu.status("N1"),
                lambda s: (
                    s["N1"]["routes"].get("N3", [""])[0] == "N2"
                    and s["N1"]["routes"].get("N4", [""])[0] == "N2"
                ),
                15,
                "N1 routes around the broken link",
            )
            s = await until(
                emu.status, lambda s: sink_at(s, "N4")["count"] > 0, 10, "the sink runs"
            )
            count = sink_at(s, "N4")["count"]
            s = await until(
                emu.status,
                lambda s: sink_at(s, "N4")["count"] >= count + 100,
                15,
                "events keep arriving after the re-route",
            )
            got = sink_at(s, "N4")
            assert got["repeats"] == 0 and got["out_of_order"] == 0 and sink_errors(s, "N4") == 0
            # while babeld had no route to N3 the overlay could relay through N2; once the
            # route is back the kernel forwards: the relays' radios carry the traffic and mso
            # relays nothing more
            relayed = {n: s[n]["traffic"]["bytes_forwarded"] for n in ("N2", "N3")}
            count = got["count"]
            s = await until(
                emu.status, lambda s: sink_at(s, "N4")["count"] >= count + 100, 15, "more events"
            )
            for n in ("N2", "N3"):
                assert s[n]["traffic"]["bytes_forwarded"] == relayed[n]
                grown = emu.counters(n)["tx_bytes"] - before[n]["tx_bytes"]
                assert grown > 100 * 20, (n, grown)
        finally:
            await emu.stop()

    asyncio.run(run())


def test_mesh_recovers_from_a_killed_relay() -> None:
    from mso.emu.netns.emulator import NetnsEmulator

    app = APP.replace("pinned: N4", "pinned: N6")

    async def run() -> None:
        emu = NetnsEmulator(loads_scenario(MESH))
        await emu.start()
        try:
            reply = await emu.deploy(app, "pipe.yaml", "N1")
            assert reply.ok, reply.error
            victim = reply.placement["mid"]
            assert victim not in ("N1", "N6")
            await until(emu.status, lambda s: sink_at(s, "N6")["count"] >= 50, 10, "events arrive")
            emu.kill(victim)  # the device dies: its node process and its babeld
            survivors = [n for n in emu.nodes if n != victim]

            def hosts(s: dict[str, Any]) -> list[str]:
                return [
                    n
                    for n, st in s.items()
                    if "mid" in st.get("apps", {}).get("pipe", {}).get("vertices", {})
                ]

            status = await until(
                lambda: emu.status("N1"),
                lambda s: (
                    victim not in s
                    and all(victim in s[n]["failed_nodes"] for n in survivors if n in s)
                    and len(hosts(s)) == 1
                ),
                15,
                f"the survivors detect {victim} and move mid off it",
            )
            assert hosts(status)[0] != victim
            status = await until(
                lambda: emu.status("N1"),
                lambda s: all(victim not in s[n]["routes"] for n in survivors if n in s),
                15,
                f"babeld withdraws the routes to {victim}",
                show=lambda s: {n: s[n]["routes"].get(victim) for n in survivors if n in s},
            )
            emitted = status["N1"]["apps"]["pipe"]["vertices"]["src"]["emitted"]
            status = await until(
                lambda: emu.status("N1"),
                lambda s: sink_at(s, "N6")["count"] >= emitted,
                10,
                "every event emitted before arrives",
            )
            got = sink_at(status, "N6")
            assert got["repeats"] == 0 and got["out_of_order"] == 0
            assert sink_errors(status, "N6") == 0
        finally:
            await emu.stop()

    asyncio.run(run())


def test_a_restarted_device_gets_a_fresh_babeld_and_its_routes_back() -> None:
    """A device killed (node and babeld, by SIGKILL: babeld's pid file stays) and restarted
    runs a new babeld and learns every route again (issue 23: it used to stay routeless)."""
    from mso.emu.netns.emulator import NetnsEmulator

    async def run() -> None:
        emu = NetnsEmulator(loads_scenario(MESH))
        await emu.start()
        try:
            old = emu.routers["N3"].pid
            emu.kill("N3")
            await until(
                lambda: emu.status("N1"),
                lambda s: "N3" not in s.get("N1", {}).get("routes", {"N3": 0}),
                20,
                "babeld withdraws the routes to N3",
            )
            said = await emu.restart("N3")
            assert said.startswith("N3 restarted") and emu.routers["N3"].pid != old
            others = {n for n in emu.nodes if n != "N3"}
            await until(
                lambda: emu.status("N3"),
                lambda s: others <= set(s.get("N3", {}).get("routes", {})),
                30,
                "the restarted N3 learns a route to every other node",
            )
        finally:
            await emu.stop()

    asyncio.run(run())


def test_cleanup_removes_what_a_killed_controller_left(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A controller that dies by SIGKILL leaves namespaces and processes; the next
    ``mso emulate --cleanup`` removes them (and kills, by PID, what ran inside)."""
    import sys

    # as a user of its own (sudo's SUDO_UID names whose they are): every testbed built
    # meanwhile cleans up after its user's dead controllers too, and on the other worker one
    # took these before this --cleanup could (CI, the slow set at load 20)
    monkeypatch.setenv("SUDO_UID", str(60000 + os.getpid() % 5000))
    script = (
        "import os, signal\n"
        "from mso.emu.netns.testbed import Testbed\n"
        "tb = Testbed(['A', 'B'])\n"
        "tb.build()\n"
        "p = tb.popen('A', ['sleep', '600'], __import__('pathlib').Path(os.environ['LOG']))\n"
        "print(os.getpid(), p.pid, flush=True)\n"
        "os.kill(os.getpid(), signal.SIGKILL)\n"
    )
    proc = subprocess.run(
        [sys.executable, "-c", script],
        capture_output=True,
        env={**os.environ, "LOG": str(tmp_path / "log")},
        timeout=60,
    )
    owner, child = (int(x) for x in proc.stdout.split())
    left = [ns for ns in namespaces() if ns.startswith(prefix(owner))]
    assert len(left) == 3  # medium and two nodes
    out = subprocess.run(
        [sys.executable, "-m", "mso", "emulate", "--cleanup"], capture_output=True, timeout=60
    )
    assert out.returncode == 0, out.stderr
    assert all(ns in out.stdout.decode() for ns in left)
    assert not [ns for ns in namespaces() if ns.startswith(prefix(owner))]
    for _ in range(100):  # killed at once; gone once its new parent has reaped it
        if not Path(f"/proc/{child}").exists() or "Z" in _state(child):
            break
        time.sleep(0.02)
    assert not Path(f"/proc/{child}").exists() or "Z" in _state(child)


def _state(pid: int) -> str:
    try:
        return Path(f"/proc/{pid}/stat").read_text().split(") ")[1][:1]
    except (OSError, IndexError):
        return "Z"


def test_cleanup_never_touches_another_users_namespaces() -> None:
    """Start-up and --cleanup remove this user's leftovers only: another user's namespace
    (or one of an older mso, named without a user) whose builder is gone stays."""
    import sys

    from mso.emu.netns.testbed import cleanup, user

    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    theirs = [f"mso-u{user() + 1}-{dead.pid}-m", f"mso-{dead.pid}-n1"]
    mine = f"{prefix(dead.pid)}m"
    try:
        for ns in [*theirs, mine]:
            subprocess.run(["ip", "netns", "add", ns], check=True, capture_output=True)
        removed = cleanup()
        assert mine in removed and not set(theirs) & set(removed)
        assert set(theirs) <= set(namespaces())
    finally:
        for ns in [*theirs, mine]:
            subprocess.run(["ip", "netns", "del", ns], capture_output=True)


def test_the_medium_lets_through_only_the_links_and_drops_their_loss() -> None:
    """The nft bridge filter alone (no babeld): a pair not in the set hears nothing, a link
    with loss 0.5 loses about half, a link that appears is effective when the call returns."""
    import socket

    from mso.emu.netns.testbed import Testbed
    from mso.net.netns import socket_in_netns

    tb = Testbed(["A", "B", "C"])
    tb.build()
    try:
        tb.set_links([("A", "B")], {("A", "B"): 0.5})

        def blast(dst: str, n: int) -> int:
            rx = socket_in_netns(tb.netns(dst), socket.AF_INET, socket.SOCK_DGRAM)
            tx = socket_in_netns(tb.netns("A"), socket.AF_INET, socket.SOCK_DGRAM)
            with rx, tx:
                rx.bind((tb.address(dst), 9999))
                rx.setblocking(False)
                for i in range(n):
                    tx.sendto(i.to_bytes(4, "big"), (tb.address(dst), 9999))
                time.sleep(0.2)  # datagrams in flight on veths: microseconds; then drain
                got = 0
                while True:
                    try:
                        rx.recv(64)
                    except BlockingIOError:
                        return got
                    got += 1

        half = blast("B", 400)
        assert 120 <= half <= 280, half  # loss 0.5 (binomial: 200 ± 10 sigma-ish bounds)
        assert blast("C", 50) == 0  # no link: nothing, broadcast or not
        tb.set_links([("A", "B"), ("A", "C")])  # loss gone, a new link
        assert blast("C", 50) == 50
        assert blast("B", 50) == 50
    finally:
        tb.teardown()


def test_the_convoy_runs_on_the_netns_line() -> None:
    """The paper's convoy app (real processing) deployed on four namespaces with babeld's
    routes: every chain is built and the trailing robot's storage receives what the leader's
    sensors emit, with no vertex raising."""
    import mso.examples
    from mso.emu.netns.emulator import NetnsEmulator

    examples = Path(mso.examples.__file__).parent

    async def run() -> dict[str, Any]:
        emu = NetnsEmulator(loads_scenario((examples / "convoy-line.yaml").read_text()))
        await emu.start()
        try:
            doc = (examples / "convoy.yaml").read_text()
            reply = await emu.deploy(doc, "convoy.yaml", "N1")
            assert reply.ok, reply.error
            assert reply.placement["laser"] == "N1" and reply.placement["storage"] == "N4"

            def stored(s: dict[str, Any]) -> int:
                vertices = s.get("N4", {}).get("apps", {}).get("convoy", {}).get("vertices", {})
                return int(vertices.get("storage", {}).get("processed", 0))

            return await until(emu.status, lambda s: stored(s) >= 20, 40, "rows reach storage")
        finally:
            await emu.stop()

    status = asyncio.run(run())
    for node, s in status.items():
        for vid, v in s["apps"]["convoy"]["vertices"].items():
            assert v["errors"] == 0, (node, vid, v["last_error"])


BATMAND = None if shutil.which("batmand") else "batmand is not installed (apt-get install batmand)"


@pytest.mark.skipif(BATMAND is not None, reason=BATMAND or "")
def test_batmand_routes_in_policy_tables_carry_the_overlay() -> None:
    """batmand installs its routes in table 66 behind policy rules, not in main: the kernel
    view reads them (before, mso saw no other node) and the app runs over them."""
    from mso.emu.netns.emulator import NetnsEmulator

    async def run() -> None:
        emu = NetnsEmulator(loads_scenario(LINE), routing="batmand")
        await emu.start()
        try:
            assert emu.testbed is not None
            ns = emu.testbed.netns("N1")
            rules = subprocess.run(["ip", "-n", ns, "rule"], capture_output=True, text=True)
            assert "lookup 66" in rules.stdout
            main = subprocess.run(["ip", "-n", ns, "route"], capture_output=True, text=True)
            assert emu.testbed.address("N4") not in main.stdout  # not in the main table
            status = await emu.status("N1")
            assert status["N1"]["routes"]["N2"] == ["N2", 1]
            assert status["N1"]["routes"]["N4"][0] == "N2"
            reply = await emu.deploy(APP, "pipe.yaml", "N2")
            assert reply.ok, reply.error
            s = await until(
                emu.status, lambda s: sink_at(s, "N4")["count"] >= 100, 15, "events arrive"
            )
            got = sink_at(s, "N4")
            assert got["repeats"] == 0 and got["out_of_order"] == 0 and sink_errors(s, "N4") == 0
        finally:
            await emu.stop()

    asyncio.run(run())
