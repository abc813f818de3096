"""What membership holds of the other nodes: each one's state by its table, the one failed set,
incarnations, and the bound on how many nodes those tables admit."""

from __future__ import annotations

from collections.abc import Callable, Mapping
from operator import attrgetter
from typing import Any

from mso.protocol import messages as m
from mso.protocol.context import NodeContext
from mso.protocol.dataplane import DataPlane
from mso.protocol.effects import Send
from mso.protocol.procedures.deploy import Deployer
from mso.protocol.procedures.membership.claims import Claims, Gossip, Vouchers
from mso.protocol.procedures.membership.detector import P, PeerEvent, PeerLife
from mso.protocol.procedures.membership.liveness import Liveness
from mso.protocol.procedures.membership.status import Heard, MembershipStatus
from mso.protocol.procedures.membership.sync import AppSyncing
from mso.protocol.procedures.remap import Remapper

# Nodes a node keeps tables of (incarnations, failures, last heard) beyond those it routes to:
# at least this many, or this factor times the nodes it routes to. A member can name any node
# (nodes have no identities yet), so the tables admit a node the routing view does not show
# only below this bound: 50,000 invented names once put a 50,000-entry map into every beat.
MIN_KNOWN = 256
KNOWN_PER_ROUTE = 4
_INSTANCES = attrgetter("instances")


class PeerTables(AppSyncing):
    """The tables of :class:`~.peers.Membership` and what reads them, beneath every layer of
    it (the layers: :mod:`.declare`, :mod:`.suspicion`, :mod:`.beats`, :mod:`.rejoin`)."""

    def __init__(
        self,
        ctx: NodeContext,
        dp: DataPlane,
        deployer: Deployer,
        recovery: Remapper,
        liveness: Liveness,
        incarnation: int = 0,
    ) -> None:
        self.ctx = ctx
        self.dp = dp
        self.deployer = deployer
        self.recovery = recovery
        self.liveness = liveness
        # grows when this node restarts (the daemon passes its start time) or rejoins after a
        # partition: others then know its old instances are gone
        self.incarnation = incarnation
        self.peers: dict[str, PeerLife] = {}  # each other node's state, by its table
        # the peers whose table says FAILED (fail-stop), kept by ``_move`` alone: read only
        self.failed: set[str] = set()
        self.failures: list[dict[str, Any]] = []  # failed nodes: who, when, detected by whom
        self.rejoins: list[dict[str, Any]] = []  # nodes back as a new incarnation: who, when
        # nodes out of this node's reach that it asks others about before declaring them
        # failed: node -> its Suspicion's procedure id (one each, so bounded by the nodes)
        self._suspicions: dict[str, int] = {}
        # nodes this node was asked about, does not hear, reaches, and asked itself: node ->
        # its Vouch's procedure id (one each, bounded by the nodes it reaches)
        self._vouching: dict[str, int] = {}
        self._incarnations: dict[str, int] = {}  # last incarnation heard of, per node
        self._failed_incarnation: dict[str, int] = {}  # the incarnation declared failed
        self._beats = 0
        self._briefed: dict[str, float] = {}  # neighbour -> its link's start, once told our figures
        self._round: list[str] = []  # the keys of ``_briefed``, sorted: a round's order
        # the last beat without figures or news, and the last steady round's sends (of which
        # round, of which beat): sent again while nothing they say changes (Beating)
        self._slim: m.Heartbeat | None = None
        self._sends: tuple[list[str], m.Heartbeat | None, list[Send]] = ([], None, [])
        # nodes that rejoined while this node's own view was in dispute (it holds a reachable
        # node failed: a healed partition whose losing side has not reset yet): synced after
        self._sync_pending: set[str] = set()
        # nodes heard back empty (a rejoin, or a newcomer's hello) lately -> when: an app this
        # node learns from a sync after that goes on to them too (sync.PASS_ON_S)
        self._heard_back: dict[str, float] = {}
        self._told_back: dict[str, set[str]] = {}  # the apps this node synced them since
        self._gossip = Gossip()  # accepted failure claims, piggybacked on the next beats
        self._claims = Claims()  # others' claims waiting for this node's own probe
        self._vouchers = Vouchers()  # when a member's "I hear it" keeps a suspect alive
        # whether a member's "I hear it" must carry the suspect's own signed answer (the
        # driver's transport sets and checks ``Hears.proof``: with node identities, and in
        # the simulator, whose sources are proven as with them); a yes without it is not taken
        self.proofs: Callable[[], bool] = lambda: False
        self._told: dict[str, float] = {}  # failed node heard directly -> when told so
        # the leader, and the routing table (a new one on every change) and failed set it is of
        self._leader_of: tuple[Mapping[str, object], frozenset[str], str] | None = None
        # failed node -> app -> the vertices it ran when declared (bounded by the failed)
        self._ran: dict[str, dict[str, set[str]]] = {}
        # cut-off nodes this node (running nothing) waits to see reset: node -> since when
        self._awaiting: dict[str, float] = {}
        self._routed = False  # given routes before: a node that appears now gets our hello

    def heard_of(self) -> set[str]:
        """Every node whose incarnation this node has heard (reachable now or not)."""
        return set(self._incarnations)

    def known_bound(self) -> int:
        """How many nodes this node keeps tables of: scales with the nodes it routes to."""
        return max(MIN_KNOWN, KNOWN_PER_ROUTE * (len(self.ctx.routes) + 1))

    def admits(self, node: str, table: Mapping[str, object]) -> bool:
        """Whether ``table`` may hold ``node``: it does already, the routing view shows the
        node, or the table is below :meth:`known_bound`."""
        return node in table or node in self.ctx.routes or len(table) < self.known_bound()

    def heard_of_node(self, node: str) -> bool:
        """Whether this node has ever heard of ``node`` (its incarnation, a route, a message
        from it, a peer state): a failure claim about any other is about nobody."""
        return (
            node in self._incarnations
            or node in self.ctx.routes
            or node in self.peers
            or node in self.liveness.last_heard
        )

    def incarnation_of(self, node: str, default: int) -> int:
        return self._incarnations.get(node, default)

    def status(self) -> MembershipStatus:
        """Whom this node holds failed or suspects, and what its detector measured."""
        return MembershipStatus(
            failed_nodes=sorted(self.failed),
            suspected_nodes=sorted(self._suspicions),
            unreachable_nodes=self.liveness.unreachable(self.failed),
            incarnation=self.incarnation,
            failures=list(self.failures),
            rejoins=list(self.rejoins),
            liveness=self.liveness.status(),
            heard={
                n: Heard(at=t, load=b.load, drain_w=b.drain_w, lifetime_s=b.lifetime_s)
                for n, (t, b) in sorted(self.liveness.heard.items())
            },
        )

    def _move(self, node: str, event: PeerEvent) -> None:
        """Take ``node``'s peer along its table; the failed set follows the table (it is its
        index: a peer is in it exactly while its table says FAILED)."""
        peer = self._peer(node)
        peer.on(event)
        if peer.state is P.FAILED:
            self.failed.add(node)
        else:
            self.failed.discard(node)

    def _peer(self, node: str) -> PeerLife:
        """How this node holds ``node`` (alive until declared failed), by the table."""
        peer = self.peers.get(node)
        if peer is None:
            peer = self.peers[node] = PeerLife(node)
        return peer

    def _leader(self) -> str:
        """The lowest node this node counts alive (itself too): kept until the routing view
        or the failed set changes, not taken over every route on every beat."""
        routes, kept = self.ctx.routes, self._leader_of
        if kept is not None and kept[0] is routes and kept[1] == self.failed:
            return kept[2]
        leader = min({self.ctx.id, *(n for n in routes if n not in self.failed)})
        self._leader_of = (routes, frozenset(self.failed), leader)
        return leader

    def _hosts(self) -> set[str]:
        """The nodes this node's views say host part of an app (one of them coordinates a
        recovery): told of failures and rejoins at once, the others by beats."""
        return {n for dep in self.ctx.apps.values() for n in dep.placed.values()}

    def _hosting(self) -> int:
        """Instances hosted here (on every beat: over the apps engaged here only, not every
        app held, and summed in C; most nodes take part in none)."""
        apps = self.ctx.apps
        return sum(map(len, map(_INSTANCES, apps.engaged_apps()))) if apps.engaged else 0
