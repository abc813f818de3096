"""Talk to a running node as a client (the CLI, the emulator controller, the Python API)."""

from __future__ import annotations

import asyncio
import contextlib
import os
import socket
import time
from typing import TYPE_CHECKING, Any

import msgspec

from mso.errors import MsoError
from mso.protocol import messages as m
from mso.protocol.framing import FrameCodec, FramingError, WrongKey, psk_from_text

if TYPE_CHECKING:  # cryptography is imported only by a client that signs
    from mso.protocol.authority import Signer

DEFAULT_KEY = "mso-insecure-default-key"


def encrypt_default() -> bool:
    """Whether frames are encrypted, as ``$MSO_ENCRYPT`` says (every member must agree)."""
    return os.environ.get("MSO_ENCRYPT", "").lower() in ("1", "true", "yes", "on")


def overlay_key(text: str | None = None) -> bytes:
    """The overlay's pre-shared key: given, or $MSO_KEY, or the (insecure) default."""
    return psk_from_text(text or os.environ.get("MSO_KEY") or DEFAULT_KEY)


class NodeUnreachable(MsoError):
    """The node did not answer."""


class Refused(MsoError):
    """The node refused a command for want of authority."""


def load_signer(path: str | None) -> Signer | None:
    """The operator's private key from ``path`` (``--sign``, ``$MSO_SIGN``), if given."""
    if not path:
        return None
    from mso.protocol.authority import KeyError_, Signer

    try:
        return Signer.load(path)
    except KeyError_ as exc:
        raise MsoError(f"--sign: {exc}") from None


class Client:
    """One authenticated connection to a node."""

    def __init__(
        self,
        host: str,
        port: int,
        psk: bytes,
        name: str = "cli",
        signer: Signer | None = None,
        encrypt: bool | None = None,
        netns: str | None = None,
    ) -> None:
        self.host, self.port, self.psk, self.name = host, port, psk, name
        self.signer = signer  # signs the commands that change an overlay
        self.netns = netns  # connect from inside this network namespace (the netns testbed)
        self._reader: asyncio.StreamReader | None = None
        self._writer: asyncio.StreamWriter | None = None
        self._codec = FrameCodec(psk, encrypt=encrypt_default() if encrypt is None else encrypt)
        self._inbox: list[m.Message] = []

    async def connect(self, timeout: float = 5.0) -> Client:
        try:
            self._reader, self._writer = await asyncio.wait_for(self._open(), timeout)
        except (OSError, TimeoutError) as exc:
            raise NodeUnreachable(f"cannot reach node at {self.host}:{self.port}: {exc}") from None
        assert self._writer is not None and self._reader is not None
        self._writer.write(self._codec.hello())
        try:  # wait for the node's hello and key confirmation
            while not self._codec.confirmed:
                data = await asyncio.wait_for(self._reader.read(1 << 16), timeout)
                if not data and self._codec.greeted:  # it hung up on our key confirmation
                    raise MsoError(
                        f"node at {self.host}:{self.port} closed the connection during the key "
                        "check: wrong overlay key? (give --key or set $MSO_KEY; or the node is "
                        "at its connection limit)"
                    )
                if not data:
                    raise NodeUnreachable(f"node at {self.host}:{self.port} closed the connection")
                _, flush = self._codec.feed(data)
                self._writer.write(flush)
        except WrongKey:
            self._writer.close()
            raise MsoError(
                f"wrong overlay key: the node at {self.host}:{self.port} holds another key "
                "(give --key or set $MSO_KEY)"
            ) from None
        except (TimeoutError, FramingError) as exc:
            raise NodeUnreachable(f"no mso hello from {self.host}:{self.port}: {exc}") from None
        await self.send(m.ClientHello(self.name))
        return self

    async def _open(self) -> tuple[asyncio.StreamReader, asyncio.StreamWriter]:
        if self.netns is None:
            return await asyncio.open_connection(self.host, self.port)
        from mso.net.netns import socket_in_netns

        sock = socket_in_netns(self.netns, socket.AF_INET, socket.SOCK_STREAM)
        try:
            sock.setblocking(False)
            await asyncio.get_running_loop().sock_connect(sock, (self.host, self.port))
        except BaseException:
            sock.close()
            raise
        return await asyncio.open_connection(sock=sock)

    async def send(self, msg: m.Message) -> None:
        assert self._writer is not None
        if self.signer is not None and isinstance(msg, self.signer.signs):
            now_ms = time.time_ns() // 1_000_000  # a grant's generation, an undeploy's time
            if isinstance(msg, m.DeployRequest):
                msg = m.DeployRequest(self.signer.grant(msg.document, now_ms), msg.file)
            elif isinstance(msg, m.StopApp) and not msg.sig:  # verified by every node
                msg = self.signer.undeploy(msg.app, now_ms)
            nonce = self._codec.peer_nonce
            assert nonce is not None
            msg = self.signer.command(nonce, msg)
        frame = self._codec.seal(m.wrap("client", "node", msg))
        if frame:
            self._writer.write(frame)
        await self._writer.drain()

    async def receive(self, timeout: float) -> m.Message:
        assert self._reader is not None and self._writer is not None
        loop = asyncio.get_running_loop()
        deadline = loop.time() + timeout
        while not self._inbox:
            remaining = deadline - loop.time()
            if remaining <= 0:
                raise NodeUnreachable(f"node at {self.host}:{self.port} did not answer in time")
            try:
                data = await asyncio.wait_for(self._reader.read(1 << 16), remaining)
            except TimeoutError:
                continue
            if not data:
                raise NodeUnreachable(f"node at {self.host}:{self.port} closed the connection")
            try:
                payloads, flush = self._codec.feed(data)
            except FramingError as exc:
                raise NodeUnreachable(f"bad stream from {self.host}:{self.port}: {exc}") from None
            if flush:
                self._writer.write(flush)
            for p in payloads:
                try:
                    self._inbox.append(m.decode(m.unwrap(p).body))
                except (msgspec.DecodeError, msgspec.ValidationError):
                    continue
            if self._codec.rejected and not payloads:
                raise NodeUnreachable(
                    f"node at {self.host}:{self.port} rejected our frames: wrong overlay key?"
                )
        msg = self._inbox.pop(0)
        if isinstance(msg, m.Refused):
            raise Refused(f"node at {self.host}:{self.port} {msg.reason}")
        return msg

    async def call(self, msg: m.Message, timeout: float = 10.0) -> m.Message:
        await self.send(msg)
        return await self.receive(timeout)

    async def close(self) -> None:
        if self._writer is not None:
            self._writer.close()
            with contextlib.suppress(OSError):
                await self._writer.wait_closed()


def split_netns(address: str) -> tuple[str | None, str]:
    """``NETNS@HOST:PORT`` -> ``(NETNS, HOST:PORT)``; a plain address has no namespace."""
    netns, at, rest = address.partition("@")
    return (netns, rest) if at and netns else (None, address)


def parse_address(text: str, default_port: int = 7000) -> tuple[str, int]:
    """``HOST:PORT`` (or ``HOST``) with a port in 0..65535."""
    host, _, port = text.rpartition(":")
    if not host:
        host, port = text, str(default_port)
    try:
        number = int(port)
    except ValueError:
        number = -1
    if not host or not 0 <= number <= 65535:
        raise MsoError(f"expected HOST:PORT with a port in 0..65535, got {text!r}")
    return host, number


async def request(
    address: str,
    msg: m.Message,
    *,
    key: str | None = None,
    timeout: float = 10.0,
    signer: Signer | None = None,
) -> Any:
    """Connect, send one request, return the reply. ``NETNS@HOST:PORT`` connects from inside
    network namespace NETNS (a node of the netns testbed)."""
    netns, address = split_netns(address)
    host, port = parse_address(address)
    client = await Client(host, port, overlay_key(key), signer=signer, netns=netns).connect()
    try:
        return await client.call(msg, timeout)
    finally:
        await client.close()
