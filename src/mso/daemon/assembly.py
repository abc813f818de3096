"""Build one node from its settled settings and run it: the core, the transport with its
keys, the routing view (kernel routes, fixed peers, or the emulator's), the device probe, the
driver that feeds the core, the metrics endpoint, and the ends a daemon needs (SIGHUP re-reads
the key file; an emulator's node stops with its emulator)."""

from __future__ import annotations

import asyncio
import contextlib
import logging
import os
import sys
import time
from typing import TYPE_CHECKING

from mso.daemon.config import DEV_KEY_WARNING, NodeFlags, NodeSettings, read_keys, settle
from mso.daemon.logs import KV, setup_logging
from mso.errors import MsoError

if TYPE_CHECKING:
    from mso.net.base import RoutingView
    from mso.net.routes_kernel import KernelRoutes
    from mso.node.core import NodeCore
    from mso.node.driver import NodeDriver

log = logging.getLogger("mso.node")


def run_daemon(flags: NodeFlags) -> None:
    """Settle and check the options, then run the node until it is stopped (Ctrl-C, a
    Shutdown from its emulator, its emulator's end)."""
    settings = settle(flags)
    setup_logging(settings.node_id, settings.verbose)
    core = build_core(settings)  # checks the policy before anything listens
    if settings.dev_key:
        print(DEV_KEY_WARNING, file=sys.stderr, flush=True)
    with contextlib.suppress(KeyboardInterrupt):
        asyncio.run(serve(settings, core))


def build_core(s: NodeSettings) -> NodeCore:
    from mso.daemon.spill import SqliteSpill
    from mso.node.core import NodeCore

    # what a source's edges held and their positions, from before a restart (--state-dir)
    spill = SqliteSpill(s.state_dir) if s.state_dir is not None else None
    return NodeCore(
        s.node_id,
        capacity=s.cpu,
        power=s.power,
        battery_wh=s.battery_wh,
        capabilities=s.capabilities,
        policy=s.policy,
        manage=s.manage,
        rules=s.rules,
        heartbeat_s=s.heartbeat_s,
        dead_after_s=s.dead_after_s,
        # a restarted daemon is a new incarnation: the others restore what it hosted before
        incarnation=time.time_ns() // 1_000_000,
        clock=time.monotonic,  # the asyncio loop's clock: what a reply's elapsed time is read on
        spill=spill,
    )


def overlay_keys(s: NodeSettings) -> list[bytes]:
    """The overlay keys (the first seals): the key file's, else the one key."""
    from mso.client import overlay_key

    if s.key_file is not None:
        return [overlay_key(k) for k in read_keys(s.key_file)]
    return [overlay_key(s.key)]


async def routing_view(
    s: NodeSettings, psk: bytes
) -> tuple[RoutingView | None, KernelRoutes | None]:
    """Where routes come from: the kernel's (read over netlink), fixed peers, or (None) the
    emulator's; the kernel view too, to close."""
    from mso.net.routes_static import StaticRoutes

    if s.routes_from == "kernel":
        from mso.net.routes_kernel import KernelRoutes

        kernel = KernelRoutes(s.node_id, s.port, psk, host=s.host)
        try:
            await kernel.start()
        except OSError as exc:
            raise MsoError(f"--routes kernel: cannot read routes or bind: {exc}") from None
        return kernel, kernel
    if s.routes_from == "auto" and s.peers:
        return StaticRoutes(s.node_id, s.peers), None
    return None, None


def rotate_keys_on_hangup(s: NodeSettings, driver: NodeDriver) -> None:
    """SIGHUP: take the key file again; open connections keep theirs."""
    import signal

    key_file = s.key_file
    if key_file is None:
        return

    def rotate() -> None:
        try:
            driver.transport.set_keys(overlay_keys(s))
            log.warning("overlay keys re-read from %s", key_file)
        except MsoError as exc:
            log.error("keeping the old keys: %s", exc)

    asyncio.get_running_loop().add_signal_handler(signal.SIGHUP, rotate)


async def serve(s: NodeSettings, core: NodeCore) -> None:
    """Run the node until its driver stops."""
    from mso.daemon.spill import SqliteSpill, keep_tidy
    from mso.node.device import DeviceProbe
    from mso.node.driver import PARENT_ENV, NodeDriver, stop_with_parent

    keys = overlay_keys(s)
    view, kernel = await routing_view(s, keys[0])  # announcements are sealed with the first
    device = DeviceProbe(battery=s.energy == "auto", interfaces=s.energy != "model")
    driver = NodeDriver(  # no view: the emulator's
        core, s.host, s.port, keys, view, device=device, authority=s.authority,
        encrypt=s.encrypt, identity=s.identity, link_mbps=s.link_mbps,
    )  # fmt: skip
    rotate_keys_on_hangup(s, driver)
    try:
        await driver.start()
    except OSError as exc:
        raise MsoError(f"cannot listen on {s.listen}: {exc.strerror}") from None
    exporter = None
    if s.metrics_at is not None:
        from mso.node.metrics import MetricsServer

        loop = asyncio.get_running_loop()
        exporter = MetricsServer(lambda: core.status(loop.time()), *s.metrics_at)
        await exporter.start()
    watch = None
    if parent := os.environ.get(PARENT_ENV):  # started by an emulator: end with it
        watch = asyncio.create_task(stop_with_parent(driver, int(parent)))
    tidy = None
    if isinstance(core.spill, SqliteSpill):  # (--state-dir) its slow work off the loop's turns
        tidy = asyncio.create_task(keep_tidy(core.spill))
        core.spill.read_apart(asyncio.get_running_loop().call_soon_threadsafe, driver.spill_ready)
    started = time.monotonic()
    fields = start_fields(s, driver, view)
    log.info("start", extra={KV: fields})
    if fields["routes"] == "none":
        log.warning(
            "no neighbours", extra={KV: {"event": "no_neighbours", "detail": NO_NEIGHBOURS}}
        )
    why = stop_on_signals(driver)
    try:
        await driver.stopped.wait()
        log.info("stop", extra={KV: stop_fields(driver, why, time.monotonic() - started)})
    finally:
        if watch is not None:
            watch.cancel()
        if tidy is not None:
            tidy.cancel()
            assert isinstance(core.spill, SqliteSpill)
            core.spill.stop_reading()
        if exporter is not None:
            await exporter.stop()
        if kernel is not None:
            await kernel.close()


NO_NEIGHBOURS = (
    "neither --peer nor --routes kernel given: this node finds no neighbour by itself "
    "(only an emulator tells it its links); give --peer ID=HOST:PORT or --routes kernel"
)


def describe_routes(s: NodeSettings, view: RoutingView | None) -> str:
    """Where this node's routes come from, for its start line."""
    if s.routes_from == "kernel":
        return "kernel"
    if view is not None:
        return "static:" + ",".join(sorted(s.peers))
    from mso.node.driver import PARENT_ENV

    if os.environ.get(PARENT_ENV):
        return "emulator"
    return "none"  # by hand, neither --peer nor --routes kernel: told at start (NO_NEIGHBOURS)


def start_fields(
    s: NodeSettings, driver: NodeDriver, view: RoutingView | None
) -> dict[str, object]:
    """The start line: enough to tell from a robot's journal which node this is, where it
    listens, how it finds its neighbours and who may command it."""
    server = driver.transport.server
    bound = server.sockets[0].getsockname()[:2] if server is not None and server.sockets else None
    rules = ""
    if s.rules is not None:
        import dataclasses

        from mso.management.guard import RuleSettings

        default = RuleSettings()
        rules = ",".join(
            f"{f.name}:{getattr(s.rules, f.name)}"
            for f in dataclasses.fields(s.rules)
            if getattr(s.rules, f.name) != getattr(default, f.name)
        )
    return {
        "event": "start",
        "listen": f"{bound[0]}:{bound[1]}" if bound else s.listen,
        "routes": describe_routes(s, view),
        "incarnation": driver.core.incarnation,
        "operator_keys": "on" if s.authority is not None and s.authority.signed else "off",
        "encrypt": "on" if s.encrypt else "off",
        "policy": s.policy or "lifetime",
        "manage": "on" if s.manage else "off",
        "rules": rules or "defaults",
        "pid": os.getpid(),
    }


def stop_on_signals(driver: NodeDriver) -> list[str]:
    """SIGTERM (systemd's stop) and SIGINT stop the node cleanly, so its stop line is written;
    the list it returns names the signal once one came."""
    import signal

    why: list[str] = []
    loop = asyncio.get_running_loop()
    stopping: list[asyncio.Task[None]] = []  # held, so the task is not collected mid-stop

    def stop(sig: signal.Signals) -> None:
        if not why:
            why.append(sig.name)
            stopping.append(loop.create_task(driver.stop()))

    for sig in (signal.SIGTERM, signal.SIGINT):
        loop.add_signal_handler(sig, stop, sig)
    return why


def stop_fields(driver: NodeDriver, why: list[str], uptime_s: float) -> dict[str, object]:
    """The stop line: why, how long it ran, what it hosted and what it saw happen."""
    core = driver.core
    hosted = sum(len(dep.instances) for dep in core.apps.values())
    seen = ",".join(f"{k}:{n}" for k, n in sorted(driver.seen.items()))
    return {
        "event": "stop",
        "reason": why[0] if why else "shutdown request",
        "uptime_s": round(uptime_s, 1),
        "apps": ",".join(sorted(core.apps)) or "none",
        "vertices": hosted,
        "seen": seen or "nothing",
        "failed_peers": ",".join(sorted(core.failed)) or "none",
    }
