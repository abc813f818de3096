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

from collections.abc import Iterable, Mapping
from typing import Any

import msgspec

from mso.errors import MsoError
from mso.planning.placement import Layout
from mso.protocol import messages as m
from mso.protocol.authority import generation
from mso.protocol.context import NodeContext
from mso.protocol.dataplane import RETRANSMIT_S, DataPlane
from mso.protocol.effects import Send, SetTimer
from mso.protocol.events import (
    AppMissing,
    Happened,
    HeartbeatTick,
    NodeReset,
    PeerFailed,
    RecoveryDue,
    Retransmit,
    RoutesChanged,
)
from mso.protocol.procedures.deploy import Deployer
from mso.protocol.procedures.membership.detector import P, PeerEvent, PeerLife, Suspicion, Vouch
from mso.protocol.procedures.membership.liveness import Liveness
from mso.protocol.procedures.membership.status import Heard, MembershipStatus
from mso.protocol.procedures.remap import Remapper
from mso.protocol.state import AppState

REJOIN_EVERY = 10  # heartbeat periods between heartbeats to reachable nodes declared failed
MONITOR_PERIOD_S = 1.0  # how often the monitor samples on its own: its figures ride on one beat
# of each period (they change no faster)
REVOCATIONS_TOLD = 16  # the operator's latest undeploys told to each newly reachable node
# Nodes a node keeps tables of (incarnations, failures, last heard) beyond those it routes to:
# at least this many, or this factor times the nodes it routes to. A member can name any node
# (nodes have no identities yet), so the tables admit a node the routing view does not show
# only below this bound: 50,000 invented names once put a 50,000-entry map into every beat.
MIN_KNOWN = 256
KNOWN_PER_ROUTE = 4


class Membership:
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
        return min({self.ctx.id, *(n for n in self.ctx.routes if n not in self.failed)})

    def _hosting(self) -> int:
        return sum(len(dep.instances) for dep in self.ctx.apps.values())

    # -- the detector: beats out, silence and unreachability judged, suspicion asked -----------
    def beat(self) -> m.Heartbeat:
        """This node's beat with its monitor's figures (see Heartbeat)."""
        return m.Heartbeat(
            self.ctx.id,
            self.incarnation,
            dict(self._failed_incarnation),
            self._leader(),
            self._hosting(),
            self.ctx.figures(),
        )

    def heartbeat(self, now: float) -> None:
        """Tell the neighbours we live; declare the silent ones failed. Our figures go on one
        beat per monitor period, and on the first beat to a neighbour since its link came up
        (``_briefed``: the time the link came up, when it was given them)."""
        every = max(1, round(MONITOR_PERIOD_S / self.liveness.period_s))
        full = self.beat()
        slim = full if self._beats % every == 0 else msgspec.structs.replace(full, figures=None)
        for n, since in sorted(self.liveness.neighbours.items()):
            if n not in self.failed:
                briefed = self._briefed.get(n) == since
                self._briefed[n] = since
                self.ctx.emit(Send(n, slim if briefed else full))
        for n in set(self._briefed) - set(self.liveness.neighbours):
            del self._briefed[n]  # bounded by the neighbours
        self._beats += 1
        if self._beats % REJOIN_EVERY == 0:  # a failed node we can reach again: a healed
            for n in sorted(self.failed):  # partition; tell it, so one side rejoins the other
                if n in self.ctx.routes:
                    self.ctx.emit(Send(n, full))
        for n in self.liveness.silent(now, self.failed):
            self.on_node_down(n, self.ctx.id, now)
        for n in self.liveness.unreachable(now, self.failed):
            self._suspect(n, now)
        self._flush_syncs()
        # this node may have become an app's recovery coordinator (it runs part of it now)
        self.ctx.publish(RecoveryDue())
        self.ctx.set_timer(HeartbeatTick(), now + self.liveness.period_s)

    def heard(self, src: str, now: float) -> None:
        """A message from ``src``, which this node holds alive: it lives (and if suspected,
        it reaches us though we do not reach it). Noted only within the tables' bound."""
        if self.admits(src, self.liveness.last_heard):
            self.liveness.heard_from(src, now)
        self.heard_directly(src, now)

    def heard_directly(self, src: str, now: float) -> None:
        """A message from a suspected node (it reaches us though we do not reach it): it
        lives, which is what the suspicion asked."""
        if src in self._suspicions:
            self._unsuspect(src, PeerEvent.VOUCHED)
            self.liveness.vouched(src, now)

    def on_routes_changed(self, ev: RoutesChanged) -> None:
        """Who is a neighbour and who is reachable; a suspected node in reach again is not
        suspected; newly reachable nodes learn our incarnation (and whom we hold failed, if a
        partition just healed) and the operator's latest undeploys (a node that restarted or
        was cut off has not heard them)."""
        now, routes = self.ctx.now, self.ctx.routes
        neighbours = {d for d, (hop, _) in routes.items() if hop == d}
        self.liveness.set_routes(now, set(routes) - self.failed, neighbours)
        self.back_in_reach(now)
        if ev.appeared:
            beat = self.beat()
            undeploys = list(self.ctx.authority.revoked.values())[-REVOCATIONS_TOLD:]
            for d in sorted(ev.appeared):
                self.ctx.send(d, beat)
                for stop in undeploys:
                    self.ctx.send(d, stop)

    def back_in_reach(self, now: float) -> None:
        """The routes changed: a suspected node this node reaches again is not suspected."""
        for node in sorted(self._suspicions):
            if node in self.ctx.routes:
                self._unsuspect(node, PeerEvent.REACHABLE)

    def _suspect(self, node: str, now: float) -> None:
        """``node`` has been out of this node's reach for the liveness window. A routing
        protocol drops a dead node's routes, but it may also leave one node without a route
        to a live one for seconds while the others still hear it: so ask the nodes this node
        still reaches, and declare it only if none does (:class:`Suspicion`)."""
        if node in self._suspicions or node in self.failed or node == self.ctx.id:
            return
        self._move(node, PeerEvent.UNREACHABLE)
        asked = sorted(n for n in self.ctx.routes if n not in self.failed and n != node)
        if not asked:  # nobody left to ask: this node is cut off from everyone
            self.on_node_down(node, self.ctx.id, now)
            return
        proc = Suspicion(self.ctx.new_pid(), now, node, asked, self.liveness.dead_after_s)
        self.ctx.begin(proc)
        self._suspicions[node] = proc.pid
        proc.start(self.ctx)

    def on_suspect(self, src: str, msg: m.Suspect, now: float) -> None:
        """Another node lost ``msg.node``: say whether we hear it (we heard it within our
        liveness window, and do not hold it failed; asked about ourselves, we live). If we do
        not but reach it, we ask it and answer when it does or our :class:`Vouch` expires."""
        node = msg.node
        if node == self.ctx.id or node in self.failed or self.liveness.hears(node, now):
            self.ctx.send(src, m.Hears(node, msg.rid, node not in self.failed))
            return
        if node not in self.ctx.routes or node == src:
            self.ctx.send(src, m.Hears(node, msg.rid, False))
            return
        proc = self.ctx.procedure(self._vouching.get(node, -1))
        if not isinstance(proc, Vouch):
            proc = Vouch(self.ctx.new_pid(), now, node, self.liveness.dead_after_s / 2)
            self.ctx.begin(proc)
            self._vouching[node] = proc.pid  # (bounded by the nodes this node reaches)
            proc.start(self.ctx)
        proc.ask(src, msg.rid)

    def on_hears(self, src: str, msg: m.Hears, now: float) -> None:
        proc = self.ctx.procedure(msg.rid)
        if isinstance(proc, Vouch) and src == proc.node == msg.node and msg.yes:
            self._vouching.pop(proc.node, None)
            proc.answered(self.ctx)
            self.ctx.end(proc.pid)
            return
        if not isinstance(proc, Suspicion) or proc.node != msg.node or src not in proc.missing:
            if not self.ctx.ours(msg.rid):  # (ours: a late answer to a suspicion that ended)
                self.ctx.refusal("hears_unasked")  # no such suspicion, or not asked (or twice)
            return
        proc.answer(src, msg.yes)
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
        if proc.outcome == "vouched":  # someone hears it: ask again a window from now
            self._move(proc.node, PeerEvent.VOUCHED)
            self.liveness.vouched(proc.node, now)
        elif proc.node in self.ctx.routes:  # (back in reach since: nothing to confirm)
            self._move(proc.node, PeerEvent.REACHABLE)
        else:
            self.on_node_down(proc.node, self.ctx.id, now)

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
        self, node: str, detector: str, now: float, incarnation: int | None = None
    ) -> None:
        if node in self.failed or node == self.ctx.id:
            return
        if not self.heard_of_node(node) or not self.admits(node, self._failed_incarnation):
            self.ctx.refusal("node_down_unknown")  # nobody it ever heard of: no such node
            return
        known = self._incarnations.get(node, 0)
        if incarnation is not None and incarnation < known:
            return  # that incarnation failed, and a newer one is already back
        self._unsuspect(node, None)
        if detector != self.ctx.id:
            self._move(node, PeerEvent.REPORTED_DOWN)
        else:  # our own word: confirmed by the nodes we asked, or a neighbour's silence
            suspected = self._peer(node).state is P.SUSPECT
            self._move(node, PeerEvent.CONFIRMED if suspected else PeerEvent.SILENT)
        self._failed_incarnation[node] = known if incarnation is None else incarnation
        self.liveness.forget(node)
        self.failures.append({"node": node, "detector": detector, "at": now})
        del self.failures[:-50]
        self.ctx.note_event(now, f"node {node} failed (detected by {detector})")
        self.ctx.publish(Happened("peer_failed", subject=node, by=detector))
        if (
            detector == self.ctx.id
        ):  # tell everyone; the others learn it from us or another detector
            for n in self.ctx.known_nodes():
                if n != self.ctx.id and n not in self.failed:
                    self.ctx.send(n, m.NodeDown(node, self.ctx.id, self._failed_incarnation[node]))
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
            self.on_node_down(src, self.ctx.id, now)
            self._rejoin(src, msg.incarnation, now, announce=True)
            return
        if known is not None and msg.incarnation < known:
            return  # sent before it reset or restarted (it overtook nothing): what it holds
            # failed and whom it outranks are gone with that incarnation
        self._incarnations[src] = msg.incarnation
        for node, inc in msg.failed.items():  # a node we never heard of (we restarted since)
            if node != self.ctx.id and self.admits(node, self._incarnations):  # failed in that
                self._incarnations.setdefault(node, inc)  # incarnation: a newer one will be a
                # restart, whose instances are gone
        if self.ctx.routes.get(src, ("", 0))[0] == src:  # a neighbour's beat, not a hello
            self.liveness.heard_from(src, now, msg)
        if msg.failed.get(self.ctx.id) == self.incarnation:
            if self._outranked_by(msg) and self._cut_off(msg):  # a healed partition we did
                self.on_node_down(src, self.ctx.id, now)  # not see: hold it failed too, and the
                self.ctx.send(src, self.beat())  # rank settles it (it is the smaller side)
            elif self._outranked_by(msg):
                self._reset(now, src)
            else:  # it runs nothing and holds us failed: our beat (we run something, and
                self.ctx.send(src, self.beat())  # hold it alive) makes it yield
        else:
            self._answer_stale_claim(src, msg)

    def _oversized(self, msg: m.Heartbeat) -> bool:
        """A beat holding far more nodes failed than this node could know of: refused, as
        weighing it would cost every beat that much (a sender's map is bounded like ours)."""
        if len(msg.failed) <= KNOWN_PER_ROUTE * self.known_bound():
            return False
        self.ctx.refusal("heartbeat_failed_map_over_bound")
        return True

    def _cut_off(self, msg: m.Heartbeat) -> bool:
        """``msg.node``, which we hold alive, holds us failed, and with us most of the nodes
        we reach and hold alive: it was cut off from them (a partition that just healed),
        and we did not declare it because our suspicion of it had not ended yet when it came
        back into reach (others had: a confirmation takes a round trip). Resetting for it
        would make the larger side reset for the smaller one; a node that only we missed
        (it stalled, or it alone lost our routes) holds failed just us and a few, and we
        yield to it as before."""
        if msg.node in self.failed:
            return False
        seen = {n for n in self.ctx.routes if n not in self.failed and n != msg.node} | {
            self.ctx.id
        }
        held = sum(1 for n in seen if n in msg.failed)
        return held > len(seen) - held

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
        elif msg.failed.get(self.ctx.id) == self.incarnation and self._outranked_by(msg):
            self._reset(now, src)
        elif self.ctx.id not in msg.failed and msg.hosting > 0 and self._hosting() == 0:
            self._reset(now, src)  # it holds us alive and runs something we hold failed: we
            # run nothing, so we yield (it does not reset for us: see _outranked_by)
        else:
            self._answer_stale_claim(src, msg)

    def _restarted_across(self, src: str, incarnation: int) -> None:
        """``src`` restarted on the other side of a partition, which has since given it
        instances (a restart brings none): its instances are that side's, and some may run
        here too. Not a rejoin: we hold this incarnation failed as well and tell it, so that
        it yields (it holds us alive and we run something) and comes back empty."""
        self._incarnations[src] = incarnation
        self._failed_incarnation[src] = incarnation
        self.ctx.send(src, self.beat())

    def _outranked_by(self, msg: m.Heartbeat) -> bool:
        """After a partition both sides may hold the other failed. A node that runs nothing
        yields to one that runs something (it loses nothing by resetting); otherwise the side
        that counts fewer failed nodes (the larger one), then the one with the lower leader,
        then the lower-named node, stays and the other resets (two nodes of one side that
        hold each other failed — not neighbours, each cut off by other failures — would
        otherwise tie for ever). One-sided (we hold the sender alive), we reset, unless the
        sender runs nothing and we run something: it yields instead (``_on_failed_heartbeat``;
        a restarted node that held everyone failed once reset every node it met).

        Only failed nodes this node can reach count (the other side of the partition): a node
        that really crashed is out of everyone's reach, and the two sides learn of it at
        different moments; counted, it once made both nodes of a tie reset, and the app was
        gone from every node."""
        if msg.node not in self.failed:
            return not (msg.hosting == 0 and self._hosting() > 0)

        def rank(hosting: int, dead: int, leader: str, node: str) -> tuple[bool, int, str, str]:
            return (hosting == 0, dead, leader, node)  # the node's own name breaks a tie

        def disputed(dead: Iterable[str]) -> int:
            return sum(1 for n in dead if n == self.ctx.id or n in self.ctx.routes)

        theirs = rank(msg.hosting, disputed(msg.failed), msg.leader or msg.node, msg.node)
        return theirs < rank(self._hosting(), disputed(self.failed), self._leader(), self.ctx.id)

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
        self._incarnations[node] = incarnation
        self.liveness.rejoin(node, now, node in self.ctx.routes, self.ctx.routes.get(node))
        self.rejoins.append({"node": node, "incarnation": incarnation, "at": now})
        del self.rejoins[:-50]
        self.ctx.note_event(now, f"node {node} rejoined (incarnation {incarnation})")
        self.ctx.publish(
            Happened("peer_rejoined", subject=node, detail=f"incarnation {incarnation}")
        )
        if announce:
            for n in self.ctx.known_nodes():
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
            if not disputed:
                self.ctx.send(node, self._app_sync(dep))
            self._claim(dep)
            self.recovery.maybe_recover(dep, now)

    def on_node_up(self, msg: m.NodeUp, now: float) -> None:
        if msg.node == self.ctx.id:
            return
        if msg.node not in self.failed and msg.node not in self._incarnations:
            if self.admits(msg.node, self._incarnations):
                self._incarnations[msg.node] = msg.incarnation
            else:
                self.ctx.refusal("unknown_node_over_bound")
            return
        if msg.node in self.failed:
            if msg.incarnation > self._failed_incarnation.get(msg.node, 0):
                self._rejoin(msg.node, msg.incarnation, now, announce=False)
        elif msg.incarnation > self._incarnations.get(msg.node, msg.incarnation):
            self.on_node_down(msg.node, msg.node, now)  # restarted unnoticed by us
            self._rejoin(msg.node, msg.incarnation, now, announce=False)

    # -- app sync: a node that rejoins (or missed an app) is told it ---------------------------
    def _claim(self, dep: AppState) -> None:
        """Tell everyone where the instances this node runs are (a node that rejoins may
        have spread, or been told, a view in which they run elsewhere: a node of a partition's
        losing side claims the vertices it ran until it resets, and its reset tells nobody).
        An instance being handed over is left out: its Moved follows."""
        for vid, h in sorted(dep.instances.items()):
            if h.handing_over is None and vid not in dep.markers:
                self.ctx.broadcast(m.Moved(dep.app.name, vid, self.ctx.id, self.incarnation))

    def _disputed(self) -> bool:
        """This node holds a node it can reach failed: a partition healed and one side is
        about to reset. Until then its view of the apps may be the losing side's, so it syncs
        no node that rejoins (its sync would spread that view; nothing would correct it)."""
        return any(n in self.ctx.routes for n in self.failed)

    def _merge_sync(self, src: str, held: AppState, msg: m.AppSync) -> None:
        """Take from a sync what is better than our view of an app we already hold. Ours may
        come from a side of a partition that has since reset (a restarted node synced by a
        node that lost the tie-break) or miss moves made while we were away, and no Moved will
        ever correct it. But a sync is a snapshot and may be older than a Moved we have had
        since. So we take the sender's word where it is first-hand (a vertex it runs itself
        and does not hold vanished, or one we place on it that it says it handed over, and
        to whom: a node held failed when the old host broadcast the move missed its Moved),
        and its hearsay only where our own entry is known bad
        (on a node we hold failed, vanished, or placed here where it does not run) — never
        where we run an instance ourselves, and never a vertex it places here (it holds
        that one vanished with our old incarnation)."""
        ours = set(held.instances) | set(held.awaiting) | set(held.restoring)
        gone = set(msg.vanished)

        def better(v: str, n: str) -> bool:
            if v not in held.placed or v in ours or n == self.ctx.id:
                return False
            if n == src and v not in gone:
                return True
            mine = held.placed[v]
            if mine == src and msg.handed.get(v) == n:  # it ran it and handed it over to n
                return True
            if n == mine and v in held.vanished:  # names the node whose old incarnation took
                return False  # it: no news (a claim from that node would be)
            bad = mine in self.failed or v in held.vanished or mine == self.ctx.id
            return bad and (v not in gone or v in held.vanished)

        taken = {v for v, n in msg.placed.items() if better(v, n)}
        for v in taken:
            held.placed[v] = msg.placed[v]
        held.vanished = (held.vanished - taken) | (taken & gone)

    def _app_sync(self, dep: AppState) -> m.AppSync:
        placed = dict(dep.placed)
        handed = {v: n for v, n in dep.handed.items() if v not in dep.instances}
        return m.AppSync(
            dep.app.name, dep.origin, dep.document, dep.epoch, placed, sorted(dep.vanished), handed
        )

    def on_app_missing(self, ev: AppMissing) -> None:
        """A live node asked to host a vertex does not hold the app: its sync was lost (the
        node that owed it failed before it could send it; nobody else would). Sync it now,
        or once this node's own view is not in dispute."""
        dep, node = self.ctx.apps.get(ev.app), ev.node
        if dep is None or node in self.failed or node == self.ctx.id or not dep.running:
            return
        if self._disputed():
            self._sync_pending.add(node)
        else:
            self.ctx.send(node, self._app_sync(dep))

    def _flush_syncs(self) -> None:
        """Sync the nodes that rejoined while this node's view was in dispute, once it is not."""
        if not self._sync_pending or self._disputed():
            return
        pending, self._sync_pending = sorted(self._sync_pending), set()
        for node in pending:
            if node in self.failed:
                continue
            for dep in self.ctx.apps.values():
                if dep.running:
                    self.ctx.send(node, self._app_sync(dep))

    def on_app_sync(self, src: str, msg: m.AppSync, now: float) -> None:
        held = self.ctx.apps.get(msg.app)
        if self.deployer.revoked(src, msg.app, msg.document):
            return
        signed = self.ctx.authority.signed
        if signed and held is not None and generation(msg.document) != generation(held.document):
            self.ctx.refusal("app_sync_other_deployment")  # (an operator deployed it again since)
            return
        if held is not None:
            self._merge_sync(src, held, msg)
            self.recovery.unpark(held)
            self.recovery.park(held)
            self.recovery.maybe_recover(held, now)
            return
        try:
            app = self.deployer.load_app(msg.app, msg.document)
        except MsoError as exc:
            self.ctx.note_event(now, f"cannot rejoin app {msg.app}: {exc}")
            return
        if not self.deployer.named(app, msg.app):
            return
        layout = Layout(app, msg.origin)
        placed = dict(layout.initial_placement()) | {
            v: n for v, n in msg.placed.items() if v in app.vertices
        }
        dep = AppState(app, layout, msg.origin, placed, epoch=msg.epoch, document=msg.document)
        dep.vanished = {v for v in msg.vanished if v in app.vertices}
        dep.placed_chains = dep.started_chains = set(range(len(layout.chains)))
        dep.running, dep.started_at = True, now
        dep.placed_at = dict.fromkeys(range(len(layout.chains)), now)
        for i, e in enumerate(app.edges):
            dep.out_edges.setdefault(e.src, []).append(i)
        self.ctx.apps[msg.app] = dep
        # (re)arm go-back-N for the app: a timer left from before a reset may have lapsed
        self.ctx.emit(SetTimer(Retransmit(msg.app), now + RETRANSMIT_S))
        self.recovery.park(dep)
        self.recovery.maybe_recover(dep, now)
