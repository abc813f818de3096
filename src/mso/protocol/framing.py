"""Authenticated, length-prefixed frames on one stream connection. Sans-IO: bytes in, bytes out.

A connection starts with each side sending a 20-byte hello: ``b"MSO1"`` and a fresh random
16-byte nonce. Each direction then has its own key, ``blake2b(key=psk, data=b"mso1" + sender
nonce + receiver nonce)``, and every frame is::

    u32 length (big endian, of what follows) | 16-byte tag | payload

with ``tag = blake2b(key=direction key, data=u64 frame counter + payload, digest_size=16)``. The
counter is implicit (0, 1, 2, ... per direction), so a frame replayed, reordered or copied from
another connection fails its tag; a receiver's fresh nonce makes every connection's keys new.
A frame whose tag fails is dropped and counted, never acted on, and the stream goes on; a length
beyond ``max_frame`` or a bad hello means the byte stream itself is not ours, and the connection
must be closed (``FramingError``).

Key confirmation: the first frame each side sends is an empty one (its tag proves the key).
Until the peer's has been verified nothing longer is accepted, so a stranger without the key
can make a node buffer at most one 20-byte frame, and a peer with the wrong key is told at once
(``WrongKey``) instead of every later frame being dropped in silence.

Key rotation: a codec holds a list of keys, the first the one it seals with, the others still
accepted. The side that accepted the connection (the *responder*) waits for the connecting
side's key confirmation, finds which of its keys that is, and answers with the same one; so a
client or neighbour still on the old key is served while the overlay moves to the next, and
connections already open are never touched (apps keep running).

Encryption (optional, ``encrypt=True``, hello ``MSE1``): each frame is
``u32 length | ChaCha20-Poly1305(direction key, nonce = counter) of the payload``, the 16-byte
Poly1305 tag in place of the blake2b one. Both ends must agree; a mismatch is told at the hello.
"""

from __future__ import annotations

import hashlib
import hmac
import os
import struct
from collections.abc import Sequence
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:  # imported when a codec encrypts: the CLI's start stays quick
    from cryptography.hazmat.primitives.ciphers.aead import ChaCha20Poly1305

MAGIC = b"MSO1"
MAGIC_ENCRYPTED = b"MSE1"
NONCE_BYTES = 16
HELLO_BYTES = len(MAGIC) + NONCE_BYTES
TAG_BYTES = 16
MAX_FRAME = 16 * 1024 * 1024
# a frame sealed by the peer but altered on the way leaves the counters apart for good: after
# this many failures in a row the stream is given up (closed, and a neighbour reconnects)
MAX_REJECTED_IN_A_ROW = 32
_LEN = struct.Struct(">I")
_CTR = struct.Struct(">Q")


class FramingError(Exception):
    """The stream cannot be framed any more (bad hello, oversized frame): close it."""


class WrongKey(FramingError):
    """The peer's key confirmation failed: it holds another overlay key."""


def derive_key(psk: bytes, sender_nonce: bytes, receiver_nonce: bytes) -> bytes:
    return hashlib.blake2b(
        b"mso1" + sender_nonce + receiver_nonce, key=psk[:64], digest_size=32
    ).digest()


def psk_from_text(text: str) -> bytes:
    """Overlay keys are given as text (flag, file); hash to a fixed-size secret."""
    return hashlib.blake2b(text.encode(), person=b"mso-overlay-key", digest_size=32).digest()


class FrameCodec:
    """Both directions of one connection: :meth:`hello` first, then :meth:`seal` / :meth:`feed`.

    ``psk``: the overlay key, or a list of keys (the first seals, all are accepted).
    Counters: ``rejected`` frames whose tag failed; ``accepted`` frames delivered.
    """

    def __init__(
        self,
        psk: bytes | Sequence[bytes],
        *,
        max_frame: int = MAX_FRAME,
        nonce: bytes | None = None,
        encrypt: bool = False,
        responder: bool = False,
    ):
        keys = [psk] if isinstance(psk, bytes) else list(psk)
        if not keys or not all(keys):
            raise ValueError("an overlay key is required")
        self._psks = keys
        self._encrypt = encrypt
        self._responder = responder  # confirms with the key the peer confirmed with
        self._magic = MAGIC_ENCRYPTED if encrypt else MAGIC
        self._max = max_frame
        self._nonce = nonce if nonce is not None else os.urandom(NONCE_BYTES)
        self._tx_key: bytes | None = None
        self._rx_key: bytes | None = None
        self._rx_candidates: list[bytes] = []  # one per accepted key until the peer confirms
        self._tx_aead: ChaCha20Poly1305 | None = None
        self._rx_aead: ChaCha20Poly1305 | None = None
        self._peer_nonce: bytes | None = None
        self._tx_ctr = 0
        self._rx_ctr = 0
        self._buf = bytearray()
        self._pending: list[bytes] = []  # sealed before the peer's hello arrived
        self._confirmed = False  # the peer's key confirmation verified
        self.peer_key_index: int | None = None  # which of our keys the peer seals with
        self.rejected = 0
        self.accepted = 0
        self._rejected_in_a_row = 0

    @property
    def ready(self) -> bool:
        return self._tx_key is not None

    @property
    def confirmed(self) -> bool:
        """The peer proved it holds the overlay key."""
        return self._confirmed

    @property
    def buffered(self) -> int:
        """Bytes received and held: at most one partial frame."""
        return len(self._buf)

    @property
    def nonce(self) -> bytes:
        """This side's hello nonce (a signer binds a command to the connection with it)."""
        return self._nonce

    @property
    def peer_nonce(self) -> bytes | None:
        return self._peer_nonce

    @property
    def greeted(self) -> bool:
        """The peer's hello has arrived (the key check is under way or done)."""
        return self._peer_nonce is not None

    def hello(self) -> bytes:
        return self._magic + self._nonce

    def seal(self, payload: bytes) -> bytes:
        """One frame for ``payload``; before the peer's hello it is queued (returns b"")."""
        if self._tx_key is None:
            self._pending.append(bytes(payload))
            return b""
        return self._seal(payload)

    def _seal(self, payload: bytes) -> bytes:
        assert self._tx_key is not None
        ctr = self._tx_ctr
        self._tx_ctr += 1
        if self._tx_aead is not None:
            sealed = self._tx_aead.encrypt(_aead_nonce(ctr), payload, None)
            return _LEN.pack(len(sealed)) + sealed
        mac = hashlib.blake2b(_CTR.pack(ctr), key=self._tx_key, digest_size=TAG_BYTES)
        mac.update(payload)  # no concatenated copy of the payload
        return b"".join((_LEN.pack(TAG_BYTES + len(payload)), mac.digest(), payload))

    def _open(self, key: bytes, ctr: int, frame: memoryview) -> bytes | None:
        """The payload of a received frame (tag first, or AEAD), None if it fails."""
        if self._encrypt:
            from cryptography.exceptions import InvalidTag

            aead = self._rx_aead if key is self._rx_key else _aead(key)
            assert aead is not None
            try:
                return aead.decrypt(_aead_nonce(ctr), bytes(frame), None)
            except InvalidTag:
                return None
        tag, body = frame[:TAG_BYTES], frame[TAG_BYTES:]
        mac = hashlib.blake2b(_CTR.pack(ctr), key=key, digest_size=TAG_BYTES)
        mac.update(body)  # straight from the receive buffer
        ok = hmac.compare_digest(bytes(tag), mac.digest())
        return bytes(body) if ok else None

    def _hello_received(self) -> bytes:
        magic = bytes(self._buf[: len(MAGIC)])
        if magic != self._magic:
            if magic in (MAGIC, MAGIC_ENCRYPTED):
                theirs = "encrypts" if magic == MAGIC_ENCRYPTED else "does not encrypt"
                raise FramingError(f"the peer {theirs} its frames and this side does not agree")
            raise FramingError("peer did not send an mso hello")
        peer_nonce = self._peer_nonce = bytes(self._buf[len(MAGIC) : HELLO_BYTES])
        del self._buf[:HELLO_BYTES]
        self._rx_candidates = [derive_key(k, peer_nonce, self._nonce) for k in self._psks]
        return b"" if self._responder else self._start_sending(0)

    def refusal(self) -> bytes:
        """A responder that refused the peer's key still confirms its own (with its current
        key) before it closes, so the peer can tell a wrong key from a lost connection."""
        if self._tx_key is not None or self._peer_nonce is None:
            return b""
        self._pending.clear()
        return self._start_sending(0)

    def _start_sending(self, key_index: int) -> bytes:
        """Seal with key ``key_index`` from now on: the key confirmation, then what waited."""
        assert self._peer_nonce is not None
        self._tx_key = derive_key(self._psks[key_index], self._nonce, self._peer_nonce)
        if self._encrypt:
            self._tx_aead = _aead(self._tx_key)
        flush = b"".join([self._seal(b""), *(self._seal(p) for p in self._pending)])
        self._pending.clear()
        return flush

    def feed(self, data: bytes) -> tuple[list[bytes], bytes]:
        """Consume received bytes; return (authenticated payloads, bytes to send now).

        The bytes to send are frames sealed before the handshake completed.
        """
        self._buf += data
        out: list[bytes] = []
        flush = b""
        if self._peer_nonce is None:
            if len(self._buf) < HELLO_BYTES:
                return out, flush
            flush = self._hello_received()
        buf = self._buf
        pos = 0
        n = len(buf)
        view = memoryview(buf)
        try:
            while n - pos >= 4:
                (length,) = _LEN.unpack_from(buf, pos)
                if length < TAG_BYTES or length > self._max + TAG_BYTES:
                    raise FramingError(f"frame length {length} out of range")
                if not self._confirmed and length != TAG_BYTES:
                    raise FramingError("the first frame is not a key confirmation")
                if n - pos - 4 < length:
                    break
                frame = view[pos + 4 : pos + 4 + length]
                pos += 4 + length
                if not self._confirmed:
                    flush += self._confirm(frame)
                    frame.release()
                    continue
                assert self._rx_key is not None
                payload = self._open(self._rx_key, self._rx_ctr, frame)
                frame.release()
                if payload is not None:
                    out.append(payload)
                    self._rx_ctr += 1
                    self.accepted += 1
                    self._rejected_in_a_row = 0
                    continue
                self.rejected += 1
                self._rejected_in_a_row += 1
                if self._rejected_in_a_row >= MAX_REJECTED_IN_A_ROW:
                    raise FramingError(f"{MAX_REJECTED_IN_A_ROW} frames in a row failed their tag")
        finally:
            view.release()  # a bytearray cannot be resized while a view is exported
        if pos:
            del buf[:pos]
        return out, flush

    def _confirm(self, frame: memoryview) -> bytes:
        """The peer's first frame: which of our keys it seals with, or WrongKey. A responder
        answers now, with that key."""
        for i, key in enumerate(self._rx_candidates):
            if self._open(key, 0, frame) is not None:
                self._rx_key = key
                if self._encrypt:
                    self._rx_aead = _aead(key)
                self.peer_key_index = i
                self._confirmed = True
                self._rx_ctr = 1
                self._rx_candidates = []
                return self._start_sending(i) if self._responder else b""
        raise WrongKey("the peer holds another overlay key")


def _aead(key: bytes) -> Any:
    from cryptography.hazmat.primitives.ciphers.aead import ChaCha20Poly1305

    return ChaCha20Poly1305(key)


def _aead_nonce(ctr: int) -> bytes:
    return b"\0\0\0\0" + _CTR.pack(ctr)
