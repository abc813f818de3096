"""End-to-end integrity of the data plane: a tag on every data frame, by a key only its two
ends hold.

Data frames (events, acks, tap copies) are authenticated hop by hop, so a relay could alter
or inject the data of the apps it carries. With node identities, the node that originates a
data frame adds a 16-byte keyed blake2b tag over its source, destination, kind and body (not
the hop count, which relays count down) in the envelope's ``origin`` field, and its
destination checks it whenever the frame was handed over by a relay (from the neighbour
itself the link proves it). The key is the pair's own: X25519 between the two nodes'
certified Ed25519 keys (the same curve: the signing key's seed gives the X25519 scalar, its
public point the Montgomery u), so it needs no distribution — a key per app would have had to
reach only the app's hosts, which nothing here can do: documents flood to every node, and
control frames are opened at every hop — and no relay, nor any third host of the app, holds
it. A frame's tag is as cheap as a link hop's (``bench/integrity.py``); a replayed frame is
a repeat its channel drops.

Sans-IO: keys and bytes in, a tag or a verdict out.
"""

from __future__ import annotations

import hashlib
import hmac
from collections import OrderedDict

import msgspec
from cryptography.hazmat.primitives import serialization
from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey
from cryptography.hazmat.primitives.asymmetric.x25519 import X25519PrivateKey, X25519PublicKey

from mso.protocol import messages as m

TAG_BYTES = 16
PAIR_DOMAIN = b"mso data pair"
MAX_PAIRS = 4096  # pair keys kept (one X25519 each, ~60 us, when a new peer's first frame comes)
_P = 2**255 - 19
_ENCODER = msgspec.msgpack.Encoder()


def x25519_private(private: Ed25519PrivateKey) -> X25519PrivateKey:
    """The X25519 key of an Ed25519 key: its seed's SHA-512, first half (clamped on use)."""
    seed = private.private_bytes(
        serialization.Encoding.Raw, serialization.PrivateFormat.Raw, serialization.NoEncryption()
    )
    return X25519PrivateKey.from_private_bytes(hashlib.sha512(seed).digest()[:32])


def x25519_public(ed_public: bytes) -> X25519PublicKey:
    """The X25519 public key of a raw Ed25519 public key: u = (1 + y) / (1 - y) mod p."""
    y = int.from_bytes(ed_public, "little") & ((1 << 255) - 1)
    u = (1 + y) * pow(1 - y, _P - 2, _P) % _P
    return X25519PublicKey.from_public_bytes(u.to_bytes(32, "little"))


def tagged_bytes(env: m.Envelope) -> bytes:
    """What a tag covers: the envelope but its hop count and origin."""
    return _ENCODER.encode([env.src, env.dst, env.kind]) + bytes(env.body)


class Pairs:
    """This node's pair keys with the nodes it sends data to or takes data from, by the
    other node's name and raw Ed25519 key (a new certificate is a new pair). Bounded."""

    def __init__(self, private: Ed25519PrivateKey, node: str) -> None:
        self._mine = x25519_private(private)
        self._node = node
        self._keys: OrderedDict[tuple[str, bytes], bytes] = OrderedDict()

    def key(self, other: str, ed_public: bytes) -> bytes:
        held = self._keys.get((other, ed_public))
        if held is not None:
            self._keys.move_to_end((other, ed_public))
            return held
        shared = self._mine.exchange(x25519_public(ed_public))
        names = _ENCODER.encode(sorted((self._node, other)))
        key = hashlib.blake2b(shared + names, digest_size=32, person=PAIR_DOMAIN[:16]).digest()
        self._keys[(other, ed_public)] = key
        while len(self._keys) > MAX_PAIRS:
            self._keys.popitem(last=False)
        return key

    def tag(self, env: m.Envelope, peer_key: bytes) -> bytes:
        """The tag of ``env`` (this node its source, ``peer_key`` its destination's key)."""
        return _tag(self.key(env.dst, peer_key), env)

    def holds(self, env: m.Envelope, peer_key: bytes) -> bool:
        """Whether ``env``'s tag is its source's (``peer_key``), to this node."""
        want = _tag(self.key(env.src, peer_key), env)
        return len(env.origin) == TAG_BYTES and hmac.compare_digest(env.origin, want)


def _tag(key: bytes, env: m.Envelope) -> bytes:
    return hashlib.blake2b(tagged_bytes(env), key=key, digest_size=TAG_BYTES).digest()


__all__ = ["TAG_BYTES", "Pairs", "tagged_bytes", "x25519_private", "x25519_public"]
