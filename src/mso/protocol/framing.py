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
"""

from __future__ import annotations

import hashlib
import hmac
import os
import struct

MAGIC = b"MSO1"
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

    Counters: ``rejected`` frames whose tag failed; ``accepted`` frames delivered.
    """

    def __init__(self, psk: bytes, *, max_frame: int = MAX_FRAME, nonce: bytes | None = None):
        if not psk:
            raise ValueError("an overlay key is required")
        self._psk = psk
        self._max = max_frame
        self._nonce = nonce if nonce is not None else os.urandom(NONCE_BYTES)
        self._tx_key: bytes | None = None
        self._rx_key: bytes | None = None
        self._peer_nonce: bytes | None = None
        self._tx_ctr = 0
        self._rx_ctr = 0
        self._buf = bytearray()
        self._pending: list[bytes] = []  # sealed before the peer's hello arrived
        self._confirmed = False  # the peer's key confirmation verified
        self.rejected = 0
        self.accepted = 0
        self._rejected_in_a_row = 0

    @property
    def ready(self) -> bool:
        return self._rx_key is not None

    @property
    def confirmed(self) -> bool:
        """The peer proved it holds the overlay key."""
        return self._confirmed

    @property
    def nonce(self) -> bytes:
        """This side's hello nonce (a signer binds a command to the connection with it)."""
        return self._nonce

    @property
    def peer_nonce(self) -> bytes | None:
        return self._peer_nonce

    def hello(self) -> bytes:
        return MAGIC + self._nonce

    def seal(self, payload: bytes) -> bytes:
        """One frame for ``payload``; before the peer's hello it is queued (returns b"")."""
        if self._tx_key is None:
            self._pending.append(bytes(payload))
            return b""
        return self._seal(payload)

    def _seal(self, payload: bytes) -> bytes:
        assert self._tx_key is not None
        mac = hashlib.blake2b(_CTR.pack(self._tx_ctr), key=self._tx_key, digest_size=TAG_BYTES)
        mac.update(payload)  # no concatenated copy of the payload
        self._tx_ctr += 1
        return b"".join((_LEN.pack(TAG_BYTES + len(payload)), mac.digest(), payload))

    def feed(self, data: bytes) -> tuple[list[bytes], bytes]:
        """Consume received bytes; return (authenticated payloads, bytes to send now).

        The bytes to send are frames sealed before the handshake completed.
        """
        self._buf += data
        out: list[bytes] = []
        flush = b""
        if self._rx_key is None:
            if len(self._buf) < HELLO_BYTES:
                return out, flush
            if bytes(self._buf[: len(MAGIC)]) != MAGIC:
                raise FramingError("peer did not send an mso hello")
            peer_nonce = self._peer_nonce = bytes(self._buf[len(MAGIC) : HELLO_BYTES])
            del self._buf[:HELLO_BYTES]
            self._rx_key = derive_key(self._psk, peer_nonce, self._nonce)
            self._tx_key = derive_key(self._psk, self._nonce, peer_nonce)
            flush = b"".join([self._seal(b""), *(self._seal(p) for p in self._pending)])
            self._pending.clear()
        buf = self._buf
        pos = 0
        n = len(buf)
        view = memoryview(buf)
        while n - pos >= 4:
            (length,) = _LEN.unpack_from(buf, pos)
            if length < TAG_BYTES or length > self._max + TAG_BYTES:
                raise FramingError(f"frame length {length} out of range")
            if not self._confirmed and length != TAG_BYTES:
                raise FramingError("the first frame is not a key confirmation")
            if n - pos - 4 < length:
                break
            start = pos + 4
            tag = bytes(view[start : start + TAG_BYTES])
            body = view[start + TAG_BYTES : start + length]
            pos = start + length
            mac = hashlib.blake2b(_CTR.pack(self._rx_ctr), key=self._rx_key, digest_size=TAG_BYTES)
            mac.update(body)  # straight from the receive buffer
            ok = hmac.compare_digest(tag, mac.digest())
            if not self._confirmed:
                body.release()
                if not ok:
                    view.release()
                    raise WrongKey("the peer holds another overlay key")
                self._confirmed = True
                self._rx_ctr += 1
                continue
            if ok:
                out.append(bytes(body))
                self._rx_ctr += 1
                self.accepted += 1
                self._rejected_in_a_row = 0
            else:
                self.rejected += 1
                self._rejected_in_a_row += 1
                if self._rejected_in_a_row >= MAX_REJECTED_IN_A_ROW:
                    body.release()
                    view.release()
                    raise FramingError(f"{MAX_REJECTED_IN_A_ROW} frames in a row failed their tag")
            body.release()
        view.release()  # a bytearray cannot be resized while a view is exported
        if pos:
            del buf[:pos]
        return out, flush
