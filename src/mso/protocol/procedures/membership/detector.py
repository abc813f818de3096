"""The failure detector's state machines: each other node as this node holds it (alive,
suspected or failed, by incarnation), and the two waits of an indirect probe.

Fail-stop failures (paper §3.4, assumption 3) with restarts and partitions: a neighbour silent
for the liveness window is declared failed by this node (``silent``) or by another detector
(``reported_down``, a ``NodeDown``); a failed node is heard again only to rejoin — as a higher
incarnation after a restart, or, after a partition heals, once one side has reset — and is
then ALIVE again (``rejoined``). A node that learns it was declared failed by a side that
outranks it *resets*: it drops its apps, forgets whom it held failed (``reset``) and comes back
as its next incarnation; the others restore what it hosted and send it the apps (``AppSync``).

A node this node's routing view stopped reaching altogether is only *suspected*
(``unreachable``): one node's missing route is no evidence that the node died while others
still hear it (babeld once left one node of a mesh with no route to a live node for 12 s, and
its word reset that node every 4 s). The :class:`Suspicion` asks the nodes this node still
reaches whether they hear it (SWIM's indirect probe, adapted to routes): one yes keeps it alive
(``vouched``; asked again a liveness window later if still out of reach), and it is declared
failed (``confirmed``) only when every node asked said no, or none said yes by the deadline. A
node asked that has not heard the suspect itself but reaches it asks it in turn (a
:class:`Vouch`, SWIM's ping-req): a node's neighbours are not always among those still reached.

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
    UNREACHABLE = "unreachable"
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
            PeerEvent.SILENT: P.FAILED,
            PeerEvent.REPORTED_DOWN: P.FAILED,
            PeerEvent.UNREACHABLE: P.SUSPECT,
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
    """This node lost every route to ``node``: before declaring it failed, it asks the nodes it
    still reaches (``asked``) whether they hear it. The outcome (``vouched``, ``confirmed`` or,
    when the wait ended for another reason, ``ended``) is for the node to act on."""

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
        self, pid: int, now: float, node: str, asked: list[str], deadline_s: float | None = None
    ) -> None:
        super().__init__(pid, now, deadline_s)
        self.node = node
        self.missing = set(asked)
        self.outcome = ""

    @property
    def name(self) -> str:
        return f"suspicion of {self.node}"

    def start(self, ctx: Messenger) -> None:
        for n in sorted(self.missing):
            ctx.send(n, m.Suspect(self.node, self.pid))

    def answer(self, src: str, yes: bool) -> None:
        """One asked node's answer (an answer from a node not asked, or twice, is refused
        by the caller)."""
        self.missing.discard(src)
        if yes:
            self.on(SuspicionEvent.VOUCHED)
            self.outcome = "vouched"
        elif self.missing:
            self.on(SuspicionEvent.DENIED)
        else:
            self.on(SuspicionEvent.ALL_DENIED)
            self.outcome = "confirmed"

    def expire(self, ctx: Messenger) -> None:
        """Nobody said yes in time (a node asked may have died too): confirmed."""
        self.on(SuspicionEvent.DEADLINE)
        self.outcome = "confirmed"

    def end(self) -> None:
        """The wait is moot: the node came back into reach, was heard, or declared failed."""
        self.on(SuspicionEvent.ENDED)
        self.outcome = "ended"

    def describe(self) -> dict[str, Any]:
        return super().describe() | {"node": self.node, "waiting_for": sorted(self.missing)}


class VouchEvent(enum.Enum):
    """What moves a Vouch along its table."""

    ASKED = "asked"
    ANSWERED = "answered"
    DEADLINE = "deadline"


class Vouch(Procedure):
    """Asked whether this node hears ``node``, which it does not hear itself but reaches: it
    asks ``node`` (a ``Suspect`` about itself, which a live node answers yes) and answers its
    askers (``askers``: asker -> their suspicion's id) with what came back by the deadline —
    SWIM's ping-req. Half the askers' window, so that a no still reaches them in time."""

    NAME = "vouch"
    INITIAL = Q.ASKING
    DEADLINE_S = 0.25  # the node sets it per run to half its liveness window
    MAX_ASKERS = 64  # one entry per asking node; a flood of names is not kept
    TRANSITIONS: ClassVar[Table] = {
        Q.ASKING: {
            VouchEvent.ASKED: Q.ASKING,
            VouchEvent.ANSWERED: Phase.FINISHED,
            VouchEvent.DEADLINE: Phase.FINISHED,
        }
    }

    def __init__(self, pid: int, now: float, node: str, deadline_s: float | None = None) -> None:
        super().__init__(pid, now, deadline_s)
        self.node = node
        self.askers: dict[str, int] = {}

    @property
    def name(self) -> str:
        return f"vouch for {self.node}"

    def ask(self, asker: str, rid: int) -> None:
        self.on(VouchEvent.ASKED)
        if asker in self.askers or len(self.askers) < self.MAX_ASKERS:
            self.askers[asker] = rid

    def start(self, ctx: Messenger) -> None:
        ctx.send(self.node, m.Suspect(self.node, self.pid))

    def _tell(self, ctx: Messenger, yes: bool) -> None:
        for asker, rid in sorted(self.askers.items()):
            ctx.send(asker, m.Hears(self.node, rid, yes))

    def answered(self, ctx: Messenger) -> None:
        """``node`` answered: it lives."""
        self.on(VouchEvent.ANSWERED)
        self._tell(ctx, True)

    def expire(self, ctx: Messenger) -> None:
        """``node`` did not answer in time: we do not hear it."""
        self.on(VouchEvent.DEADLINE)
        self._tell(ctx, False)

    def describe(self) -> dict[str, Any]:
        return super().describe() | {"node": self.node, "askers": sorted(self.askers)}
