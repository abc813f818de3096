"""Deployment (Algorithm 1, :mod:`mso.protocol.procedures.deploy`): the announce, capability
queries, probes, chain building, start and stop. Part of the wire's message union
(:data:`mso.protocol.messages.Message`, which re-exports every name: import them from there);
each message tagged and laid out as every other."""

from __future__ import annotations

import msgspec


class _Msg(msgspec.Struct, tag_field="t", array_like=True):
    pass


class AppAnnounce(_Msg, tag="announce"):
    """The app document and the deploying node, sent to every node before placement."""

    app: str
    origin: str
    document: str
    epoch: int = 0  # this deployment's incarnation: data of an earlier one is not accepted
    # each vertex placed by capability: the node chosen, and the nodes that qualify, best first
    # (after a failure the next live one takes it)
    resolved: dict[str, str] = msgspec.field(default_factory=dict)
    capable: dict[str, list[str]] = msgspec.field(default_factory=dict)


class CapabilityQuery(_Msg, tag="capability_query"):
    """From the deploying node to every node (§3.3): which of you offers what these vertices
    require? ``needs``: vertex -> what it requires; ``anchors``: the nodes an answer reports its
    hops to (those a ``near`` constraint may name). Nodes that offer some of what a vertex
    requires answer with their offers (so a refusal can say what no node has), the others
    decline, so the deploying node chooses as soon as every node has spoken."""

    app: str
    qid: int
    needs: dict[str, dict[str, float]]
    anchors: list[str] = msgspec.field(default_factory=list)


class CapabilityReply(_Msg, tag="capability_reply"):
    """A node with some of what a :class:`CapabilityQuery` asks for: what it offers
    (its ``cpu`` included), its remaining energy (None: wall power), its hops to the anchors.
    ``declined``: it has none of it (no offers; not a candidate, but no need to wait for it)."""

    app: str
    qid: int
    node: str
    offers: dict[str, float]
    energy_j: float | None = None
    hops: dict[str, int] = msgspec.field(default_factory=dict)
    declined: bool = False


class Probe(_Msg, tag="probe"):
    """Travels hop by hop toward ``target``; each hop appends its capacity and its power
    figures ``[cpu_w, tx_uj_per_byte, rx_uj_per_byte]`` (for the bytes planner; a peer that
    predates them sends none, and the planner takes the defaults for every hop), and each hop
    that forwards it the rate of the link it forwards over (``rates``, Mb/s, 0: not known)."""

    app: str
    chain: int
    segment: int
    requester: str
    target: str
    nodes: list[str]
    capacities: list[float]
    power: list[list[float]] = []
    rates: list[float] = []


class ProbeReply(_Msg, tag="probe_reply"):
    app: str
    chain: int
    segment: int
    nodes: list[str]
    capacities: list[float]
    power: list[list[float]] = []
    rates: list[float] = []


class ChainPlaced(_Msg, tag="placed"):
    """A chain's placement, broadcast so every node knows the whole mapping."""

    app: str
    chain: int
    assignments: dict[str, str]


class BuildChain(_Msg, tag="build"):
    """From a chain head's node to each node hosting part of the chain: create its vertices."""

    app: str
    chain: int
    vertices: list[str]


class ChainPartReady(_Msg, tag="part_ready"):
    """A builder's part of a chain is up, in the builder's ``incarnation`` (-1: not said)."""

    app: str
    chain: int
    node: str
    incarnation: int = -1


class ChainBuilt(_Msg, tag="built"):
    """From a chain head's node to the origin: the chain's overlay exists, on nodes in these
    ``incarnations`` (as their builders said)."""

    app: str
    chain: int
    incarnations: dict[str, int] = {}


class StartApp(_Msg, tag="start"):
    """The overlay is complete: sources may emit. ``incarnations``: of each node it runs on,
    as its builders said, so that every node that holds the app knows a restart of one of
    them as a restart, though that node never sent it a beat (nobody says hello to every
    node at a first start: :meth:`~.membership.peers.Membership.on_routes_changed`)."""

    app: str
    incarnations: dict[str, int] = {}


class StopApp(_Msg, tag="stop"):
    """Undeploy ``app`` everywhere. On nodes with operator keys it carries the operator's
    signature of ``app`` and ``at`` (its clock, ms) by key ``key``: every node verifies it, and
    it revokes the app's grants made before ``at`` (:mod:`mso.protocol.authority`)."""

    app: str
    at: int = 0
    key: str = ""
    sig: bytes = b""


class DeployFailed(_Msg, tag="deploy_failed"):
    app: str
    reason: str
