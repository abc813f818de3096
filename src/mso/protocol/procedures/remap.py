"""Chain remap (§3.4.2), global remap (§3.4.3) and failure recovery, as their coordinator
sees them: PROBING each chain's route in dependency order (re-probed if a probe is lost) and
placing it with the deployment's own placement code, then MOVING the vertices whose node
changed one at a time (relocations, or restores for lost instances), then FINISHED. A remap
fails when placement fails, a probe is never answered, a step fails, or at its deadline."""

from __future__ import annotations

import enum
from typing import Any, ClassVar

from mso.planning.placement import Hop
from mso.protocol.procedures.base import Phase, Procedure, Table

PROBE_ATTEMPTS = 5


class S(enum.Enum):
    PROBING = "probing"
    MOVING = "moving"


class Remap(Procedure):
    NAME = "remap"
    INITIAL = S.PROBING
    TRANSITIONS: ClassVar[Table] = {
        S.PROBING: {
            "probe": S.PROBING,  # probes sent for the next chain (or sent again)
            "placed": S.PROBING,  # a chain placed, more to go
            "placed_all": S.MOVING,
        },
        S.MOVING: {"moved": S.MOVING, "all_moved": Phase.FINISHED},
    }

    def __init__(
        self,
        pid: int,
        now: float,
        app: str,
        chains: list[int],
        client: int | None,
        placed: dict[str, str],
        movable: set[str],
        recovery: dict[str, Any] | None = None,
    ) -> None:
        # every chain may need its probes retried, and every vertex a move
        super().__init__(pid, now, 10.0 + 5.0 * len(chains) + 0.5 * len(movable))
        self.app = app
        self.chains = chains  # still to place, in dependency order
        self.client = client
        self.placed = placed  # the placement being built
        self.movable = movable  # only these are re-placed
        self.recovery = recovery  # set when this remap recovers from a failure
        self.moves: list[tuple[str, str]] = []  # (vertex, node) still to do
        self.moved: dict[str, str] = {}
        self.probes: dict[int, list[Hop]] = {}
        self.expected = 0
        self.probe_attempts = 0
        self.weights: dict[str, float] = {}  # node -> factor on its probed capacity

    @property
    def name(self) -> str:
        return "recovery" if self.recovery is not None else self.NAME

    def describe(self) -> dict[str, Any]:
        return super().describe() | {"app": self.app, "chains_left": list(self.chains)}
