"""App sync, membership's part in bringing a node that rejoins (or missed an app) up to date:
it is told the app and where its vertices run (``AppSync``), and what it says is merged with
care (a sync is a snapshot). A mixin of :class:`~.peers.Membership`, kept apart so that each
module does one thing."""

from __future__ import annotations

from collections.abc import Mapping

from mso.errors import MsoError
from mso.model.app import MAX_REPLICAS
from mso.planning.placement import Layout
from mso.protocol import kept
from mso.protocol import messages as m
from mso.protocol.authority import generation
from mso.protocol.context import NodeContext
from mso.protocol.dataplane import RETRANSMIT_S
from mso.protocol.effects import SetTimer
from mso.protocol.events import AppMissing, PlacementStale, Retransmit
from mso.protocol.procedures import placement
from mso.protocol.procedures.deploy import Deployer, holders
from mso.protocol.procedures.remap import Remapper
from mso.protocol.state import AppState

# an app learnt from a sync goes on to the nodes heard back empty this long before: heard
# while this node held no app yet (both restarted at once), nobody else may tell them
# (fault seed 44222: a node back with its one neighbour, both empty; the app never reached it)
PASS_ON_S = 5.0


class AppSyncing:
    """What :class:`~.peers.Membership` does to sync apps (it provides these attributes)."""

    ctx: NodeContext
    failed: set[str]
    deployer: Deployer
    recovery: Remapper
    incarnation: int
    _sync_pending: set[str]
    _heard_back: dict[str, float]
    _told_back: dict[str, set[str]]
    _incarnations: dict[str, int]

    def admits(self, node: str, table: Mapping[str, object]) -> bool:
        raise NotImplementedError  # Membership's: whether ``table`` may hold ``node``

    # -- app sync: a node that rejoins (or missed an app) is told it ---------------------------
    def _claim(self, dep: AppState) -> None:
        """Tell the app's nodes where the instances this node runs are (a node that rejoins
        may have spread, or been told, a view in which they run elsewhere: a node of a
        partition's losing side claims the vertices it ran until it resets, and its reset
        tells nobody)."""
        for vid in _claimed(dep):
            placement.announce(self.ctx, dep, vid, self.ctx.id, incarnation=self.incarnation)

    def _claim_to(self, node: str) -> None:
        """Tell ``node``, in reach again, where the instances this node runs are, for every
        app it takes part in: a move made while it was out of reach -- held *unreachable*, not
        failed, so no rejoin sync follows -- reached every member but it. First-hand claims at
        their current version: a receiver that has them already takes nothing. So are the
        vertices this node handed over and knows no later move of, with the incarnation of
        the node it handed them to: if that node restarted since, they went with it, and the
        receiver may be the one to restore them (seed 22770: a move's news lost in a partition
        to the node that coordinates the recovery; the new host died, nobody restored it)."""
        for dep in self.ctx.apps.values():
            if node in placement.members(dep):
                for vid in _claimed(dep):
                    msg = placement.moved(dep, vid, self.ctx.id, self.incarnation)
                    self.ctx.send(node, msg)
                for vid, to in sorted(dep.handed.items()):
                    if vid not in dep.instances and dep.placed.get(vid) == to != node:
                        inc = self.ctx.incarnation_of(to, -1)  # (vanished: with an older one)
                        inc = inc - 1 if vid in dep.vanished and inc > 0 else inc
                        self.ctx.send(node, placement.moved(dep, vid, to, inc))

    def _first_to_hear(self, node: str) -> bool:
        """Whether ``node``, just heard, is one of the first nodes to hear it: a neighbour by
        the routing view, or a node the view has no route to yet (its link came up and the
        routes lag its beats: babeld, the emulator's convergence)."""
        hop = self.ctx.routes.get(node)
        return hop is None or hop[0] == node

    def _syncs(self, dep: AppState, node: str) -> bool:
        """Whether this node tells ``node``, back with nothing, the app ``dep``: it hosts
        part of it (its instances, or its view), or it is among the first to hear ``node``
        (it holds every app it held; a host may be down or back empty itself, seed 91). Not
        every node that holds the app: each node that heard a restart's hello sent it every
        app (999 syncs at 1,000 nodes) -- unless the app has no host left but ``node`` (every
        live vertex placed there, now vanished, or on nodes held failed): then every node that
        holds it does, as no host will (seed 866: a line whose far end alone held the app, the
        restarted node's one neighbour back empty too)."""
        if node not in holders(dep):  # issue 24.1: only the nodes that take part hold it
            return False
        if dep.instances or self.ctx.id in dep.placed.values() or self._first_to_hear(node):
            return True
        return not any(
            n != node and n not in self.failed and v not in dep.vanished
            for v, n in dep.placed.items()
        )

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
        to whom, where we know of no later move than the sync: a node held failed when the
        old host broadcast the move missed its Moved;
        with operator keys, a claim to run a vertex only where our view's host is the sender
        or failed, as a Moved is weighed: any member may send a sync), and its hearsay only
        where our own entry is known bad
        (on a node we hold failed, vanished, or placed here where it does not run) — never
        where we run an instance ourselves, and never a vertex it places here (it holds
        that one vanished with our old incarnation)."""
        ours = set(held.instances) | set(held.awaiting) | set(held.restoring)
        gone = set(msg.vanished)
        signed = self.ctx.authority.signed
        if held.stored and src != self.ctx.id:
            # our view is what our last process kept (mso.protocol.kept), maybe from before
            # moves it made itself: a live node's is as good where it is as new (it may
            # place a vertex here: one that vanished with that process; fault seed 1564)
            held.stored = False
            newer = {  # (the same placement: ours stands, and what we know vanished of it)
                v
                for v, n in msg.placed.items()
                if v in held.placed
                and v not in ours
                and (n, msg.versions.get(v, 0)) != (held.placed[v], held.versions.get(v, 0))
                and msg.versions.get(v, 0) >= held.versions.get(v, 0)
            }
            for v in newer:
                held.placed[v] = msg.placed[v]
                held.versions[v] = max(held.versions.get(v, 0), msg.versions.get(v, 0))
            here = {v for v in newer if msg.placed[v] == self.ctx.id}
            held.vanished.replace((held.vanished - newer) | (newer & gone) | here)
            return
        heard = self._corroborate(src, held, msg, ours)
        # placed on a node in an incarnation older than one heard from it (the sender's own
        # too: a sync sent as its daemon reset, heard after its rejoin): gone with it, no news
        # (fault seed 142461: it undid a vanishing, and nobody restored the vertex)
        outlived = self._outlived(msg)

        def better(v: str, n: str) -> bool:
            if v not in held.placed or v in ours or n == self.ctx.id or v in heard:
                return False
            if v in outlived:
                return False
            mine = held.placed[v]  # first-hand; with operator keys only where a Moved from
            told = not signed or placement.may_tell(held, v, src, self.failed)  # src would be
            if n == src and v not in gone and told:
                return True
            older = msg.versions.get(v, 0) < held.versions.get(v, 0)
            # it ran it and handed it over to n, unless we know of a later move than the
            # sync's (it got the vertex back since: fault seed 273897, a sync sent while the
            # vertex was on its way back to the sender named the move before)
            if mine == src and msg.handed.get(v) == n and not older:
                return True
            if n == mine and v in held.vanished:  # names the node whose old incarnation took
                return False  # it: no news (a claim from that node would be)
            if older:
                return False  # an older view (seed 24380: a node that missed a move)
            bad = mine in self.failed or v in held.vanished or mine == self.ctx.id
            return bad and (v not in gone or v in held.vanished)

        taken = {v for v, n in msg.placed.items() if better(v, n)}
        for v in taken:
            held.placed[v] = msg.placed[v]
            held.versions[v] = max(held.versions.get(v, 0), msg.versions.get(v, 0))
        held.vanished.replace((held.vanished - taken) | (taken & gone))

    def _corroborate(self, src: str, held: AppState, msg: m.AppSync, ours: set[str]) -> set[str]:
        """With operator keys, the vertices a node placed on a sync's word alone (it learnt
        the app from it: no view to weigh that word by) are placed where most senders say,
        one vote a sender, the first word kept on a tie; one is corroborated, and weighed
        from then on as any placement is, once two senders agree. A captured member's first
        sync ("c runs on me") used to stick: the host's own word then came from a node that
        was not c's host in this view. Until then the node does not act on it where the
        node named has not said so itself or another sender names another node (a tie: a
        captured member against the one honest member of a two-member app): the vertex's
        events wait (:meth:`AppState.unconfirmed`). Returns the vertices still on hearsay."""
        for v in [
            v for v, votes in held.hearsay.items() if v in ours or held.placed[v] not in votes
        ]:
            del held.hearsay[v]  # (it runs here now, or a Moved or a restore placed it since)
        for v, votes in list(held.hearsay.items()):
            n = msg.placed.get(v)
            if n is None or n == self.ctx.id:
                continue
            for k in list(votes):
                votes[k].discard(src)  # (a sender's newest word is its vote)
                if not votes[k] and k != held.placed[v]:
                    del votes[k]
            votes.setdefault(n, set()).add(src)
            now = held.placed[v]
            best = max(votes, key=lambda k: (len(votes[k]), k == now))
            held.placed[v] = best
            if len(votes[best]) >= 2:
                del held.hearsay[v]
        return set(held.hearsay)

    def _app_sync(self, dep: AppState) -> m.AppSync:
        handed = {v: n for v, n in dep.handed.items() if v not in dep.instances}
        known = self._incarnations
        hosts = set(dep.placed.values())
        incarnations = {n: known[n] for n in hosts if n in known} | {self.ctx.id: self.incarnation}
        if dep.stored:  # a view our last process kept: for a node not heard since, the
            # incarnation it knew (fault seed 265408: N4, back, synced N1 its view placing `a`
            # on N2 with no incarnation; N1, which had heard N2 back empty, took `a` as
            # running there, and held N2 the coordinator while N2 held N1 it: nobody was)
            stale = dep.kept_incarnations
            incarnations = {n: stale[n] for n in hosts if n in stale} | incarnations
        return kept.record(dep, handed, incarnations)

    def _outlived(self, msg: m.AppSync) -> set[str]:
        """The vertices a sync places on a node in an incarnation older than one we heard
        from it: they went with that incarnation (the sender had not heard of the restart)."""
        return {
            v
            for v, n in msg.placed.items()
            if n != self.ctx.id
            and n in msg.incarnations
            and msg.incarnations[n] < self._incarnations.get(n, -1)
        }

    def learn_incarnations(self, incarnations: Mapping[str, int]) -> None:
        """The incarnations of the nodes a sync or a chain's placement puts vertices on, where
        we know none (this node restarted since, or never heard of them: no node says hello
        to every node at its start): else a node that restarted while out of our reach, first
        heard in its new incarnation, would be taken as running what was placed on it, and
        nothing would restore it."""
        for node, inc in incarnations.items():
            if node == self.ctx.id or node in self.failed or inc < 0:
                continue
            if node not in self._incarnations and self.admits(node, self._incarnations):
                self._incarnations[node] = inc

    def on_app_missing(self, ev: AppMissing) -> None:
        """A live node asked to host a vertex does not hold the app: its sync was lost (the
        node that owed it failed before it could send it; nobody else would). Sync it now,
        or once this node's own view is not in dispute."""
        dep, node = self.ctx.apps.get(ev.app), ev.node
        if dep is None or node in self.failed or node == self.ctx.id or not dep.running:
            return
        if self._disputed() and not ev.ahead:
            self._sync_pending.add(node)
        else:
            self.ctx.send(node, self._app_sync(dep))

    def _heard_empty(self, node: str, now: float) -> None:
        """``node`` is back with no app: note it (bounded, as the nodes admitted are)."""
        for n in [n for n, at in self._heard_back.items() if now - at > PASS_ON_S]:
            del self._heard_back[n]
            self._told_back.pop(n, None)
        self._heard_back[node] = now
        self._told_back[node] = set()

    def _sync_back(self, node: str, dep: AppState) -> None:
        """Sync ``node``, heard back lately, the app: once (an app this node lets go and
        learns again is not passed on again: seed 136149, the node synced twice held it past
        the quiet phase, taking no part)."""
        self._told_back.setdefault(node, set()).add(dep.app.name)
        self.ctx.send(node, self._app_sync(dep))

    def _pass_on(self, src: str, dep: AppState, now: float) -> None:
        """An app just learnt from ``src``'s sync: to the nodes heard back empty lately that
        this node would have synced, had it held the app then."""
        if self._disputed():
            return
        for node, at in sorted(self._heard_back.items()):
            late = now - at > PASS_ON_S or node == src or node in self.failed
            told = dep.app.name in self._told_back.get(node, ())
            if not late and not told and self._syncs(dep, node):
                self._sync_back(node, dep)

    def _flush_syncs(self) -> None:
        """Sync the nodes that rejoined while this node's view was in dispute, once it is not."""
        if not self._sync_pending or self._disputed():
            return
        pending, self._sync_pending = sorted(self._sync_pending), set()
        for node in pending:
            if node in self.failed:
                continue
            for dep in self.ctx.apps.values():
                if dep.running and self._syncs(dep, node):
                    self.ctx.send(node, self._app_sync(dep))

    def on_app_sync(self, src: str, msg: m.AppSync, now: float) -> None:
        held = self.ctx.apps.get(msg.app)
        if self.deployer.revoked(src, msg.app, msg.document):
            return
        signed = self.ctx.authority.signed
        if signed and held is not None and generation(msg.document) != generation(held.document):
            self.ctx.refusal("app_sync_other_deployment")  # (an operator deployed it again since)
            return
        if src != self.ctx.id:  # (our last process's: of nodes maybe restarted since)
            self.learn_incarnations(msg.incarnations)
        # kept by our last process (mso.protocol.kept), and nothing done on it yet: a live
        # node's view is taken as a node back empty takes it (fault seeds 1564, 1614), with
        # what the kept view learnt vanished since where both place it alike (a rejoin heard
        # before this sync, fault seed 451)
        gone_since: set[str] = set()
        counted: dict[str, int] = {}  # the kept view's versions where the sync places alike
        ran_here: dict[str, int] = {}  # moved here at a later move than the sync knows
        if held is not None and held.stored and src != self.ctx.id and _idle(held):
            del self.ctx.apps[msg.app]
            alike = {v for v, n in held.placed.items() if msg.placed.get(v) == n}
            gone_since = held.vanished & alike
            counted = {v: k for v, k in held.versions.items() if v in alike and k > 0}
            ran_here = {
                v: k
                for v, k in held.versions.items()
                if held.placed.get(v) == self.ctx.id and k > msg.versions.get(v, 0)
            }
            held = None
        if held is not None:
            for v, ns in msg.replicas.items():  # (where this node knows none)
                if held.replicas.get(v) and not held.replica_nodes.get(v):
                    held.replica_nodes[v] = [n for n in ns[:MAX_REPLICAS] if isinstance(n, str)]
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
        try:  # the nodes chosen by capability come with the sync (§3.3)
            layout = Layout(app, msg.origin, resolved=msg.resolved)
        except MsoError as exc:
            self.ctx.note_event(now, f"cannot rejoin app {msg.app}: {exc}")
            return
        signed = self.ctx.authority.signed  # then a pinned vertex is where the pin says
        pinned = layout.pinned if signed else {}
        placed = dict(layout.initial_placement()) | {
            v: n for v, n in msg.placed.items() if v in app.vertices and v not in pinned
        }
        mine = src == self.ctx.id  # kept by this node's last process (mso.protocol.kept)
        if mine and set(placed) != set(app.vertices):  # (it was not placed yet: not running)
            self.ctx.note_event(now, f"cannot take app {msg.app} back: it was never placed")
            return
        dep = AppState(app, layout, msg.origin, placed, epoch=msg.epoch, document=msg.document)
        dep.versions = {v: k for v, k in msg.versions.items() if v in app.vertices and k > 0}
        # not lowered: a sync from a view kept from before ours (a daemon restarted too) took
        # its versions back, and a stale word at ours then un-vanished what went with a
        # restart: the app ran nowhere (restart seed 104403)
        for v, k in counted.items():
            dep.versions[v] = max(k, dep.versions.get(v, 0))
        dep.replica_nodes = {  # (bounded as a ReplicaSet is)
            v: [n for n in ns[:MAX_REPLICAS] if isinstance(n, str)]
            for v, ns in msg.replicas.items()
            if dep.replicas.get(v)
        }
        if signed:  # on the sender's word alone (_corroborate)
            dep.hearsay = {
                v: {n: {src}}
                for v, n in placed.items()
                if v in msg.placed and v not in pinned and n != self.ctx.id
            }
        dep.vanished.replace({v for v in msg.vanished if v in app.vertices} | self._outlived(msg))
        if mine:  # kept by its last process
            dep.stored = True
            dep.kept_incarnations = {
                n: k for n, k in msg.incarnations.items() if n != self.ctx.id and k >= 0
            }
        # what the sync places here does not run here (this node held none of the app): it
        # went with this node's last process, or with its reset (seed 122789: the sender had
        # not heard of the reset; held running here, nobody restored it)
        dep.vanished |= {v for v, n in placed.items() if n == self.ctx.id}
        dep.vanished |= {v for v in gone_since if placed.get(v) != src or v in msg.vanished}
        for v, k in ran_here.items():  # first-hand: it ran here at a move later than the
            if v in dep.placed and v not in pinned:  # sync knows of, and went with that
                dep.placed[v], dep.versions[v] = self.ctx.id, k  # process (the sync's host
                dep.vanished.add(v)  # had let the app go: seed 125537, nobody recovered)
        placement.recall(self.ctx, dep)  # (what its last process heard, if later)
        dep.capable = {v: list(ns) for v, ns in msg.capable.items() if v in layout.resolved}
        dep.placed_chains = dep.started_chains = set(range(len(layout.chains)))
        dep.running, dep.started_at = True, now
        dep.placed_at = dict.fromkeys(range(len(layout.chains)), now)
        self.ctx.apps[msg.app] = dep
        # (re)arm go-back-N for the app: a timer left from before a reset may have lapsed
        self.ctx.emit(SetTimer(Retransmit(msg.app), now + RETRANSMIT_S))
        self.recovery.park(dep)
        self.recovery.maybe_recover(dep, now)
        self._pass_on(src, dep, now)
        if mine or src not in msg.placed.values():  # (a host's view is kept up to date)
            self.ctx.publish(PlacementStale(msg.app, sync=True))


def _idle(dep: AppState) -> bool:
    """Nothing of the app runs, starts, is restored or recovered here."""
    busy = dep.instances or dep.awaiting or dep.restoring or dep.recovering is not None
    return not busy


def _claimed(dep: AppState) -> list[str]:
    """The vertices this node runs that it may claim: not one being handed over (its Moved
    follows) nor one a marker is moving."""
    return [
        vid
        for vid, h in sorted(dep.instances.items())
        if h.handing_over is None and vid not in dep.markers
    ]
