"""What every role of a move shares: the node's context and data plane, the moves this node
coordinates, and whether a step of a move is warranted."""

from __future__ import annotations

from mso.protocol import warrant
from mso.protocol.context import NodeContext
from mso.protocol.dataplane import DataPlane
from mso.protocol.procedures.relocation._state import Relocation
from mso.protocol.state import AppState


class Role:
    """The base of each role's mixin (:class:`~.relocator.Relocator` is all of them)."""

    def __init__(self, ctx: NodeContext, dp: DataPlane) -> None:
        self.ctx = ctx
        self.dp = dp
        self.orders = warrant.Orders()  # operator orders taken (mso.protocol.warrant)

    def _reloc(self, pid: int) -> Relocation | None:
        proc = self.ctx.procedure(pid)
        return proc if isinstance(proc, Relocation) else None

    def _open(self) -> list[Relocation]:
        return [p for p in self.ctx.open() if isinstance(p, Relocation)]

    def unwarranted(
        self, dep: AppState, src: str, vertex: str, rid: int, order: bytes, paced: bool = True
    ) -> bool:
        """A step of a move that does not trace to a decision this node can check (with
        operator keys: :func:`mso.protocol.warrant.refused`; ``paced``: a chain end's move
        counts against its interval here); counted by why."""
        ctx = self.ctx
        why = warrant.refused(
            dep,
            ctx.id,
            src,
            vertex,
            rid,
            order,
            ctx.failed,
            ctx.authority,
            self.orders,
            ctx.now,
            paced=paced,
        )
        if why:
            ctx.refusal(f"move_{why}")
        return bool(why)
