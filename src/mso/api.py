"""The Python API to a running overlay, and mso's one client path: the CLI, the dashboard and
the emulator controller ask their nodes through it, so a reply is judged in one place.

    from mso.api import Overlay

    overlay = Overlay("127.0.1.1:7000", key="...", sign="op.key")   # sign: an operator key
    overlay.deploy("examples/convoy.yaml")
    overlay.relocate("convoy", "scan_matcher", direction="upstream")
    overlay.remap("convoy", chains=[0, 4])          # or everything=True, or chains=["a-b-c"]
    print(overlay.status()["N1"]["apps"])
    print(typed_status(overlay.status())["N1"].monitor.drain_w)   # typed: mso.node.status

The address is any node of the overlay (``HOST:PORT``), the name of a running emulator's
overlay (``Overlay("convoy-line")``), a node id of a running emulator, or None: the node of the
one emulator running (or of ``overlay=NAME``). ``deploy`` takes an :class:`mso.App` built in
Python, an app file's path, or its text. Refusals raise
:class:`mso.errors.MsoError` with the node's reason (:class:`CommandFailed` when the node
answered and did not do it). ``AsyncOverlay`` is the same for asyncio code; it can also keep
one connection open (:meth:`AsyncOverlay.open`, or a connected client given), so that repeated
timed calls do not each pay a connect and a key check. Its every call takes a ``timeout``.
On an overlay with node identities a client is served only with its own certified key,
``Overlay(..., client_key="me.key")`` (``mso keygen --client``; default ``$MSO_CLIENT_KEY``,
else the one an emulator run with ``--identities`` left for its user), or the operator key
(``sign=``): :mod:`mso.protocol.clients`.

A running emulator takes commands too (:class:`EmulatorControl`, by overlay name): fail or
restart a node, cut or heal a link, move a node, stop the run with its summary. To start an
emulator or a simulation from Python: :mod:`mso.emu.session` (``Emulation``, ``simulate``).

Light to import: ``mso status`` comes through here and imports neither asyncio nor the model.
"""

from __future__ import annotations

import os
from collections.abc import AsyncIterator, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any, TypeVar

from mso.client import connect, load_client_identity, load_signer, request, request_blocking
from mso.errors import MsoError
from mso.protocol import messages as m

if TYPE_CHECKING:
    from mso.client import Client
    from mso.model.app import App
    from mso.node.status import NodeStatus
    from mso.protocol.authority import Signer
    from mso.protocol.clients import ClientIdentity

R = TypeVar("R")

DEPLOY_S = 30.0  # a deployment probes routes and starts every vertex: it may take a while
COMMAND_S = 10.0  # any other command's reply
# a relocation is answered at its handover: once producers have switched, the old instance first
# finishes its call and the events before the markers (a 2 s/event vertex takes seconds); the
# coordinator allows 5 s to prepare and 60 s to hand over (``mso.protocol.procedures.relocation``)
RELOCATE_S = 70.0
TAP_LEASE_S = 3.0  # a tap ends this long after its client stops asking (it asks 3 times as often)


class TapEnded(MsoError):
    """A tap ended on the node's side (the app stopped, the edge is unknown, too many taps);
    ``reason`` is the node's word."""

    def __init__(self, what: str, reason: str) -> None:
        super().__init__(f"{what}: {reason}")
        self.reason = reason


class CommandFailed(MsoError):
    """The node answered and did not carry the command out; ``reason`` is the node's word."""

    def __init__(self, what: str, reason: str) -> None:
        super().__init__(f"{what}: {reason}")
        self.reason = reason


def expect(reply: Any, kind: type[R]) -> R:
    """``reply`` if it is of the kind asked for (ok or not); anything else is an error."""
    if not isinstance(reply, kind):
        raise MsoError(f"unexpected reply {reply!r}")
    return reply


def judge(reply: Any, kind: type[R], what: str) -> R:
    """``reply`` if it is of the kind asked for and says ok; else :class:`CommandFailed`."""
    if not isinstance(reply, kind) or not getattr(reply, "ok", False):
        raise CommandFailed(what, getattr(reply, "error", "") or repr(reply))
    return reply


def key_for(key: str | None, address: str) -> str | None:
    """The overlay key to reach ``address`` with: ``key`` if given, else $MSO_KEY, else the key
    an emulator of this user made up for the overlay that has a node there (None: neither,
    the development key)."""
    if key is not None or os.environ.get("MSO_KEY"):
        return key
    from mso.emu.overlays import key_for as emulated_key

    return emulated_key(address)


def resolve_address(via: str | None, overlay: str | None = None) -> str:
    """``HOST:PORT`` as given; the name of a running overlay (its first node); a node id of a
    running emulator (in ``overlay``, if named); or, given nothing, the first node of the one
    running emulator (or of ``overlay``)."""
    from mso.emu.overlays import emulator_address, find_overlay, running_overlays

    if via is None:
        _, state = find_overlay(overlay)
        return str(next(iter(state["nodes"].values())))
    if ":" in via:
        return via
    if overlay is None and via in (named := running_overlays(everyone=True)):
        nodes = named[via]["nodes"]
        if nodes:
            return str(next(iter(nodes.values())))
    addr = emulator_address(via, overlay)
    if addr is None:
        raise MsoError(
            f"unknown node or overlay {via!r}: no running emulator knows it; use HOST:PORT"
        )
    return addr


class TapCounts:
    """A tap's counts carried on across its consumer's moves: each host counts from when it
    serves the tap, and a relay that followed the consumer passes on the old host's last word
    (``host`` set)."""

    def __init__(self) -> None:
        self.node = ""
        self.base = (0, 0)  # (seen, dropped) before the host serving now
        self.last = (0, 0)  # the host serving now's

    def carry(self, msg: m.TapEvents) -> m.TapEvents:
        """``msg`` with ``seen`` and ``dropped`` counted since the tap opened."""
        import msgspec

        if msg.host:  # the old host's final counts; the new one starts from 0
            self.base = (self.base[0] + msg.seen, self.base[1] + msg.dropped)
            self.node, self.last = msg.node, (0, 0)
            return msgspec.structs.replace(msg, seen=self.base[0], dropped=self.base[1])
        if self.node and msg.node != self.node:  # served elsewhere now: counted anew there
            self.base = (self.base[0] + self.last[0], self.base[1] + self.last[1])
        self.node, self.last = msg.node, (msg.seen, msg.dropped)
        seen, dropped = self.base[0] + msg.seen, self.base[1] + msg.dropped
        return msgspec.structs.replace(msg, seen=seen, dropped=dropped)


def decode_event(payload: bytes, fields: Sequence[str] = ()) -> Any:
    """An event as a tap copies it (msgpack, as on the edge), decoded without importing its
    format: a mapping, a list, a value; a positional format's ``fields`` name its items."""
    import msgspec

    value = msgspec.msgpack.decode(payload)
    if fields and isinstance(value, list) and len(value) == len(fields):
        return dict(zip(fields, value, strict=True))
    return value


def deploy_request(app: App | str | Path, planner: str | None = None) -> m.DeployRequest:
    """An app as a deploy request: an :class:`App` built in Python, the path of an app file, or
    an app file's text (a string of more than one line); validated here first, so errors point
    at its lines. ``planner`` overrides the app's ``planner:`` (written into the document every
    node reads)."""
    from mso.model.app import App
    from mso.model.appfile import load_app, loads_app, with_planner
    from mso.model.yamlfile import read_text_file

    if isinstance(app, App):
        from mso.model.appdoc import app_document

        app.validate()
        text, file = app_document(app), f"<app {app.name}>"
        loads_app(text, file=file)  # what every node will load: code that does not import here
    elif isinstance(app, str) and "\n" in app:
        text, file = app, "<app text>"
        loads_app(text, file=file)
    else:
        path = Path(app)
        load_app(path)
        text, file = read_text_file(path), str(path)
    if planner is not None:
        text = with_planner(text, planner, file=file)
    return m.DeployRequest(text, file)


def asked_node(nodes: dict[str, Any]) -> dict[str, Any]:
    """The status of the node asked (a status not asked everywhere holds that node only)."""
    return next(iter(nodes.values()), {})


def typed_status(nodes: dict[str, Any]) -> dict[str, NodeStatus]:
    """A status reply's nodes as typed records (:class:`mso.node.status.NodeStatus`); it
    imports the node's modules, so plain ``status()`` stays light."""
    from mso.node.status import from_wire

    return {node: from_wire(status) for node, status in nodes.items()}


def running(nodes: dict[str, Any]) -> list[str]:
    """The apps running, by name, as the nodes in ``nodes`` hold them: only the nodes that
    take part in an app hold it (issue 24.1), so ask everywhere to hear of every app."""
    return sorted({a for st in nodes.values() for a in st.get("apps", {})})


def held_by(nodes: dict[str, Any], app: str) -> dict[str, Any] | None:
    """``app`` as the node asked holds it, else as the first node in ``nodes`` that does."""
    found: dict[str, Any] | None = asked_node(nodes).get("apps", {}).get(app)
    if found is None:
        found = next((st["apps"][app] for st in nodes.values() if app in st.get("apps", {})), None)
    return found


def chain_indices(nodes: dict[str, Any], app: str, chains: Sequence[int | str]) -> list[int]:
    """Chains named by index (``3``, ``"3"``) or as ``head-...-tail`` -> their indices."""
    found = held_by(nodes, app)
    if found is None:
        raise MsoError(f"no running app named {app!r}")
    known = ["-".join(c) for c in found["chains"]]
    indices: list[int] = []
    for c in chains:
        if isinstance(c, int) or c.isdigit():
            indices.append(int(c))
        elif c in known:
            indices.append(known.index(c))
        else:
            raise MsoError(f"unknown chain {c!r} (chains: {', '.join(known)})")
    return indices


class AsyncOverlay:
    """Asynchronous access to an overlay through one of its nodes."""

    def __init__(
        self,
        address: str | None = None,
        *,
        key: str | None = None,
        timeout: float | None = None,
        sign: str | None = None,
        overlay: str | None = None,
        signer: Signer | None = None,
        client: Client | None = None,
        owned: bool = False,
        client_key: str | None = None,
    ) -> None:
        self._address, self._overlay = address, overlay
        self.key = key
        # every reply's, over any call's own; None: each call's (DEPLOY_S, COMMAND_S by default)
        self.timeout = timeout
        # an operator key (a file, or loaded): commands that change the overlay are signed
        self.signer = signer if signer is not None else load_signer(sign)
        # this client's own certified key (--client-key, $MSO_CLIENT_KEY): nodes that require
        # identities serve no other (an operator key stands for one: mso.protocol.clients)
        self._identity = load_client_identity(client_key)
        self._looked = self._identity is not None  # for an emulated overlay's client key
        self._client = client  # a connection kept open (by the caller, or by open())
        self._owned = owned  # close() closes it: opened here, or handed over with ``owned``

    @property
    def address(self) -> str:
        """The node asked, resolved when first needed (so a bad app file is reported first)."""
        if self._address is None or ":" not in self._address:
            self._address = resolve_address(self._address, self._overlay)
        return self._address

    @property
    def identity(self) -> ClientIdentity | None:
        """This client's certified key: given, $MSO_CLIENT_KEY, or the one an emulator run
        with identities left for its user (found as the overlay key is, :func:`key_for`)."""
        if self._identity is None and not self._looked:
            from mso.emu.overlays import client_key_for

            self._looked = True
            self._identity = load_client_identity(client_key_for(self.address))
        return self._identity

    async def open(self, name: str = "cli", timeout: float = 5.0) -> AsyncOverlay:
        """Keep one connection open for the calls that follow, until :meth:`close`."""
        if self._client is None:
            self._client = await connect(
                self.address,
                key=key_for(self.key, self.address),
                signer=self.signer,
                name=name,
                timeout=timeout,
                identity=self.identity,
            )
            self._owned = True
        return self

    async def close(self) -> None:
        if self._client is not None and self._owned:
            client, self._client = self._client, None
            await client.close()

    async def ask(self, msg: m.Message, timeout: float = COMMAND_S) -> m.Message:
        """Send one message and return the reply, unjudged."""
        wait = self.timeout or timeout
        if self._client is not None:
            return await self._client.call(msg, wait)
        reply: m.Message = await request(
            self.address,
            msg,
            key=key_for(self.key, self.address),
            timeout=wait,
            signer=self.signer,
            identity=self.identity,
        )
        return reply

    async def deploy(
        self,
        app: App | str | Path,
        *,
        check: bool = True,
        timeout: float = DEPLOY_S,
        planner: str | None = None,
    ) -> m.DeployReply:
        """Deploy an app: an :class:`App`, an app file's path or its text (validated here
        first, so errors point at its lines); ``planner`` overrides the app's."""
        req = deploy_request(app, planner)
        return await self.deploy_request(req, check=check, timeout=timeout)

    async def deploy_request(
        self, req: m.DeployRequest, *, check: bool = True, timeout: float = DEPLOY_S
    ) -> m.DeployReply:
        """Deploy an app document; ``check=False`` returns a failed deployment's reply too."""
        reply = await self.ask(req, timeout)
        if check:
            return judge(reply, m.DeployReply, "deployment failed")
        return expect(reply, m.DeployReply)

    async def undeploy(self, app: str | App, *, check: bool = True) -> None:
        """Stop an app on every node (``check``: an error if it runs nowhere)."""
        name = app if isinstance(app, str) else app.name
        if check and name not in (apps := await self.apps()):
            raise MsoError(f"no running app named {name!r} (running: {', '.join(apps) or 'none'})")
        await self.ask(m.StopApp(name))

    async def revoke_node(self, node_key: str) -> None:
        """Have every node refuse the node key ``node_key`` (its id from ``mso keygen
        --node``): the node asked passes the operator's signed word on to every node."""
        reply = await self.ask(m.RevokeNode(node_key))
        if isinstance(reply, m.Refused):
            raise CommandFailed("revocation refused", reply.reason)
        expect(reply, m.RevokeNode)

    async def relocate(
        self,
        app: str,
        vertex: str,
        *,
        direction: str = "",
        target: str = "",
        check: bool = True,
        timeout: float = RELOCATE_S,
    ) -> m.RelocateReply:
        """Move one interior vertex upstream, downstream, or to ``target`` (§3.4.1)."""
        reply = await self.ask(m.RelocateRequest(app, vertex, direction, target), timeout)
        if check:
            return judge(reply, m.RelocateReply, "relocation refused")
        return expect(reply, m.RelocateReply)

    async def remap(
        self,
        app: str,
        *,
        chains: Sequence[int | str] = (),
        everything: bool = False,
        check: bool = True,
        timeout: float = COMMAND_S,
    ) -> m.RemapReply:
        """Re-place chains (by index or ``head-...-tail``) or all of them, in dependency order
        (§3.4.2, §3.4.3); a remap of the whole app may want a longer ``timeout``."""
        indices = [c for c in chains if isinstance(c, int)]
        if len(indices) < len(chains):  # a name: the chains are as the node knows them
            indices = chain_indices(await self.status(), app, chains)
        reply = await self.ask(m.RemapRequest(app, indices, everything), timeout)
        if check:
            return judge(reply, m.RemapReply, "remap refused")
        return expect(reply, m.RemapReply)

    async def status(
        self, *, everywhere: bool = True, timeout: float = COMMAND_S
    ) -> dict[str, Any]:
        """Every reachable node's status, by node id (only the node asked's, if not
        ``everywhere``)."""
        reply = await self.ask(m.StatusRequest(everywhere=everywhere), timeout)
        return expect(reply, m.StatusReply).nodes

    async def apps(self) -> list[str]:
        """The apps running, by name (every node is asked: a node holds only the apps it
        takes part in)."""
        return running(await self.status())

    async def tap(
        self, app: str, edge: str, *, rate: float = 10.0, lease_s: float = TAP_LEASE_S
    ) -> AsyncIterator[m.TapEvents]:
        """What a running edge carries (``src->dst``, ``src:dst`` or a vertex with one output),
        as the node hosting its consumer sees it: every message counts the events since the
        tap opened and brings copies of at most ``rate`` a second (0: counts and delays only;
        :func:`decode_event` reads them). Its own connection, asked again every third of
        ``lease_s``; the tap ends on the nodes within ``lease_s`` of the caller's stopping.
        Raises :class:`TapEnded` when the node ends it. The counts go on across the
        consumer's moves (:class:`TapCounts`)."""
        import asyncio

        client = await connect(
            self.address,
            key=key_for(self.key, self.address),
            name="tap",
            signer=self.signer,
            identity=self.identity,
        )
        try:
            loop = asyncio.get_running_loop()
            ask = m.Tap(app, edge, rate, lease_s)
            await client.send(ask)
            renew = heard = loop.time()
            renew += lease_s / 3
            counts = TapCounts()
            while True:
                msg = await client.poll(max(0.01, renew - loop.time()))
                now = loop.time()
                if isinstance(msg, m.TapEvents):
                    heard = now
                    if msg.ended:
                        raise TapEnded(f"tap of {app} {edge} (at {msg.node})", msg.ended)
                    yield counts.carry(msg)
                elif now - heard > lease_s + COMMAND_S:
                    raise MsoError(f"tap of {app} {edge}: no word from {self.address}")
                if now >= renew:
                    await client.send(ask)
                    renew = now + lease_s / 3
        finally:
            await client.close()


class Overlay:
    """Blocking access to an overlay through one of its nodes (not for use inside a loop).

    :meth:`status` asks over a blocking socket (no asyncio: ``mso status`` starts quicker)."""

    def __init__(
        self,
        address: str | None = None,
        *,
        key: str | None = None,
        timeout: float | None = None,
        sign: str | None = None,
        overlay: str | None = None,
        client_key: str | None = None,
    ) -> None:
        self._async = AsyncOverlay(
            address, key=key, timeout=timeout, sign=sign, overlay=overlay, client_key=client_key
        )

    @property
    def address(self) -> str:
        return self._async.address

    def deploy(self, app: App | str | Path, *, planner: str | None = None) -> m.DeployReply:
        """Deploy an :class:`App`, an app file's path or its text."""
        import asyncio

        req = deploy_request(app, planner)  # before the address: file errors first
        return asyncio.run(self._async.deploy_request(req))

    def undeploy(self, app: str | App) -> None:
        import asyncio

        asyncio.run(self._async.undeploy(app))

    def revoke_node(self, node_key: str) -> None:
        import asyncio

        asyncio.run(self._async.revoke_node(node_key))

    def relocate(
        self, app: str, vertex: str, *, direction: str = "", target: str = ""
    ) -> m.RelocateReply:
        import asyncio

        return asyncio.run(self._async.relocate(app, vertex, direction=direction, target=target))

    def remap(
        self, app: str, *, chains: Sequence[int | str] = (), everything: bool = False
    ) -> m.RemapReply:
        import asyncio

        return asyncio.run(self._async.remap(app, chains=chains, everything=everything))

    def status(self, *, everywhere: bool = True) -> dict[str, Any]:
        msg = m.StatusRequest(everywhere=everywhere)
        reply = request_blocking(
            self.address,
            msg,
            key=key_for(self._async.key, self.address),
            timeout=self._async.timeout or COMMAND_S,
            identity=self._async.identity or self._operator_client(),
        )
        return expect(reply, m.StatusReply).nodes

    def apps(self) -> list[str]:
        return running(self.status())

    def _operator_client(self) -> ClientIdentity | None:
        """The client an operator key makes of its holder (status is asked unsigned)."""
        if self._async.signer is None:
            return None
        from mso.protocol.clients import operator_client

        return operator_client(self._async.signer)


class EmulatorControl:
    """Commands to a running emulator, found by its overlay's name (None: the one running, or
    $MSO_OVERLAY's): what its console takes, over the Unix socket beside its state file.

        control = EmulatorControl("convoy-line")
        control.fail("N3"); control.restart("N3"); control.cut("N1", "N2")

    Each returns what the emulator did, in words; a refusal raises :class:`CommandFailed`."""

    def __init__(self, overlay: str | None = None, *, timeout: float = 60.0) -> None:
        self.overlay = overlay if overlay is not None else os.environ.get("MSO_OVERLAY")
        self.timeout = timeout  # a restart waits for its node to answer (up to 20 s)

    def command(self, line: str) -> str:
        """Send one command line; the emulator's answer."""
        import json
        import socket

        from mso.emu.overlays import find_overlay, folder_of

        if "\n" in line or len(line.encode()) > 1000:
            raise MsoError("a command is one line of at most 1000 bytes")
        name, _ = find_overlay(self.overlay)
        path = folder_of(name) / f"{name}.sock"
        with socket.socket(socket.AF_UNIX) as s:
            s.settimeout(self.timeout)
            folder = os.open(path.parent, os.O_RDONLY | os.O_DIRECTORY)
            try:  # through the folder: sun_path is short
                s.connect(f"/proc/self/fd/{folder}/{path.name}")
            except OSError as exc:
                raise MsoError(f"cannot reach the emulator of {name!r} at {path}: {exc}") from None
            finally:
                os.close(folder)
            s.sendall(line.encode() + b"\n")
            data = b""
            try:
                while not data.endswith(b"\n") and len(data) < 1 << 16:
                    chunk = s.recv(4096)
                    if not chunk:
                        break
                    data += chunk
            except TimeoutError:
                raise MsoError(f"the emulator of {name!r} did not answer within "
                               f"{self.timeout:g} s") from None  # fmt: skip
        try:
            answer = json.loads(data)
        except ValueError:
            raise MsoError(f"the emulator of {name!r} gave no answer") from None
        if not isinstance(answer, dict) or not answer.get("ok"):
            error = answer.get("error") if isinstance(answer, dict) else None
            raise CommandFailed(line.split()[0] if line.split() else "command", str(error))
        return str(answer.get("said", ""))

    def fail(self, node: str) -> str:
        return self.command(f"fail {node}")

    def restart(self, node: str) -> str:
        return self.command(f"restart {node}")

    def cut(self, a: str, b: str) -> str:
        return self.command(f"cut {a} {b}")

    def heal(self, a: str, b: str) -> str:
        return self.command(f"heal {a} {b}")

    def move(self, node: str, x: float, y: float) -> str:
        return self.command(f"move {node} {x!r} {y!r}")

    def stop(self) -> str:
        """End the run: the emulator prints its summary and stops every node."""
        return self.command("stop")
