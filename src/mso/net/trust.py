"""Whom a transport trusts, with node identities: a neighbour's proof of its name, the origin
of what it hands over, a client's certificate, and the node and client keys an operator
revoked.

The transport (:mod:`mso.net.tcp`) asks; this holds the keys and the verdicts and counts what
it refuses. The checks themselves are sans-IO: :mod:`mso.protocol.identity` (links),
:mod:`mso.protocol.origin` (end to end) and :mod:`mso.protocol.revocation`.
"""

from __future__ import annotations

import logging
import time

import msgspec

from mso.net.base import Counters
from mso.net.limits import ConnectionCounters
from mso.net.relaying import RelayBudget
from mso.protocol import clients
from mso.protocol import messages as m
from mso.protocol.authority import Authority
from mso.protocol.dataseal import Pairs
from mso.protocol.identity import Identity, check, parse_cert
from mso.protocol.origin import Verifier
from mso.protocol.revocation import Revocations

log = logging.getLogger("mso.net")
# origins a neighbour may make this node check a second, per class (heartbeats: hellos to a
# non-neighbour), with a second's burst: a check is a signature's verification (about 120 us),
# so a neighbour's flood of frames in others' names costs this node at most about 6% of a
# core and 60 ms at a time, not its heartbeats (a burst of the relay budget's 4,000 frames
# would hold the loop half a second, as long as a neighbour's liveness window)
CHECKS_PER_S = 500.0
BEAT_CHECKS_PER_S = 50.0
# a check hashes the whole frame: each CHECK_BYTES of it cost as much as a small frame's check
# (SHA-512 of 64 KiB, about 0.13 ms), so a flood of 8 MiB frames (18 ms to check each, 129
# checks' worth) holds to the same share of a core as one of small frames
CHECK_BYTES = 65536


class Trust:
    """A node's identity, the operator keys and revocations it holds, and its verdicts."""

    def __init__(
        self,
        identity: Identity | None,
        authority: Authority,
        counters: Counters,
        connection_counters: ConnectionCounters,
        checks: RelayBudget | None = None,
    ) -> None:
        self.identity = identity
        self.authority = authority
        self.counters = counters
        self.connection_counters = connection_counters
        self.checks = checks or RelayBudget(CHECKS_PER_S, BEAT_CHECKS_PER_S, burst_s=1.0)
        self.origins = Verifier()  # other nodes' signatures on what they originate
        # pair keys for the end-to-end tags of data frames (mso.protocol.dataseal)
        self.pairs = Pairs(identity.private, identity.node) if identity is not None else None
        self.revocations = Revocations()  # node keys an operator revoked through the overlay

    @property
    def required(self) -> bool:
        """Neighbours must prove their names: this node has an identity and operator keys."""
        return self.identity is not None and self.authority.signed

    def revoked(self) -> frozenset[str]:
        """Node keys refused: by this node's configuration, or by an operator's word."""
        return self.authority.revoked_nodes | self.revocations.keys()

    def hello(
        self, msg: m.PeerHello, theirs: bytes, mine: bytes, called: str | None, address: str
    ) -> str | None:
        """The id of the key a neighbour proved its name with on the connection whose hellos
        are ``theirs`` and ``mine`` (``called``: the node this one called, if it did), or
        None when the proof does not hold (counted)."""
        why = check(
            msg.node, msg.cert, msg.sig, theirs, mine, self.authority.operators, self.revoked()
        )
        if why is None and called is not None and msg.node != called:
            why = f"it says it is {msg.node}, and {called} was called"
        if why is not None:
            self.connection_counters.identity_refused += 1
            log.warning("refusing %s from %s: %s", msg.node, address or "?", why)
            return None
        cert = parse_cert(msg.cert)
        self.origins.learn(cert)
        return cert.key_id

    def seal(self, dst: str, payload: bytes) -> bytes:
        """A data frame this node originates, with its end-to-end tag for ``dst`` (untagged,
        counted, while ``dst``'s certificate is not known here yet)."""
        cert = self.origins.by_node.get(dst)
        if self.pairs is None or cert is None:
            self.counters.data_untagged += 1
            return payload
        env = m.unwrap(payload)
        env.origin = self.pairs.tag(env, cert.key)
        return m.rewrap(env)

    def _data_refused(self, peer: str, env: m.Envelope) -> str | None:
        """Why a data frame ``peer`` relayed is not its source's, unaltered (None: it is)."""
        cert = self.origins.by_node.get(env.src)
        if self.pairs is None:
            return "no identity of this node's to check it with"
        if cert is None:
            return "its source's certificate is not known here"
        if cert.key_id in self.revoked():
            return f"node key {cert.key_id} is revoked"
        if not self.pairs.holds(env, cert.key):
            return "an end-to-end tag that does not hold"
        return None

    def client(
        self, msg: m.ClientHello, theirs: bytes, mine: bytes, address: str
    ) -> clients.Admitted | str:
        """The client a hello proves on the connection whose hellos are ``theirs`` and
        ``mine``, or why not (counted; the client is then refused each request, told why)."""
        said = clients.check(msg, theirs, mine, self.authority.certifiers, self.revoked())
        if isinstance(said, str):
            self.connection_counters.client_refused += 1
            log.info("client %r from %s: %s", msg.name, address or "?", said)
        return said

    def command(
        self, client: clients.Admitted | str | None, nonce: bytes, msg: m.Message
    ) -> m.Message | str:
        """What a client (as it proved itself, None: identities not required) may have this
        node carry out of ``msg``, or why not (counted): its role, then the authority (a
        command client may sign what its connection carries with its own key)."""
        if client is not None and (why := clients.may(client, msg)):
            self.authority.refused += 1
            return why
        if self.authority.open and not isinstance(msg, m.Authorized):
            return msg
        own = {client.key_id: client.public} if isinstance(client, clients.Admitted) else None
        return self.authority.command(nonce, msg, own)

    def origin(self, peer: str, env: m.Envelope, msg: m.Message, now: float) -> m.Message | None:
        """``msg`` as the word of its proven originator alone, or None when it is not proven
        (counted): :meth:`mso.protocol.origin.Verifier.admit`. What ``peer`` hands over in
        others' names is checked within its budget of checks (``CHECKS_PER_S``; markers with
        control frames; a frame costs a check per ``CHECK_BYTES`` it holds), past which it
        is dropped (``frames_dropped_rate``)."""
        if env.kind == m.DATA:
            why = self._data_refused(peer, env) if env.src != peer else None
            if why is not None:
                self.counters.frames_data_refused += 1
                log.info("from %s via %s: %s: %s", env.src, peer, type(msg).__name__, why)
                return None
            return msg
        budget = m.CONTROL if env.kind == m.MARKER else env.kind
        cost = 1 + len(env.body) // CHECK_BYTES
        if env.src != peer and not self.checks.allow(peer, budget, now, cost):
            self.counters.frames_dropped_rate += 1
            return None
        wall_ms = time.time_ns() // 1_000_000
        said = self.origins.admit(peer, env, msg, wall_ms, self.authority.operators, self.revoked())
        if isinstance(said, str):
            self.counters.frames_origin_refused += 1
            log.info("from %s via %s: %s: %s", env.src, peer, type(msg).__name__, said)
            return None
        return said

    def hears(self, peer: str, env: m.Envelope, msg: m.Hears, now: float) -> m.Hears:
        """``msg`` with the proof it may carry (:meth:`mso.protocol.origin.Verifier.hears`):
        a proof that does not hold, or one past ``peer``'s budget of checks, is stripped
        (counted in ``frames_origin_refused``): the core then takes the yes as a member's
        word alone."""
        if msg.proof and env.src != msg.node and not self.checks.allow(peer, m.CONTROL, now):
            self.counters.frames_dropped_rate += 1
            return msgspec.structs.replace(msg, proof=b"")
        wall_ms = time.time_ns() // 1_000_000
        ops, revoked = self.authority.operators, self.revoked()
        said, why = self.origins.hears(env.src, env, msg, wall_ms, ops, revoked)
        if why is not None:
            self.counters.frames_origin_refused += 1
            log.info("from %s via %s: Hears of %s: %s", env.src, peer, msg.node, why)
        return said

    def revoke(self, msg: m.RevokeNode, via: str | None) -> str | None:
        """None when ``msg`` is a new revocation an operator signed (now held: the caller
        closes links proven with that key and passes it on); '' when held already; else why
        it is refused (counted)."""
        why = self.revocations.take(msg, self.authority.operators)
        if why:
            self.authority.refused += 1
            log.info("from %s: %s", via or "a client", why)
            return f"refused: {why}"
        if why is None:
            log.warning("node key %s revoked by operator %s", msg.node_key, msg.key)
        return why
