"""Membership at one node, the component: heartbeats, fail-stop failure detection, the one set
of failed peers, incarnations, reset and rejoin.

Each node beats to its neighbours (with its monitor's figures); a neighbour silent for the
liveness window is declared failed, and the detector tells everyone. A node out of this node's
reach for the window is only suspected: it is declared failed when none of the nodes this node
still reaches hears it (a :class:`~.detector.Suspicion`), not on this node's missing route
alone. Declaring is one place (:meth:`Membership.on_node_down`); it publishes
:class:`~mso.protocol.events.PeerFailed`, on which moves that needed the node fail or become
restores and the chains it touched are recovered (:mod:`..remap`). A node that restarts comes
back as a higher incarnation; after a partition heals, the side that loses a deterministic
tie-break resets (drops its apps) and rejoins, and is sent the apps again (``AppSync``) with its
pinned vertices restored.

:class:`Membership` is its layers, each a module, each using only those beneath it:
:mod:`.tables` (what it holds of the others; with :mod:`.sync`'s app sync), :mod:`.declare`,
:mod:`.suspicion`, :mod:`.beats` (beats out), :mod:`.rejoin` (beats in, reset, rejoin).
"""

from __future__ import annotations

from mso.protocol.procedures.membership.beats import (
    MONITOR_PERIOD_S,
    REJOIN_EVERY,
    REVOCATIONS_TOLD,
)
from mso.protocol.procedures.membership.rejoin import YIELD_WAIT_S, Rejoining
from mso.protocol.procedures.membership.tables import KNOWN_PER_ROUTE, MIN_KNOWN

__all__ = [
    "KNOWN_PER_ROUTE",
    "MIN_KNOWN",
    "MONITOR_PERIOD_S",
    "REJOIN_EVERY",
    "REVOCATIONS_TOLD",
    "YIELD_WAIT_S",
    "Membership",
]


class Membership(Rejoining):
    """This node's view of the others, and its part in keeping it (module docstring)."""
