"""The user-space emulator on loopback: real node processes, real sockets."""

from __future__ import annotations

import asyncio
import os
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from mso.emu.controller import Emulator
from mso.model.network import LinkSpec
from mso.scenario import loads_scenario
from runtime_vertices import pipe_app
from waits import patience, until

TESTS = Path(__file__).resolve().parent

APP = pipe_app(200)

SQUARE = """
name: square
link_defaults: {delay_ms: 1.0}
nodes: {N1: {}, N2: {}, N3: {}, N4: {}}
links:
  - [N1, N2]
  - [N2, N4]
  - [N1, N3]
  - [N3, N4]
"""

LINE = """
name: line
link_defaults: {delay_ms: 0.5, bandwidth_mbps: 54}
nodes: {N1: {}, N2: {}, N3: {}, N4: {}}
links: [[N1, N2], [N2, N3], [N3, N4]]
"""


@pytest.fixture(autouse=True)
def node_pythonpath(monkeypatch: pytest.MonkeyPatch) -> Iterator[None]:
    """Node processes import the test vertices from this directory."""
    path = os.environ.get("PYTHONPATH", "")
    monkeypatch.setenv("PYTHONPATH", f"{TESTS}{os.pathsep}{path}" if path else str(TESTS))
    yield


def sink(status: dict[str, Any]) -> dict[str, int]:
    stats: dict[str, int] = status["N4"]["apps"]["pipe"]["vertices"]["sink"]["stats"]
    return stats


async def all_arrive(
    emu: Emulator, app: str = "pipe", sink_at: str = "N4", ok: Any = lambda st: True
) -> tuple[dict[str, Any], int, int]:
    """A status once every event N1's src emitted before this call has reached the sink (and
    ``ok`` holds), with src's count before and after: the sink's count lies between the two
    whatever the load (in one status the source and the sink are read at different moments,
    so a sink a few events behind there is a loaded machine, not a loss)."""

    def emitted(st: dict[str, Any]) -> int:
        return int(st["N1"]["apps"][app]["vertices"]["src"]["emitted"])

    def arrived(st: dict[str, Any]) -> bool:
        return bool(st[sink_at]["apps"][app]["vertices"]["sink"]["stats"]["count"] >= upto)

    upto = emitted(await emu.status("N1"))
    what = f"the {upto} events emitted at the sink"
    status = await until(emu.status, lambda st: arrived(st) and ok(st), 10, what)
    return status, upto, emitted(await emu.status("N1"))


async def flowing(emu: Emulator, events: int) -> None:
    """Until the pipe's sink on N4 has had ``events`` (the app runs: a wait, not a sleep)."""
    await until(lambda: emu.status("N1"), lambda st: sink(st)["count"] >= events, 10,
                f"{events} events at the sink")  # fmt: skip


def test_deploy_and_count_exactly_once() -> None:
    async def run() -> tuple[dict[str, Any], list[int], int, int]:
        emu = Emulator(loads_scenario(LINE))
        await emu.start()
        pids = [n.process.pid for n in emu.nodes.values() if n.process is not None]
        try:
            reply = await emu.deploy(APP, "pipe.yaml", "N2")  # from any node, not the source's
            assert reply.ok, reply.error
            assert reply.placement["src"] == "N1" and reply.placement["sink"] == "N4"
            await flowing(emu, 200)
            return (*await all_arrive(emu), pids)
        finally:
            await emu.stop()

    status, upto, later, pids = asyncio.run(run())
    got = sink(status)
    assert got["repeats"] == 0 and got["out_of_order"] == 0
    assert upto <= got["count"] <= later  # none lost, none made up
    assert (
        status["N2"]["traffic"]["bytes_forwarded"] > 0
        or status["N3"]["traffic"]["bytes_forwarded"] > 0
    )
    for pid in pids:  # every node process is gone: no orphans
        with pytest.raises(ProcessLookupError):
            os.kill(pid, 0)


def test_link_break_reroutes_traffic() -> None:
    scenario = loads_scenario(SQUARE)
    app = APP.replace(
        "  mid: {code: runtime_vertices:Double, output: runtime_vertices:Num}",
        "  mid: {code: runtime_vertices:Double, output: runtime_vertices:Num, pinned: N1}",
    )

    async def run() -> tuple[dict[str, Any], dict[str, Any]]:
        emu = Emulator(scenario, convergence_s=0.2)
        await emu.start()
        try:
            assert (await emu.deploy(app, "pipe.yaml", "N1")).ok

            def via_n2(st: dict[str, Any]) -> bool:
                return bool(
                    sink_at(st, "N4")["count"] > 0 and st["N2"]["traffic"]["bytes_forwarded"] > 0
                )

            before = await until(emu.status, via_n2, 10, "a flow through N2")
            await emu.cut("N1", "N2")

            def via_n3(st: dict[str, Any]) -> bool:
                rerouted = st["N1"]["routes"]["N4"][0] == "N3"
                forwarded = st["N3"]["traffic"]["bytes_forwarded"] > 0
                return bool(
                    rerouted
                    and forwarded
                    and sink_at(st, "N4")["count"] >= sink(before)["count"] + 300
                )

            after = await until(emu.status, via_n3, 10, "the flow rerouted through N3")
            return before, after
        finally:
            await emu.stop()

    before, after = asyncio.run(run())
    assert before["N2"]["traffic"]["bytes_forwarded"] > 0  # first via N2
    assert after["N1"]["routes"]["N4"][0] == "N3"
    assert after["N3"]["traffic"]["bytes_forwarded"] > 0  # then via N3
    b, a = sink(before), sink(after)
    assert a["count"] >= b["count"] + 300  # kept flowing at 200 events/s
    assert a["repeats"] == 0 and a["out_of_order"] == 0


def stop_daemons(procs: list[subprocess.Popen[bytes]]) -> None:
    """Stop the daemons :func:`start_pair` started (ours, by their handles)."""
    for p in procs:
        p.terminate()
        p.wait(timeout=5)


def start_pair(
    tmp_path: Path, only: tuple[str, ...] = ("N1", "N4"), port: int = 0
) -> tuple[list[subprocess.Popen[bytes]], int]:
    """Two daemons N1 and N4 configured by files, as on real devices (no emulator); ``only``
    some of them (the other later, on the same ``port``)."""
    from mso.emu.controller import _free_port

    port = port or _free_port(["127.0.1.1", "127.0.1.2"])
    procs = []
    pairs = (("N1", "N4", "127.0.1.1", "127.0.1.2"), ("N4", "N1", "127.0.1.2", "127.0.1.1"))
    for me, other, ip, oip in pairs:
        if me not in only:
            continue
        cfg = tmp_path / f"{me}.yaml"
        cfg.write_text(
            f"id: {me}\nlisten: {ip}:{port}\nkey: k1\npeers: {{{other}: '{oip}:{port}'}}\n"
        )
        procs.append(subprocess.Popen([sys.executable, "-m", "mso", "node", "--config", str(cfg)]))
    return procs, port


def test_python_api_against_running_daemons(tmp_path: Path) -> None:
    import time

    from mso.api import Overlay
    from mso.errors import MsoError

    procs, port = start_pair(tmp_path)
    app_file = tmp_path / "pipe.yaml"
    app_file.write_text(
        APP.replace(
            "  mid: {code: runtime_vertices:Double, output: runtime_vertices:Num}",
            "  mid: {code: runtime_vertices:Counter, output: runtime_vertices:Num}",
        )
    )
    try:
        overlay = Overlay(f"127.0.1.2:{port}", key="k1")
        deadline = time.monotonic() + patience(20.0)
        while True:  # until both daemons listen and see each other
            try:
                if overlay.status()["N4"].get("connected") == ["N1"]:
                    break
            except MsoError:
                pass
            assert time.monotonic() < deadline, "the two daemons did not link"
            time.sleep(0.05)  # poll period
        placement = overlay.deploy(app_file).placement
        moved = overlay.relocate("pipe", "mid", target="N4" if placement["mid"] == "N1" else "N1")
        assert moved.ok and moved.node != placement["mid"]
        with pytest.raises(MsoError, match="end of chain"):
            overlay.relocate("pipe", "src", direction="downstream")
        deadline = time.monotonic() + patience(10.0)
        while True:  # until events have passed the moved vertex to the sink
            status = overlay.status()
            if sink(status)["count"] > 0 or time.monotonic() > deadline:
                break
            time.sleep(0.05)  # poll period
    finally:
        stop_daemons(procs)
    got = sink(status)
    assert got["count"] > 0 and got["repeats"] == 0 and got["out_of_order"] == 0
    assert "mid" in status[moved.node]["apps"]["pipe"]["vertices"]


def test_the_benchmarks_client_path_through_the_api() -> None:
    """What the benchmarks ask through mso.api: a deployment judged there (``check``), a call's
    own timeout, and a connection of its own (signed and encrypted as the emulator's) that its
    caller closes while the emulator's kept connection goes on serving."""
    from mso.api import CommandFailed
    from mso.client import NodeUnreachable

    async def run() -> None:
        emu = Emulator(loads_scenario(LINE), encrypt=True)
        await emu.start()
        try:
            assert (await emu.deploy(APP, "pipe.yaml", "N1", check=True)).ok
            with pytest.raises(CommandFailed, match="deployment failed"):  # it runs already
                await emu.deploy(APP, "pipe.yaml", "N1", check=True)
            trial = await emu.open_overlay("N4", "trial", timeout=patience(2.0))
            try:
                reply = await trial.remap("pipe", chains=[0], check=False, timeout=patience(10.0))
                assert reply.app == "pipe"
                with pytest.raises(NodeUnreachable, match="did not answer in time"):
                    await trial.remap("pipe", everything=True, timeout=1e-9)
            finally:
                await trial.close()
            kept = emu.overlay("N4")
            await kept.close()  # not its own: the emulator's connection stays open
            here = await kept.status(everywhere=False, timeout=patience(5.0))
            assert "pipe" in here["N4"]["apps"]
        finally:
            await emu.stop()

    asyncio.run(run())


def test_static_peers_from_config_files(tmp_path: Path) -> None:
    """Without an emulator: two daemons configured by files, as on real devices."""
    from mso.client import request
    from mso.protocol import messages as m

    procs, port = start_pair(tmp_path)
    app = APP.replace(
        "  mid: {code: runtime_vertices:Double, output: runtime_vertices:Num}\n", ""
    ).replace("  - [src, mid]\n  - [mid, sink]\n", "  - [src, sink]\n")

    async def run() -> dict[str, Any]:
        addr = f"127.0.1.1:{port}"

        async def read() -> dict[str, Any]:
            st = await request(addr, m.StatusRequest(), key="k1", timeout=2)
            assert isinstance(st, m.StatusReply)
            return st.nodes

        await until(  # both daemons listen and are connected
            read, lambda st: st["N1"].get("connected") == ["N4"], 20, "the two daemons linked"
        )
        deploy = m.DeployRequest(app, "pipe.yaml")
        reply = await request(addr, deploy, key="k1", timeout=patience(10.0))
        assert reply.ok, reply.error

        async def everywhere() -> dict[str, Any]:
            status = await request(addr, m.StatusRequest(everywhere=True), key="k1", timeout=2)
            assert isinstance(status, m.StatusReply)
            return status.nodes

        return await until(
            everywhere, lambda st: sink_at(st, "N4")["count"] >= 100, 10, "100 events"
        )

    try:
        nodes = asyncio.run(run())
    finally:
        stop_daemons(procs)
    got = sink(nodes)
    assert got["count"] >= 100 and got["repeats"] == 0 and got["out_of_order"] == 0


def test_a_deploy_sent_while_its_pinned_node_is_held_failed_waits_for_its_rejoin(
    tmp_path: Path,
) -> None:
    """The race of a fresh clone's flake, made certain: N1 holds N4 failed (its daemon is not
    up yet) when the deployment, which pins the sink to N4, arrives; N4 rejoins a moment
    later. The deployment waits for it and succeeds (it was announced without N4, and never
    answered within the client's wait)."""
    from mso.client import request
    from mso.protocol import messages as m

    procs, port = start_pair(tmp_path, only=("N1",))
    addr = f"127.0.1.1:{port}"

    async def run() -> m.Message:
        async def read() -> dict[str, Any]:
            st = await request(addr, m.StatusRequest(), key="k1", timeout=2)
            assert isinstance(st, m.StatusReply)
            return st.nodes

        await until(read, lambda st: "N4" in st["N1"]["failed_nodes"], 20, "N1 holding N4 failed")
        later, _ = start_pair(tmp_path, only=("N4",), port=port)
        procs.extend(later)
        return await request(addr, m.DeployRequest(APP, "pipe.yaml"), key="k1",
                             timeout=patience(10.0))  # fmt: skip

    try:
        reply = asyncio.run(run())
    finally:
        stop_daemons(procs)
    assert isinstance(reply, m.DeployReply) and reply.ok, reply
    assert reply.placement["sink"] == "N4"


def test_relocation_across_processes_keeps_every_event() -> None:
    app = APP.replace(
        "  mid: {code: runtime_vertices:Double, output: runtime_vertices:Num}",
        "  mid: {code: runtime_vertices:Counter, output: runtime_vertices:Num}",
    )

    async def run() -> tuple[list[Any], dict[str, Any], int, int]:
        emu = Emulator(loads_scenario(LINE))
        await emu.start()
        try:
            assert (await emu.deploy(app, "pipe.yaml", "N1")).ok
            # N3 coordinates the moves: it runs the app once the deploy's StartApp reaches it,
            # which may trail the reply
            running = lambda st: st["N3"]["apps"]["pipe"]["running"]  # noqa: E731
            await until(lambda: emu.status("N3"), running, 10, "N3 running the app")
            replies = []
            for k in range(6):
                seen = sink(await emu.status("N4"))["count"]  # events flow between the moves
                await until(lambda: emu.status("N4"), lambda st, n=seen: sink(st)["count"] > n + 20,
                            10, "events through mid since the last move")  # fmt: skip
                direction = "downstream" if k % 2 == 0 else "upstream"
                replies.append(await emu.relocate("pipe", "mid", direction=direction, via="N3"))
            return (replies, *await all_arrive(emu))
        finally:
            await emu.stop()

    replies, status, upto, later = asyncio.run(run())
    assert sum(r.ok for r in replies) >= 3, [r.error for r in replies]
    hosts = [  # (a node that takes no part in the app holds none of it: issue 24.1)
        n for n, st in status.items() if "mid" in st["apps"].get("pipe", {}).get("vertices", {})
    ]
    assert len(hosts) == 1
    got = sink(status)
    assert got["repeats"] == 0 and got["out_of_order"] == 0  # the counter's state moved too
    assert upto <= got["count"] <= later  # none lost, none made up


def test_lossy_links_lose_no_event() -> None:
    """Loss applied in the sender's link layer is recovered by acks and retransmission."""
    lossy = LINE.replace(
        "link_defaults: {delay_ms: 0.5, bandwidth_mbps: 54}", "link_defaults: {loss: 0.2}"
    )
    app = APP.replace("rate: 200", "rate: 100")

    async def run() -> tuple[dict[str, Any], int, int]:
        emu = Emulator(loads_scenario(lossy))
        await emu.start()
        try:
            assert (await emu.deploy(app, "pipe.yaml", "N1")).ok
            await flowing(emu, 200)
            # every event emitted so far must reach the sink, however many resends it takes
            return await all_arrive(emu)
        finally:
            await emu.stop()

    status, upto, later = asyncio.run(run())
    dropped = sum(st["traffic"]["frames_dropped_loss"] for st in status.values())
    assert dropped > 5  # the links did lose frames
    got = sink(status)
    assert got["repeats"] == 0 and got["out_of_order"] == 0
    assert upto <= got["count"] <= later


def test_mobility_changes_links_while_the_app_runs() -> None:
    moving = """
name: moving
radio_range: 150
nodes:
  R1: {pos: [0, 0]}
  R2: {pos: [100, 50]}
  R3: {pos: [150, 150]}
  R4: {pos: [250, 230]}
mobility: {model: random_waypoint, area: [300, 300], speed: [60, 120], pause_s: 0,
           seed: 3, fixed: [R1, R4], step_s: 0.2}
"""
    app = """
name: pipe
vertices:
  src: {code: runtime_vertices:CountingSource, pinned: R1, rate: 50, output: runtime_vertices:Num}
  sink: {code: runtime_vertices:Recorder, pinned: R1}
edges: [[src, sink]]
"""

    async def run() -> dict[str, Any]:
        emu = Emulator(loads_scenario(moving))
        await emu.start()
        try:
            assert (await emu.deploy(app, "pipe.yaml", "R1")).ok
            loop = asyncio.get_running_loop()
            mobility = asyncio.create_task(emu.play_mobility(loop.time()))
            await asyncio.sleep(3.0)
            mobility.cancel()
            assert emu.positions and emu.positions["R1"] == (0.0, 0.0)  # fixed nodes stay
            return await emu.status("R1")
        finally:
            await emu.stop()

    status = asyncio.run(run())
    changes = sum(
        st["monitor"]["route_changes"] + st["monitor"]["neighbour_changes"]
        for st in status.values()
    )
    assert changes > 0  # the robots moved and the routing views followed
    got = status["R1"]["apps"]["pipe"]["vertices"]["sink"]["stats"]
    assert got["count"] > 100 and got["repeats"] == 0 and got["out_of_order"] == 0


MESH = """
name: mesh
link_defaults: {delay_ms: 0.5}
nodes: {N1: {}, N2: {}, N3: {}, N4: {}, N5: {}, N6: {}}
links: [[N1, N2], [N2, N3], [N3, N6], [N1, N4], [N4, N5], [N5, N6], [N2, N5], [N3, N5]]
"""


def test_a_killed_relay_is_detected_and_its_chain_recovered() -> None:
    """SIGKILL the node hosting the interior vertex: survivors detect it, one remaps, the
    source's node replays, and the sink gets every event once, in order."""
    app = APP.replace("pinned: N4", "pinned: N6").replace("rate: 200", "rate: 100")

    async def run() -> tuple[str, int, dict[str, Any]]:
        emu = Emulator(loads_scenario(MESH), convergence_s=0.2)
        await emu.start()
        try:
            reply = await emu.deploy(app, "pipe.yaml", "N1")
            assert reply.ok, reply.error
            victim = reply.placement["mid"]
            assert victim not in ("N1", "N6")

            def read() -> Any:
                return emu.status("N1")

            await until(read, lambda st: sink_at(st, "N6")["count"] >= 100, 10, "a flow")
            emu.kill(victim)

            def recovered(st: dict[str, Any]) -> bool:
                records = [r for s in st.values() for r in recoveries(s)]
                told = all(s["failed_nodes"] == [victim] for s in st.values())
                return victim not in st and told and any(r["ok"] for r in records)

            status = await until(read, recovered, 10, f"{victim} declared failed, recovered")
            emitted = int(status["N1"]["apps"]["pipe"]["vertices"]["src"]["emitted"])
            status = await until(  # what is still in flight arrives
                read, lambda st: sink_at(st, "N6")["count"] >= emitted, 5, "the replay"
            )
            return victim, emitted, status
        finally:
            await emu.stop()

    victim, emitted, status = asyncio.run(run())
    assert victim not in status
    for node, st in status.items():
        assert st["failed_nodes"] == [victim], node
    records = [r for st in status.values() for r in recoveries(st)]
    assert len(records) == 1 and records[0]["ok"], records
    hosts = [  # (a node that takes no part in the app holds none of it: issue 24.1)
        n for n, st in status.items() if "mid" in st["apps"].get("pipe", {}).get("vertices", {})
    ]
    assert len(hosts) == 1 and hosts[0] != victim
    got = sink_at(status, "N6")
    assert got["repeats"] == 0 and got["out_of_order"] == 0
    # in order, no gap and no repeat: every event emitted by the first reading has arrived (the
    # source runs on while the sink is read, so the sink may be a little ahead of that reading)
    assert got["count"] >= emitted


def recoveries(node_status: dict[str, Any]) -> list[dict[str, Any]]:
    """The pipe's recoveries a node records; none at a node that holds none of the app (only
    its origin, hosts and replicas' nodes hold it: issue 24.1)."""
    got: list[dict[str, Any]] = node_status["apps"].get("pipe", {}).get("recoveries", [])
    return got


def sink_at(status: dict[str, Any], node: str) -> dict[str, int]:
    """The sink's counters; zeros while it is not (yet) running there."""
    vertex = status.get(node, {}).get("apps", {}).get("pipe", {}).get("vertices", {})
    stats: dict[str, int] | None = vertex.get("sink", {}).get("stats")
    return stats or {"count": 0, "repeats": 0, "out_of_order": 0}


ROBOTS = """
name: robots
node_defaults: {power: {idle_w: 1.0, cpu_w: 6.0}, battery_wh: 5.0}
link_defaults: {delay_ms: 0.5}
nodes:
  N1: {cpu: 4.0, battery_wh: 0.5}
  N2: {}
  N3: {}
links: [[N1, N2], [N2, N3]]
"""

WORK = """
name: work
vertices:
  src: {code: runtime_vertices:CountingSource, pinned: N1, rate: 50, cost: 0.1,
        output: runtime_vertices:Num}
  work: {code: runtime_vertices:Double, cost: 20, output: runtime_vertices:Num}
  sink: {code: runtime_vertices:Recorder, pinned: N3, cost: 0.1}
edges: [[src, work], [work, sink]]
"""


def test_the_energy_rule_moves_work_between_node_processes() -> None:
    """The same rules as in the simulator, on real processes: the poor leader's costly vertex
    moves one hop downstream after the guard's confirmations, and the sink misses nothing."""

    async def run() -> dict[str, Any]:
        emu = Emulator(loads_scenario(ROBOTS))
        await emu.start()
        try:
            reply = await emu.deploy(WORK, "work.yaml", "N1")
            assert reply.ok and reply.placement["work"] == "N1", reply
            await until(
                lambda: emu.status("N1"),
                lambda st: "work" in st["N2"]["apps"]["work"]["vertices"],
                30,
                "the rules' relocation of work to N2",
            )
            # the coordinator's record of the move ends it (the moved vertex runs before)
            recorded = lambda st: bool(st["N1"]["management"]["done"])  # noqa: E731
            return await all_arrive(emu, "work", "N3", recorded)
        finally:
            await emu.stop()

    status, upto, later = asyncio.run(run())
    assert "work" in status["N2"]["apps"]["work"]["vertices"]
    done = status["N1"]["management"]["done"]
    assert len(done) == 1 and "relocate work/work -> N2" in done[0]
    got = status["N3"]["apps"]["work"]["vertices"]["sink"]["stats"]
    assert got["repeats"] == 0 and got["out_of_order"] == 0
    assert upto <= got["count"] <= later  # none lost, none made up


def test_a_cut_off_sink_node_rejoins_when_its_link_comes_back() -> None:
    """The sink's node is out of reach for longer than failure detection, then its link comes
    back. Out of reach is not failed (the sink is pinned there: re-placing nothing would let
    events flow): it is held unreachable, its chain parked with the events kept, and taken
    back as it is (the same incarnation, real start-time incarnations across processes): the
    chain is unparked and the sink gets what was kept, with no repeat and nothing skipped."""
    app = APP.replace("rate: 200", "rate: 100")

    def parked(st: dict[str, Any], node: str) -> dict[str, str] | None:
        got: dict[str, str] | None = st.get(node, {}).get("apps", {}).get("pipe", {}).get("parked")
        return got

    def cut_off(st: dict[str, Any]) -> bool:
        return "N4" in st["N1"]["unreachable_nodes"] and "src-mid-sink" in (parked(st, "N1") or {})

    def back(st: dict[str, Any]) -> bool:
        # (a node that takes no part in the app holds none of it: parked None, issue 24.1)
        healed = all(not s["unreachable_nodes"] and not parked(st, n) for n, s in st.items())
        return healed and "N4" in st and sink_at(st, "N4")["count"] > during_count + 100

    during_count = 0

    async def run() -> tuple[dict[str, Any], dict[str, Any], dict[str, Any]]:
        nonlocal during_count
        emu = Emulator(loads_scenario(LINE))
        await emu.start()
        try:
            assert (await emu.deploy(app, "pipe.yaml", "N1")).ok

            def read() -> Any:
                return emu.status("N1")

            before = await until(read, lambda st: sink_at(st, "N4")["count"] > 0, 10, "a flow")
            await emu.cut("N3", "N4")
            # N4 is unreachable: only N1..N3 answer
            during = await until(read, cut_off, 10, "N4 held unreachable, its chain parked")
            during_count = sink_at(before, "N4")["count"]
            await emu.heal("N3", "N4")
            after = await until(read, back, 15, "N4 back, its chain unparked, a flow")
            return before, during, after
        finally:
            await emu.stop()

    before, during, after = asyncio.run(run())
    assert during["N1"]["failed_nodes"] == []
    why = during["N1"]["apps"]["pipe"]["parked"]["src-mid-sink"]
    assert why == "'sink' is pinned to N4, out of reach", why
    for node, st in after.items():
        assert st["failed_nodes"] == [] and not parked(after, node), node
        assert st["incarnation"] == before[node]["incarnation"], node  # nobody reset
    got = sink(after)  # the same sink: every event kept while it was away, in order
    assert got["count"] > 100 and got["repeats"] == 0 and got["out_of_order"] == 0, got


# -- store and forward on node processes: a sink's node cut off, then back (issue 22) -----------
LINE3 = """
name: line
link_defaults: {delay_ms: 0.5, bandwidth_mbps: 54}
nodes: {N1: {}, N2: {}, N3: {}}
links: [[N1, N2], [N2, N3]]
"""


def store_forward_app(log: Path) -> str:
    return f"""
name: sf
vertices:
  src: {{code: runtime_vertices:CountingSource, pinned: N3, rate: 50,
        params: {{size: 1000}}, output: runtime_vertices:Num}}
  mid: {{code: runtime_vertices:Double, output: runtime_vertices:Num, pinned: N2}}
  sink: {{code: runtime_vertices:FileSeen, pinned: N1, params: {{path: '{log}'}}}}
edges: [[src, mid], [mid, sink]]
"""


def test_a_cut_off_sink_gets_every_event_in_order_after_the_heal(tmp_path: Path) -> None:
    log = tmp_path / "seen.txt"
    scenario = loads_scenario(LINE3)

    async def run() -> dict[str, Any]:
        emu = Emulator(scenario, log_dir=tmp_path, manage=False)
        await emu.start()
        try:
            assert (await emu.deploy(store_forward_app(log), "sf.yaml", "N3")).ok

            def made(st: dict[str, Any]) -> int:
                return int(st["N3"]["apps"]["sf"]["edges"]["src->mid"]["sent"])

            def held(st: dict[str, Any]) -> int:
                edge = st["N2"]["apps"]["sf"]["edges"]["mid->sink"]
                return int(edge["sent"] - edge["delivered"])

            def caught_up(st: dict[str, Any]) -> bool:
                seen = len(log.read_text().split()) if log.exists() else 0
                return made(st) >= 50 * 4 and seen >= made(st)

            await until(lambda: emu.status("N3"), lambda st: made(st) >= 50, 10, "a flow")
            link = scenario.network.link("N1", "N2") or LinkSpec("N1", "N2")
            await emu.set_link("N1", "N2", False)  # N1 out of reach: held, not delivered
            during = await until(
                lambda: emu.status("N2"), lambda st: held(st) >= 50 * 2, 10, "events held at N2"
            )
            await emu.set_link("N1", "N2", True, link)
            status = await until(lambda: emu.status("N3"), caught_up, 30, "the sink caught up")
            return {"during": during, "after": status}
        finally:
            await emu.stop()

    result = asyncio.run(run())
    held = result["during"]["N2"]["apps"]["sf"]["edges"]["mid->sink"]
    assert held["sent"] - held["delivered"] >= 50 * 2, f"held while cut off: {held}"
    seen = [int(x) for x in log.read_text().split()]
    made = result["after"]["N3"]["apps"]["sf"]["edges"]["src->mid"]["sent"]
    distinct = sorted(set(seen))
    assert distinct == list(range(len(distinct))), "none missing"
    assert list(dict.fromkeys(seen)) == distinct, "in order"
    # the one exception, documented: the sink's node may reset at the heal (it held the others
    # failed), and its replacement gets again what it had processed but not yet acknowledged
    assert len(seen) - len(distinct) <= 5, "at most the last unacknowledged events again"
    assert len(distinct) >= made >= 50 * 4
