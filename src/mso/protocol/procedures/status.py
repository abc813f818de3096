"""Status fan-out: a client asks one node; it asks every node it can reach and answers with
what came back by the deadline (nodes that did not answer are simply absent)."""

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
        self.client = client
        self.got = dict(mine)
        self.missing = set(others)

    def start(self, ctx: Messenger) -> None:
        for n in sorted(self.missing):
            ctx.send(n, m.StatusRequest(req=self.pid))

    def receive(self, ctx: Messenger, msg: m.StatusReply) -> None:
        self.on(StatusEvent.REPLY)
        self.got.update(msg.nodes)
        self.missing.difference_update(msg.nodes)
        if not self.missing:
            self.on(StatusEvent.ALL_ANSWERED)
            ctx.reply(self.client, m.StatusReply(self.pid, self.got))

    def expire(self, ctx: Messenger) -> None:
        """The defined outcome of a late node: answer with the others."""
        self.on(StatusEvent.DEADLINE)
        ctx.reply(self.client, m.StatusReply(self.pid, self.got))
