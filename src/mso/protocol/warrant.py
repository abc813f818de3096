"""Warrants: why a node takes a relocation's step from another (issue 27).

A relocation's steps (``Prepare`` to its target, ``Switch`` to the producers, ``Rewire`` to
the surviving ends of a restore) are sent by the move's coordinator, which need not host the
vertex: an operator's command goes to whichever node the client reached, a remap is
coordinated by a chain's end, a recovery by the lowest-named surviving host. With operator
keys configured, a member used to coordinate any move of an app it took part in, in its own
name: the steps did not say who asked. Now a receiver takes a step only when it traces to a
decision it can check itself (:func:`refused`):

- the step is the receiver's own (it coordinates the move);
- the coordinator hosts the vertex in the receiver's view (its rules move what it hosts, or it
  restores its own crashed instance);
- the vertex has no instance in the receiver's view (its node is held failed here, or its
  instance vanished with a restart): a restore after a failure the receiver itself holds; a
  recovery's other moves too (of a chain that lost a vertex, by a node hosting part of the
  app);
- the coordinator hosts an end of a chain through the vertex (a chain remap, which only the
  head's rules ask for, or an energy remap of a junction's chains by the junction's host),
  at most one move of the vertex per :data:`CHAIN_END_INTERVAL_S` (the rules remap a chain
  at most every 15 s; a captured chain end moved a vertex as often as it liked) — kept by the
  move's target (its refusal is answered: the move ends before any switch) and its producers
  (whose switch commits it), not by the old host: a host refusing on its own clock a move a
  producer had switched for left the producer's events with a twin that never got the
  state, and the stream stopped (``bench/chain_end.py``) —, and not
  at all on a node told ``strict_moves`` (its operator's choice: a chain end's remap then
  needs an operator's order, see docs/security.md);
- the step carries an operator's *order*: the ``RelocateRequest`` or ``RemapRequest`` the
  client sent, signed by the client over its own fields and the time (``at``, the signer's
  clock in ms), with no connection in it, so every node verifies it (by an operator key, or a
  ``command`` client's key whose operator certificate travels with it). An order made before
  the app's deployment does not apply to it, and each receiver takes an order for one move of
  a vertex only (the newest it took, per coordinator and move), so a captured node replaying
  an order it relayed or coordinated moves nothing again.

A move's markers are sent by the vertex's producers, not its coordinator, so a marker proves
nothing: the producer of every input of a vertex used to have its host hand the vertex's state
to any node it named. Now (with operator keys) a host hands a vertex over at a marker only for
a move it holds a warrant for (:class:`Leaving`): one it coordinates, or one whose coordinator
told it with a ``Moving`` whose warrant it checked as a ``Prepare``'s. A marker that comes
before its move's ``Moving`` waits for it, for as long as a committed move may take. And a
marker is taken only from its edge's producer (the node this node's view places the edge's
producer on): one from another node waits until the view agrees (a move of the producer not
heard of yet), else is refused at the same deadline; a member knowing a running move's number
and target used to end an edge's drain early with a marker of its own.

Sans-IO: messages, keys and the receiver's view in; a verdict out.
"""

from __future__ import annotations

from collections import OrderedDict
from collections.abc import Mapping, Set
from typing import Any

import msgspec
from cryptography.exceptions import InvalidSignature
from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PublicKey

from mso.protocol import messages as m
from mso.protocol.authority import (
    Authority,
    KeyError_,
    Signer,
    certified_key,
    generation,
    order_bytes,
)
from mso.protocol.clients import parse_cert
from mso.protocol.state import AppState

MAX_ORDERS = 4096  # (app, vertex) whose last order a node remembers
# how long a marker waits for its move's Moving, and a Moving for its markers: the deadline
# of a committed move (mso.protocol.procedures.relocation.SWITCH_DEADLINE_S)
HOLD_S = 60.0
# a chain end's warrant moves a vertex at most once per interval at each node: below the
# rules' own chain_interval_s (15 s), as a node sees a move's steps later than it was decided
CHAIN_END_INTERVAL_S = 10.0
MAX_HELD = 4096  # markers waiting, and moves warranted, at most (each of a vertex hosted here)
Order = m.RelocateRequest | m.RemapRequest
_DECODER = msgspec.msgpack.Decoder(m.RelocateRequest | m.RemapRequest)


def sign(signer: Signer, req: Order, at_ms: int, cert: bytes = b"") -> Order:
    """``req`` as an order every node can verify (:meth:`Signer.order`)."""
    return signer.order(req, at_ms, cert)


def carried(req: Order) -> bytes:
    """What a coordinator puts in the steps of a move it was asked (b"": no order)."""
    return m.encode(req) if req.sig else b""


def verify(
    req: Order, operators: Mapping[str, Ed25519PublicKey], revoked: Set[str] = frozenset()
) -> str:
    """'' when ``req`` is signed by an operator, or by a command client an operator certified
    and did not revoke; else why not."""
    pub = operators.get(req.key)
    if pub is None and req.cert:
        try:
            cert = parse_cert(req.cert)
        except KeyError_ as exc:
            return str(exc)
        if cert.operator not in operators or cert.role != "command" or cert.key_id != req.key:
            return f"an order by client key {req.key} no operator gave command of"
        if cert.key_id in revoked:
            return f"an order by client key {req.key}, revoked"
        key = certified_key(cert, operators)
        if isinstance(key, str):
            return "an order whose client certificate does not verify"
        pub = key
    if pub is None:
        return f"an order by key {req.key}, no operator's"
    try:
        pub.verify(req.sig, order_bytes(req))
    except InvalidSignature:
        return "an order whose signature does not verify"
    return ""


class Orders:
    """The orders this node took, per (app, vertex): the newest, by which coordinator, for
    which move. Another move on an order no newer is a replay. And the last move of each
    vertex it took on a chain end's warrant, by whom and when (:meth:`chain_end`)."""

    def __init__(self) -> None:
        self._took: OrderedDict[tuple[str, str], tuple[int, str, int]] = OrderedDict()
        self._ends: OrderedDict[tuple[str, str], tuple[str, int, float]] = OrderedDict()

    def chain_end(
        self, app: str, vertex: str, src: str, rid: int, now: float, moved_at: float = -1e18
    ) -> bool:
        """Whether a step of move ``rid`` by the chain end ``src`` may be taken now: a step
        of the move last taken so, or of a new move once the interval has passed since the
        last move this node took a step of and since the vertex last moved in its view
        (``moved_at``: a node new to the vertex's moves — a producer's new host — knows
        that much of them)."""
        key = (app, vertex)
        held = self._ends.get(key)
        if held is None or held[:2] != (src, rid):
            last = max(held[2] if held is not None else -1e18, moved_at)
            if now - last < CHAIN_END_INTERVAL_S:
                return False
            self._ends[key] = (src, rid, now)
        self._ends.move_to_end(key)
        while len(self._ends) > MAX_ORDERS:
            self._ends.popitem(last=False)
        return True

    def take(self, app: str, vertex: str, at: int, src: str, rid: int) -> bool:
        key = (app, vertex)
        held = self._took.get(key)
        if held is not None and held != (at, src, rid) and at <= held[0]:
            return False
        self._took[key] = (at, src, rid)
        self._took.move_to_end(key)
        while len(self._took) > MAX_ORDERS:
            self._took.popitem(last=False)
        return True


def refused(
    dep: AppState,
    here: str,
    src: str,
    vertex: str,
    rid: int,
    order: bytes,
    failed: Set[str],
    authority: Authority,
    orders: Orders,
    now: float = 0.0,
    *,
    paced: bool = True,
) -> str:
    """Why a step of a move of ``vertex`` coordinated by ``src`` (move ``rid``) is not taken
    here ('' if it is), at ``now``: the module docstring's rules, with operator keys only.
    Not ``paced``: a chain end's move is not held to its interval here (the old host's
    ``Moving``: the target and the producers keep the pace, and the host must not refuse a
    move a producer has switched for)."""
    if not authority.signed or src == here:
        return ""
    host = dep.placed.get(vertex)
    if host == src or host in failed or vertex in dep.vanished:
        return ""
    lost = dep.lost(set(failed))
    hosts = set(dep.placed.values())
    end = False
    for c in dep.layout.chains:
        if vertex not in c.vertices:
            continue
        if src in hosts and any(v in lost for v in c.vertices):  # its recovery's
            return ""
        end = end or src in (dep.placed.get(c.head), dep.placed.get(c.tail))
    if end and not order:  # the chain's remap (an order, if it carries one, decides)
        if authority.strict_moves:
            return "chain_end_without_an_order"
        moved_at = dep.moved_at.get(vertex, -1e18)
        if paced and not orders.chain_end(dep.app.name, vertex, src, rid, now, moved_at):
            return "chain_end_too_often"
        return ""
    if not order:
        return "no_warrant"
    try:
        req = _DECODER.decode(order)
    except (msgspec.DecodeError, msgspec.ValidationError, RecursionError):
        return "order_malformed"
    if req.app != dep.app.name or not _names(dep, req, vertex):
        return "order_of_another_move"
    if req.at < generation(dep.document):
        return "order_older_than_deployment"
    if verify(req, authority.operators, authority.revoked_nodes):
        authority.refused += 1
        return "order_not_verified"
    if not orders.take(dep.app.name, vertex, req.at, src, rid):
        return "order_replayed"
    return ""


def could_take(dep: AppState, src: str, vertex: str) -> bool:
    """Whether ``src`` could move ``vertex`` onto itself on its own warrant, and so already
    holds where its output goes and whose events it acks: it hosts the vertex, or an end of
    a chain through it, in this node's view. A move's target that runs no instance of the
    app (told of none of its moves) may take from such a coordinator where the vertex's
    neighbours run (:func:`mso.protocol.procedures.placement.brief`)."""
    if dep.placed.get(vertex) == src:
        return True
    return any(
        vertex in c.vertices and src in (dep.placed.get(c.head), dep.placed.get(c.tail))
        for c in dep.layout.chains
    )


def _names(dep: AppState, req: Order, vertex: str) -> bool:
    """Whether the order asks for a move of ``vertex``."""
    if isinstance(req, m.RelocateRequest):
        return req.vertex == vertex
    chains = dep.layout.chains
    wanted = range(len(chains)) if req.everything else req.chains
    return any(0 <= c < len(chains) and vertex in chains[c].vertices for c in wanted)


class Leaving:
    """The moves of vertices hosted here that a coordinator told this node of and whose
    warrant it checked, and the markers that came before theirs (both bounded, both
    forgotten after :data:`HOLD_S`)."""

    def __init__(self) -> None:
        self._moves: OrderedDict[tuple[str, str], tuple[int, str, float]] = OrderedDict()
        self._held: OrderedDict[tuple[str, str, int], tuple[m.Marker, float]] = OrderedDict()
        # markers from another node than their edge's producer, by (app, edge, sender)
        self._strays: OrderedDict[tuple[str, int, str], tuple[m.Marker, float]] = OrderedDict()

    def warranted(self, app: str, vertex: str, rid: int, to: str, now: float) -> list[m.Marker]:
        """Move ``rid`` of ``vertex`` to ``to`` is warranted here: the markers of it that
        waited, to be taken now."""
        self._moves[(app, vertex)] = (rid, to, now)
        self._moves.move_to_end((app, vertex))
        _bound(self._moves)
        due = [
            k
            for k, (mk, _) in self._held.items()
            if k[:2] == (app, vertex) and (mk.rid, mk.to) == (rid, to)
        ]
        return [self._held.pop(k)[0] for k in due]

    def takes(self, app: str, vertex: str, marker: m.Marker) -> bool:
        """Whether ``marker`` belongs to a move of ``vertex`` told and warranted here."""
        held = self._moves.get((app, vertex))
        return held is not None and held[:2] == (marker.rid, marker.to)

    def hold(self, app: str, vertex: str, marker: m.Marker, now: float) -> None:
        """``marker`` waits for its move's warrant (the newest one of its edge)."""
        self._held[(app, vertex, marker.edge)] = (marker, now)
        self._held.move_to_end((app, vertex, marker.edge))
        _bound(self._held)

    def stray(self, app: str, vertex: str, sender: str, marker: m.Marker, now: float) -> None:
        """``marker`` came from ``sender``, not its edge's producer in this node's view: it
        waits for the view to agree (the newest one of its edge from that sender), apart
        from the producer's own markers, which it never displaces."""
        key = (app, marker.edge, sender)
        self._strays[key] = (marker, now)
        self._strays.move_to_end(key)
        _bound(self._strays)

    def strays(self) -> list[tuple[str, m.Marker]]:
        """The markers waiting for their sender to be their edge's producer, with it."""
        return [(k[2], mk) for k, (mk, _) in self._strays.items()]

    def unstray(self, sender: str, marker: m.Marker) -> None:
        """``marker`` is now its producer's: it waits no longer as a stray."""
        self._strays.pop((marker.app, marker.edge, sender), None)

    @property
    def held(self) -> int:
        """How many markers wait for their move's warrant or their producer."""
        return len(self._held) + len(self._strays)

    def done(self, app: str, vertex: str) -> None:
        """``vertex`` was handed over: its move is over here."""
        self._moves.pop((app, vertex), None)

    def expire(self, now: float) -> tuple[int, int]:
        """Forget what is older than :data:`HOLD_S`; how many markers never got a warrant,
        and how many never came from their edge's producer."""
        for move in [k for k, v in self._moves.items() if now - v[2] > HOLD_S]:
            del self._moves[move]
        return _expire(self._held, now), _expire(self._strays, now)

    def clear(self) -> None:
        self._moves.clear()
        self._held.clear()
        self._strays.clear()


def _expire(table: OrderedDict[Any, tuple[m.Marker, float]], now: float) -> int:
    """Drop the markers waiting longer than :data:`HOLD_S`; how many."""
    stale = [k for k, (_, since) in table.items() if now - since > HOLD_S]
    for k in stale:
        del table[k]
    return len(stale)


def _bound(table: OrderedDict[Any, Any]) -> None:
    while len(table) > MAX_HELD:
        table.popitem(last=False)
