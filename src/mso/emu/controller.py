"""The user-space MANET emulator (the default; no root): one OS process per node.

Each node runs the ordinary ``mso node`` daemon on its own loopback address (127.0.1.i). The
controller turns the scenario into a link graph, tells every node its current neighbours (with
each link's bandwidth, delay and loss, applied in the sender's link layer) and its routes
(shortest paths, pushed ``convergence_s`` after a link change, as a routing protocol would
converge), plays the scenario's timeline (``mso.scenario.timeline``, shared with the
simulator), and stops every process it started —
by PID, on Ctrl-C, at the end of ``duration``, or if it fails.

It never gives up on a node: an operator's commands (:meth:`Emulator.fail`, ``restart``,
``cut``, ``heal``, ``move``; the console and ``mso emulator`` send them) change the same
timeline the script plays, a node that dies unscripted loses its links as a failed one does and
can be restarted, and a node that does not answer is told (``tell``), never fatal.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import os
import random
import secrets
import shutil
import socket
import subprocess
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from mso.api import AsyncOverlay
from mso.client import Client, NodeUnreachable, overlay_key
from mso.daemon.logs import RUN_START_ENV
from mso.emu.overlays import (
    _claim,
    give,
    keep_logs,
    make_log_dir,
    remove_key,
    state_file,
    write_key,
)
from mso.errors import MsoError
from mso.model.network import LinkSpec, Network
from mso.node.driver import BATTERY_EMPTY_EXIT, PARENT_ENV
from mso.protocol import messages as m
from mso.protocol.authority import Signer
from mso.protocol.procedures.membership.liveness import DEAD_AFTER_S, HEARTBEAT_S, check_timing
from mso.scenario import Scenario
from mso.scenario.format import LinkChange, NodeFailure, NodeRestart
from mso.scenario.timeline import Action, Crash, Cut, Move, OperatorChange, Restart, Timeline

TELL = Callable[[float, str], None]


def _free_port(hosts: list[str]) -> int:
    """A port free on every one of ``hosts`` (one port, many loopback addresses)."""
    rng = random.Random()
    for _ in range(200):
        port = rng.randrange(20000, 40000)
        ok = True
        for host in hosts:
            with socket.socket() as s:
                try:
                    s.bind((host, port))
                except OSError:
                    ok = False
                    break
        if ok:
            return port
    raise MsoError("no free port on the loopback addresses")


# every node process imports mso, binds and meets its neighbours within this: 20 s was tight
# for four processes at load 17 on two cores (perhaps why a CI run's `mso demo` exited 2 there;
# its message was not kept); a process that exits fails the wait at once, so a slow start
# costs time, never a false error
NODE_START_S = 60.0


@dataclass
class EmulatedNode:
    id: str
    host: str
    port: int
    process: subprocess.Popen[bytes] | None = None
    client: Client | None = None
    log: Path | None = None


@dataclass
class Emulator:
    """Start, drive and stop an emulated MANET."""

    scenario: Scenario
    key: str | None = None
    convergence_s: float = 0.0
    port: int = 0
    log_dir: Path | None = None
    nodes: dict[str, EmulatedNode] = field(default_factory=dict)
    version: int = 0
    routes: dict[str, dict[str, list[Any]]] = field(default_factory=dict)
    positions: dict[str, tuple[float, float]] = field(default_factory=dict)
    _route_task: asyncio.Task[None] | None = None
    _own_logs: bool = False
    failed: bool = False  # a node died or misbehaved: its logs are kept for a look
    dead: dict[str, float] = field(default_factory=dict)  # node -> when its process died
    killed: set[str] = field(default_factory=set)  # killed on purpose (scenario, benchmark)
    # restarted nodes whose process does not listen yet: their links are not pushed (a relay
    # announced before it runs swallowed a healed edge's frames, resent every 0.25 s)
    starting: set[str] = field(default_factory=set)
    _watch_task: asyncio.Task[None] | None = None
    policy: str | None = None  # every node's policy (apps may name their own)
    manage: bool = True  # run the management rules on the nodes
    _playing: bool = False  # a timeline is being played (play_changes / play_mobility)
    name: str | None = None  # the overlay's name (default: the scenario's, made unique)
    dashboard: str | None = None  # the dashboard's URL, told to `mso overlays`
    metrics_port: int | None = None  # each node serves Prometheus metrics here (0: a free port)
    heartbeat_s: float | None = None  # every node's heartbeat period (None: the node default)
    dead_after_s: float | None = None  # every node's failure timeout (None: the node default)
    # modules every node may import app code from (None: $MSO_ALLOW_CODE, else the examples)
    allow_code: tuple[str, ...] | None = None
    operator_keys: tuple[str, ...] = ()  # public keys every node obeys (--operator-key)
    encrypt: bool = False  # ChaCha20-Poly1305 frames between every node and with the emulator
    # this emulator's own key: its nodes take LinkStates and Shutdowns signed with it only
    signer: Signer = field(default_factory=Signer)
    # node identities (mso.emu.identities): the emulator's key is the run's operator key, each
    # node has its own certified key, clients need one; where the user's keys were left
    identities: bool = False
    user_keys: tuple[Path, Path] | None = None
    timeline: Timeline | None = None  # the one player of scripted and operator changes
    t0: float = 0.0  # loop time of the run's start: every time told is seconds after it
    wall0: float = 0.0  # the same moment on the wall clock, for the nodes' log lines
    tell: TELL | None = None  # told (run time, a sentence) of every fault and command
    story: list[tuple[float, str]] = field(default_factory=list)  # what was told, in order
    emptied: set[str] = field(default_factory=set)  # stopped by an empty battery (fail-stop)

    async def start(self, timeout: float = NODE_START_S) -> None:
        names = list(self.scenario.network.nodes)
        if len(names) > 250:
            raise MsoError("the user-space emulator supports at most 250 nodes")
        hb, da = self.heartbeat_s, self.dead_after_s
        if hb is not None or da is not None:  # checked before any node process would refuse
            why = check_timing(
                HEARTBEAT_S if hb is None else hb, DEAD_AFTER_S if da is None else da
            )
            if why:
                raise MsoError(why)
        self._begin()
        hosts = [f"127.0.1.{i + 1}" for i in range(len(names))]
        port = self.port or _free_port(hosts)
        if self.metrics_port == 0:
            while (mp := _free_port(hosts)) == port:
                pass
            self.metrics_port = mp
        self.name = _claim(self.name, self.scenario.name)
        if self.log_dir is None:  # ours to remove after a clean stop
            self.log_dir = make_log_dir("mso-emu-")
            self._own_logs = True
        env = self._env()
        for name, host in zip(names, hosts, strict=True):
            self.nodes[name] = EmulatedNode(name, host, port)
            self._spawn(name, env)
        try:
            await asyncio.gather(*(self._connect(n, timeout) for n in self.nodes.values()))
            await self.push_links(routes=True)
            await self.wait_links(timeout)
        except BaseException:
            await self.stop()
            raise
        self._started()

    def _make_identities(self, names: list[str]) -> None:
        """The secure configuration for this run (:mod:`mso.emu.identities`)."""
        from mso.emu.identities import leave_for_user, node_identities

        assert self.log_dir is not None and self.name is not None
        if self.signer.public_text() not in self.operator_keys:
            self.operator_keys += (self.signer.public_text(),)
        node_identities(self.signer, names, self.log_dir / "identities")
        self.user_keys = leave_for_user(self.signer, self.name)

    def _begin(self) -> None:
        """The run's clock starts: the console's times, the scripted changes' and every node's
        log lines (``MSO_RUN_START``) count seconds from here."""
        self.t0 = asyncio.get_running_loop().time()
        self.wall0 = time.time()

    def _started(self) -> None:
        """The nodes are up: the timeline and the watch start."""
        if self.timeline is None:
            self.timeline = Timeline(self.scenario)
        self._watch_task = asyncio.create_task(self._watch())
        self.write_state()

    def now(self) -> float:
        """Seconds since the run started (the clock of everything told)."""
        return asyncio.get_running_loop().time() - self.t0

    def say(self, text: str) -> None:
        """Tell what happened (a fault, a command's outcome, a node that does not answer)."""
        at = self.now()
        self.story.append((at, text))
        del self.story[:-500]
        if self.tell is not None:
            self.tell(at, text)

    def __post_init__(self) -> None:
        if self.key == "":  # never a silent fall-back to the development key
            raise MsoError("--key: an empty overlay key is refused (give one, or leave --key out)")

    def _env(self) -> dict[str, str]:
        """The nodes' environment. Their overlay key is the one given (``--key``, $MSO_KEY),
        else one made up for this run and left for this user only (:func:`write_key`): with
        the development key any local user could join a loopback overlay. With
        ``identities``, the run's keys are made here too."""
        env = dict(os.environ)
        key = self.key or env.get("MSO_KEY", "")
        if not key:
            key = secrets.token_hex(16)
            assert self.name is not None
            write_key(self.name, key)
        env["MSO_KEY"] = key
        env["MSO_EMULATOR_KEY"] = self.signer.public_text()
        if self.identities and self.user_keys is None:  # (both backends start through here)
            self._make_identities(list(self.scenario.network.nodes))
        if self.encrypt:
            env["MSO_ENCRYPT"] = "1"
        else:
            env.pop("MSO_ENCRYPT", None)
        self.key = env["MSO_KEY"]
        env[PARENT_ENV] = str(os.getpid())  # a node outlives no emulator, even one killed
        env[RUN_START_ENV] = repr(self.wall0)  # its log lines on the run's clock
        return env

    def _spawn(self, name: str, env: dict[str, str]) -> None:
        """Start node ``name``'s daemon process (again, for a restart)."""
        assert self.log_dir is not None
        node = self.nodes[name]
        node.log = self.log_dir / f"{name}.log"
        with node.log.open("ab") as out:
            node.process = subprocess.Popen(
                self._node_command(name), stdout=out, stderr=subprocess.STDOUT, env=env,
                start_new_session=True,
            )  # fmt: skip

    def _node_command(self, name: str) -> list[str]:
        """The ``mso node`` command line of node ``name`` (its scenario capacities)."""
        node = self.nodes[name]
        spec = self.scenario.network.nodes[name]
        cmd = [
            sys.executable, "-m", "mso", "node", "--id", name,
            "--listen", f"{node.host}:{node.port}", "--cpu", str(spec.cpu),
            "--power", ",".join(str(x) for x in (spec.power.idle_w, spec.power.cpu_w,
                                                 spec.power.tx_uj_per_byte,
                                                 spec.power.rx_uj_per_byte,
                                                 spec.power.cpu_energy)),
        ]  # fmt: skip
        cmd += ["--energy", "model"]  # the scenario's device, not the host's battery
        assert self.log_dir is not None  # each node's own state, kept across its restarts
        cmd += ["--state-dir", str(self.log_dir / "state" / name)]
        if spec.battery_wh is not None:
            cmd += ["--battery-wh", str(spec.battery_wh)]
        for name, amount in spec.capabilities.items():
            cmd += ["--capability", f"{name}={amount!r}"]
        if self.policy is not None:
            cmd += ["--policy", self.policy]
        if not self.manage:
            cmd.append("--no-manage")
        if self.heartbeat_s is not None:
            cmd += ["--heartbeat", repr(self.heartbeat_s)]
        if self.dead_after_s is not None:
            cmd += ["--dead-after", repr(self.dead_after_s)]
        if self.metrics_port is not None:
            cmd += ["--metrics", f"{node.host}:{self.metrics_port}"]
        for module in self.allow_code or ():
            cmd += ["--allow-code", module]
        for pub in self.operator_keys:
            cmd += ["--operator-key", pub]
        if self.identities:
            cmd += ["--identity", str(self.log_dir / "identities" / f"{node.id}.key")]
        return cmd

    # -- faults and commands ------------------------------------------------------------------
    def _node(self, node: str) -> EmulatedNode:
        n = self.nodes.get(node)
        if n is None:
            raise MsoError(f"unknown node {node!r} (nodes: {', '.join(self.nodes)})")
        return n

    def running(self, node: str) -> bool:
        proc = self._node(node).process
        return proc is not None and proc.poll() is None

    async def change(self, change: OperatorChange) -> None:
        """Apply one change now (on the timeline the script plays) and carry it out."""
        assert self.timeline is not None, "start() first"
        try:
            actions = self.timeline.apply(change)
        except ValueError as exc:
            raise MsoError(str(exc)) from None
        await self.carry_out(actions)

    async def carry_out(self, actions: list[Action]) -> None:
        """Do what the timeline says: kill, restart, push the links that changed. A node that
        does not come back is told, not raised: the run goes on."""
        for action in actions:
            if isinstance(action, Crash):
                if self.running(action.node):
                    self.kill(action.node)
            elif isinstance(action, Restart):
                try:
                    await self._start_again(action.node)
                except MsoError as exc:
                    self.say(f"{action.node} did not come back: {exc}")
                if action.node in self.starting:  # not started here: the links as they are
                    self.starting.discard(action.node)
                    await self._links_changed()
            else:  # a restart's links (its sync comes first) wait until it listens
                self.starting.update(a.node for a in actions if isinstance(a, Restart))
                await self._links_changed()

    async def fail(self, node: str) -> str:
        """Fail-stop ``node`` now (SIGKILL by PID); its links go."""
        if not self.running(node):
            raise MsoError(f"node {node} is not running ('restart {node}' starts it)")
        await self.change(NodeFailure(self.now(), node))
        return f"{node} failed (killed); its links are down"

    async def restart(self, node: str, timeout: float = NODE_START_S) -> str:
        """Start a failed, killed or crashed ``node`` again: a new process, so a new
        incarnation; its links come back once it listens. The others restore what it hosted."""
        if self.running(node):
            raise MsoError(f"node {node} is still running ('fail {node}' stops it)")
        assert self.timeline is not None, "start() first"
        if node not in self.timeline.dead:  # died before the watch saw it
            await self.change(NodeFailure(self.now(), node))
        await self.change(NodeRestart(self.now(), node))
        if not self.running(node) or self._node(node).client is None:
            raise MsoError(f"node {node} did not come back; see {self._node(node).log}")
        fresh = " with a full battery" if node in self.emptied else ""
        self.emptied.discard(node)
        return f"{node} restarted{fresh} (a new incarnation); its links are back"

    async def cut(self, a: str, b: str) -> str:
        """Cut the link ``a``-``b`` until :meth:`heal` (whatever the radio or script says)."""
        assert self.timeline is not None, "start() first"
        if (min(a, b), max(a, b)) in self.timeline.cuts:
            raise MsoError(f"{a}-{b} is already cut")
        await self.change(Cut(self.now(), a, b))
        return f"cut {a}-{b}"

    async def heal(self, a: str, b: str) -> str:
        """Undo a :meth:`cut` (the link is back if the radio still gives it)."""
        assert self.timeline is not None, "start() first"
        if (min(a, b), max(a, b)) not in self.timeline.cuts:
            cuts = ", ".join("-".join(k) for k in sorted(self.timeline.cuts)) or "none"
            raise MsoError(f"{a}-{b} is not cut (cut: {cuts})")
        await self.change(Cut(self.now(), a, b, cut=False))
        up = self.scenario.network.link(a, b) is not None
        return f"healed {a}-{b}" + ("" if up else " (the radio gives no link there now)")

    async def move(self, node: str, x: float, y: float) -> str:
        """Put ``node`` at (x, y) metres and keep it there; links follow positions if the
        scenario has a radio range."""
        await self.change(Move(self.now(), node, (x, y)))
        if self.timeline is not None and self.timeline.positions != self.positions:
            self.positions = dict(self.timeline.positions)
            self.write_state()
        if self.scenario.radio_range is None:
            return f"{node} is at ({x:g}, {y:g}); links do not follow (no radio_range)"
        near = ", ".join(self.scenario.network.neighbours(node)) or "none"
        return f"{node} is at ({x:g}, {y:g}); in range of {near}"

    async def _start_again(self, node: str, timeout: float = NODE_START_S) -> None:
        n = self._node(node)
        if n.process is not None and n.process.poll() is None and node not in self.killed:
            return  # never killed (the timeline only thought so)
        if n.process is not None:  # killed a moment ago, maybe not reaped yet
            await asyncio.to_thread(n.process.wait, 5)
        if n.client is not None:
            with contextlib.suppress(Exception):
                await n.client.close()
            n.client = None
        self._spawn(node, self._env())
        self.dead.pop(node, None)
        self.killed.discard(node)
        await self._connect(n, timeout)
        self.starting.discard(node)
        await self._links_changed()

    async def _watch(self, period: float = 0.05) -> None:
        """Notice node processes that die: their links vanish, as a routing protocol would
        notice (routes follow after the convergence delay). One that died unscripted is told
        and stays down until restarted."""
        loop = asyncio.get_running_loop()
        while True:
            await asyncio.sleep(period)
            for name, node in list(self.nodes.items()):
                if name in self.dead or node.process is None or node.process.poll() is None:
                    continue
                self.dead[name] = loop.time()
                code = node.process.returncode
                if code == BATTERY_EMPTY_EXIT:
                    self.emptied.add(name)
                    self.say(f"{name}'s battery is empty: it stopped (fail-stop)")
                elif name not in self.killed:
                    if code != -9:  # a crash, not a kill -9 by hand: keep the logs
                        self.failed = True
                    self.say(self.died(name, code))
                if node.client is not None:
                    with contextlib.suppress(Exception):
                        await node.client.close()
                    node.client = None
                assert self.timeline is not None
                if name not in self.timeline.dead:
                    with contextlib.suppress(MsoError):
                        await self.change(NodeFailure(self.now(), name))

    def died(self, node: str, code: int | None) -> str:
        """Why a node process ended that no one asked to stop, in words."""
        how = "killed by hand" if code == -9 else f"exited with code {code}"
        return f"{node} died ({how}, not scripted): its links are down; 'restart {node}' again"

    def kill(self, node: str) -> float:
        """Fail-stop ``node`` now (SIGKILL to its process, by PID); returns the loop time."""
        n = self._node(node)
        if n.process is None:
            raise MsoError(f"node {node} has no process")
        self.killed.add(node)
        n.process.kill()
        return asyncio.get_running_loop().time()

    def live(self) -> list[str]:
        return [n for n in self.nodes if n not in self.dead and n not in self.killed]

    async def _connect(self, node: EmulatedNode, timeout: float) -> None:
        loop = asyncio.get_running_loop()
        deadline = loop.time() + timeout
        psk = overlay_key(self.key)
        while True:
            if node.process is not None and node.process.poll() is not None:
                self.failed = True
                raise MsoError(f"node {node.id} exited at start; see {node.log}")
            try:
                node.client = await self.client_for(node, psk).connect(1.0)
                return
            except NodeUnreachable:
                if loop.time() > deadline:
                    raise MsoError(f"node {node.id} did not start within {timeout:g} s") from None
                await asyncio.sleep(0.05)

    def client_for(self, node: EmulatedNode, psk: bytes, name: str = "emulator") -> Client:
        """A (not yet connected) client of ``node``; it signs LinkStates and Shutdowns with
        this emulator's key, and encrypts when the overlay does."""
        from mso.protocol.clients import operator_client

        return Client(
            node.host, node.port, psk, name, signer=self.signer, encrypt=self.encrypt,
            identity=operator_client(self.signer),  # (with identities, a client must be one)
        )  # fmt: skip

    def _link_state(self, node: str, routes: bool, net: Network) -> m.LinkState:
        neighbours: dict[str, list[Any]] = {}
        for n in net.neighbours(node):
            link = net.link(node, n)
            assert link is not None
            peer = self.nodes[n]
            neighbours[n] = [peer.host, peer.port, link.bandwidth_mbps, link.delay_ms, link.loss]
        if routes:  # converged: shortest paths on the current links
            table: dict[str, list[Any]] = {}
            for dst in net.nodes:
                r = net.route(node, dst)
                if r is not None and dst != node:
                    table[dst] = [r[1], len(r) - 1]
            self.routes[node] = table
        links = [[a, b] for a, b in sorted(net.links)] if routes else []
        return m.LinkState(
            version=self.version,
            neighbours=neighbours,
            routes=self.routes.get(node, {}),
            links=links,
        )

    async def push_links(self, routes: bool) -> None:
        """Send every node its neighbours, and its routes if they have converged (without the
        links of a restarted node that does not listen yet: it relays nothing before)."""
        self.version += 1
        net = self.scenario.network
        if self.starting:
            links = [s for (a, b), s in net.links.items() if not {a, b} & self.starting]
            net = Network(list(net.nodes.values()), links)
        for name, node in list(self.nodes.items()):
            if node.client is not None and name not in self.killed:
                with contextlib.suppress(MsoError, OSError):
                    await node.client.send(self._link_state(name, routes, net))

    async def wait_links(self, timeout: float = 10.0) -> None:
        """Wait until every node has a connection to each of its current neighbours."""
        loop = asyncio.get_running_loop()
        deadline = loop.time() + timeout
        net = self.scenario.network
        for name in self.nodes:
            while True:
                nodes = await self.overlay(name).status(everywhere=False, timeout=5.0)
                connected = set(nodes[name].get("connected", []))
                if set(net.neighbours(name)) <= connected:
                    break
                if loop.time() > deadline:
                    raise MsoError(f"node {name} did not connect to its neighbours in time")
                await asyncio.sleep(0.02)

    async def set_link(self, a: str, b: str, up: bool, link: LinkSpec | None = None) -> None:
        """A link appears or disappears now; routes follow after the convergence delay."""
        await self.change(LinkChange(self.now(), a, b, up, link or LinkSpec(a, b)))

    async def _converge(self) -> None:
        await asyncio.sleep(self.convergence_s)
        await self.push_links(routes=True)

    async def play(self, t0: float | None = None, timeline: Timeline | None = None) -> None:
        """Play the scenario's timeline (scripted changes and mobility, the same player the
        simulator uses) at its times, seconds after ``t0`` (the run's start), until it ends or
        is cancelled. A step that fails is told and the play goes on."""
        tl = timeline or self.timeline or Timeline(self.scenario)
        self.timeline = tl
        start = self.t0 if t0 is None else t0
        loop = asyncio.get_running_loop()
        self._playing = True
        try:
            while (at := tl.next_at()) is not None:
                await asyncio.sleep(max(0.0, start + at - loop.time()))
                actions = tl.advance(at)
                for action in actions:
                    if isinstance(action, Crash):
                        self.say(f"{action.node} fails (scripted)")
                    elif isinstance(action, Restart):
                        self.say(f"{action.node} restarts (scripted)")
                await self.carry_out(actions)  # together: a restart's links wait for it
                if tl.positions and tl.positions != self.positions:
                    self.positions = dict(tl.positions)
                    if self.name is not None and self.nodes:
                        self.write_state()  # a dashboard elsewhere draws them
        finally:
            self._playing = False

    async def play_changes(self, t0: float | None = None) -> None:
        """Play the whole timeline (changes and mobility) unless it is already playing."""
        if not self._playing:
            await self.play(t0)

    async def play_mobility(self, t0: float | None = None) -> None:
        """Kept for callers that start both: the timeline plays mobility with the changes."""
        await self.play_changes(t0)

    async def _links_changed(self) -> None:
        await self.push_links(routes=self.convergence_s <= 0)
        if self.convergence_s > 0:
            if self._route_task is not None:
                self._route_task.cancel()
            self._route_task = asyncio.create_task(self._converge())

    def address(self, node: str) -> str:
        n = self.nodes.get(node)
        if n is None:
            raise MsoError(f"unknown node {node!r} (nodes: {', '.join(self.nodes)})")
        return f"{n.host}:{n.port}"

    def overlay(self, node: str) -> AsyncOverlay:
        """The overlay through ``node``, over the connection this emulator keeps to it (its
        requests and their replies are judged in :mod:`mso.api`, as the CLI's are)."""
        address = self.address(node)
        client = self.nodes[node].client
        if client is None:
            raise MsoError(f"node {node} is not running")
        return AsyncOverlay(address, client=client)

    async def open_overlay(
        self, node: str, name: str = "emulator", timeout: float = 5.0
    ) -> AsyncOverlay:
        """The overlay through ``node`` over a new connection (signed and encrypted as this
        emulator's), for the caller to close: a node that drops it leaves the kept one be."""
        address = self.address(node)
        client = self.client_for(self.nodes[node], overlay_key(self.key), name)
        return AsyncOverlay(address, client=await client.connect(timeout), owned=True)

    async def deploy(
        self, document: str, file: str, via: str, *, check: bool = False
    ) -> m.DeployReply:
        """Deploy from ``via``; a failed deployment's reply is returned, not raised (unless
        ``check``: then it raises :class:`mso.api.CommandFailed`)."""
        req = m.DeployRequest(document=document, file=file)
        return await self.overlay(via).deploy_request(req, check=check)

    async def relocate(
        self,
        app: str,
        vertex: str,
        *,
        direction: str = "",
        target: str = "",
        via: str | None = None,
    ) -> m.RelocateReply:
        """Relocate through ``via``; a refusal's reply is returned, not raised."""
        ov = self.overlay(via or self.live()[0])
        return await ov.relocate(app, vertex, direction=direction, target=target, check=False)

    async def undeploy(self, app: str, via: str | None = None) -> None:
        """Stop an app on every node (its stones are freed)."""
        await self.overlay(via or self.live()[0]).undeploy(app, check=False)

    async def status(self, via: str | None = None, timeout: float = 5.0) -> dict[str, Any]:
        """Every reachable node's status, asked through ``via`` or else through each live
        node in turn until one answers (one that does not is told, not fatal)."""
        if via is not None:
            return await self.overlay(via).status(timeout=timeout)
        silent = []
        for name in self.live():
            if self.nodes[name].client is None:
                continue
            try:
                return await self.overlay(name).status(timeout=timeout)
            except (MsoError, OSError) as exc:
                silent.append(f"{name} ({exc})")
        raise NodeUnreachable(
            "no node answered a status request: " + ("; ".join(silent) or "none is running")
        )

    def node_positions(self) -> dict[str, tuple[float, float]]:
        """Where the nodes are now: moved by the timeline, else as the scenario placed them."""
        static = {n: s.pos for n, s in self.scenario.network.nodes.items() if s.pos is not None}
        return static | self.positions

    def write_state(self) -> None:
        """Let `mso status` / `mso deploy --via N1` in another terminal find the nodes (never
        the key: whoever drives the overlay brings it)."""
        assert self.name is not None
        state = {
            "name": self.name,
            "pid": os.getpid(),
            "uid": os.geteuid(),
            "scenario": self.scenario.name,
            "nodes": {n: self.address(n) for n in self.nodes},
            "dashboard": self.dashboard,
            "positions": {n: list(p) for n, p in self.node_positions().items()},
            "logs": {n: str(node.log) for n, node in self.nodes.items() if node.log},  # mso logs
        }
        tmp = state_file(self.name).with_suffix(".tmp")
        tmp.write_text(json.dumps(state))
        give(tmp)
        tmp.replace(state_file(self.name))

    async def stop(self, grace: float = 3.0) -> None:
        """Ask every node to shut down; kill (by PID) whatever is still running after grace."""
        for task in (self._route_task, self._watch_task):
            if task is not None:
                task.cancel()
        for node in self.nodes.values():
            if node.client is not None:
                with contextlib.suppress(Exception):
                    await node.client.send(m.Shutdown())
                with contextlib.suppress(Exception):
                    await node.client.close()
                node.client = None
        loop = asyncio.get_running_loop()
        deadline = loop.time() + grace
        for node in self.nodes.values():
            proc = node.process
            if proc is None:
                continue
            while proc.poll() is None and loop.time() < deadline:
                await asyncio.sleep(0.02)
            if proc.poll() is None:
                proc.kill()
                proc.wait(timeout=5)
        if self.name is not None:
            path = state_file(self.name)
            with contextlib.suppress(OSError, ValueError):
                if json.loads(path.read_text()).get("pid") == os.getpid():
                    path.unlink()
                    remove_key(self.name)
        clean = all(
            n.process is None or n.process.returncode in (0, -9, BATTERY_EMPTY_EXIT)
            for n in self.nodes.values()
        )
        if self._own_logs and self.log_dir is not None:
            if clean and not self.failed:
                shutil.rmtree(self.log_dir, ignore_errors=True)
            else:
                keep_logs(self.log_dir, "a node crashed or exited with an error")
                self.say(f"node logs kept for a look in {self.log_dir} (removed in a day)")
