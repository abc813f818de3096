"""The coordinator of a move (or a restore): checks it can be made, asks the target to prepare,
switches the producers once it is prepared, ends it at ``HandoverDone``, and fails it (or makes
it a restore) when a node it needs fails; a restore's prepare is asked again until answered.
"""

from __future__ import annotations

from mso.errors import MsoError
from mso.protocol import messages as m
from mso.protocol import warrant
from mso.protocol.context import NodeContext
from mso.protocol.dataplane import DataPlane
from mso.protocol.effects import Reply, SetTimer
from mso.protocol.events import (
    AppMissing,
    Deadline,
    Happened,
    PeerFailed,
    PeerRejoined,
    RecoveryDue,
    RelocationEnded,
    Retry,
)
from mso.protocol.procedures import placement
from mso.protocol.procedures.base import STEP_TIMEOUT_S
from mso.protocol.procedures.relocation._role import Role
from mso.protocol.procedures.relocation._state import (
    STEP_ATTEMPTS,
    SWITCH_DEADLINE_S,
    Relocation,
    RelocationEvent,
    S,
)
from mso.protocol.state import AppState

MAX_FAILED_RESTORES = 64  # remembered to unprepare what a held prepare made after all
SWITCH_AGAIN = -1  # a Retry of a committed move's Switch (not an attempt of its prepare)


class Coordinator(Role):
    """The coordinator of a relocation or a restore: asks, switches the producers, ends."""

    def __init__(self, ctx: NodeContext, dp: DataPlane) -> None:
        super().__init__(ctx, dp)
        # restores that failed here (rid -> (app, vertex)), the last few, and moves that failed
        # before their switch with their target held failed (no Unprepare sent): a prepare
        # held while the target was down may still reach it, and its answer gets an Unprepare
        self._failed_restores: dict[int, tuple[str, str]] = {}

    def request(self, client: int | None, msg: m.RelocateRequest, now: float) -> bool:
        """Coordinate a relocation (a client's, a member's or the rules'); False if refused
        (the client, if any, is told why)."""
        dep = self.ctx.apps.get(msg.app)
        if dep is None or not dep.running:
            self._refuse(client, msg, f"no running app named {msg.app!r}")
            return False
        try:
            target = self.relocation_target(dep, msg.vertex, "" if msg.target else msg.direction)
        except MsoError as exc:
            self._refuse(client, msg, str(exc))
            return False
        target = msg.target or target
        if target != self.ctx.id and target not in self.ctx.routes:
            self._refuse(client, msg, f"target node {target!r} is not reachable")
            return False
        source = dep.placed[msg.vertex]
        if target == source:
            self._refuse(client, msg, f"{msg.vertex!r} already runs on {target}")
            return False
        if msg.vertex in dep.lost(self.ctx.failed):  # no instance to hand over: restored
            why = f"node {source} failed" if source in self.ctx.failed else "its node restarted"
            self._refuse(client, msg, f"{msg.vertex!r} does not run anywhere ({why})")
            return False
        if why := self.cannot_hand_over(dep, msg.vertex):
            self._refuse(client, msg, why)
            return False
        if self.moving(msg.app, msg.vertex):
            self._refuse(client, msg, f"{msg.vertex!r} is already being relocated")
            return False
        pid = self.ctx.new_pid()
        reloc = Relocation(pid, now, msg.app, msg.vertex, source, target, client)
        reloc.order = warrant.carried(msg)
        self.ctx.begin(reloc)
        self.prepare(dep, reloc)
        return True

    def _send_prepare(self, dep: AppState, reloc: Relocation, prepare: m.Prepare) -> None:
        """A ``Prepare``, after the app for a target that may not hold it: only the nodes
        that take part in an app hold it (issue 24.1), so a target that runs none of it by
        this node's view (a node just chosen by capability is pinned, not yet a host), or one
        asked again (it may have let the app go), is sent it first."""
        target = reloc.target
        reloc.briefed = dict(prepare.versions)
        hosts = {dep.origin, *dep.placed.values()}
        if target != self.ctx.id and (target not in hosts or reloc.attempts > 1):
            self.ctx.publish(AppMissing(dep.app.name, target, ahead=True))
        self.ctx.send(target, prepare)

    def prepare(self, dep: AppState, reloc: Relocation) -> None:
        """Ask a move's target to prepare an instance. With operator keys the vertex's host,
        if another node, is told the move too (``Moving``), so it knows the markers that
        will come for it (:class:`mso.protocol.warrant.Leaving`)."""
        order = reloc.order
        self._send_prepare(dep, reloc, placement.prepare(dep, reloc.vertex, reloc.pid, order=order))
        if self.ctx.authority.signed and reloc.source != self.ctx.id:
            moving = m.Moving(reloc.app, reloc.vertex, reloc.pid, reloc.target, order)
            self.ctx.send(reloc.source, moving)

    def moving(self, app: str, vertex: str) -> bool:
        """A relocation or restore of ``vertex`` this node coordinates is under way."""
        return any(r.app == app and r.vertex == vertex for r in self._open())

    def cannot_hand_over(self, dep: AppState, vertex: str) -> str:
        """Why a live instance of ``vertex`` cannot be moved now ("" if it can): its node, or
        the node of a producer whose marker the handover waits for, is out of reach (held
        unreachable, not failed), or that producer is lost (its node failed, or its instance
        vanished with a restart) and not restored yet. Its instance drains and hands over, or
        nothing: a move started anyway waits on a marker that cannot come, past its commit
        (seeds 5449, 8978)."""
        here, routes, failed = self.ctx.id, self.ctx.routes, self.ctx.failed
        source = dep.placed[vertex]
        if source != here and source not in routes:
            return f"{vertex!r} runs on {source}, out of reach: it cannot hand over its state"
        for e in dep.app.edges:
            node = dep.placed.get(e.src, here)
            if e.dst != vertex:
                continue
            if node in failed or e.src in dep.vanished:  # (a parked chain's, or not yet
                # restored): no marker comes from it; a move committed anyway held the
                # vertex's events for its deadline and left nodes disagreeing (seed 71642)
                return f"{vertex!r} takes events from {e.src!r}, lost with {node}"
            if node != here and node not in routes:
                return f"{vertex!r} takes events from {e.src!r} on {node}, out of reach"
        return ""

    def on_relocate_request(self, msg: m.RelocateRequest, now: float) -> None:
        """A relocation asked by another node. Where operator keys are configured that is a
        command a member has no authority for (a node's own rules relocate without asking)."""
        if self.ctx.authority.signed:
            self.ctx.refusal("relocate_from_member")
            return
        if not self.request(None, msg, now):  # refused (no such vertex, no route, ...)
            self.ctx.refusal("relocate_refused")

    def relocation_target(self, dep: AppState, vertex: str, direction: str = "") -> str:
        """Where an upstream or downstream relocation takes ``vertex`` (MsoError if it cannot
        move): upstream is its predecessor's node; downstream is its successor's node or, when
        they share a node, the next node toward the chain's tail."""
        app, lay = dep.app, dep.layout
        if vertex not in app.vertices:
            raise MsoError(f"unknown vertex {vertex!r} in app {app.name!r}")
        for c in lay.chains:
            if vertex in (c.head, c.tail):
                raise MsoError(
                    f"{vertex!r} is an end of chain {c.name}; chain ends are never relocated "
                    f"(it would disturb the chains before or after it)"
                )
        pinned = app.vertices[vertex].pinned
        if pinned is not None:
            raise MsoError(f"{vertex!r} is pinned to {pinned}; pinned vertices are not relocated")
        if not direction:
            return ""
        (pred,) = app.predecessors()[vertex]
        (succ,) = app.successors()[vertex]
        here = dep.placed[vertex]
        if direction == "upstream":
            target = dep.placed[pred]
        elif direction == "downstream":
            target = dep.placed[succ]
            if target == here:
                tail = dep.placed[next(c for c in lay.chains if vertex in c.vertices).tail]
                route = self.ctx.routes.get(tail) if here == self.ctx.id else None
                target = route[0] if route else tail
        else:
            raise MsoError(f"expected direction 'upstream' or 'downstream', got {direction!r}")
        if target == here:
            where = "predecessor's" if direction == "upstream" else "next downstream"
            raise MsoError(f"{vertex!r} already runs on its {where} node {here}")
        return target

    def _refuse(self, client: int | None, msg: m.RelocateRequest, reason: str) -> None:
        if client is not None:
            reply = m.RelocateReply(msg.app, msg.vertex, False, error=reason)
            self.ctx.emit(Reply(client, reply))

    def on_prepared(self, src: str, msg: m.Prepared, now: float) -> None:
        reloc = self._reloc(msg.rid)
        dep = self.ctx.apps.get(msg.app)
        if reloc is not None and src != reloc.target and self.ctx.authority.signed:
            self.ctx.refusal("prepared_not_by_its_target")  # (only the node asked answers)
            return
        if reloc is None or dep is None or (reloc.app, reloc.vertex) != (msg.app, msg.vertex):
            self.ctx.refusal("prepared_unexpected")
            if not msg.error and self._failed_restores.get(msg.rid) == (msg.app, msg.vertex):
                # a restore (or move) that failed here (its target was held failed) prepared
                # anyway: a prepare held while the node was down reaches it when it is back.
                # Nothing will resume or switch to that instance; drop it rather than leave a
                # twin (or a target holding the app for the switch's 60 s).
                self.ctx.send(msg.node, m.Unprepare(msg.app, msg.vertex, msg.rid))
            return
        if msg.error:
            if msg.no_app and reloc.restore and self._sync_again(dep, reloc):
                return
            if msg.no_app:  # a node that missed the app's sync: the retry will find it
                self.ctx.publish(AppMissing(dep.app.name, reloc.target))
                if self._ask_again(dep, reloc, now):
                    return
            self.fail(reloc, msg.error, now)
            return
        reloc.on(RelocationEvent.PREPARED_RESTORE if reloc.restore else RelocationEvent.PREPARED)
        if not reloc.restore:  # committed: the old instance drains what it holds, then hands
            reloc.deadline = max(reloc.deadline, now + SWITCH_DEADLINE_S)  # over; a busy
            self.ctx.set_timer(Deadline(reloc.pid), reloc.deadline)  # vertex may take a while
        if reloc.restore:  # the surviving ends of its edges resume the replacement
            edges, version = dep.app.edges, dep.versions.get(reloc.vertex, 0)
            for edge, producer in reloc.resumes:
                other = dep.placed[edges[edge].src if producer else edges[edge].dst]
                rewire = m.Rewire(msg.app, edge, reloc.target, msg.rid, producer, reloc.order)
                rewire.version = version
                self.ctx.send(other, rewire)
            return
        self._switch(dep, reloc)
        self.ctx.emit(SetTimer(Retry(reloc.pid, SWITCH_AGAIN), now + STEP_TIMEOUT_S))

    def _switch(self, dep: AppState, reloc: Relocation) -> None:
        """Tell each producer of the moving vertex to switch to the target (again, a second
        on: a producer that went out of reach just as the target was prepared never got it,
        and the move waited for its marker the switch's 60 s, the target holding the app;
        restart seed 100429. A producer that switched already drops it: ``AppState.switched``)."""
        for edge, e in enumerate(dep.app.edges):
            if e.dst == reloc.vertex:
                switch = m.Switch(
                    reloc.app, edge, reloc.target, reloc.pid, reloc.source, reloc.order
                )
                self.ctx.send(dep.placed[e.src], switch)

    def _ask_again(self, dep: AppState, reloc: Relocation, now: float) -> bool:
        """A move's target did not hold the app yet (the sync that carries it to a node that
        hosts nothing of it may trail the deploy's reply): ask again once the sync is sent,
        at once (a sync sent just before reaches it first), then on a timer, a few times."""
        if reloc.restore or reloc.state is not S.PREPARING or reloc.attempts >= STEP_ATTEMPTS:
            return False
        reloc.on(RelocationEvent.RETRY)
        reloc.attempts += 1
        if reloc.attempts == 1:
            prepare = placement.prepare(dep, reloc.vertex, reloc.pid, order=reloc.order)
            self._send_prepare(dep, reloc, prepare)
        else:
            self.ctx.emit(SetTimer(Retry(reloc.pid, reloc.attempts), now + STEP_TIMEOUT_S / 4))
        return True

    def _sync_again(self, dep: AppState, reloc: Relocation) -> bool:
        """A restore's target answered that it holds none of the app: the ``AppSync`` sent
        ahead of the ``Prepare`` was lost (or the target let the app go before it came).
        Send the app again with the same ``Prepare`` just behind it, a few times, rather
        than fail the restore (its recovery then ran a second time, on a second target)."""
        if reloc.synced_again >= STEP_ATTEMPTS or reloc.target in self.ctx.failed:
            return False
        reloc.synced_again += 1
        self.ctx.publish(AppMissing(dep.app.name, reloc.target, ahead=True))
        prepare = placement.prepare(dep, reloc.vertex, reloc.pid, True, reloc.resumes, reloc.order)
        reloc.briefed = dict(prepare.versions)
        self.ctx.send(reloc.target, prepare)
        return True

    def on_handover_done(self, src: str, msg: m.HandoverDone, now: float) -> None:
        reloc = self._reloc(msg.rid)
        if reloc is None or (reloc.app, reloc.vertex) != (msg.app, msg.vertex):
            self.ctx.refusal("handover_done_unexpected")
            return
        if src != reloc.target and self.ctx.authority.signed:
            self.ctx.refusal("handover_done_not_by_its_target")
            return
        reloc.on(RelocationEvent.HANDED_OVER)
        self.ctx.end(reloc.pid)
        dep = self.ctx.apps.get(reloc.app)
        # first-hand, from the new host: a coordinator that hosts no part of the app is not
        # told of the move otherwise; a twin of that version (two coordinators restored the
        # vertex, each on the other's node) is ordered as a Moved's is, so a coordinator that
        # runs the twin that prevails keeps it in its view (fault seed 146144: it ran the
        # vertex and placed it on the node that had yielded)
        taken = dep is not None and placement.learn(
            dep, reloc.vertex, reloc.target, msg.version, now, False, placement.prevails(self.ctx)
        )
        if dep is not None and not taken:
            self.ctx.dropped()
        if dep is not None:
            self._brief_again(dep, reloc)
        self._ended(reloc, "")

    def _brief_again(self, dep: AppState, reloc: Relocation) -> None:
        """Tell a move's new host of the moves this node heard of since its ``Prepare``: a
        move announced meanwhile went to the app's members as its announcer knew them, and
        the target, no member yet, missed it (fault seed 175875: two moves at once, ``a`` onto
        N1 and ``b`` off N6; N1 kept ``b`` on N6 for good). The new host takes each as any
        relayed ``Moved``: newer versions win."""
        for v, version in placement.versions(dep).items():
            node = dep.placed.get(v)
            if node is None or node == reloc.target or v == reloc.vertex or v in dep.vanished:
                continue
            if version > reloc.briefed.get(v, 0):
                inc = self.ctx.incarnation if node == self.ctx.id else -1
                self.ctx.send(reloc.target, placement.moved(dep, v, node, inc))

    def fail(self, reloc: Relocation, why: str, now: float) -> None:
        """A relocation or restore failed: whoever waits (a client, a remap) is told. If no
        producer had switched yet, the target drops the instance it prepared."""
        unprepared = reloc.state is S.PREPARING and reloc.target not in self.ctx.failed
        if unprepared:
            self.ctx.send(reloc.target, m.Unprepare(reloc.app, reloc.vertex, reloc.pid))
        # (a move's target seen restarting as it prepared: its new incarnation took the
        # Prepare and waited for a switch for 60 s, holding the app; restart seed 100772)
        if reloc.restore or (reloc.state is S.PREPARING and not unprepared):
            self._failed_restores[reloc.pid] = (reloc.app, reloc.vertex)
            while len(self._failed_restores) > MAX_FAILED_RESTORES:
                del self._failed_restores[next(iter(self._failed_restores))]
        reloc.fail(self.ctx, why)
        self.ctx.end(reloc.pid)
        self._ended(reloc, why)

    def _ended(self, reloc: Relocation, error: str) -> None:
        """Tell whoever waits for a relocation how it ended: its client, and (by an internal
        event) whoever started it: a remap, a crash restore."""
        if error:
            reloc.tell_client(self.ctx, reloc.refusal(error))
        else:
            elapsed = self.ctx.elapsed_ms(reloc.started_at)
            reloc.tell_client(
                self.ctx, m.RelocateReply(reloc.app, reloc.vertex, True, reloc.target, elapsed)
            )
        ended = RelocationEnded(
            reloc.pid, reloc.app, reloc.vertex, reloc.target, reloc.remap, error
        )
        self.ctx.publish(ended)
        self.ctx.publish(
            Happened(
                reloc.name,
                reloc.app,
                reloc.vertex,
                f"{reloc.source} -> {reloc.target}",
                by=who_asked(reloc),
                took_ms=round(self.ctx.elapsed_ms(reloc.started_at), 3),
                error=error,
            )
        )

    def expire(self, reloc: Relocation, now: float) -> None:
        why = f"{reloc.name} did not finish within {reloc.deadline - reloc.started_at:g} s"
        self.fail(reloc, why, now)

    def on_peer_failed(self, ev: PeerFailed) -> None:
        """Moves that needed the failed node: before the switch they fail; a committed move
        whose old host failed becomes a restore at its target."""
        node, now = ev.node, self.ctx.now
        for reloc in self._open():
            if reloc.restore and node == reloc.target:
                # the replacement died with its host (or never started there): this restore
                # is over, so that the recovery this failure starts may place the vertex
                # anew; a prepare still on its way to the node is refused when answered
                self.fail(reloc, f"node {node} failed while {reloc.vertex!r} was restored", now)
                continue
            if reloc.restore or node not in (reloc.source, reloc.target):
                continue
            dep = self.ctx.apps.get(reloc.app)
            if node == reloc.source and reloc.state is S.SWITCHING and dep is not None:
                # committed: producers send to the new instance, which waits for a handover
                # the old host will never send; restore the vertex there instead
                reloc.on(RelocationEvent.SOURCE_FAILED)
                self.start_restore(dep, reloc, reloc.pid, now)
                continue
            self.fail(reloc, f"node {node} failed during the relocation of {reloc.vertex!r}", now)

    def on_peer_rejoined(self, ev: PeerRejoined) -> None:
        """A move's end heard back in a later incarnation, never held failed here: its
        instances went with its last process, as with a failure (fault seed 230733: the
        target of a remap's move restarted before the handover; its coordinator, which never
        held it failed, waited out the move's deadline, past the quiet phase, holding an app
        it took no part in)."""
        if ev.restarted:
            self.on_peer_failed(PeerFailed(ev.node))

    def start_restore(self, dep: AppState, reloc: Relocation, rid: int, now: float) -> None:
        """Start a replacement for ``reloc.vertex`` on ``reloc.target``: its surviving
        producers replay what it had not passed on, its consumers say where they stand."""
        if not reloc.restore:
            reloc.as_restore(now)
            self.ctx.emit(SetTimer(Deadline(rid), reloc.deadline))
        edges = dep.app.edges
        lost = dep.lost(self.ctx.failed)
        reloc.resumes = [
            [i, True] for i, e in enumerate(edges) if e.dst == reloc.vertex and e.src not in lost
        ] + [[i, False] for i, e in enumerate(edges) if e.src == reloc.vertex and e.dst not in lost]
        reloc.attempts += 1
        if reloc.restored_at is None:
            reloc.restored_at = dep.versions.get(reloc.vertex, 0)
        prepare = placement.prepare(dep, reloc.vertex, rid, True, reloc.resumes, reloc.order)
        self._send_prepare(dep, reloc, prepare)
        self.ctx.emit(SetTimer(Retry(rid, reloc.attempts), now + STEP_TIMEOUT_S))

    def on_retry(self, key: Retry, now: float) -> None:
        """A restore's prepare was not answered in time: ask again, a few times."""
        rid = key.pid
        reloc = self._reloc(rid)
        dep = self.ctx.apps.get(reloc.app) if reloc is not None else None
        if reloc is None or dep is None:
            return
        if key.attempt == SWITCH_AGAIN:  # a move with no handover yet: the switch again
            if not reloc.restore and reloc.state is S.SWITCHING:
                reloc.on(RelocationEvent.RETRY)
                self._switch(dep, reloc)
                self.ctx.emit(SetTimer(Retry(rid, SWITCH_AGAIN), now + STEP_TIMEOUT_S))
            return
        if not reloc.restore:  # a move's target that did not hold the app (_ask_again)
            if reloc.state is S.PREPARING and key.attempt == reloc.attempts:
                prepare = placement.prepare(dep, reloc.vertex, rid, order=reloc.order)
                self._send_prepare(dep, reloc, prepare)
            return
        if reloc.attempts >= STEP_ATTEMPTS or reloc.target in self.ctx.failed:
            why = f"restoring {reloc.vertex!r} on {reloc.target} did not complete"
            self.fail(reloc, why, now)
            return
        where = dep.placed[reloc.vertex]
        lost = reloc.vertex in dep.lost(self.ctx.failed)
        # a later move than this restore began on, onto a live node, held lost only as it was
        # when it began (a relayed word keeps a vertex vanished: it says where, not that it
        # survived; fault seed 274022): its ends were asked on a view from before that move
        later = dep.versions.get(reloc.vertex, 0) > (reloc.restored_at or 0)
        if where != reloc.target and (not lost or (later and where not in self.ctx.failed)):
            # restored meanwhile by another coordinator (its target tells only the newest
            # one) and maybe moved since: asked again, the target would start a second
            # instance. Done; an instance prepared for this restore and never resumed is
            # dropped. (Placed on our target, it is still ours: a replacement waiting for an
            # end that was lost since is asked again, without that end.)
            self.ctx.send(reloc.target, m.Unprepare(reloc.app, reloc.vertex, reloc.pid))
            reloc.on(RelocationEvent.HANDED_OVER)
            self.ctx.end(reloc.pid)
            reloc.target = where
            self._ended(reloc, "")
            if lost:  # held lost there too: the recovery rule looks at it on this view
                self.ctx.publish(RecoveryDue(reloc.app))
            return
        reloc.on(RelocationEvent.RETRY)
        if reloc.retried is not None:  # a recovery's record of what it sent again
            reloc.retried.append(f"restore {reloc.vertex} on {reloc.target}")
        self.start_restore(dep, reloc, rid, now)  # idempotent at every end: just ask again


def who_asked(reloc: Relocation) -> str:
    """Who a move is for, in words for its log line: an operator's request, a step of a remap,
    a restore (a crash or a failure), else this node's rules."""
    if reloc.client is not None:
        return "operator"
    if reloc.remap is not None:
        return "remap"
    return "recovery" if reloc.restore else "rule"
