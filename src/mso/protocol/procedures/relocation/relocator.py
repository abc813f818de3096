"""The relocation component: one object per node, in every role of a move, so the node's router
and the other procedures hold one thing (each role's steps are in its own module)."""

from __future__ import annotations

from mso.protocol.procedures.relocation.coordinator import Coordinator
from mso.protocol.procedures.relocation.new_host import NewHost
from mso.protocol.procedures.relocation.old_host import OldHost
from mso.protocol.procedures.relocation.producer import Producer


class Relocator(Coordinator, NewHost, Producer, OldHost):
    """This node's part in relocations and restores, in every role (package docstring)."""

    def on_reset(self) -> None:
        self.leaving.clear()
        self._twins.clear()
        self._handover_to.clear()
        self._parts.clear()
        self._early.clear()
        self._sources.clear()
