"""Relocation (paper §3.4.1) and restore, as their coordinator sees them.

A *relocation* moves a live vertex from ``source`` to ``target`` with a marker: PREPARING (the
target creates the instance) → SWITCHING (producers switch and send a marker the old way; the
old host hands the state over) → FINISHED when the target reports the handover. A *restore*
replaces an instance lost with a failed node: PREPARING → RESUMING (the surviving ends of its
edges say where they stand and replay) → FINISHED when the replacement runs. Both fail on a
refusal, on the failure of a node they need, or at their deadline (5 s to be prepared; once
producers have switched, ``SWITCH_DEADLINE_S`` for the old instance to drain and hand over); a
restore's prepare is retried (``Retry`` timer) a few times first, since messages to a node
behind a failure can be lost while routes converge.

The steps themselves are carried out by the node core's handlers (``mso.node.core``), which
move the procedure along this table; a step arriving in the wrong state raises.
"""

from __future__ import annotations

import enum
from typing import Any, ClassVar

from mso.protocol.procedures.base import Phase, Procedure, Table

STEP_TIMEOUT_S = 1.0  # a restore step not answered by then is sent again
# once producers have switched, the move is committed: the old instance hands over after it has
# processed everything before the markers, which a slow vertex may take a while to do
SWITCH_DEADLINE_S = 60.0
STEP_ATTEMPTS = 5


class S(enum.Enum):
    PREPARING = "preparing"
    SWITCHING = "switching"
    RESUMING = "resuming"


class Relocation(Procedure):
    """A relocation (or, with ``restore``, a restore) this node coordinates."""

    NAME = "relocation"
    INITIAL = S.PREPARING
    DEADLINE_S = 5.0
    TRANSITIONS: ClassVar[Table] = {
        S.PREPARING: {
            "prepared": S.SWITCHING,
            "prepared_restore": S.RESUMING,
            "retry": S.PREPARING,
            "handed_over": Phase.FINISHED,  # a restore of a vertex that never went
        },
        S.SWITCHING: {"handed_over": Phase.FINISHED},
        # a restore's prepare is re-sent until answered: answers may come more than once
        S.RESUMING: {
            "prepared_restore": S.RESUMING,
            "handed_over": Phase.FINISHED,
            "retry": S.RESUMING,
        },
    }

    def __init__(
        self,
        pid: int,
        now: float,
        app: str,
        vertex: str,
        source: str,
        target: str,
        client: int | None,
        remap: int | None = None,
    ) -> None:
        super().__init__(pid, now)
        self.app = app
        self.vertex = vertex
        self.source = source  # node the vertex leaves
        self.target = target  # node it goes to
        self.client = client
        self.remap = remap  # the remap this relocation is a step of
        # a restore: no marker, no handover; the surviving ends of its edges resume it
        # (``resumes``: [edge, the other end is the producer])
        self.restore = False
        self.resumes: list[list[Any]] = []
        self.attempts = 0

    def as_restore(self) -> None:
        self.restore = True
        self.deadline = self.started_at + STEP_TIMEOUT_S * (STEP_ATTEMPTS + 1)

    @property
    def name(self) -> str:
        return "restore" if self.restore else self.NAME

    def describe(self) -> dict[str, Any]:
        return super().describe() | {
            "app": self.app,
            "vertex": self.vertex,
            "from": self.source,
            "to": self.target,
        }
