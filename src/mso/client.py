"""Talk to a running node as a client (the CLI, the emulator controller, the Python API)."""

from __future__ import annotations

import contextlib
import os
import socket
import time
from typing import TYPE_CHECKING, Any

import msgspec

from mso.errors import MsoError
from mso.protocol import messages as m
from mso.protocol.framing import FrameCodec, FramingError, WrongKey, psk_from_text

if TYPE_CHECKING:  # cryptography is imported only by a client that signs; asyncio only by
    import asyncio  # the asyncio client (`mso status` asks with a blocking socket: quicker start)

    from mso.protocol.authority import Signer
    from mso.protocol.clients import ClientIdentity

DEFAULT_KEY = "mso-insecure-default-key"
ORDERS = (m.RelocateRequest, m.RemapRequest)  # signed as orders too (mso.protocol.warrant)


def encrypt_default() -> bool:
    """Whether frames are encrypted, as ``$MSO_ENCRYPT`` says (every member must agree)."""
    return os.environ.get("MSO_ENCRYPT", "").lower() in ("1", "true", "yes", "on")


def overlay_key(text: str | None = None) -> bytes:
    """The overlay's pre-shared key: given, or $MSO_KEY, or the (insecure) development key (an
    emulated overlay's own key is found by :func:`mso.api.key_for`). An empty key is an error,
    never a silent fall-back to the development key."""
    if text == "":
        raise MsoError("--key: an empty overlay key is refused (give one, or leave --key out)")
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


def load_client_identity(path: str | None = None) -> ClientIdentity | None:
    """This client's own certified key from ``path`` (``--client-key``), else
    ``$MSO_CLIENT_KEY``, if either is given (nodes that require identities serve no other)."""
    path = path or os.environ.get("MSO_CLIENT_KEY") or None
    if not path:
        return None
    from mso.protocol.authority import KeyError_
    from mso.protocol.clients import ClientIdentity

    try:
        return ClientIdentity.load(path)
    except KeyError_ as exc:
        raise MsoError(f"--client-key: {exc}") from None


class Exchange:
    """The sans-IO half of a client connection: the key check, framing, signing, decoding.

    Shared by the asyncio :class:`Client` and the blocking :func:`request_blocking`, so both
    say the same thing about a wrong key or a node that hangs up.
    """

    def __init__(
        self,
        host: str,
        port: int,
        psk: bytes,
        signer: Signer | None = None,
        encrypt: bool | None = None,
        identity: ClientIdentity | None = None,
    ) -> None:
        self.host, self.port = host, port
        self.signer = signer  # signs the commands that change an overlay
        # who this client is, to a node that requires identities (an operator key is one)
        self.identity = identity if identity is not None else load_client_identity()
        if self.identity is None and signer is not None:
            from mso.protocol.clients import operator_client

            self.identity = operator_client(signer)
        self.codec = FrameCodec(psk, encrypt=encrypt_default() if encrypt is None else encrypt)
        self.inbox: list[m.Message] = []

    @property
    def where(self) -> str:
        return f"{self.host}:{self.port}"

    def unreachable(self, exc: BaseException) -> NodeUnreachable:
        return NodeUnreachable(f"cannot reach node at {self.where}: {exc}")

    def handshake(self, data: bytes) -> bytes:
        """Bytes read while the key is being checked -> bytes to send back."""
        if not data and self.codec.greeted:  # it hung up on our key confirmation
            raise MsoError(
                f"wrong overlay key: the node at {self.where} closed the connection at our key "
                "confirmation, so it holds another key (give --key or set $MSO_KEY)"
            )
        if not data:
            raise NodeUnreachable(f"node at {self.where} closed the connection")
        try:
            _, flush = self.codec.feed(data)
        except WrongKey:
            raise MsoError(
                f"wrong overlay key: the node at {self.where} holds another key "
                "(give --key or set $MSO_KEY)"
            ) from None
        except FramingError as exc:
            raise self.no_hello(exc) from None
        return flush

    def no_hello(self, exc: BaseException) -> NodeUnreachable:
        return NodeUnreachable(f"no mso hello from {self.where}: {exc}")

    def hello(self, name: str) -> bytes:
        """The client's hello as a frame: its name, and its proof when it has an identity."""
        if self.identity is None:
            return self.seal(m.ClientHello(name))
        peer = self.codec.peer_hello
        return self.seal(self.identity.hello(name, self.codec.hello(), peer))

    def seal(self, msg: m.Message) -> bytes:
        """One message as a frame (signed first when it changes the overlay and we sign:
        with the operator key, or with a command client's own key what it may sign)."""
        own = self.identity.signer if self.identity is not None and self.signer is None else None
        if own is not None and isinstance(msg, own.signs):
            nonce = self.codec.peer_nonce
            assert nonce is not None
            if isinstance(msg, ORDERS) and not msg.sig and self.identity is not None:
                cert = msgspec.msgpack.encode(self.identity.cert)  # (its key's, with it)
                msg = own.order(msg, time.time_ns() // 1_000_000, cert)
            msg = own.command(nonce, msg)
        elif self.signer is not None and isinstance(msg, self.signer.signs):
            now_ms = time.time_ns() // 1_000_000  # a grant's generation, an undeploy's time
            if isinstance(msg, ORDERS) and not msg.sig:  # a move's every step shows it
                msg = self.signer.order(msg, now_ms)
            if isinstance(msg, m.DeployRequest):
                msg = msgspec.structs.replace(msg, document=self.signer.grant(msg.document, now_ms))
            elif isinstance(msg, m.StopApp) and not msg.sig:  # verified by every node
                msg = self.signer.undeploy(msg.app, now_ms)
            elif isinstance(msg, m.RevokeNode) and not msg.sig:  # verified by every node too
                msg = self.signer.revoke_node(msg.node_key, now_ms)
            nonce = self.codec.peer_nonce
            assert nonce is not None
            msg = self.signer.command(nonce, msg)
        return self.codec.seal(m.wrap("client", "node", msg))

    def received(self, data: bytes) -> bytes:
        """Bytes read after the handshake -> bytes to send back; decoded messages queue up."""
        if not data:
            raise NodeUnreachable(f"node at {self.where} closed the connection")
        try:
            payloads, flush = self.codec.feed(data)
        except FramingError as exc:
            raise NodeUnreachable(f"bad stream from {self.where}: {exc}") from None
        for p in payloads:
            try:
                self.inbox.append(m.decode(m.unwrap(p).body))
            except (msgspec.DecodeError, msgspec.ValidationError):
                continue
        if self.codec.rejected and not payloads:
            raise NodeUnreachable(f"node at {self.where} rejected our frames: wrong overlay key?")
        return flush

    def late(self) -> NodeUnreachable:
        return NodeUnreachable(f"node at {self.where} did not answer in time")

    def next_message(self) -> m.Message:
        msg = self.inbox.pop(0)
        if isinstance(msg, m.Refused):
            raise Refused(f"node at {self.where} {msg.reason}")
        return msg


class Client:
    """One authenticated connection to a node (asyncio)."""

    def __init__(
        self,
        host: str,
        port: int,
        psk: bytes,
        name: str = "cli",
        signer: Signer | None = None,
        encrypt: bool | None = None,
        netns: str | None = None,
        identity: ClientIdentity | None = None,
    ) -> None:
        self.host, self.port, self.psk, self.name = host, port, psk, name
        self.netns = netns  # connect from inside this network namespace (the netns testbed)
        self._reader: asyncio.StreamReader | None = None
        self._writer: asyncio.StreamWriter | None = None
        self._encrypt = encrypt
        self._x = Exchange(host, port, psk, signer, encrypt, identity)
        self._codec = self._x.codec
        # a call timed out: its reply may still come and would be read as the next call's, so
        # the next call opens the connection anew (replies carry no request id)
        self._stale = False

    @property
    def signer(self) -> Signer | None:
        return self._x.signer

    async def connect(self, timeout: float = 5.0) -> Client:
        import asyncio

        try:
            reader, writer = await asyncio.wait_for(self._open(), timeout)
        except (OSError, TimeoutError) as exc:
            raise self._x.unreachable(exc) from None
        self._reader, self._writer = reader, writer
        writer.write(self._codec.hello())
        try:  # wait for the node's hello and key confirmation
            while not self._codec.confirmed:
                data = await asyncio.wait_for(reader.read(1 << 16), timeout)
                writer.write(self._x.handshake(data))
        except MsoError:
            writer.close()
            raise
        except TimeoutError as exc:
            raise self._x.no_hello(exc) from None
        self._writer.write(self._x.hello(self.name))
        await self._writer.drain()
        return self

    async def _open(self) -> tuple[asyncio.StreamReader, asyncio.StreamWriter]:
        import asyncio

        if self.netns is None:
            return await asyncio.open_connection(self.host, self.port)
        sock = _netns_socket(self.netns)
        try:
            sock.setblocking(False)
            await asyncio.get_running_loop().sock_connect(sock, (self.host, self.port))
        except BaseException:
            sock.close()
            raise
        return await asyncio.open_connection(sock=sock)

    async def send(self, msg: m.Message) -> None:
        assert self._writer is not None
        frame = self._x.seal(msg)
        if frame:
            self._writer.write(frame)
        await self._writer.drain()

    async def receive(self, timeout: float) -> m.Message:
        import asyncio

        assert self._reader is not None and self._writer is not None
        loop = asyncio.get_running_loop()
        deadline = loop.time() + timeout
        while not self._x.inbox:
            remaining = deadline - loop.time()
            if remaining <= 0:
                raise self._x.late()
            try:
                data = await asyncio.wait_for(self._reader.read(1 << 16), remaining)
            except TimeoutError:
                continue
            flush = self._x.received(data)
            if flush:
                self._writer.write(flush)
        return self._x.next_message()

    async def poll(self, timeout: float) -> m.Message | None:
        """The next message the node sends, or None if none came within ``timeout`` (a stream
        of replies, as a tap's: the connection stays usable)."""
        try:
            return await self.receive(timeout)
        except NodeUnreachable:
            if self._x.inbox or self._reader is None or self._reader.at_eof():
                raise
            return None

    async def call(self, msg: m.Message, timeout: float = 10.0) -> m.Message:
        """Send ``msg`` and wait for the node's answer to it."""
        if self._stale:
            await self._reopen(timeout)
        await self.send(waiting(msg, timeout))
        try:
            return await self.receive(timeout)
        except NodeUnreachable:
            self._stale = True
            raise

    async def _reopen(self, timeout: float) -> None:
        """A fresh connection (and key exchange) in place of one a late reply may arrive on."""
        await self.close()
        x = self._x
        self._x = Exchange(self.host, self.port, self.psk, x.signer, self._encrypt, x.identity)
        self._codec = self._x.codec
        self._stale = False
        await self.connect(min(timeout, 5.0))

    async def close(self) -> None:
        if self._writer is not None:
            self._writer.close()
            with contextlib.suppress(OSError):
                await self._writer.wait_closed()


def waiting(msg: m.Message, timeout: float) -> m.Message:
    """A deployment or remap request saying how long the client waits (unless it says
    already): the node ends it before then if it has not finished, rather than answer
    nobody. (Before an order is signed: its signature covers the wait.)"""
    if isinstance(msg, m.DeployRequest | m.RemapRequest) and not msg.within_s:
        return msgspec.structs.replace(msg, within_s=timeout)
    return msg


def _ip_literal(host: str) -> bool:
    for family in (socket.AF_INET, socket.AF_INET6):
        try:
            socket.inet_pton(family, host)
        except OSError:
            continue
        return True
    return False


def _netns_socket(netns: str) -> socket.socket:
    from mso.net.netns import socket_in_netns

    return socket_in_netns(netns, socket.AF_INET, socket.SOCK_STREAM)


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


async def connect(
    address: str,
    *,
    key: str | None = None,
    signer: Signer | None = None,
    name: str = "cli",
    timeout: float = 5.0,
    identity: ClientIdentity | None = None,
) -> Client:
    """A connection to the node at ``address``, its key checked. ``NETNS@HOST:PORT`` connects
    from inside network namespace NETNS (a node of the netns testbed)."""
    netns, address = split_netns(address)
    host, port = parse_address(address)
    client = Client(
        host, port, overlay_key(key), name, signer=signer, netns=netns, identity=identity
    )
    return await client.connect(timeout)


async def request(
    address: str,
    msg: m.Message,
    *,
    key: str | None = None,
    timeout: float = 10.0,
    signer: Signer | None = None,
    identity: ClientIdentity | None = None,
) -> Any:
    """Connect (:func:`connect`), send one request, return the reply."""
    client = await connect(address, key=key, signer=signer, identity=identity)
    try:
        return await client.call(msg, timeout)
    finally:
        await client.close()


def request_blocking(
    address: str,
    msg: m.Message,
    *,
    key: str | None = None,
    timeout: float = 10.0,
    identity: ClientIdentity | None = None,
) -> Any:
    """:func:`request` over a blocking socket, for a CLI command that asks once: it spares the
    ~30 ms of importing asyncio (``mso status`` answers within its start-up budget)."""
    netns, address = split_netns(address)
    host, port = parse_address(address)
    x = Exchange(host, port, overlay_key(key), identity=identity)
    deadline = time.monotonic() + timeout
    try:
        if netns is None and not _ip_literal(host):
            sock = socket.create_connection((host, port), timeout=min(timeout, 5.0))
        else:  # an address needs no name lookup (nor the idna codec it imports)
            family = socket.AF_INET6 if ":" in host else socket.AF_INET
            sock = socket.socket(family) if netns is None else _netns_socket(netns)
            sock.settimeout(min(timeout, 5.0))
            with contextlib.ExitStack() as on_error:
                on_error.callback(sock.close)
                sock.connect((host, port))
                on_error.pop_all()
    except OSError as exc:
        raise x.unreachable(exc) from None
    with sock:
        try:
            sock.sendall(x.codec.hello())
            while not x.codec.confirmed:
                sock.sendall(x.handshake(sock.recv(1 << 16)))
        except TimeoutError as exc:
            raise x.no_hello(exc) from None
        except OSError as exc:
            raise x.unreachable(exc) from None
        try:
            sock.sendall(x.hello("cli") + x.seal(waiting(msg, timeout)))
            while not x.inbox:
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    raise x.late()
                sock.settimeout(remaining)
                flush = x.received(sock.recv(1 << 16))
                if flush:
                    sock.sendall(flush)
        except TimeoutError:
            raise x.late() from None
        except OSError as exc:
            raise x.unreachable(exc) from None
    return x.next_message()
