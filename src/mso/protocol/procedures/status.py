"""Status fan-out: a client asks one node; it asks every node it can reach and answers with
what came back by the deadline (nodes that did not answer are simply absent).

One fan-out at a time: a request that comes while one is gathering joins it and is answered
with what it gathers (at most ``MAX_WAITERS``; past them, the node answers with its own
status alone). Each fan-out holds this node's whole status until the others answer: 20
clients asking 20 times a second while the node was busy kept 1,200 fan-outs in flight, 171 MB
of status dicts, and the node never gave the memory back."""

from __future__ import annotations

import enum
from typing import Any, ClassVar

from mso.protocol import messages as m
from mso.protocol.procedures.base import Messenger, Phase, Procedure, Table


class S(enum.Enum):
    WAITING = "waiting"


class StatusEvent(enum.Enum):
    """What moves a StatusFanout along its table."""

    REPLY = "reply"
    ALL_ANSWERED = "all_answered"
    DEADLINE = "deadline"


MAX_WAITERS = 256  # clients one fan-out answers


class StatusFanout(Procedure):
    NAME = "status"
    INITIAL = S.WAITING
    DEADLINE_S = 1.0
    TRANSITIONS: ClassVar[Table] = {
        S.WAITING: {
            StatusEvent.REPLY: S.WAITING,
            StatusEvent.ALL_ANSWERED: Phase.FINISHED,
            StatusEvent.DEADLINE: Phase.FINISHED,
        }
    }

    def __init__(
        self, pid: int, now: float, client: int, mine: dict[str, Any], others: list[str]
    ) -> None:
        super().__init__(pid, now)
        self.clients = [client]
        self.got = dict(mine)
        self.missing = set(others)

    def join(self, client: int) -> bool:
        """``client`` is answered with what this fan-out gathers; False when it is full."""
        if self.done or len(self.clients) >= MAX_WAITERS:
            return False
        self.clients.append(client)
        return True

    def _answer(self, ctx: Messenger) -> None:
        for client in self.clients:
            ctx.reply(client, m.StatusReply(self.pid, self.got))

    def start(self, ctx: Messenger) -> None:
        for n in sorted(self.missing):
            ctx.send(n, m.StatusRequest(req=self.pid))

    def receive(self, ctx: Messenger, msg: m.StatusReply) -> None:
        self.on(StatusEvent.REPLY)
        self.got.update(msg.nodes)
        self.missing.difference_update(msg.nodes)
        if not self.missing:
            self.on(StatusEvent.ALL_ANSWERED)
            self._answer(ctx)

    def abandon(self, ctx: Messenger, why: str) -> None:
        """The node resets: its waiting clients get what came in (its own status at least)."""
        if not self.done:
            self._answer(ctx)
        super().abandon(ctx, why)

    def expire(self, ctx: Messenger) -> None:
        """The defined outcome of a late node: answer with the others."""
        self.on(StatusEvent.DEADLINE)
        self._answer(ctx)
