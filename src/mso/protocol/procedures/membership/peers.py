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
"""

from __future__ import annotations

import os
from collections.abc import Callable, Mapping
from operator import attrgetter
from typing import Any

import msgspec

from mso.protocol import messages as m
from mso.protocol.context import NodeContext
from mso.protocol.dataplane import DataPlane
from mso.protocol.effects import Send
from mso.protocol.events import (
    Happened,
    HeartbeatTick,
    NodeReset,
    PeerFailed,
    RecoveryDue,
    RoutesChanged,
)
from mso.protocol.procedures.deploy import Deployer
from mso.protocol.procedures.membership import ranks, reach
from mso.protocol.procedures.membership.claims import (
    INCARNATION_MARGIN,
    LONE_YES_WINDOWS,
    MAX_NEWS,
    MEMBERS_YES_WINDOWS,
    NONCE_BYTES,
    Claims,
    Gossip,
    Vouchers,
    ask_whom,
    rounds,
)
from mso.protocol.procedures.membership.detector import P, PeerEvent, PeerLife, Suspicion, Vouch
from mso.protocol.procedures.membership.liveness import Liveness
from mso.protocol.procedures.membership.status import Heard, MembershipStatus
from mso.protocol.procedures.membership.sync import AppSyncing
from mso.protocol.procedures.relocation import Relocation
from mso.protocol.procedures.remap import Remapper

REJOIN_EVERY = 10  # heartbeat periods between heartbeats to reachable nodes declared failed
# how long a node that runs nothing waits for a node on the smaller side of a healed partition
# to reset (it hears a node of ours that runs something within a REJOIN_EVERY round) before
# yielding to it
YIELD_WAIT_S = 1.5
MONITOR_PERIOD_S = 1.0  # how often the monitor samples on its own: its figures ride on one beat
# of each period (they change no faster)
REVOCATIONS_TOLD = 16  # the operator's latest undeploys told to each newly reachable node
# Nodes a node keeps tables of (incarnations, failures, last heard) beyond those it routes to:
# at least this many, or this factor times the nodes it routes to. A member can name any node
# (nodes have no identities yet), so the tables admit a node the routing view does not show
# only below this bound: 50,000 invented names once put a 50,000-entry map into every beat.
MIN_KNOWN = 256
KNOWN_PER_ROUTE = 4
_INSTANCES, _VANISHED = attrgetter("instances"), attrgetter("vanished")


class Membership(AppSyncing):
    """This node's view of the others, and its part in keeping it (module docstring)."""

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
        # nodes that rejoined while this node's own view was in dispute (it holds a reachable
        # node failed: a healed partition whose losing side has not reset yet): synced after
        self._sync_pending: set[str] = set()
        # nodes heard back empty (a rejoin, or a newcomer's hello) lately -> when: an app this
        # node learns from a sync after that goes on to them too (sync.PASS_ON_S)
        self._heard_back: dict[str, float] = {}
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

    def start(self, now: float) -> None:
        self.ctx.set_timer(HeartbeatTick(), now + self.liveness.period_s)

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
        app held, and summed in C)."""
        return sum(map(len, map(_INSTANCES, self.ctx.apps.engaged_apps())))

    # -- the detector: beats out, silence and unreachability judged, suspicion asked -----------
    def beat(self, news: list[m.NodeDown] | None = None, figures: bool = True) -> m.Heartbeat:
        """This node's beat, with its monitor's figures unless ``figures`` is False (see
        Heartbeat)."""
        return m.Heartbeat(
            self.ctx.id,
            self.incarnation,
            dict(self._failed_incarnation),
            self._leader(),
            self._hosting(),
            self.ctx.figures() if figures else None,
            news or [],
        )

    def heartbeat(self, now: float) -> None:
        """Tell the neighbours we live; declare the silent ones failed. Our figures go on one
        beat per monitor period, and on the first beat to a neighbour since its link came up
        (``_briefed``: the time the link came up, when it was given them)."""
        every = max(1, round(MONITOR_PERIOD_S / self.liveness.period_s))
        slim = self.beat(self._gossip.next_beat(), figures=self._beats % every == 0)
        # the figures (hops to the nodes within two hops) are made only for a beat that
        # carries them, not on every beat
        full = slim if slim.figures is not None else None
        for n, since in sorted(self.liveness.neighbours.items()):
            if n not in self.failed:
                briefed = self._briefed.get(n) == since
                self._briefed[n] = since
                if not briefed and full is None:
                    full = msgspec.structs.replace(slim, figures=self.ctx.figures())
                self.ctx.emit(Send(n, full if not briefed and full is not None else slim))
        if not self._briefed.keys() <= self.liveness.neighbours.keys():
            for n in set(self._briefed) - set(self.liveness.neighbours):
                del self._briefed[n]  # bounded by the neighbours
        self._beats += 1
        if self._beats % REJOIN_EVERY == 0:  # a failed node we can reach again: a healed
            for n in sorted(self.failed):  # partition; tell it, so one side rejoins the other
                if n in self.ctx.routes:
                    if full is None:
                        full = msgspec.structs.replace(slim, figures=self.ctx.figures())
                    self.ctx.emit(Send(n, full))
        away = set(self.liveness.unreachable(self.failed))
        for n in self.liveness.silent(now, self.failed):  # silent with a route: suspected;
            if n in self.ctx.routes or self._needed(n, away):  # out of reach, only if the
                self._suspect(n, now)  # apps cannot progress without re-placing what it runs
        for n in self._blocking(now, away):  # unreachable, and it runs part of an app we run:
            self._suspect(n, now)  # asked about like a silent neighbour
        for claim, at in self._claims.due(now, self.liveness.dead_after_s / 2):
            if self.liveness.hears(claim.node, now, within=now - at):
                self.ctx.refusal("node_down_refuted")  # it answered our probe: it lives
            elif claim.node not in self.failed:
                self._declare(claim, now)  # our own probe agrees
        self._flush_syncs()
        # this node may have become an app's recovery coordinator (it runs part of it now);
        # with nothing failed and nothing vanished no app has a vertex to recover
        if self.failed or any(map(_VANISHED, self.ctx.apps.engaged_apps())):
            self.ctx.publish(RecoveryDue())
        self.ctx.set_timer(HeartbeatTick(), now + self.liveness.period_s)

    def heard(self, src: str, now: float) -> None:
        """A message from ``src``, which this node holds alive: it lives (and if suspected,
        it reaches us though we do not reach it). Noted only within the tables' bound."""
        if self.admits(src, self.liveness.last_heard):
            self.liveness.heard_from(src, now)
        self.heard_directly(src, now)

    def quiet_beat(self, src: str, msg: m.Heartbeat, now: float) -> bool:
        """Take a beat with no news (no claims, not from a suspect, holding failed only nodes
        heard of, not this one): a beat in the incarnation known, without figures, or a
        non-neighbour's first (the N² hellos of a start-up). All :meth:`heard` and
        :meth:`on_heartbeat` would do is note the incarnation and the sender's liveness clock:
        done here, outside the core's effect machinery. False: weigh it whole. Keep it in step
        with :meth:`on_heartbeat` (tests/test_sim_scale.py runs the two ways side by side)."""
        if msg.news or src in self._suspicions or src in self._vouchers.since:
            return False
        # (the liveness table's few neighbours, which on_routes_changed keeps equal to the
        # routes whose next hop is their destination: not the N-entry routing table)
        neighbour = src in self.liveness.neighbours
        known = self._incarnations.get(src)
        if known is None:
            if neighbour or not self.admits(src, self._incarnations) or self._newcomer(msg):
                return False
        elif (
            known != msg.incarnation
            or src not in self.liveness.last_heard
            or msg.figures is not None
        ):
            return False
        held = msg.failed
        if held and (
            self.ctx.id in held
            or len(held) > KNOWN_PER_ROUTE * self.known_bound()
            or not all(n in self._incarnations for n in held)
        ):
            return False
        if known is None:
            if self.admits(src, self.liveness.last_heard):
                self.liveness.heard_from(src, now)
            self._incarnations[src] = msg.incarnation
            return True
        self.liveness.heard_from(src, now, msg if neighbour else None)  # (a hello: no gaps)
        return True

    def heard_directly(self, src: str, now: float) -> None:
        """A message from a suspected node (it reaches us though we do not reach it): it
        lives, which is what the suspicion asked."""
        if self._vouchers.since:
            self._vouchers.heard(src)
        if src in self._suspicions:
            self._unsuspect(src, PeerEvent.VOUCHED)
            self.liveness.vouched(src, now)

    def on_routes_changed(self, ev: RoutesChanged) -> None:
        """Who is a neighbour and who is reachable; a suspected node in reach again is not
        suspected; newly reachable nodes learn our incarnation (and whom we hold failed, if a
        partition just healed) and the operator's latest undeploys (a node that restarted or
        was cut off has not heard them).

        At a first start (incarnation 0: the simulator's nodes at t=0) only the neighbours
        are told, not every node: N² hellos on routes of many hops were most of a 1,000-node
        start-up. The nodes that need that incarnation learn it otherwise -- the neighbours
        from our beats, the nodes of an app we host part of from its placement
        (``ChainPlaced`` carries the incarnations its probe found) or a sync -- and the others
        know our routes, which is all a claim about us needs (:meth:`heard_of_node`). A node
        that may have run before (a daemon's incarnation is its start time; the simulator's
        revived nodes count up) tells every node, as its neighbours may not know its old
        incarnation: a node that held it out of reach learns of the restart from its hello."""
        now, routes = self.ctx.now, self.ctx.routes
        neighbours = {d for d, (hop, _) in routes.items() if hop == d}
        self.liveness.set_routes(now, routes, neighbours, self.failed)
        everyone = self._routed or self.incarnation > 0
        self._routed = self._routed or bool(routes)
        if ev.appeared:
            beat = self.beat()
            undeploys = list(self.ctx.authority.revoked.values())[-REVOCATIONS_TOLD:]
            for d in sorted(ev.appeared):
                if everyone or d in neighbours:
                    self.ctx.send(d, beat)
                for stop in undeploys:
                    self.ctx.send(d, stop)
                if d not in self.failed:  # (a failed one is synced when it rejoins)
                    self._claim_to(d)

    def _suspect(self, node: str, now: float) -> None:
        """``node``, which this node watches, has been silent for the liveness window. One
        node's silence is not evidence enough (a routing daemon may leave it without a route
        to a live node for seconds while the others still hear it): ask a few members
        (:func:`~.claims.ask_whom`), and declare it only if none hears it (:class:`Suspicion`)."""
        if node in self._suspicions or node in self.failed or node == self.ctx.id:
            return
        if self._peer(node).state is P.ALIVE:
            self._move(node, PeerEvent.SILENT)
        said = self.liveness.heard.get(node)
        asked = ask_whom(node, self.ctx.id, said[1] if said else None, self.ctx.routes, self.failed)
        if not asked:  # nobody left to ask: this node is cut off (its own probes agree)
            self.on_node_down(node, self.ctx.id, now)
            return
        nonce = os.urandom(NONCE_BYTES) if self.proofs() else b""
        proc = Suspicion(self.ctx.new_pid(), now, node, asked, self.liveness.dead_after_s, nonce)
        self.ctx.begin(proc)
        self._suspicions[node] = proc.pid
        proc.start(self.ctx)

    def _blocking(self, now: float, away: set[str]) -> list[str]:
        """Nodes out of reach for the liveness window, not heard in it, that host a vertex of
        an app this node runs part of whose re-placing would let events flow again
        (:func:`.reach.re_placeable`): the app cannot progress otherwise, so they are
        suspected like a silent neighbour (a few asked); if nobody hears them they are
        declared, their vertices re-placed, and the incarnation rules take them back exactly
        once when they are heard again. Any other node out of reach stays unreachable (a
        robot that drove off with its pinned sink, or the node beyond it on a line that
        broke): taken back as it is, no reset."""
        if not away:
            return []
        window = self.liveness.dead_after_s
        return [
            n
            for n in sorted(away)
            if now - self._silent_since(n) > window
            and not self.liveness.hears(n, now)
            and self._needed(n, away)
        ]

    def _silent_since(self, node: str) -> float:
        """When ``node``, out of reach, fell silent: when it was last heard if that was
        within the window before it went out of reach (a host of the app we exchange events
        with, or a neighbour: declared from its last word, as a silent neighbour is -- counted
        from the route's loss, detection took a tick longer, 0.60 s against 0.50), else when
        it went (a node long unheard whose route merely flapped is not suspected at once)."""
        gone = self.liveness.gone[node]
        heard = self.liveness.last_heard.get(node)
        return heard if heard is not None and gone - heard < self.liveness.dead_after_s else gone

    def _needed(self, node: str, away: set[str]) -> bool:
        """``node`` runs a vertex of an app this node runs part of whose re-placing would let
        events flow again (:func:`.reach.re_placeable`), or one next to a vertex being restored
        (the replacement waits for every surviving end of its edges to say where it stands,
        and one out of reach cannot: it is re-placed too), or the old host of a move this node
        coordinates (its handover cannot come: declared, the move's target restores the
        vertex)."""
        restoring: set[tuple[str, str]] = set()
        for proc in self.ctx.open():
            if isinstance(proc, Relocation) and proc.source == node and not proc.restore:
                return True
            if isinstance(proc, Relocation) and proc.restore:
                restoring.add((proc.app, proc.vertex))
        for dep in self.ctx.apps.values():
            if not dep.instances:
                continue
            app, placed = dep.app.name, dep.placed
            lost = dep.lost(self.failed) | {  # what a failed node ran and is not running
                v  # again elsewhere (restored, a node next to it is no longer needed: 3238)
                for n in self.failed
                for v in self._ran.get(n, {}).get(app, ())
                if placed.get(v) == n or (app, v) in restoring
            }
            near = {e.src for e in dep.app.edges if e.dst in lost}
            near |= {e.dst for e in dep.app.edges if e.src in lost}
            for v, n in dep.placed.items():
                if n != node:
                    continue
                if v in near or reach.re_placeable(
                    dep.app, dep.placed, dep.layout.resolved, v, away
                ):
                    return True
        return False

    def on_suspect(self, src: str, msg: m.Suspect, now: float) -> None:
        """Another node lost ``msg.node``: say whether we hear it (we heard it within our
        liveness window, and do not hold it failed; asked about ourselves, we live). If we do
        not but reach it, we ask it and answer when it does or our :class:`Vouch` expires."""
        node = msg.node
        if node == self.ctx.id:
            self.ctx.send(src, m.Hears(node, msg.rid, True, 0, msg.nonce))
            return
        ago = self.liveness.ago_ms(node, now)
        hears = self.liveness.hears(node, now, self.liveness.dead_after_s / 2)
        if node in self.failed or (hears and not msg.nonce):
            self.ctx.send(src, m.Hears(node, msg.rid, node not in self.failed, ago, msg.nonce))
            return
        if (
            node not in self.ctx.routes
            or node == src
            or (node in self.liveness.neighbours and not hears)
        ):
            self.ctx.send(src, m.Hears(node, msg.rid, False, ago, msg.nonce))  # (a neighbour
            return  # we watch and have not heard: our own beats are the probe)
        # not heard lately but reached, or heard and the asker wants the proof: ask it
        proc = self.ctx.procedure(self._vouching.get(node, -1))
        if not isinstance(proc, Vouch):
            wait = min(self.liveness.dead_after_s / 2, 2 * self.liveness.period_s)
            proc = Vouch(self.ctx.new_pid(), now, node, wait)
            self.ctx.begin(proc)
            self._vouching[node] = proc.pid  # (bounded by the nodes this node reaches)
            proc.start(self.ctx)
        proc.ask(self.ctx, src, msg.rid, msg.nonce)

    def on_hears(self, src: str, msg: m.Hears, now: float) -> None:
        if msg.rid == 0 and src == msg.node:
            return  # the answer to our own probe of a claim: hearing it was the point
        proc = self.ctx.procedure(msg.rid)
        if isinstance(proc, Vouch) and src == proc.node == msg.node and msg.yes:
            proc.answered(self.ctx, msg.nonce, msg.proof)
            if proc.done:
                self._vouching.pop(proc.node, None)
                self.ctx.end(proc.pid)
            return
        if not isinstance(proc, Suspicion) or proc.node != msg.node or src not in proc.missing:
            if not self.ctx.ours(msg.rid):  # (ours: a late answer to a suspicion that ended)
                self.ctx.refusal("hears_unasked")  # no such suspicion, or not asked (or twice)
            return
        if proc.nonce and msg.yes:  # with proofs: the suspect's own word, or nothing
            if msg.proof and msg.nonce == proc.nonce:  # (the transport checked its signature)
                self.liveness.vouched(msg.node, now)  # it answered our challenge: alive now
                self._vouchers.heard(msg.node)
                proc.heard_by.add(src)
                proc.answer(src, True)
            else:
                self.ctx.refusal("hears_unproven")  # a member's word alone: not taken
                proc.set_aside(src)
            if proc.done:
                self.suspected(proc, now)
            return
        yes = msg.yes
        if yes and msg.ago_ms >= 0:  # heard then: the silence clock runs from there
            at = now - msg.ago_ms / 1e3
            self.liveness.vouched(msg.node, at)
            yes = now - at <= self.liveness.dead_after_s / 2
        if yes:
            proc.heard_by.add(src)
            grace = LONE_YES_WINDOWS * self.liveness.dead_after_s
            bound = MEMBERS_YES_WINDOWS * self.liveness.dead_after_s
            if not self._vouchers.counts(msg.node, proc.heard_by, proc.asked, now, grace, bound):
                proc.set_aside(src)  # one member's word, for too long: another's, or none
        if src in proc.missing:
            proc.answer(src, yes)
        if proc.done:
            self.suspected(proc, now)

    def suspicion_expired(self, proc: Suspicion, now: float) -> None:
        """Nobody said they hear the suspected node in time: it failed."""
        proc.expire(self.ctx)
        self.suspected(proc, now)

    def vouch_expired(self, proc: Vouch) -> None:
        """The node we asked on others' behalf did not answer: we tell them no."""
        self._vouching.pop(proc.node, None)
        proc.expire(self.ctx)
        self.ctx.end(proc.pid)

    def suspected(self, proc: Suspicion, now: float) -> None:
        """A suspicion ended with its answers or at its deadline: act on its outcome."""
        self.ctx.end(proc.pid)
        self._suspicions.pop(proc.node, None)
        if proc.outcome == "vouched":  # someone heard it lately: judged again from then
            self._move(proc.node, PeerEvent.VOUCHED)
        else:
            if proc.heard_by and proc.outcome == "confirmed":
                self.ctx.refusal("hears_uncorroborated")  # a member's lone yes, set aside
            self.on_node_down(proc.node, self.ctx.id, now, witness=proc.witness)
            if self._peer(proc.node).state is P.SUSPECT:  # (not declared after all)
                self._move(proc.node, PeerEvent.VOUCHED)

    def _unsuspect(self, node: str, event: PeerEvent | None) -> None:
        """End ``node``'s open suspicion, if any (``event``: why, by the peer's table; None
        to leave the peer's state to the caller)."""
        pid = self._suspicions.pop(node, None)
        if pid is None:
            return
        proc = self.ctx.procedure(pid)
        if isinstance(proc, Suspicion):
            proc.end()
            self.ctx.end(pid)
        if event:
            self._move(node, event)

    # -- declaring a peer failed: one place ----------------------------------------------------
    def on_node_down(
        self,
        node: str,
        detector: str,
        now: float,
        incarnation: int | None = None,
        witness: str = "",
        tell: bool = True,
    ) -> None:
        """A claim that ``node`` failed: this node's own (its detector's word), or another's,
        acted on only when plausible and corroborated (:mod:`.claims`). ``tell``: False when
        the node is back already (a restart seen in its beat: its rejoin follows at once, and
        the nodes that need it learn of that, not of a failure that is over)."""
        if node in self.failed or node == self.ctx.id:
            return
        if not self.heard_of_node(node) or not self.admits(node, self._failed_incarnation):
            self.ctx.refusal("node_down_unknown")  # nobody it ever heard of: no such node
            return
        seen = self._incarnations.get(node)
        known = 0 if seen is None else seen
        if incarnation is not None and incarnation < known:
            return  # that incarnation failed, and a newer one is already back
        if seen is not None and incarnation is not None and incarnation > seen + INCARNATION_MARGIN:
            self.ctx.refusal("node_down_implausible_incarnation")  # never seen: not believed
            return
        inc = known if incarnation is None else incarnation
        claim = m.NodeDown(node, detector, inc, witness)
        if detector != self.ctx.id and not self._believe(claim, now):
            return
        self._declare(claim, now, tell)

    def _believe(self, claim: m.NodeDown, now: float) -> bool:
        """Another node's claim: refused if this node hears the victim itself; acted on when
        it names a witness, a second detector agrees, or this node's own probe does (no route
        to the victim, or no answer to a ``Suspect`` within half the window: then
        ``heartbeat`` declares it)."""
        node = claim.node
        if self.liveness.hears(node, now, within=self.liveness.dead_after_s / 2):
            self.ctx.refusal("node_down_heard")  # we hear it: it lives
            return False
        if self._claims.corroborated(claim) or node not in self.ctx.routes:
            return True
        if self._claims.hold(claim, now):
            self.ctx.send(node, m.Suspect(node, 0))  # our own probe: does it answer?
        return False

    def _declare(self, claim: m.NodeDown, now: float, tell: bool = True) -> None:
        """``claim.node`` failed, by this node's detector or a claim it believes: the one
        place a peer is declared."""
        node, detector = claim.node, claim.detector
        self._claims.drop(node)
        self._vouchers.heard(node)
        self._unsuspect(node, None)
        if detector != self.ctx.id:
            self._move(node, PeerEvent.REPORTED_DOWN)
        else:  # our own word: confirmed by the nodes we asked (or nobody left to ask), or
            # a node cut off that holds most of those we reach failed (``ranks.cut_off``)
            self._move(node, PeerEvent.CONFIRMED)
        self._failed_incarnation[node] = claim.incarnation
        self._ran[node] = {  # what it ran, by our views: restored now, next to nodes that
            a: {v for v, n in dep.placed.items() if n == node}  # may be out of reach
            for a, dep in self.ctx.apps.items()
        }
        self.liveness.forget(node)
        self.failures.append({"node": node, "detector": detector, "at": now})
        del self.failures[:-50]
        self.ctx.note_event(now, f"node {node} failed (detected by {detector})")
        self.ctx.publish(Happened("peer_failed", subject=node, by=detector))
        # it spreads on our next beats; the nodes that host the apps (one of them coordinates
        # the recovery) are told at once
        self._gossip.add(claim, rounds(len(self.ctx.routes) + 1))
        if detector == self.ctx.id and tell:
            for n in sorted(self._hosts() - self.failed - {self.ctx.id}):
                self.ctx.send(n, claim)
        # moves that needed it fail or become restores; the chains it touched are recovered
        self.ctx.publish(PeerFailed(node))

    # -- heartbeats in: restarts, healed partitions, who resets --------------------------------
    def on_heartbeat(self, src: str, msg: m.Heartbeat, now: float) -> None:
        if self._oversized(msg):
            return
        known = self._incarnations.get(src)
        if known is None and not self.admits(src, self._incarnations):
            self.ctx.refusal("unknown_node_over_bound")
            return
        if known is not None and msg.incarnation > known:  # it restarted: its instances went
            self.on_node_down(src, self.ctx.id, now, tell=False)
            self._rejoin(src, msg.incarnation, now, announce=True)
            return
        if known is not None and msg.incarnation < known:
            return  # sent before it reset or restarted (it overtook nothing): what it holds
            # failed and whom it outranks are gone with that incarnation
        self._incarnations[src] = msg.incarnation
        if known is None and self._newcomer(msg):
            if src in self._hosts():
                # it runs nothing, yet we place vertices there: a restart of a node we never
                # heard a beat from (it joined an app by a move after its start): what it ran
                # is gone (fault seed 10630: a move's marker went to a node that had no c)
                self._rejoin(src, msg.incarnation, now, announce=True)
            else:
                self._sync_pending.add(src)  # (bounded: its incarnation was admitted)
                self._flush_syncs()
        elif known is None and msg.incarnation > 0 and msg.hosting == 0:
            self._heard_empty(src, now)  # we hold no app yet: told it when we learn one
        for node, inc in msg.failed.items():  # a node we never heard of (we restarted since)
            if node != self.ctx.id and self.admits(node, self._incarnations):  # failed in that
                self._incarnations.setdefault(node, inc)  # incarnation: a newer one will be a
                # restart, whose instances are gone
        if self.ctx.routes.get(src, ("", 0))[0] == src:  # a neighbour's beat, not a hello
            self.liveness.heard_from(src, now, msg)
        for claim in msg.news[:MAX_NEWS]:  # claims it accepted, piggybacked: weighed as ours
            if claim.node not in (src, self.ctx.id):  # would be weighed by a NodeDown
                self.on_node_down(claim.node, claim.detector, now, claim.incarnation, claim.witness)
        if msg.failed.get(self.ctx.id) == self.incarnation:
            view = self._view()
            if ranks.outranked_by(view, msg) and ranks.cut_off(view, msg):  # a healed
                self.on_node_down(src, self.ctx.id, now)  # partition we did not see: hold it
                self.ctx.send(src, self.beat())  # failed too, and the rank settles it (it
                # is the smaller side)
            elif ranks.outranked_by(view, msg):
                self._reset(now, src)
            else:  # it runs nothing and holds us failed: our beat (we run something, and
                self.ctx.send(src, self.beat())  # hold it alive) makes it yield
        else:
            self._answer_stale_claim(src, msg)

    def _newcomer(self, msg: m.Heartbeat) -> bool:
        """A node never heard of before (the caller knows) that may have run before
        (incarnation > 0: a daemon's start time, a revived simulated node), runs nothing, and
        meets this node running apps: a restart whose neighbours may never have known it
        either (at a first start nobody says hello to every node), so nobody would take it for
        one and sync it the apps -- this node does."""
        return msg.incarnation > 0 and msg.hosting == 0 and self._running()

    def _running(self) -> bool:
        """An app runs here (what a node back with no instances needs to be told of)."""
        return any(dep.running for dep in self.ctx.apps.values())

    def _oversized(self, msg: m.Heartbeat) -> bool:
        """A beat holding far more nodes failed than this node could know of: refused, as
        weighing it would cost every beat that much (a sender's map is bounded like ours)."""
        if len(msg.failed) <= KNOWN_PER_ROUTE * self.known_bound():
            return False
        self.ctx.refusal("heartbeat_failed_map_over_bound")
        return True

    def _view(self) -> ranks.View:
        """What the tie-break reads of this node (:mod:`.ranks`)."""
        return ranks.View(
            self.ctx.id,
            self.incarnation,
            self.ctx.routes,
            frozenset(self.failed),
            self._incarnations,
            self._hosting(),
            self._leader(),
        )

    def _awaits_its_reset(self, msg: m.Heartbeat, now: float) -> bool:
        """Whether this node, which runs nothing, should not yield to ``msg.node`` (held
        failed here, running something) although the tie-break says so: it is on the smaller
        side of a healed partition and will reset when it hears a node of ours that runs
        something (our views place work on one), and we take its new incarnation back.
        Yielding, we would reset, be declared failed by everyone who holds us alive, and drop
        the replicas we keep, for nothing. At most ``YIELD_WAIT_S``: where no node of ours
        outranks it, we yield as before."""
        src = msg.node
        if (
            self._hosting() > 0
            or msg.hosting == 0
            or not self._hosts() - self.failed - {src}  # no node of ours our views place work on
            or not ranks.holds_more_failed(self._view(), msg)
        ):
            self._awaiting.pop(src, None)
            return False
        if len(self._awaiting) >= self.known_bound():
            self._awaiting.clear()
        since = self._awaiting.setdefault(src, now)
        return now - since < YIELD_WAIT_S

    def _answer_stale_claim(self, src: str, msg: m.Heartbeat) -> None:
        """``src`` holds an older incarnation of ours failed: our beat tells it we are back."""
        claim = msg.failed.get(self.ctx.id)
        if claim is not None and claim < self.incarnation:
            self.ctx.send(src, self.beat())

    def on_failed_heartbeat(self, src: str, msg: m.Heartbeat, now: float) -> None:
        """A node we declared failed is heard again: it restarted (a higher incarnation), or
        a partition healed. Then the side that loses the tie-break resets and rejoins."""
        if self._oversized(msg):
            return
        if msg.incarnation < self._incarnations.get(src, msg.incarnation):
            return  # from an incarnation that has since reset: it must not reset us
        if msg.incarnation > self._failed_incarnation.get(src, 0):
            if msg.hosting > 0 and self._hosting() > 0 and self._disputed():
                self._restarted_across(src, msg.incarnation)
                return
            self._rejoin(src, msg.incarnation, now, announce=True)
        elif self._awaits_its_reset(msg, now):
            self._tell_held_failed(src, now)
        elif msg.failed.get(self.ctx.id) == self.incarnation and ranks.outranked_by(
            self._view(), msg
        ):
            self._reset(now, src)
        elif self.ctx.id not in msg.failed and msg.hosting > 0 and self._hosting() == 0:
            self._reset(now, src)  # it holds us alive and runs something we hold failed: we
            # run nothing, so we yield (it does not reset for us: see ranks.outranked_by)
        else:
            self._answer_stale_claim(src, msg)
            self._tell_held_failed(src, now)

    def _tell_held_failed(self, src: str, now: float) -> None:
        """``src``, held failed in the incarnation it still runs, is heard directly: tell it at
        once (our beat lists it failed), so that it resets and rejoins now rather than at the
        next ``REJOIN_EVERY`` round. At most once a heartbeat period per node."""
        if now - self._told.get(src, float("-inf")) < self.liveness.period_s:
            return
        if len(self._told) >= self.known_bound():
            self._told.clear()
        self._told[src] = now
        self.ctx.send(src, self.beat())

    def _restarted_across(self, src: str, incarnation: int) -> None:
        """``src`` restarted on the other side of a partition, which has since given it
        instances (a restart brings none): its instances are that side's, and some may run
        here too. Not a rejoin: we hold this incarnation failed as well and tell it, so that
        it yields (it holds us alive and we run something) and comes back empty."""
        self._incarnations[src] = incarnation
        self._failed_incarnation[src] = incarnation
        self.ctx.send(src, self.beat())

    def _reset(self, now: float, by: str) -> None:
        """Rejoin as a new incarnation: the others have recovered without this node's
        instances, so it drops them (and every app) and is told the apps again."""
        dropped = sorted(self.ctx.apps)
        self.dp.stop_all("reset")
        self.ctx.apps.clear()
        for proc in self.ctx.open():  # nobody waits for them any more
            self.ctx.end(proc.pid)
        self.dp.outbox.clear()
        self.ctx.publish(NodeReset())  # each component drops what it waited for
        self._sync_pending.clear()  # it holds no app any more: nothing to sync
        for node in self.failed:
            self.liveness.rejoin(node, now, node in self.ctx.routes, self.ctx.routes.get(node))
        for node in sorted(self.failed):
            self._move(node, PeerEvent.RESET)
        for node in sorted(self._suspicions):  # (their procedures were ended above)
            self._move(node, PeerEvent.RESET)
        self._suspicions.clear()
        self._vouching.clear()
        self._failed_incarnation.clear()
        self._ran.clear()
        self._awaiting.clear()
        self._gossip.clear()
        self._claims.clear()
        self._vouchers.clear()
        self.incarnation += 1
        self.ctx.note_event(
            now,
            f"declared failed by {by}: rejoined as incarnation {self.incarnation}"
            + (f", dropping {', '.join(dropped)}" if dropped else ""),
        )
        self.ctx.publish(
            Happened("reset", subject=self.ctx.id, detail=f"incarnation {self.incarnation}", by=by)
        )
        self.heartbeat(now)
        beat = self.beat()
        for n in sorted(
            self.ctx.routes
        ):  # everyone learns the new incarnation, not just neighbours
            if n not in self.liveness.neighbours:
                self.ctx.send(n, beat)

    def _rejoin(self, node: str, incarnation: int, now: float, announce: bool) -> None:
        """``node`` is back with no instances: restore what it hosted, unpark what was pinned
        to it, and tell it the apps."""
        if node in self.failed:
            self._move(node, PeerEvent.REJOINED)
        self._failed_incarnation.pop(node, None)
        self._ran.pop(node, None)
        self._awaiting.pop(node, None)
        self._gossip.drop(node)
        self._claims.drop(node)
        self._vouchers.heard(node)
        self._incarnations[node] = incarnation
        self._heard_empty(node, now)
        self.liveness.rejoin(node, now, node in self.ctx.routes, self.ctx.routes.get(node))
        self.rejoins.append({"node": node, "incarnation": incarnation, "at": now})
        del self.rejoins[:-50]
        self.ctx.note_event(now, f"node {node} rejoined (incarnation {incarnation})")
        self.ctx.publish(
            Happened("peer_rejoined", subject=node, detail=f"incarnation {incarnation}")
        )
        if announce and self._first_to_hear(node):  # to the nodes that host the apps (one of
            # them restores what it hosted) and our neighbours, as a claim goes, by the node's
            # neighbours alone (:meth:`_first_to_hear`): every node it reaches hears it back
            # from its own hello (a restart's: :meth:`on_routes_changed`) or at its next
            # REJOIN_EVERY round (told by every node that heard it, a restart at 1,000 nodes
            # cost 7,557 NodeUp; told every known node, a mobile network of 200 spent half
            # its membership messages on it)
            for n in sorted(self._hosts() | set(self.liveness.neighbours)):
                if n not in (self.ctx.id, node) and n not in self.failed:
                    self.ctx.send(n, m.NodeUp(node, incarnation))
        disputed = self._disputed()
        if disputed:
            self._sync_pending.add(node)
        for dep in list(self.ctx.apps.values()):
            dep.vanished |= {v for v, n in dep.placed.items() if n == node}
            self.recovery.unpark(dep)
            if not dep.running:
                continue
            if not disputed and self._syncs(dep, node):
                self.ctx.send(node, self._app_sync(dep))
            self._claim(dep)
            self.recovery.maybe_recover(dep, now)

    def on_node_up(self, msg: m.NodeUp, now: float) -> None:
        if msg.node == self.ctx.id:
            return
        if msg.node not in self.failed and msg.node not in self._incarnations:
            if not self.admits(msg.node, self._incarnations):
                self.ctx.refusal("unknown_node_over_bound")
            elif msg.incarnation > 0 and self._running():
                # back with no instances, from a start whose hellos went to its neighbours
                # only: its first beat will not look new any more, so it is told the apps
                # (and what we placed there restored) now (fault seeds 6828, 8554)
                self._rejoin(msg.node, msg.incarnation, now, announce=False)
            else:
                self._incarnations[msg.node] = msg.incarnation
            return
        if msg.node in self.failed:
            if msg.incarnation > self._failed_incarnation.get(msg.node, 0):
                self._rejoin(msg.node, msg.incarnation, now, announce=False)
        elif msg.incarnation > self._incarnations.get(msg.node, msg.incarnation):
            self.on_node_down(msg.node, msg.node, now)  # restarted unnoticed by us
            self._rejoin(msg.node, msg.incarnation, now, announce=False)
