"""The coordinator's side of a move as a table: its states, the events that move it, its
deadlines and its retry budget.

A *relocation* is PREPARING, then SWITCHING once the new instance is prepared and the producers
are told to switch, then FINISHED at ``HandoverDone``. Before the switch a failure (a refusal, a
node it needs failing, its deadline) ends it and the target drops the instance it prepared
(``Unprepare``); once producers have switched the move is committed, and if the old host fails
the move becomes a *restore* at the same target (``source_failed``).

A *restore* replaces an instance lost with a failed node (or a crashed one): PREPARING (the target
creates the instance) → RESUMING (the surviving ends of its edges say where they stand and
replay: their roles are in :mod:`..restore`) → FINISHED when the replacement runs. Its prepare
is retried (``Retry``) a few times, since messages to a node behind a failure can be lost while
routes converge.
"""

from __future__ import annotations

import enum
from typing import Any, ClassVar

from mso.protocol import messages as m
from mso.protocol.procedures.base import STEP_TIMEOUT_S, Phase, Procedure, Table

# once producers have switched, the move is committed: the old instance hands over after it has
# processed everything before the markers, which a slow vertex may take a while to do
SWITCH_DEADLINE_S = 60.0
STEP_ATTEMPTS = 5


class S(enum.Enum):
    PREPARING = "preparing"
    SWITCHING = "switching"
    RESUMING = "resuming"


class RelocationEvent(enum.Enum):
    """What moves a Relocation along its table."""

    PREPARED = "prepared"
    PREPARED_RESTORE = "prepared_restore"
    RETRY = "retry"
    HANDED_OVER = "handed_over"
    SOURCE_FAILED = "source_failed"


class Relocation(Procedure):
    """A relocation (or, with ``restore``, a restore) this node coordinates."""

    NAME = "relocation"
    INITIAL = S.PREPARING
    DEADLINE_S = 5.0
    TRANSITIONS: ClassVar[Table] = {
        S.PREPARING: {
            RelocationEvent.PREPARED: S.SWITCHING,
            RelocationEvent.PREPARED_RESTORE: S.RESUMING,
            RelocationEvent.RETRY: S.PREPARING,
            RelocationEvent.HANDED_OVER: Phase.FINISHED,  # a restore of a vertex that never went
        },
        # the old host failed after producers switched: its instance and what it held are
        # gone, the new one waits for a handover that never comes; it is restored instead
        S.SWITCHING: {
            RelocationEvent.HANDED_OVER: Phase.FINISHED,
            RelocationEvent.RETRY: S.SWITCHING,  # the Switch sent again (a producer cut off)
            RelocationEvent.SOURCE_FAILED: S.RESUMING,
        },
        # a restore's prepare is re-sent until answered: answers may come more than once
        S.RESUMING: {
            RelocationEvent.PREPARED_RESTORE: S.RESUMING,
            RelocationEvent.HANDED_OVER: Phase.FINISHED,
            RelocationEvent.RETRY: S.RESUMING,
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
        self.synced_again = 0  # a restore's target answered it holds no app: sent it again
        self.retried: list[str] | None = None  # a recovery's log of steps sent again
        self.order = b""  # the operator's order it carries out, for its steps' receivers
        # the versions of the view its last Prepare carried: moves told since are told the
        # target at the end (it was no member of the app when they were announced)
        self.briefed: dict[str, int] = {}
        # a restore: the vertex's version in this node's view when it began (a later one
        # elsewhere is a move or restore this one did not know of: ``Relocator.on_retry``)
        self.restored_at: int | None = None

    def refusal(self, why: str) -> m.Message:
        return m.RelocateReply(self.app, self.vertex, False, error=why)

    def as_restore(self, now: float | None = None) -> None:
        """Become a restore, with a restore's deadline from ``now`` (a committed relocation
        whose old host failed) or from the start."""
        self.restore = True
        since = self.started_at if now is None else max(self.started_at, now)
        self.deadline = since + STEP_TIMEOUT_S * (STEP_ATTEMPTS + 1)

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
