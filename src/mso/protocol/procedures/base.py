"""What every distributed procedure shares: explicit states, one transition table, a deadline.

Modelled on h11's ``_state.py``: a procedure's ``TRANSITIONS`` maps ``state -> {event: next
state}``; :meth:`Procedure.on` moves along it and raises :class:`IllegalTransition` for any
event the table does not allow in the current state, so a message arriving at the wrong moment
is caught, not half-handled. The node core counts illegal transitions in status (tests run the
core strict, where they raise). Every procedure has a deadline: the core arms one timer per
procedure, and a procedure still running when it fires fails with a defined outcome
(:meth:`Procedure.expire`) — no wait can hang forever.

Procedures are sans-IO: they act on the node through a
:class:`~mso.protocol.context.NodeContext` (send, reply, set a timer, the node's tables), which
the core implements.
"""

from __future__ import annotations

import enum
import math
from typing import TYPE_CHECKING, Any, ClassVar, Protocol

if TYPE_CHECKING:
    from mso.protocol import messages as m

# state -> {event: next state}; each machine's events are an enum of its own, so a misspelt
# event is a type error, not a transition missed at run time
Table = dict[enum.Enum, dict[enum.Enum, enum.Enum]]


class IllegalTransition(Exception):
    """An event the procedure's transition table does not allow in its current state."""


class Phase(enum.Enum):
    """States every procedure ends in."""

    FINISHED = "finished"
    FAILED = "failed"


STEP_TIMEOUT_S = 1.0  # a step of a procedure not answered by then is sent again (or given up)
# a procedure a client waits for ends this long before the client stops waiting (its request's
# ``within_s``), for the reply's way back
REPLY_MARGIN_S = 0.5


def within_client_wait(within_s: float, longest_s: float) -> float:
    """A procedure's deadline for a client that waits ``within_s``: ``REPLY_MARGIN_S`` before
    it stops waiting (half its wait, for a short one), at most ``longest_s``; that if the
    client said nothing (0), or nothing sensible (NaN, infinite, negative)."""
    if not (math.isfinite(within_s) and within_s > 0):
        return longest_s
    return min(longest_s, max(within_s - REPLY_MARGIN_S, within_s / 2))


class Messenger(Protocol):
    """What a procedure's own methods may do to its node when it ends: tell others. (The
    node's whole :class:`~mso.protocol.context.NodeContext` is one.)"""

    def send(self, dst: str, msg: m.Message) -> None: ...

    def reply(self, client: int, msg: m.Message) -> None: ...


class StateMachine:
    """Explicit states and one transition table: the shape every procedure, and every
    participant's part in one, shares."""

    NAME: ClassVar[str] = "machine"
    INITIAL: ClassVar[enum.Enum]
    # state -> {event: next state}; FINISHED and FAILED are terminal
    TRANSITIONS: ClassVar[Table]

    def __init__(self) -> None:
        self.state: enum.Enum = self.INITIAL

    @property
    def name(self) -> str:
        return self.NAME

    @property
    def done(self) -> bool:
        return self.state in (Phase.FINISHED, Phase.FAILED)

    def on(self, event: enum.Enum) -> None:
        """Take the transition ``event`` from the current state, or raise."""
        nxt = self.TRANSITIONS.get(self.state, {}).get(event)
        if nxt is None:
            raise IllegalTransition(
                f"{self.name}: event {event.value!r} is not allowed in state {self.state.name}"
            )
        self.state = nxt


class Procedure(StateMachine):
    """One run of a distributed procedure at the node that coordinates it."""

    NAME: ClassVar[str] = "procedure"
    DEADLINE_S: ClassVar[float] = 10.0

    def __init__(self, pid: int, now: float, deadline_s: float | None = None) -> None:
        super().__init__()
        self.pid = pid
        self.started_at = now
        self.deadline = now + (self.DEADLINE_S if deadline_s is None else deadline_s)
        self.error = ""
        self.client: int | None = None  # the client waiting for its outcome, if any
        self.app = ""  # the app it acts on, if one
        self.told_client = False

    def tell_client(self, ctx: Messenger, reply: m.Message) -> None:
        """Tell the waiting client how the procedure ended: once, whatever ends it (a
        second ending, the node's reset after its outcome, is not told)."""
        if self.client is not None and not self.told_client:
            self.told_client = True
            ctx.reply(self.client, reply)

    def refusal(self, why: str) -> m.Message | None:
        """The reply that tells this procedure's client it was ended unfinished, and why
        (None: a procedure no client waits for)."""
        return None

    def refuse_client(self, ctx: Messenger, why: str) -> None:
        """Tell the waiting client, if any, that the procedure will not finish for it."""
        reply = self.refusal(why)
        if reply is not None:
            self.tell_client(ctx, reply)

    def abandon(self, ctx: Messenger, why: str) -> None:
        """Ended from outside, unfinished (the node resets: every procedure goes with its
        state): the waiting client is told why rather than left waiting."""
        self.refuse_client(ctx, why)
        self.fail(ctx, why)

    def on(self, event: enum.Enum) -> None:
        try:
            super().on(event)
        except IllegalTransition as exc:
            raise IllegalTransition(f"{exc} (procedure {self.pid})") from None

    def fail(self, ctx: Messenger, error: str) -> None:
        """End unsuccessfully (every state may fail); subclasses report to whoever waits."""
        if not self.done:
            self.error = error
            self.state = Phase.FAILED

    def expire(self, ctx: Messenger) -> None:
        """The deadline passed with the procedure still running: its defined failure."""
        self.fail(ctx, f"{self.name} did not finish within {self.DEADLINE_S:g} s")

    def describe(self) -> dict[str, Any]:
        return {"procedure": self.name, "state": self.state.name, "deadline": self.deadline}


def table_rows(cls: type[StateMachine]) -> list[tuple[str, str, str]]:
    """(state, event, next state) rows of a procedure's table: the docs are drawn from them."""
    return [
        (state.name, str(event.value), nxt.name)
        for state, events in cls.TRANSITIONS.items()
        for event, nxt in events.items()
    ]
