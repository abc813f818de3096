"""The failure detector's state machines: each other node as this node holds it (alive,
suspected or failed, by incarnation), and the two waits of an indirect probe.

Fail-stop failures (paper §3.4, assumption 3) with restarts and partitions, SWIM-style: a node
this node watches (a neighbour, or a former neighbour now out of reach) that has been silent
for the liveness window is *suspected* (``silent``); the :class:`Suspicion` asks a few members
(at most ``K_ASKED``: the suspect's other neighbours first, as its last figures named them,
then this node's own) whether they hear it, never every member. One that heard it recently
enough keeps it alive (``vouched``; the answer says *when* it heard it, and the silence clock
runs from then, not from the answer) — if its yes counts (:class:`.claims.Vouchers`: not one
member's word alone for long, or a captured member keeps a dead node alive); it is declared
failed (``confirmed``) when every node asked said no, or none said yes by the deadline, and the
first that said no is the claim's witness. A node asked that has not heard the suspect itself
but reaches it asks it in turn (a :class:`Vouch`, SWIM's ping-req).

Another detector's claim (``reported_down``, a ``NodeDown`` sent to the nodes that host the
apps, or piggybacked on heartbeats) is acted on only when corroborated (membership checks it);
a failed node is heard again only to rejoin — as a higher incarnation after a restart, or,
after a partition heals, once one side has reset — and is then ALIVE again (``rejoined``). A
node that learns it was declared failed by a side that outranks it *resets*: it drops its
apps, forgets whom it held failed (``reset``) and comes back as its next incarnation; the
others restore what it hosted and send it the apps (``AppSync``).

The waits have deadlines: silence is judged against the liveness window (``dead_after_s``), a
suspicion's answers too; a failed node that is reachable again is sent a heartbeat every
``REJOIN_EVERY`` beats so a healed partition is noticed even if nobody speaks first.
"""

from __future__ import annotations

import enum
from typing import Any, ClassVar

from mso.protocol import messages as m
from mso.protocol.procedures.base import Messenger, Phase, Procedure, StateMachine, Table


class P(enum.Enum):
    ALIVE = "alive"
    SUSPECT = "suspect"
    FAILED = "failed"


class PeerEvent(enum.Enum):
    """What moves a PeerLife along its table."""

    SILENT = "silent"
    REPORTED_DOWN = "reported_down"
    VOUCHED = "vouched"
    REACHABLE = "reachable"
    CONFIRMED = "confirmed"
    RESET = "reset"
    REJOINED = "rejoined"


class PeerLife(StateMachine):
    """Another node, as this node holds it."""

    NAME = "peer"
    INITIAL = P.ALIVE
    TRANSITIONS: ClassVar[Table] = {
        P.ALIVE: {
            PeerEvent.SILENT: P.SUSPECT,
            PeerEvent.CONFIRMED: P.FAILED,
            PeerEvent.REPORTED_DOWN: P.FAILED,
        },
        P.SUSPECT: {
            PeerEvent.VOUCHED: P.ALIVE,
            PeerEvent.REACHABLE: P.ALIVE,
            PeerEvent.CONFIRMED: P.FAILED,
            PeerEvent.REPORTED_DOWN: P.FAILED,
            PeerEvent.RESET: P.ALIVE,
        },
        P.FAILED: {PeerEvent.REJOINED: P.ALIVE, PeerEvent.RESET: P.ALIVE},
    }

    def __init__(self, node: str) -> None:
        super().__init__()
        self.node = node

    @property
    def name(self) -> str:
        return f"peer {self.node}"


class Q(enum.Enum):
    ASKING = "asking"


class SuspicionEvent(enum.Enum):
    """What moves a Suspicion along its table."""

    DENIED = "denied"
    ALL_DENIED = "all_denied"
    VOUCHED = "vouched"
    DEADLINE = "deadline"
    ENDED = "ended"


class Suspicion(Procedure):
    """``node``, which this node watches, has been silent for the window: before declaring it
    failed, this node asks a few others (``asked``) whether they hear it. The outcome
    (``vouched``, ``confirmed``, ``unanswered`` when none of the asked answered in time, or,
    when the wait ended for another reason, ``ended``) is for
    the node to act on; ``witness`` is the first that said no."""

    NAME = "suspicion"
    INITIAL = Q.ASKING
    DEADLINE_S = 0.5  # the node sets it per run to its liveness window (``dead_after_s``)
    TRANSITIONS: ClassVar[Table] = {
        Q.ASKING: {
            SuspicionEvent.DENIED: Q.ASKING,
            SuspicionEvent.ALL_DENIED: Phase.FINISHED,
            SuspicionEvent.VOUCHED: Phase.FINISHED,
            SuspicionEvent.DEADLINE: Phase.FINISHED,
            SuspicionEvent.ENDED: Phase.FINISHED,
        }
    }

    def __init__(
        self,
        pid: int,
        now: float,
        node: str,
        asked: list[str],
        deadline_s: float | None = None,
        nonce: bytes = b"",
    ) -> None:
        super().__init__(pid, now, deadline_s)
        self.node = node
        self.missing = set(asked)
        self.asked = len(self.missing)
        self.heard_by: set[str] = set()  # the asked that said they hear it
        self.answers = 0  # the asked that answered at all (a yes set aside counts)
        self.outcome = ""
        self.witness = ""
        # this suspicion's challenge (with node identities): a yes counts when it carries
        # the suspect's own signed answer to it (:class:`~mso.protocol.messages.Hears`)
        self.nonce = nonce

    @property
    def name(self) -> str:
        return f"suspicion of {self.node}"

    def start(self, ctx: Messenger) -> None:
        for n in sorted(self.missing):
            ctx.send(n, m.Suspect(self.node, self.pid, self.nonce))

    def answer(self, src: str, yes: bool) -> None:
        """One asked node's answer (an answer from a node not asked, or twice, is refused
        by the caller)."""
        self.missing.discard(src)
        self.answers += 1
        if not yes and not self.witness:
            self.witness = src
        if yes:
            self.on(SuspicionEvent.VOUCHED)
            self.outcome = "vouched"
        elif self.missing:
            self.on(SuspicionEvent.DENIED)
        else:
            self.on(SuspicionEvent.ALL_DENIED)
            self.outcome = "confirmed"

    def set_aside(self, src: str) -> None:
        """An asked node's yes that does not count on its own (:class:`.claims.Vouchers`):
        another's yes may still come; with none, it is confirmed."""
        self.missing.discard(src)
        self.answers += 1
        if self.missing:
            self.on(SuspicionEvent.DENIED)
        else:
            self.on(SuspicionEvent.ALL_DENIED)
            self.outcome = "confirmed"

    def expire(self, ctx: Messenger) -> None:
        """Nobody said yes in time (a node asked may have died too): confirmed if one of
        the asked answered; ``unanswered`` if none did -- then the asker's own routes may be
        what failed (a link broken that the routing view still uses), which is no evidence
        against the suspect."""
        self.on(SuspicionEvent.DEADLINE)
        self.outcome = "confirmed" if self.answers else "unanswered"

    def end(self) -> None:
        """The wait is moot: the node came back into reach, was heard, or declared failed."""
        self.on(SuspicionEvent.ENDED)
        self.outcome = "ended"

    def describe(self) -> dict[str, Any]:
        return super().describe() | {"node": self.node, "waiting_for": sorted(self.missing)}


class VouchEvent(enum.Enum):
    """What moves a Vouch along its table."""

    ASKED = "asked"
    TOLD = "told"
    ANSWERED = "answered"
    DEADLINE = "deadline"


class Vouch(Procedure):
    """Asked whether this node hears ``node``: it asks ``node`` (a ``Suspect`` about itself,
    which a live node answers yes) and answers its askers (``askers``: asker -> their
    suspicion's id and challenge) with what came back by the deadline — SWIM's ping-req.
    Half the askers' window, so that a no still reaches them in time.

    With node identities each asker's challenge goes on to ``node`` (one ``Suspect`` per
    distinct challenge), and each asker is told yes with ``node``'s own signed answer to its
    challenge (the proof its yes needs: a member's word alone is not taken); without them
    ``node``'s first answer is every asker's."""

    NAME = "vouch"
    INITIAL = Q.ASKING
    DEADLINE_S = 0.25  # the node sets it per run to half its liveness window
    MAX_ASKERS = 64  # one entry per asking node; a flood of names is not kept
    TRANSITIONS: ClassVar[Table] = {
        Q.ASKING: {
            VouchEvent.ASKED: Q.ASKING,
            VouchEvent.TOLD: Q.ASKING,
            VouchEvent.ANSWERED: Phase.FINISHED,
            VouchEvent.DEADLINE: Phase.FINISHED,
        }
    }

    def __init__(self, pid: int, now: float, node: str, deadline_s: float | None = None) -> None:
        super().__init__(pid, now, deadline_s)
        self.node = node
        self.askers: dict[str, tuple[int, bytes]] = {}

    @property
    def name(self) -> str:
        return f"vouch for {self.node}"

    def ask(self, ctx: Messenger, asker: str, rid: int, nonce: bytes = b"") -> None:
        """``asker`` asks (again, or first): ``node`` is asked with its challenge, unless an
        asker's same challenge (or, without one, any question) is already on its way."""
        self.on(VouchEvent.ASKED)
        if asker not in self.askers and len(self.askers) >= self.MAX_ASKERS:
            return
        sent = {n for _, n in self.askers.values()}
        self.askers[asker] = (rid, nonce)
        if nonce not in sent and (nonce or not sent):
            ctx.send(self.node, m.Suspect(self.node, self.pid, nonce))

    def start(self, ctx: Messenger) -> None:
        """Nothing to send yet: each asker's question goes on as it comes (:meth:`ask`)."""

    def answered(self, ctx: Messenger, nonce: bytes = b"", proof: bytes = b"") -> None:
        """``node`` answered ``nonce`` (b"": a question without one): it lives. The askers of
        that challenge are told, with its proof, and those that sent none; an answer without
        a challenge is every asker's (no proof)."""
        told = [a for a, (_, n) in self.askers.items() if n == nonce or not n or not nonce]
        for asker in sorted(told):
            rid, n = self.askers.pop(asker)
            ctx.send(asker, m.Hears(self.node, rid, True, 0, n, proof if n else b""))
        self.on(VouchEvent.TOLD if self.askers else VouchEvent.ANSWERED)

    def expire(self, ctx: Messenger) -> None:
        """``node`` did not answer in time: we do not hear it."""
        self.on(VouchEvent.DEADLINE)
        for asker, (rid, nonce) in sorted(self.askers.items()):
            ctx.send(asker, m.Hears(self.node, rid, False, -1, nonce))

    def describe(self) -> dict[str, Any]:
        return super().describe() | {"node": self.node, "askers": sorted(self.askers)}
