"""Relocation (§3.4.1): a move of a running vertex with its state, losing no event, and a
restore's coordinator. Every role of the procedure, one module each:

    coordinator           new host            producer(s)           old host
      Prepare  ──────────▶  host an instance
               ◀──────────  Prepared (once started)
      Switch   ─────────────────────────────▶  send to the new host;
                                               Marker ─────────────▶  drain to the marker(s)
                                                                      snapshot
                            Handover  ◀─────────────────────────────  state + channels
               ◀──────────  HandoverDone       (the old host tells everyone: Moved)

- :mod:`._state` — the coordinator's table: its states, the events that move it, its
  deadlines and retries (:class:`Relocation`).
- :mod:`.coordinator` — asks the target, switches the producers, ends the move (a restore:
  asks again); where an upstream or downstream move goes, and when a move is refused.
- :mod:`.new_host` — the target: prepares the instance (or refuses: a twin, a restore of a
  vertex restored since), drops it when the move fails, takes the handover and the output
  events sent ahead of it.
- :mod:`.producer` — a producer of the vertex: switches its edge, sends a marker the old way.
- :mod:`.old_host` — the node the vertex leaves: takes the markers (with operator keys only
  those of a warranted move, from the edge's producer), drains to them, snapshots, hands over.
- :mod:`._role` — what the roles share: the node's context, the open moves, the warrant check.
- :mod:`.relocator` — the component, :class:`Relocator`: one object per node in every role.

A step arriving in the wrong state raises :class:`~mso.protocol.procedures.base.IllegalTransition`.
With operator keys a step from another node is taken only on a warrant
(:mod:`mso.protocol.warrant`). A restore's participants other than its coordinator are in
:mod:`..restore`.
"""

from mso.protocol.procedures.relocation._state import (
    STEP_ATTEMPTS,
    SWITCH_DEADLINE_S,
    Relocation,
    RelocationEvent,
    S,
)
from mso.protocol.procedures.relocation.coordinator import MAX_FAILED_RESTORES, who_asked
from mso.protocol.procedures.relocation.relocator import Relocator

__all__ = [
    "MAX_FAILED_RESTORES",
    "STEP_ATTEMPTS",
    "SWITCH_DEADLINE_S",
    "Relocation",
    "RelocationEvent",
    "Relocator",
    "S",
    "who_asked",
]
