"""Membership's part of a node's status, as typed records (they stand at the node's top
level on the wire: see :mod:`mso.node.status`)."""

from __future__ import annotations

from typing import Any

import msgspec

from mso.protocol.procedures.membership.liveness import LivenessStatus


class Heard(msgspec.Struct, frozen=True, kw_only=True):
    """What a neighbour's last beat said of its figures, and when: what the rules weighed."""

    at: float
    load: float
    drain_w: float
    lifetime_s: float | None


class MembershipStatus(msgspec.Struct, frozen=True, kw_only=True):
    """Membership's part of a node's status (at the node's top level on the wire)."""

    failed_nodes: list[str]
    suspected_nodes: list[str]
    # out of reach, declared failed by nobody: held with their incarnation, their instances
    # presumed running (nothing is re-placed for them)
    unreachable_nodes: list[str]
    incarnation: int
    failures: list[dict[str, Any]]  # who, when, detected by whom (recent)
    rejoins: list[dict[str, Any]]  # who, as which incarnation, when (recent)
    liveness: LivenessStatus
    heard: dict[str, Heard]
