"""``mso emulate --backend netns``: the scenario on the namespace testbed, with a real routing
daemon (babeld or batmand: ``--routing``) — the path a real deployment takes.

Each node is the ordinary ``mso node`` daemon started inside its own network namespace with
``--routes kernel``: it reads the routes the daemon installs in its namespace and finds the other
nodes by their announcements, and the kernel forwards multi-hop traffic. The controller keeps
the user-space emulator's interface (:class:`~mso.emu.controller.Emulator`: deploy, status,
kill, restart, play the timeline) but carries out link changes as nftables set updates on the
testbed's bridge instead of LinkStates, and leaves routes to the daemon: ``--convergence`` does not
apply; the daemon's own convergence is what the middleware sees.

It talks to every node over a socket made inside the node's namespace (to 127.0.0.1 there), so
nothing outside the testbed's namespaces is contacted and the controller's traffic never
touches the emulated radio. The testbed is torn down on every exit path (stop, Ctrl-C, an
exception, interpreter exit, SIGTERM); what a killed controller leaves, the next run or
``mso emulate --cleanup`` removes.
"""

from __future__ import annotations

import asyncio
import atexit
import contextlib
import shutil
import subprocess
from collections import deque
from dataclasses import dataclass, field

from mso.client import Client
from mso.emu.controller import EmulatedNode, Emulator
from mso.emu.netns.daemons import DAEMONS, missing
from mso.emu.netns.testbed import Testbed, unavailable
from mso.emu.overlays import _claim, make_log_dir
from mso.errors import MsoError
from mso.protocol.procedures.membership.liveness import DEAD_AFTER_S, HEARTBEAT_S, check_timing

NODE_PORT = 7000
HEARTBEAT_NETNS_S = 0.1
DEAD_AFTER_NETNS_S = 0.5
"""As in user space. babeld takes 1.6-2.8 s to re-route after a link break and the route is
*missing* meanwhile; that once made a failure timeout shorter than that declare live nodes
failed, so this backend waited 3 s. mso's heartbeats now cross such gaps through a neighbour
that still reaches the node (the overlay relay), and with 0.1 s beats and 0.5 s of silence a
relay killed was detected in 0.93 s (babeld) and 0.50 s (batmand), a crashed daemon in 0.37-
0.43 s, and a 20 s route starvation declared nobody failed (bench/failure.py --heartbeat 0.1
--dead-after 0.5, bench/results/failure-netns-fast*.md)."""


class NamespacesUnavailable(MsoError):
    """Network namespaces (or the routing daemon) cannot be used here; the user-space
    backend can."""


def check_available(routing: str = "babeld") -> None:
    """Raise :class:`NamespacesUnavailable` saying why the netns backend cannot run here with
    routing daemon ``routing``."""
    why = unavailable()
    if why is None:
        why = missing(routing)
    if why is None and shutil.which("tc") is None:
        why = "tc (iproute2) is not installed"
    if why is not None:
        raise NamespacesUnavailable(f"the netns backend cannot run here: {why}")


@dataclass
class NetnsEmulator(Emulator):
    """An :class:`Emulator` whose nodes live in network namespaces and route with a routing
    daemon (``routing``: a name in :data:`~mso.emu.netns.daemons.DAEMONS`)."""

    testbed: Testbed | None = None
    routing: str = "babeld"
    routers: dict[str, subprocess.Popen[bytes]] = field(default_factory=dict)
    rates: dict[str, float | None] = field(default_factory=dict)

    async def start(self, timeout: float = 30.0) -> None:
        check_available(self.routing)
        self._begin()
        names = list(self.scenario.network.nodes)
        if self.heartbeat_s is None and self.dead_after_s is None:
            self.heartbeat_s, self.dead_after_s = HEARTBEAT_NETNS_S, DEAD_AFTER_NETNS_S
        self.name = _claim(self.name, self.scenario.name)
        hb, da = self.heartbeat_s, self.dead_after_s
        if hb is not None or da is not None:
            why = check_timing(
                HEARTBEAT_S if hb is None else hb, DEAD_AFTER_S if da is None else da
            )
            if why:
                raise MsoError(why)
        if self.log_dir is None:
            self.log_dir = make_log_dir("mso-netns-")
            self._own_logs = True
        self.testbed = tb = Testbed(names)
        atexit.register(tb.teardown)  # an interpreter exit the finally below did not see
        try:
            await asyncio.to_thread(tb.build)
            self._shape()
            await self.push_links(routes=True)
            env = self._env()
            for name in names:
                self.nodes[name] = EmulatedNode(name, tb.address(name), NODE_PORT)
                self._start_router(name)
                self._spawn(name, env)
            await asyncio.gather(*(self._connect(n, timeout) for n in self.nodes.values()))
            await self.wait_links(timeout)
        except BaseException:
            await self.stop()
            raise
        self._started()

    # -- processes ------------------------------------------------------------------------
    def _node_command(self, name: str) -> list[str]:
        cmd = super()._node_command(name)
        i = cmd.index("--listen")
        cmd[i + 1] = f"0.0.0.0:{NODE_PORT}"
        cmd[cmd.index("--energy") + 1] = "interfaces"  # each node's eth0 is its own radio
        # the kernel's view knows no link's rate: each node is configured with its links' as
        # the scenario shapes them now (probes carry them to the bytes planner)
        net = self.scenario.network
        for peer in net.neighbours(name):
            link = net.link(name, peer)
            if link is not None and link.bandwidth_mbps:
                cmd += ["--link-mbps", f"{peer}={link.bandwidth_mbps!r}"]
        return [*cmd, "--routes", "kernel"]

    def _spawn(self, name: str, env: dict[str, str]) -> None:
        assert self.testbed is not None and self.log_dir is not None
        node = self.nodes[name]
        node.log = self.log_dir / f"{name}.log"
        node.process = self.testbed.popen(name, self._node_command(name), node.log, env)

    def _start_router(self, name: str) -> None:
        assert self.testbed is not None and self.log_dir is not None
        old = self.routers.get(name)
        if old is not None and old.poll() is None:
            return
        self.routers[name] = DAEMONS[self.routing](self.testbed, name, self.log_dir)

    def client_for(self, node: EmulatedNode, psk: bytes, name: str = "emulator") -> Client:
        """A client connecting from inside the node's namespace, to 127.0.0.1 there."""
        assert self.testbed is not None
        return Client(
            "127.0.0.1", node.port, psk, name, signer=self.signer, encrypt=self.encrypt,
            netns=self.testbed.netns(node.id),
        )  # fmt: skip

    def kill(self, node: str) -> float:
        """Fail-stop the device: its node process and its routing daemon (by PID)."""
        at = super().kill(node)
        proc = self.routers.get(node)
        if proc is not None and proc.poll() is None:
            proc.kill()
            proc.wait(timeout=5)
        return at

    async def _start_again(self, node: str, timeout: float = 30.0) -> None:
        """The device comes back: its routing daemon first (a fresh one), then its node."""
        self._start_router(node)
        await super()._start_again(node, timeout)

    # -- links ----------------------------------------------------------------------------
    def _shape(self) -> None:
        """Each node's radio gets the fastest rate of its links (tbf on its egress)."""
        assert self.testbed is not None
        net = self.scenario.network
        template = self.scenario.link_template
        for n in net.nodes:
            rates = [
                s.bandwidth_mbps
                for (a, b), s in net.links.items()
                if n in (a, b) and s.bandwidth_mbps is not None
            ]
            rate = max(rates) if rates else (template.bandwidth_mbps if template else None)
            self.testbed.shape(n, rate)
            self.rates[n] = rate

    async def push_links(self, routes: bool) -> None:
        """Make the bridge's filter show the scenario's current links (the routing daemon
        does the rest)."""
        assert self.testbed is not None
        self.version += 1
        links = self.scenario.network.links
        self.testbed.set_links(links, {k: s.loss for k, s in links.items()})

    async def _links_changed(self) -> None:
        await self.push_links(routes=True)

    def reachable(self, node: str) -> set[str]:
        """The nodes ``node`` can reach over the scenario's current links."""
        net = self.scenario.network
        seen, todo = {node}, deque([node])
        while todo:
            for n in net.neighbours(todo.popleft()):
                if n not in seen and n not in self.dead:
                    seen.add(n)
                    todo.append(n)
        return seen - {node}

    async def wait_links(self, timeout: float = 30.0) -> None:
        """Wait until every node has a connection to each node it can reach: the daemon has
        converged and the kernel views have learned every id."""
        loop = asyncio.get_running_loop()
        deadline = loop.time() + timeout
        for name in self.live():
            while True:
                nodes = await self.overlay(name).status(everywhere=False, timeout=5.0)
                connected = set(nodes[name].get("connected", []))
                if self.reachable(name) <= connected:
                    break
                if loop.time() > deadline:
                    raise MsoError(
                        f"node {name} did not reach {sorted(self.reachable(name) - connected)} "
                        f"within {timeout:g} s; see {self.log_dir}"
                    )
                await asyncio.sleep(0.05)

    def address(self, node: str) -> str:
        """``NETNS@127.0.0.1:PORT``: the node as seen from inside its namespace, which is how
        `mso status` / `mso deploy` in another terminal reach it (with the key given, or the
        one this run made up and left for its user: :func:`mso.emu.overlays.key_for`)."""
        n = self.nodes.get(node)
        if n is None or self.testbed is None:
            raise MsoError(f"unknown node {node!r} (nodes: {', '.join(self.nodes)})")
        return f"{self.testbed.netns(node)}@127.0.0.1:{n.port}"

    def counters(self, node: str) -> dict[str, int]:
        """The kernel's byte and packet counters of ``node``'s radio (eth0)."""
        assert self.testbed is not None
        return self.testbed.counters(node)

    async def stop(self, grace: float = 3.0) -> None:
        try:
            await super().stop(grace)
        finally:
            for proc in self.routers.values():
                if proc.poll() is None:
                    proc.kill()
                with contextlib.suppress(Exception):
                    proc.wait(timeout=5)
            if self.testbed is not None:
                self.testbed.teardown()
                atexit.unregister(self.testbed.teardown)
