"""The dashboard's server: asks one node of the overlay for everyone's status once per interval,
turns it into a view (:mod:`mso.dashboard.view`) and pushes it to every open page by
Server-Sent Events; relays the page's relocation and remap requests to the overlay.

A small HTTP/1.1 server on asyncio's streams (no framework: five routes, one of them a stream)
so the dashboard adds no dependency and little CPU. It binds 127.0.0.1 unless told otherwise.
The overlay key stays in this process: the page never sees it, and a control request is taken
only from a page this server served (same-origin JSON), and on every address it listens on
it checks ``Host`` (the address or name it listens on, an address literal of that kind, or
``localhost``) and ``Origin``: a web page elsewhere cannot drive the overlay through the
user's browser, DNS rebinding included (a rebound name is never an address literal).
"""

from __future__ import annotations

import asyncio
import contextlib
import ipaddress
import json
import logging
import os
from collections import deque
from collections.abc import AsyncIterator, Callable
from importlib import resources
from typing import Any
from urllib.parse import urlsplit

from mso.api import AsyncOverlay, CommandFailed
from mso.client import NodeUnreachable, Refused, load_signer, parse_address
from mso.dashboard.view import Tracker
from mso.errors import MsoError
from mso.net.http import BadRequest, read_request, response

log = logging.getLogger("mso.dashboard")

STATIC = {
    "/": ("index.html", "text/html; charset=utf-8"),
    "/static/app.js": ("app.js", "text/javascript; charset=utf-8"),
    "/static/style.css": ("style.css", "text/css; charset=utf-8"),
}
MAX_BODY = 4096
MAX_STREAMS = 32
CSP = "Content-Security-Policy: default-src 'self'; style-src 'self'; img-src 'self' data:\r\n"
Positions = Callable[[], dict[str, tuple[float, float]]]


class Dashboard:
    """Serve the live view of one overlay, reached through any of ``addresses``."""

    def __init__(
        self,
        addresses: list[str],
        key: str | None = None,
        *,
        name: str = "",
        interval: float = 1.0,
        listen: str = "127.0.0.1:0",
        positions: Positions | None = None,
        expected: list[str] | None = None,
        sign: str | None = None,
    ) -> None:
        if not addresses:
            raise MsoError("the dashboard needs the address of a node")
        if not interval > 0:
            raise MsoError(f"--interval: expected seconds > 0, got {interval:g}")
        self.addresses = list(addresses)
        self._key = key
        # an operator key file (default $MSO_SIGN): the page's controls are signed with it, for
        # nodes started with --operator-key
        self._signer = load_signer(sign if sign is not None else os.environ.get("MSO_SIGN"))
        self.name = name
        self.interval = interval
        self.host, self.port = parse_address(listen, default_port=0)
        self.positions = positions
        self.expected = expected
        self.view: dict[str, Any] = {}
        self.updates = 0  # views made (the benchmark counts them)
        self.poll_s: deque[float] = deque(maxlen=1000)  # how long each status round took
        self.error = ""  # why the last poll failed, shown on the page
        self.ended = False  # stopped: the run is over (the page's last view says so)
        self._streams: set[asyncio.Queue[bytes]] = set()
        self._server: asyncio.Server | None = None
        self._poller: asyncio.Task[None] | None = None
        self._session: AsyncOverlay | None = None  # one connection kept for the polls
        self._via = 0  # index in addresses of the node asked
        self._tracker: Tracker | None = None
        self._changed = asyncio.Event()

    @property
    def url(self) -> str:
        host = f"[{self.host}]" if ":" in self.host else self.host
        return f"http://{host}:{self.port}/"

    async def start(self) -> str:
        loop = asyncio.get_running_loop()
        self._tracker = Tracker(loop.time())
        try:
            self._server = await asyncio.start_server(self._handle, self.host, self.port)
        except OSError as exc:
            raise MsoError(f"dashboard: cannot listen on {self.host}:{self.port}: {exc}") from None
        self.port = self._server.sockets[0].getsockname()[1]
        self._poller = asyncio.create_task(self._poll())
        return self.url

    async def stop(self) -> None:
        if self._poller is not None:
            self._poller.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._poller
        self.ended = True  # the page says the run is over, and stops reconnecting
        final = b"data: " + self._document() + b"\n\n"
        for q in self._streams:
            while not q.empty():  # a slow page gets the end, not a backlog
                q.get_nowait()
            q.put_nowait(final)
            q.put_nowait(b"")  # ends the stream
        if self._server is not None:
            self._server.close()
            with contextlib.suppress(Exception):
                await asyncio.wait_for(self._server.wait_closed(), 2.0)
        if self._session is not None:
            await self._session.close()

    async def wait_update(self, timeout: float) -> None:
        """Until the next view is made (for tests and the benchmark)."""
        self._changed.clear()
        await asyncio.wait_for(self._changed.wait(), timeout)

    # -- polling ----------------------------------------------------------------------------
    async def _status(self) -> dict[str, Any]:
        """Everyone's status through one node; another node if that one stops answering."""
        for _ in range(len(self.addresses)):
            try:
                if self._session is None:
                    # (the operator key, if given, is a client of nodes with identities too)
                    session = AsyncOverlay(
                        self.addresses[self._via], key=self._key, signer=self._signer
                    )
                    self._session = await session.open("dashboard", 2.0)
                return await self._session.status(timeout=5.0)
            except (MsoError, ConnectionError, OSError) as exc:
                self.error = str(exc)
                if self._session is not None:
                    with contextlib.suppress(Exception):
                        await self._session.close()
                self._session = None
                self._via = (self._via + 1) % len(self.addresses)
        raise NodeUnreachable(self.error)

    async def _poll(self) -> None:
        loop = asyncio.get_running_loop()
        assert self._tracker is not None
        next_at = loop.time()
        while True:
            try:
                asked = loop.time()
                nodes = await self._status()
                self.poll_s.append(loop.time() - asked)
                self.error = ""
            except NodeUnreachable:
                nodes = None
            now = loop.time()
            if nodes is not None:
                pos = self.positions() if self.positions is not None else None
                self.view = self._tracker.update(nodes, now, pos, self.expected)
            self._publish()
            next_at = max(next_at + self.interval, now)  # late: skip, never burst
            await asyncio.sleep(next_at - now)

    def _publish(self) -> None:
        self.updates += 1
        data = b"data: " + self._document() + b"\n\n"
        for q in self._streams:
            if q.full():  # a slow page gets the latest view, not a backlog
                with contextlib.suppress(asyncio.QueueEmpty):
                    q.get_nowait()
            q.put_nowait(data)
        self._changed.set()

    def _document(self) -> bytes:
        doc = dict(self.view)
        doc.update(
            overlay=self.name,
            via=self.addresses[self._via],
            interval=self.interval,
            error=self.error,
            ended=self.ended,
        )
        return json.dumps(doc, separators=(",", ":")).encode()

    # -- HTTP -------------------------------------------------------------------------------
    async def _handle(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        try:
            try:
                method, path, headers, body = await asyncio.wait_for(
                    read_request(reader, MAX_BODY), 10.0
                )
                self._check_host(headers)
                if method == "GET" and path == "/events":
                    await self._stream(writer)
                    return
                status, ctype, payload = await self._route(method, path, headers, body)
            except BadRequest as exc:
                status, ctype = exc.status, "application/json"
                payload = json.dumps({"error": str(exc)}).encode()
            except (TimeoutError, asyncio.IncompleteReadError, ConnectionError):
                return
            writer.write(response(status, ctype, payload, CSP))
            await writer.drain()
        except ConnectionError:
            pass
        finally:
            writer.close()
            with contextlib.suppress(Exception):
                await writer.wait_closed()

    def _host_ok(self, name: str | None) -> bool:
        """Is ``name`` (a ``Host`` header's) one this dashboard is reached by? A page that
        rebinds its own name to this address still sends its own name, so names other than
        ``localhost`` and the one given to ``--listen`` are refused, on every address."""
        if not name:
            return False
        name = name.lower()
        if name in ("localhost", self.host.lower()):
            return True
        try:
            asked = ipaddress.ip_address(name)
        except ValueError:
            return False
        try:
            bound = ipaddress.ip_address(self.host)
        except ValueError:  # listening on a name: localhost's literals, or only that name
            return self.host.lower() == "localhost" and asked.is_loopback
        if bound.is_unspecified:  # every address of this machine: any literal
            return True
        return asked.is_loopback if bound.is_loopback else asked == bound

    def _check_host(self, headers: dict[str, str]) -> None:
        """Refuse a request whose ``Host`` is not this dashboard's, or that a page of another
        origin sent (checked for every request, on every address it listens on)."""
        host = headers.get("host", "")
        try:
            name = urlsplit("//" + host).hostname
        except ValueError:
            name = None
        if not self._host_ok(name):
            raise BadRequest(
                403,
                f"Host {host[:100]!r} refused: this dashboard answers to the address it listens "
                f"on ({self.host}) or localhost only",
            )
        origin = headers.get("origin")
        if origin is not None:
            parts = urlsplit(origin)
            if parts.scheme != "http" or parts.netloc != host:
                raise BadRequest(
                    403,
                    f"Origin {origin[:100]!r} refused: requests come from the dashboard's own "
                    "page only",
                )

    async def _route(
        self, method: str, path: str, headers: dict[str, str], body: bytes
    ) -> tuple[int, str, bytes]:
        path = urlsplit(path).path
        if method == "GET" and path in STATIC:
            name, ctype = STATIC[path]
            return (
                200,
                ctype,
                resources.files("mso.dashboard").joinpath("static", name).read_bytes(),
            )
        if method == "GET" and path == "/api/view":
            return 200, "application/json", self._document()
        if method == "POST" and path in ("/api/relocate", "/api/remap"):
            if not headers.get("content-type", "").startswith("application/json"):
                raise BadRequest(415, "expected a JSON body (Content-Type: application/json)")
            try:
                req = json.loads(body)
            except ValueError as exc:
                raise BadRequest(400, f"bad JSON: {exc}") from None
            if not isinstance(req, dict):
                raise BadRequest(400, "expected a JSON object")
            if path == "/api/relocate":
                answer = await self.relocate(req)
            else:
                answer = await self.remap(req)
            return 200 if answer.get("ok") else 409, "application/json", json.dumps(answer).encode()
        if path in STATIC or path in ("/api/view", "/api/relocate", "/api/remap", "/events"):
            raise BadRequest(405, f"{method} is not allowed on {path}")
        raise BadRequest(404, f"no such page: {path}")

    async def _stream(self, writer: asyncio.StreamWriter) -> None:
        if len(self._streams) >= MAX_STREAMS:
            writer.write(response(503, "text/plain", b"too many open dashboards"))
            return
        q: asyncio.Queue[bytes] = asyncio.Queue(maxsize=2)
        self._streams.add(q)
        try:
            writer.write(
                b"HTTP/1.1 200 OK\r\nContent-Type: text/event-stream\r\n"
                b"Cache-Control: no-store\r\nX-Accel-Buffering: no\r\nConnection: close\r\n\r\n"
                b"retry: 2000\n\n"
            )
            if self.view:
                writer.write(b"data: " + self._document() + b"\n\n")
            await writer.drain()
            while True:
                try:
                    data = await asyncio.wait_for(q.get(), 15.0)
                except TimeoutError:
                    data = b": keep-alive\n\n"
                if not data:
                    return
                writer.write(data)
                await writer.drain()
        finally:
            self._streams.discard(q)

    # -- controls ---------------------------------------------------------------------------
    async def relocate(self, req: dict[str, Any]) -> dict[str, Any]:
        """Move a vertex: {app, vertex, target} or {app, vertex, direction}."""
        app, vertex = _text(req, "app"), _text(req, "vertex")
        target, direction = _text(req, "target", ""), _text(req, "direction", "")
        if direction not in ("", "upstream", "downstream"):
            raise BadRequest(400, "direction: expected upstream or downstream")
        if bool(target) == bool(direction):
            raise BadRequest(400, "give exactly one of target or direction")
        loop = asyncio.get_running_loop()
        assert self._tracker is not None
        try:
            async with self._controls() as overlay:
                reply = await overlay.relocate(app, vertex, direction=direction, target=target)
        except CommandFailed as exc:
            self._tracker.note(
                loop.time(), "relocation", f"{vertex} → {target or direction}", exc.reason, ok=False
            )
            return {"ok": False, "error": exc.reason}
        self._tracker.attribute(
            loop.time(),
            app,
            vertex,
            reply.node,
            "relocation",
            "asked from the dashboard",
            reply.elapsed_ms,
        )
        return {"ok": True, "vertex": vertex, "node": reply.node, "elapsed_ms": reply.elapsed_ms}

    async def remap(self, req: dict[str, Any]) -> dict[str, Any]:
        """Re-place chains: {app, chains: [index, ...]} or {app, all: true}."""
        app = _text(req, "app")
        chains = req.get("chains", [])
        everything = req.get("all", False) is True
        if not isinstance(chains, list) or not all(
            isinstance(c, int) and not isinstance(c, bool) and 0 <= c < 10_000 for c in chains
        ):
            raise BadRequest(400, "chains: expected a list of chain indices")
        if bool(chains) == everything:
            raise BadRequest(400, "give chains or all, not both or neither")
        loop = asyncio.get_running_loop()
        assert self._tracker is not None
        what = f"{app}: remap of " + ("every chain" if everything else f"chains {chains}")
        try:
            async with self._controls() as overlay:
                reply = await overlay.remap(app, chains=chains, everything=everything)
        except CommandFailed as exc:
            self._tracker.note(loop.time(), "remap", what, exc.reason, ok=False)
            return {"ok": False, "error": exc.reason}
        self._tracker.note(
            loop.time(), "remap", what, "asked from the dashboard", took_ms=reply.elapsed_ms
        )
        for v, n in reply.moved.items():
            self._tracker.attribute(
                loop.time(), app, v, n, "remap", "asked from the dashboard", None
            )
        return {"ok": True, "moved": reply.moved, "elapsed_ms": reply.elapsed_ms}

    @contextlib.asynccontextmanager
    async def _controls(self) -> AsyncIterator[AsyncOverlay]:
        """The overlay through the node polled, signed with the operator key if there is one;
        a refusal for want of authority or a node that does not answer is said to the page."""
        try:
            yield AsyncOverlay(
                self.addresses[self._via], key=self._key, timeout=30.0, signer=self._signer
            )
        except Refused as exc:  # no operator authority: said to the page, nothing changed
            raise BadRequest(403, str(exc)) from None
        except NodeUnreachable as exc:
            raise BadRequest(502, str(exc)) from None


def _text(req: dict[str, Any], name: str, default: str | None = None) -> str:
    value = req.get(name, default)
    if not isinstance(value, str) or (default is None and not value) or len(value) > 200:
        raise BadRequest(400, f"{name}: expected a non-empty string")
    return value


DEFAULT_LISTEN = "127.0.0.1:8765"


async def start_dashboard(
    addresses: list[str],
    key: str | None,
    name: str,
    listen: str,
    interval: float,
    positions: Any = None,
    expected: list[str] | None = None,
) -> Dashboard:
    """Start a dashboard on ``listen``, or on the default port (a free one if that is taken)."""

    def make(where: str) -> Dashboard:
        return Dashboard(
            addresses, key, name=name, interval=interval, listen=where,
            positions=positions, expected=expected,
        )  # fmt: skip

    board = make(listen or DEFAULT_LISTEN)
    try:
        await board.start()
    except MsoError:
        if listen:
            raise
        board = make(DEFAULT_LISTEN.rsplit(":", 1)[0] + ":0")
        await board.start()
    return board
