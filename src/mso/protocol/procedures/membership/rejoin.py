"""Beats in, and nodes coming back: a restart seen as a higher incarnation, a healed partition
settled by the tie-break (:mod:`.ranks`: the losing side resets), a node back rejoined and
sent the apps (:mod:`.sync`)."""

from __future__ import annotations

from mso.protocol import messages as m
from mso.protocol.events import Happened, NodeReset, PeerRejoined
from mso.protocol.procedures.membership import ranks
from mso.protocol.procedures.membership.beats import Beating
from mso.protocol.procedures.membership.claims import MAX_NEWS
from mso.protocol.procedures.membership.detector import PeerEvent
from mso.protocol.procedures.membership.tables import KNOWN_PER_ROUTE

# how long a node that runs nothing waits for a node on the smaller side of a healed partition
# to reset (it hears a node of ours that runs something within a REJOIN_EVERY round) before
# yielding to it
YIELD_WAIT_S = 1.5


class Rejoining(Beating):
    """Membership's layer that weighs beats in, resets and rejoins."""

    def quiet_beat(self, src: str, msg: m.Heartbeat, now: float) -> bool:
        """Take a beat with no news (no claims, not from a suspect, holding failed only nodes
        heard of, not this one): a beat in the incarnation known, or a non-neighbour's first
        (the N² hellos of a start-up). All :meth:`heard` and :meth:`on_heartbeat` would do is
        note the incarnation and the sender's liveness clock, and a neighbour's figures if it
        carries them (one beat in ten: weighed whole, they were half of what receiving beats
        cost): done here, outside the core's effect machinery. False: weigh it whole. Keep it
        in step with :meth:`on_heartbeat` (tests/test_sim_scale.py runs the two ways side by
        side)."""
        if msg.news or src in self._suspicions or src in self._vouchers.since:
            return False
        # (the liveness table's few neighbours, which on_routes_changed keeps equal to the
        # routes whose next hop is their destination: not the N-entry routing table)
        neighbour = src in self.liveness.neighbours
        known = self._incarnations.get(src)
        if known is None:
            if neighbour or not self.admits(src, self._incarnations) or self._newcomer(msg):
                return False
        elif known != msg.incarnation or src not in self.liveness.last_heard:
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
        something (a neighbour whose last beat said it runs an instance: not where our views
        place work, which may be a node that restarted since, and a node that takes no part
        in an app holds none of it), and we take its new incarnation back. Yielding, we would
        reset, be declared failed by everyone who holds us alive, and drop the replicas we
        keep, for nothing. At most ``YIELD_WAIT_S``: where no node of ours outranks it, we
        yield as before."""
        src = msg.node
        if (
            self._hosting() > 0
            or msg.hosting == 0
            or not any(n != src and n not in self.failed for n in self.liveness.busy)
            or not ranks.smaller_side(self._view(), msg)
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
        self.deployer.abandon(f"declared failed by {by}, reset during the deployment")
        self.dp.stop_all("reset")
        self.ctx.apps.clear()
        for proc in self.ctx.open():  # they go with the state; a waiting client is told why
            proc.abandon(
                self.ctx, f"{self.ctx.id}: declared failed by {by}, reset during the {proc.name}"
            )
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
        held = node in self.failed
        restarted = not held and incarnation > self._incarnations.get(node, incarnation)
        if held:
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
        self.ctx.publish(PeerRejoined(node, restarted))
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
                self._sync_back(node, dep)
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
