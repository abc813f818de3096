"""Authenticated, length-prefixed frames on one stream connection. Sans-IO: bytes in, bytes out.

A connection starts with each side sending a 52-byte hello: ``b"MSO2"``, a fresh random 16-byte
nonce and a fresh X25519 public key. Each direction then has its own key, ``blake2b(key=psk,
data=b"mso2" + sender hello + receiver hello + X25519 shared secret)``, and every frame is::

    u32 length (big endian, of what follows) | 16-byte tag | payload

with ``tag = blake2b(key=direction key, data=u64 frame counter + payload, digest_size=16)``. The
counter is implicit (0, 1, 2, ... per direction), so a frame replayed, reordered or copied from
another connection fails its tag; a receiver's fresh nonce makes every connection's keys new.
A frame whose tag fails is dropped and counted, never acted on, and the stream goes on; a length
beyond ``max_frame`` or a bad hello means the byte stream itself is not ours, and the connection
must be closed (``FramingError``).

Key confirmation: the first frame each side sends is an empty one (its tag proves the key).
Until the peer's has been verified nothing longer is accepted, so a stranger without the key
can make a node buffer at most one 20-byte frame. The side that accepted the connection (the
*responder*) proves it holds the key only after the connecting side (the *initiator*) has
proved it: a wrong key gets no confirmation, only a close (``WrongKey``), so an outsider who
connects learns nothing to test guesses of the key against offline (a node used to answer a
wrong key with its own confirmation: 182,000 guesses a second, a passphrase key fell in 0.8 s).
An eavesdropper learns nothing either: the direction keys depend on the X25519 secret of
the two ephemeral keys, which it cannot compute. What is left is the initiator's confirmation,
sent to whoever it connected to (an impostor at a neighbour's or a node's address could test
guesses against it); keys given as text are stretched with scrypt (:func:`psk_from_text`,
about 16 MiB and tens of ms a guess), so a passphrase costs that much per guess there.

Key rotation: a codec holds a list of keys, the first the one it seals with, the others still
accepted. The responder waits for the initiator's key confirmation, finds which of its keys
that is, and answers with the same one; so a client or neighbour still on the old key is
served while the overlay moves to the next, and connections already open are never touched
(apps keep running).

Encryption (optional, ``encrypt=True``, hello ``MSE2``): each frame is
``u32 length | ChaCha20-Poly1305(direction key, nonce = counter) of the payload``, the 16-byte
Poly1305 tag in place of the blake2b one. Both ends must agree; a mismatch is told at the hello.
"""

from __future__ import annotations

import functools
import hashlib
import hmac
import os
import struct
from collections.abc import Sequence
from typing import TYPE_CHECKING, Any

from cryptography.hazmat.primitives.asymmetric.x25519 import X25519PrivateKey, X25519PublicKey

if TYPE_CHECKING:  # imported when a codec encrypts: the CLI's start stays quick
    from cryptography.hazmat.primitives.ciphers.aead import ChaCha20Poly1305

MAGIC = b"MSO2"
MAGIC_ENCRYPTED = b"MSE2"
NONCE_BYTES = 16
DH_BYTES = 32
HELLO_BYTES = len(MAGIC) + NONCE_BYTES + DH_BYTES
# scrypt's cost for keys given as text: 16 MiB and tens of ms per guess
SCRYPT_N, SCRYPT_R = 1 << 14, 8
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


def derive_key(psk: bytes, sender_hello: bytes, receiver_hello: bytes, shared: bytes) -> bytes:
    """One direction's key: the overlay key, both hellos and the ephemeral keys' secret."""
    return hashlib.blake2b(
        b"mso2" + sender_hello + receiver_hello + shared, key=psk[:64], digest_size=32
    ).digest()


@functools.lru_cache(maxsize=64)
def psk_from_text(text: str) -> bytes:
    """Overlay keys are given as text (flag, file): stretched to a fixed-size secret with
    scrypt, so that each guess at a passphrase costs an offline guesser as much (once per
    process and key here)."""
    return hashlib.scrypt(
        text.encode(),
        salt=b"mso-overlay-key",
        n=SCRYPT_N,
        r=SCRYPT_R,
        p=1,
        maxmem=64 * 1024 * 1024,
        dklen=32,
    )


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
        self._dh = X25519PrivateKey.generate()  # this connection's ephemeral key
        self._hello = self._magic + self._nonce + self._dh.public_key().public_bytes_raw()
        self._peer_hello = b""
        self._shared = b""  # the X25519 secret, once the peer's hello is in
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
    def peer_hello(self) -> bytes:
        """The peer's whole hello (b"" until it arrived): what a node identity's proof signs."""
        return self._peer_hello

    @property
    def greeted(self) -> bool:
        """The peer's hello has arrived (the key check is under way or done)."""
        return self._peer_nonce is not None

    def hello(self) -> bytes:
        return self._hello

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

    def _check_magic(self) -> None:
        """The hello's first bytes, checked as soon as they are in (not a whole hello later)."""
        magic = bytes(self._buf[: len(MAGIC)])
        if magic != self._magic:
            if magic in (MAGIC, MAGIC_ENCRYPTED):
                theirs = "encrypts" if magic == MAGIC_ENCRYPTED else "does not encrypt"
                raise FramingError(f"the peer {theirs} its frames and this side does not agree")
            raise FramingError("peer did not send an mso hello")

    def _hello_received(self) -> bytes:
        hello = self._peer_hello = bytes(self._buf[:HELLO_BYTES])
        try:  # (a low-order public key gives an all-zero secret: refused)
            peer_key = X25519PublicKey.from_public_bytes(hello[-DH_BYTES:])
            self._shared = self._dh.exchange(peer_key)
        except ValueError:
            raise FramingError("the peer's hello holds no usable key") from None
        self._peer_nonce = hello[len(MAGIC) : len(MAGIC) + NONCE_BYTES]
        del self._buf[:HELLO_BYTES]
        self._rx_candidates = [derive_key(k, hello, self._hello, self._shared) for k in self._psks]
        return b"" if self._responder else self._start_sending(0)

    def _start_sending(self, key_index: int) -> bytes:
        """Seal with key ``key_index`` from now on: the key confirmation, then what waited."""
        assert self._peer_nonce is not None
        self._tx_key = derive_key(
            self._psks[key_index], self._hello, self._peer_hello, self._shared
        )
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
            if len(self._buf) >= len(MAGIC):
                self._check_magic()
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
        answers now, with that key, and never before (a wrong key gets nothing to test
        guesses against)."""
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
