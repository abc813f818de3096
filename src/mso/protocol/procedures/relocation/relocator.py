"""The relocation component: one object per node, in every role of a move, so the node's router
and the other procedures hold one thing (each role's steps are in its own module)."""

from __future__ import annotations

from mso.protocol import messages as m
from mso.protocol.events import RoutesChanged
from mso.protocol.procedures.relocation.coordinator import Coordinator
from mso.protocol.procedures.relocation.new_host import NewHost
from mso.protocol.procedures.relocation.old_host import OldHost
from mso.protocol.procedures.relocation.producer import Producer


class Relocator(Coordinator, NewHost, Producer, OldHost):
    """This node's part in relocations and restores, in every role (package docstring)."""

    def on_handover_done(self, src: str, msg: m.HandoverDone, now: float) -> None:
        """Heard by the move's coordinator and by its old host (which keeps the handover
        until then); a node that is only the old host takes it for that alone."""
        if self.handover_taken(src, msg) and self._reloc(msg.rid) is None:
            return
        Coordinator.on_handover_done(self, src, msg, now)

    def on_routes_changed(self, ev: RoutesChanged) -> None:
        """A node reachable again gets the handovers kept for it at once."""
        if ev.appeared and self.kept:
            self.send_kept_again(self.ctx.now, ev.appeared)

    def on_reset(self) -> None:
        self.kept.clear()
        self._taken.clear()
        self.leaving.clear()
        self._twins.clear()
        self._handover_to.clear()
        self._parts.clear()
        self._early.clear()
        self._sources.clear()
