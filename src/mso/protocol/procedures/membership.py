"""Membership, as one node sees each other node: alive or failed, by incarnation.

Fail-stop failures (paper §3.4, assumption 3) with restarts and partitions: a neighbour silent
for the liveness window is declared failed by this node (``silent``) or by another detector
(``reported_down``, a ``NodeDown``); a failed node is heard again only to rejoin — as a higher
incarnation after a restart, or, after a partition heals, once one side has reset — and is
then ALIVE again (``rejoined``). A node that learns it was declared failed by a side that
outranks it *resets*: it drops its apps, forgets whom it held failed (``reset``) and comes back
as its next incarnation; the others restore what it hosted and send it the apps (``AppSync``).

The waits have deadlines: silence is judged against the liveness window (``dead_after_s``); a
failed node that is reachable again is sent a heartbeat every ``REJOIN_EVERY`` beats so a
healed partition is noticed even if nobody speaks first.
"""

from __future__ import annotations

import enum
from typing import ClassVar

from mso.protocol.procedures.base import StateMachine, Table


class P(enum.Enum):
    ALIVE = "alive"
    FAILED = "failed"


class PeerLife(StateMachine):
    """Another node, as this node holds it."""

    NAME = "peer"
    INITIAL = P.ALIVE
    TRANSITIONS: ClassVar[Table] = {
        P.ALIVE: {"silent": P.FAILED, "reported_down": P.FAILED},
        P.FAILED: {"rejoined": P.ALIVE, "reset": P.ALIVE},
    }

    def __init__(self, node: str) -> None:
        super().__init__()
        self.node = node

    @property
    def name(self) -> str:
        return f"peer {self.node}"
