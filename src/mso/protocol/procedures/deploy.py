"""Deployment (Algorithm 1) as its origin sees it: BUILDING while chains are probed, placed
and built across the nodes (each chain by the node holding its head), FINISHED when every chain
reports built and the origin starts the app, FAILED when a node refuses (bad code, placement
impossible) or at the deadline — then the app is stopped everywhere and the client told why,
instead of waiting for ever on a probe or a chain build that was lost."""

from __future__ import annotations

import enum
from typing import Any, ClassVar

from mso.protocol.procedures.base import Phase, Procedure, Table


class S(enum.Enum):
    BUILDING = "building"


class Deploy(Procedure):
    NAME = "deploy"
    INITIAL = S.BUILDING
    DEADLINE_S = 30.0
    TRANSITIONS: ClassVar[Table] = {
        S.BUILDING: {"built": S.BUILDING, "all_built": Phase.FINISHED},
    }

    def __init__(self, pid: int, now: float, app: str) -> None:
        super().__init__(pid, now)
        self.app = app

    def describe(self) -> dict[str, Any]:
        return super().describe() | {"app": self.app}
