"""The asyncio driver of ``mso node``: thin glue between a NodeCore and the network.

It builds a transport (:class:`~mso.net.tcp.TcpTransport`) and a routing view (the emulator's by
default, or the static ``--peer`` one), hands the core what arrives (``receive`` from
neighbours, ``request`` from clients, ``set_routes`` when the view changes, ``on_timer``) with
``loop.time()``, and carries out the core's effects: frames to send, timers, replies. Sockets,
shaping, forwarding and holding frames while routes converge live in :mod:`mso.net`.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import os
import threading
from collections.abc import Callable, Hashable, Mapping
from typing import NoReturn

import msgspec

from mso.management import load_policy
from mso.model.appfile import loads_app
from mso.net.base import RoutesChanged, RoutingView, encode
from mso.net.limits import DEFAULT_LIMITS, Limits
from mso.net.routes_emulator import EmulatorRoutes
from mso.net.tcp import TcpTransport
from mso.node.core import Effect, NodeCore, Reply, Send, SetTimer
from mso.node.device import DeviceProbe
from mso.node.status import LinkStatus
from mso.protocol import effects as fx
from mso.protocol import kept
from mso.protocol import messages as m
from mso.protocol.authority import Authority
from mso.protocol.events import Happened, MonitorTick
from mso.protocol.identity import Identity
from mso.runtime.executor import Executor

log = logging.getLogger("mso.node")
DEVICE_PERIOD_S = 1.0


class NodeDriver:
    """Runs one NodeCore on an asyncio loop."""

    def __init__(
        self,
        core: NodeCore,
        host: str,
        port: int,
        psk: bytes | list[bytes],
        view: RoutingView | None = None,
        limits: Limits = DEFAULT_LIMITS,
        authority: Authority | None = None,
        encrypt: bool = False,
        device: DeviceProbe | None = None,
        identity: Identity | None = None,
        link_mbps: Mapping[str, float] | None = None,
    ) -> None:
        self.core = core
        # configured, by peer ("*": the rest); a link's shape in the view (emulator) wins
        self.link_mbps = dict(link_mbps or {})
        core.link_rates = self._link_rate
        # what the OS measures (battery, CPU time, interface bytes), read every second and on
        # every status request; None keeps the energy model alone (emulation)
        self.device = device
        self._device_timer: asyncio.TimerHandle | None = None
        self.loop = asyncio.get_running_loop()
        # without a view of its own the node waits for the emulator's LinkStates
        self.view: RoutingView = view if view is not None else EmulatorRoutes(core.id)
        self.counters = self.view.counters
        # subscribed before the driver: on a change the transport reconnects and releases
        # waiting frames first, then the core hears of the new routes
        self.authority = authority or Authority()
        core.authority = self.authority  # the core checks undeploys and revoked grants with it
        self.transport = TcpTransport(
            core.id, host, port, psk, self.view, limits, self.authority, encrypt, identity
        )
        self.transport.set_receiver(self._receive, self._read_done)
        # with node identities a member's "I hear it" carries the suspect's own signed word,
        # which the transport sets and checks (mso.net.trust): the core asks for it
        transport = self.transport
        core.membership.proofs = lambda: transport.requires_identity
        self.transport.set_client_handler(self._request)
        self.view.subscribe(self._routes_changed)
        self._timers: dict[Hashable, asyncio.TimerHandle] = {}
        # vertex code runs in the executor's threads, whose results queue here and wake the
        # loop once per burst, or (a cheap instance) inline on this thread, in turns scheduled
        # with call_soon and drained right after: no wake-up at all
        self.executor = Executor(self._vertex_result, self._schedule_inline)
        self._results: list[fx.VertexResult] = []
        # while a read's frames or a timer are handled, the inline jobs they make wait for
        # its end and run in the same turn (a turn of the loop saved per hop: no epoll_wait,
        # no handle); otherwise (a client's request, a worker's result) in a turn of their own
        self._in_turn = False
        self._inline_due = False
        self._results_lock = threading.Lock()
        self._loop_thread = threading.get_ident()
        self.stopped = asyncio.Event()
        self._warmed: set[int] = set()  # app documents whose imports are done
        # apps whose announcement or sync is warming in a thread: the messages for the app
        # that arrive meanwhile, held to follow it in order (bounded: MAX_HELD_WARMING)
        self._warming: dict[str, list[tuple[str, m.Message]]] = {}
        self.seen: dict[str, int] = {}  # what happened, by kind: the stop line's summary

    @property
    def _server(self) -> asyncio.Server | None:
        """The listening server (tests read its port)."""
        return self.transport.server

    def _observe(self, status: bool = False, device: bool = False) -> None:
        """Hand the core what the driver measures: byte counters always; for a status, the
        device's readings and the links' state too; the device's every second."""
        links = self._link_status() if status else None
        reading = self.device.read() if self.device is not None and (status or device) else None
        c = self.counters
        self.core.observe(self.loop.time(), c.bytes_out, c.bytes_in, links=links, device=reading)

    def _link_status(self) -> LinkStatus:
        return LinkStatus(
            traffic=self.counters.as_dict(),
            connections=self.transport.connection_counters.as_dict(),
            connected=self.transport.connected(),
            tasks=len(asyncio.all_tasks(self.loop)),
            timers=len(self._timers),
            authority=self.authority.status(),
        )

    def _device_tick(self) -> None:
        self._observe(device=True)
        self._device_timer = self.loop.call_later(DEVICE_PERIOD_S, self._device_tick)

    async def start(self) -> None:
        await self.transport.start()
        recalled = kept.recall(self.core.spill)  # the apps the core takes back at its start
        for sync in recalled:  # (mso.protocol.kept): imports in a thread first, as for any
            await self.loop.run_in_executor(None, warm_imports, sync.document)  # app new here
        self._apply(self.core.start(self.loop.time(), recalled))
        if self.device is not None:
            self._device_tick()
        if self.view.routes() or self.view.neighbours():  # a static view knows them already
            self._routes_changed(None)

    async def stop(self) -> None:
        for t in self._timers.values():
            t.cancel()
        if self._device_timer is not None:
            self._device_timer.cancel()
        self.executor.shutdown()
        await self.transport.close()
        self.stopped.set()

    # -- inbound ----------------------------------------------------------------------------
    def _receive(self, src: str, msg: m.Message) -> None:
        self._in_turn = True  # (until the read's end: ``_read_done``)
        said = msg.body if type(msg) is m.Sequenced else msg  # (a control stream's frame)
        app = getattr(said, "app", None)
        if isinstance(app, str) and app in self._warming:
            self._hold_warming(app, src, msg)
            return
        if isinstance(said, m.AppAnnounce | m.AppSync) and said.app not in self.core.apps:
            if hash(said.document) not in self._warmed:
                self._warming[said.app] = []
            self._warm(said.document, lambda: self._warmed_app(said.app, src, msg))
            return
        self._receive_now(src, msg)

    def _hold_warming(self, app: str, src: str, msg: m.Message) -> None:
        """A message for an app whose announcement or sync is warming: it follows that, in
        order. Only the nodes that take part in an app hold it (issue 24.1): a move's or
        restore's target is sent the app (``AppSync``) just ahead of its ``Prepare``, and a
        ``Prepare`` that overtook the sync was answered "does not run app" (a restore failed,
        and the recovery ran twice)."""
        held = self._warming[app]
        if len(held) >= MAX_HELD_WARMING:
            self.core.refusal("held_while_warming_full")
            return
        held.append((src, msg))

    def _warmed_app(self, app: str, src: str, msg: m.Message) -> None:
        """The app's imports are done: its announcement or sync, then what came meanwhile."""
        held = self._warming.pop(app, [])
        self._receive_now(src, msg)
        for s, later in held:
            if self.stopped.is_set():
                return
            self._receive(s, later)
        if held:
            self._read_done()

    def _receive_now(self, src: str, msg: m.Message) -> None:
        if isinstance(msg, m.StatusRequest):
            self._observe(status=True)
        self._apply(self.core.receive(src, msg, self.loop.time()))

    def _warm(self, document: str, then: Callable[[], None]) -> None:
        """Import an app's code, formats and policy in a thread, then hand the message on.
        The core loads the app on the control plane; with its modules already imported that
        is quick, while a first import (numpy, scipy: seconds on a small CPU) would stop the
        heartbeats and get this node declared failed. Messages for the app that overtake it
        are held by the core until the announcement arrives."""

        key = hash(document)
        if key in self._warmed:  # imported once already (a redeploy, a rejoin): go on
            then()
            return

        def done(_: asyncio.Future[None]) -> None:
            if len(self._warmed) >= MAX_WARMED:
                self._warmed.clear()
            self._warmed.add(key)
            if not self.stopped.is_set():
                then()

        self.loop.run_in_executor(None, warm_imports, document).add_done_callback(done)

    def _request(self, client: int, msg: m.Message) -> None:
        if isinstance(msg, m.DeployRequest):
            asked = self.loop.time()

            def deploy() -> None:  # the client's wait counts from its request, warming too
                now = self.loop.time()
                req = msg
                if msg.within_s > 0:  # (not NaN)
                    req = msgspec.structs.replace(
                        msg, within_s=max(msg.within_s - (now - asked), 1e-3)
                    )
                self._apply(self.core.request(client, req, now))

            self._warm(msg.document, deploy)
        elif isinstance(msg, m.LinkState):
            self.apply_links(msg)
        elif isinstance(msg, m.Shutdown):
            self.loop.create_task(self.stop())
        else:
            self._request_now(client, msg)

    def _request_now(self, client: int, msg: m.Message) -> None:
        if isinstance(msg, m.StatusRequest):
            self._observe(status=True)
        self._apply(self.core.request(client, msg, self.loop.time()))

    def _link_rate(self, peer: str) -> float | None:
        """The rate of the link to ``peer``: the emulator's shape of it (the scenario's
        ``bandwidth_mbps``), else the configured ``link_mbps`` for that peer or for every
        link; nothing here measures it."""
        n = self.view.neighbours().get(peer)
        rate = n.shape.bandwidth_mbps if n is not None else None
        if rate is not None:
            return rate
        return self.link_mbps.get(peer, self.link_mbps.get("*"))

    def _routes_changed(self, _: RoutesChanged | None) -> None:
        self._apply(self.core.set_routes(dict(self.view.routes()), self.loop.time()))

    # -- outbound ---------------------------------------------------------------------------
    def _apply(self, effects: list[Effect]) -> None:
        for eff in effects:
            if isinstance(eff, Send):
                try:
                    payload, kind = encode(self.core.id, eff.dst, eff.msg)
                except (OverflowError, TypeError, ValueError) as exc:  # a bug, not a crash
                    log.error("cannot encode %s for %s: %s", type(eff.msg).__name__, eff.dst, exc)
                    self.counters.frames_unroutable += 1
                    continue
                self.transport.send(eff.dst, payload, kind)
            elif isinstance(eff, SetTimer):
                old = self._timers.pop(eff.key, None)
                if old is not None:
                    old.cancel()
                self._timers[eff.key] = self.loop.call_at(eff.at, self._fire, eff.key)
            elif isinstance(eff, Reply):
                self.transport.reply(eff.client, eff.msg)
            elif isinstance(eff, fx.CancelTimer):
                timer = self._timers.pop(eff.key, None)
                if timer is not None:
                    timer.cancel()
            else:
                self.executor.submit(eff)
        for h in self.core.drain_happened():
            self._log_happened(h)
        view, failed = self.view, self.core.failed
        if isinstance(view, EmulatorRoutes) and failed != view.avoided:  # (no copy per event)
            view.avoid(frozenset(failed))  # relay nothing through a daemon held failed

    def _log_happened(self, h: Happened) -> None:
        """One line for what the core reported: a deployment, a move, a peer failed or back."""
        self.seen[h.what] = self.seen.get(h.what, 0) + 1
        level = logging.WARNING if h.error or h.what in ("peer_failed", "reset") else logging.INFO
        if h.by == "remap" and not h.error:
            level = logging.DEBUG  # a remap's steps: the remap's own line says where all went
        if log.isEnabledFor(level):
            kv: dict[str, object] = {"event": h.what, "app": h.app}
            if h.subject:
                kv["vertex" if h.app else "peer"] = h.subject
            if h.detail:
                kv["move" if h.app else "detail"] = h.detail
            kv |= {"by": h.by, "took_ms": h.took_ms, "error": h.error, "asked": h.asked}
            log.log(level, "%s", h.what, extra={"kv": kv})

    def _vertex_result(self, result: fx.VertexResult) -> None:
        """Called from a worker thread, or from an inline turn (drained when it ends)."""
        with self._results_lock:
            wake = not self._results
            self._results.append(result)
        if wake and threading.get_ident() != self._loop_thread:
            # RuntimeError: the loop closed while the node stopped, nothing to tell
            with contextlib.suppress(RuntimeError):
                self.loop.call_soon_threadsafe(self._drain_results)

    def _schedule_inline(self) -> None:
        if self._in_turn:
            self._inline_due = True
        else:
            self.loop.call_soon(self._run_inline)

    def _read_done(self) -> None:
        """The frames of one read are handled: run the inline jobs they made now."""
        self._in_turn = False
        if self._inline_due:
            self._inline_due = False
            self._run_inline()

    def _run_inline(self) -> None:
        """A turn of the cheap instances' jobs on this thread, then their results."""
        if self.stopped.is_set():
            return
        self.executor.run_inline()
        self._drain_results()

    def _drain_results(self) -> None:
        with self._results_lock:
            results, self._results = self._results, []
        for result in results:
            self._apply(self.core.on_vertex(result, self.loop.time()))

    def spill_ready(self, key: str) -> None:
        """On the loop: the spill store's reader thread has events of ``key`` in memory."""
        if not self.stopped.is_set():
            self._apply(self.core.on_spill(key, self.loop.time()))

    def _fire(self, key: Hashable) -> None:
        self._timers.pop(key, None)
        if isinstance(key, MonitorTick):  # the monitor samples the byte counters
            self._observe()
            if self.device is not None and not self.device.battery and self.core.monitor.empty:
                self._battery_empty()
        self._in_turn = True  # a rated source's tick runs its call in this turn
        try:
            self._apply(self.core.on_timer(key, self.loop.time()))
        finally:
            self._read_done()

    def _battery_empty(self) -> NoReturn:
        """An emulated device (its battery modelled, not read from the OS) whose battery is
        spent stops at once, as a robot does: no goodbye, nothing handed over (fail-stop)."""
        kv = {"event": "battery_empty", "detail": "the modelled battery is spent: fail-stop"}
        log.error("battery empty", extra={"kv": kv})
        for handler in logging.getLogger().handlers:
            handler.flush()
        os._exit(BATTERY_EMPTY_EXIT)

    # -- links ------------------------------------------------------------------------------
    def apply_links(self, state: m.LinkState) -> None:
        """Take the emulator's view: neighbours, shapes and routes (older versions ignored)."""
        if isinstance(self.view, EmulatorRoutes):
            self.view.apply(state)
        else:
            log.warning("ignoring a LinkState: this node's routing view is not the emulator's")


async def run_node(core: NodeCore, host: str, port: int, psk: bytes) -> None:
    """Serve until a Shutdown request or cancellation."""
    driver = NodeDriver(core, host, port, psk)
    await driver.start()
    log.info("node %s listening on %s:%s", core.id, host, port)
    try:
        await driver.stopped.wait()
    finally:
        if not driver.stopped.is_set():
            await driver.stop()


MAX_WARMED = 256
# messages held for an app while its announcement or sync warms (a few seconds at most)
MAX_HELD_WARMING = 4096
BATTERY_EMPTY_EXIT = 3  # the exit code of a node whose modelled battery emptied
PARENT_ENV = "MSO_PARENT_PID"  # set by an emulator for the node processes it starts
PARENT_CHECK_S = 0.5


async def stop_with_parent(driver: NodeDriver, parent: int) -> None:
    """Stop the node once the process that started it is gone (an emulator killed or crashed:
    the node is re-parented), so no node process outlives its emulator."""
    while not driver.stopped.is_set() and os.getppid() == parent:
        await asyncio.sleep(PARENT_CHECK_S)
    if not driver.stopped.is_set():
        await driver.stop()


def warm_imports(document: str) -> None:
    """Import what an app document names (code, formats, its policy), as far as it loads;
    errors are the core's to report when it loads the app for real."""
    try:
        app = loads_app(document, file="<warm>")
        if app.policy is not None:
            load_policy(app.policy, where="<warm>")
    except Exception:  # the core reports it, with the app's name
        log.debug("warming an app's imports failed", exc_info=True)
