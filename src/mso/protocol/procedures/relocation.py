"""Relocation (§3.4.1), every role in one place: the coordinator (relocation and restore modes),
the producer, the old host and the new host.

A *relocation* moves a running vertex with its state and loses no event::

    coordinator           new host            producer(s)           old host
      Prepare  ──────────▶  host an instance
               ◀──────────  Prepared (once started)
      Switch   ─────────────────────────────▶  send to the new host;
                                               Marker ─────────────▶  drain to the marker(s)
                                                                      snapshot
                            Handover  ◀─────────────────────────────  state + channels
               ◀──────────  HandoverDone       (the old host tells everyone: Moved)

The coordinator's :class:`Relocation` is PREPARING, then SWITCHING once the new instance is
prepared and the producers are told to switch, then FINISHED at ``HandoverDone``. Before the
switch a failure (a refusal, a node it needs failing, its deadline) ends it and the target drops
the instance it prepared (``Unprepare``); once producers have switched the move is committed, and
if the old host fails the move becomes a *restore* at the same target (``source_failed``).

A *restore* replaces an instance lost with a failed node (or a crashed one): PREPARING (the target
creates the instance) → RESUMING (the surviving ends of its edges say where they stand and
replay: their roles are in :mod:`.restore`) → FINISHED when the replacement runs. Its prepare
is retried (``Retry``) a few times, since messages to a node behind a failure can be lost while
routes converge. A step arriving in the wrong state raises :class:`IllegalTransition`. With
operator keys a step from another node is taken only on a warrant (:mod:`mso.protocol.warrant`).
"""

from __future__ import annotations

import enum
from typing import Any, ClassVar

from mso.errors import MsoError
from mso.model.app import MAX_REPLICAS
from mso.protocol import effects as fx
from mso.protocol import messages as m
from mso.protocol import provenance, warrant
from mso.protocol.channel import AckGate, InChannel
from mso.protocol.context import NodeContext
from mso.protocol.dataplane import DataPlane
from mso.protocol.effects import Reply, Send, SetTimer
from mso.protocol.events import (
    AppMissing,
    Deadline,
    Happened,
    InstanceFailed,
    InstanceReady,
    MarkerReached,
    PeerFailed,
    RelocationEnded,
    ReplacementPrepared,
    Retry,
    Snapshotted,
)
from mso.protocol.procedures import placement
from mso.protocol.procedures.base import STEP_TIMEOUT_S, Phase, Procedure, Table
from mso.protocol.procedures.instance import InstanceEvent
from mso.protocol.state import AppState, Restoring

# once producers have switched, the move is committed: the old instance hands over after it has
# processed everything before the markers, which a slow vertex may take a while to do
SWITCH_DEADLINE_S = 60.0
MAX_FAILED_RESTORES = 64  # remembered to unprepare what a held prepare made after all
STEP_ATTEMPTS = 5


class S(enum.Enum):
    PREPARING = "preparing"
    SWITCHING = "switching"
    RESUMING = "resuming"


class RelocationEvent(enum.Enum):
    """What moves a Relocation along its table."""

    PREPARED = "prepared"
    PREPARED_RESTORE = "prepared_restore"
    RETRY = "retry"
    HANDED_OVER = "handed_over"
    SOURCE_FAILED = "source_failed"


class Relocation(Procedure):
    """A relocation (or, with ``restore``, a restore) this node coordinates."""

    NAME = "relocation"
    INITIAL = S.PREPARING
    DEADLINE_S = 5.0
    TRANSITIONS: ClassVar[Table] = {
        S.PREPARING: {
            RelocationEvent.PREPARED: S.SWITCHING,
            RelocationEvent.PREPARED_RESTORE: S.RESUMING,
            RelocationEvent.RETRY: S.PREPARING,
            RelocationEvent.HANDED_OVER: Phase.FINISHED,  # a restore of a vertex that never went
        },
        # the old host failed after producers switched: its instance and what it held are
        # gone, the new one waits for a handover that never comes; it is restored instead
        S.SWITCHING: {
            RelocationEvent.HANDED_OVER: Phase.FINISHED,
            RelocationEvent.SOURCE_FAILED: S.RESUMING,
        },
        # a restore's prepare is re-sent until answered: answers may come more than once
        S.RESUMING: {
            RelocationEvent.PREPARED_RESTORE: S.RESUMING,
            RelocationEvent.HANDED_OVER: Phase.FINISHED,
            RelocationEvent.RETRY: S.RESUMING,
        },
    }

    def __init__(
        self,
        pid: int,
        now: float,
        app: str,
        vertex: str,
        source: str,
        target: str,
        client: int | None,
        remap: int | None = None,
    ) -> None:
        super().__init__(pid, now)
        self.app = app
        self.vertex = vertex
        self.source = source  # node the vertex leaves
        self.target = target  # node it goes to
        self.client = client
        self.remap = remap  # the remap this relocation is a step of
        # a restore: no marker, no handover; the surviving ends of its edges resume it
        # (``resumes``: [edge, the other end is the producer])
        self.restore = False
        self.resumes: list[list[Any]] = []
        self.attempts = 0
        self.retried: list[str] | None = None  # a recovery's log of steps sent again
        self.order = b""  # the operator's order it carries out, for its steps' receivers

    def as_restore(self, now: float | None = None) -> None:
        """Become a restore, with a restore's deadline from ``now`` (a committed relocation
        whose old host failed) or from the start."""
        self.restore = True
        since = self.started_at if now is None else max(self.started_at, now)
        self.deadline = since + STEP_TIMEOUT_S * (STEP_ATTEMPTS + 1)

    @property
    def name(self) -> str:
        return "restore" if self.restore else self.NAME

    def describe(self) -> dict[str, Any]:
        return super().describe() | {
            "app": self.app,
            "vertex": self.vertex,
            "from": self.source,
            "to": self.target,
        }


class Relocator:
    """This node's part in relocations and restores, in every role (module docstring)."""

    def __init__(self, ctx: NodeContext, dp: DataPlane) -> None:
        self.ctx = ctx
        self.dp = dp
        self._handover_to: dict[int, str] = {}  # rid -> coordinator, at a move's new host
        # at a move's new host: output events sent ahead of the handover, and a handover that
        # came before all of them (rid -> edge -> [(first, events)]; rid -> (from, handover))
        self._parts: dict[int, dict[int, list[tuple[int, list[bytes]]]]] = {}
        self._early: dict[int, tuple[str, m.Handover]] = {}
        # restores that failed here (rid -> (app, vertex)), the last few: a prepare held while
        # the target was down may still reach it, and its answer gets an Unprepare
        self._failed_restores: dict[int, tuple[str, str]] = {}
        # at a move's new host: the node its Prepare said the vertex leaves, and the vertex's
        # host in this node's view when asked (rid -> nodes), the only ones whose handover it
        # takes (with operator keys; a target that took no part in the app since a move of
        # the vertex missed its Moved: its own view alone had the handover refused, and the
        # vertex lost)
        self._sources: dict[int, set[str]] = {}
        # at a move's new host: the move each instance awaiting a handover was prepared for,
        # and when ((app, vertex) -> (rid, since)): another move's Prepare meanwhile is refused
        self._twins: dict[tuple[str, str], tuple[int, float]] = {}
        self.orders = warrant.Orders()  # operator orders taken (mso.protocol.warrant)
        self.leaving = warrant.Leaving()  # moves of vertices hosted here, told and warranted

    def _reloc(self, pid: int) -> Relocation | None:
        proc = self.ctx.procedure(pid)
        return proc if isinstance(proc, Relocation) else None

    def _open(self) -> list[Relocation]:
        return [p for p in self.ctx.open() if isinstance(p, Relocation)]

    def forget(self, rid: int) -> None:
        """A restore's replacement ran or was dropped: no handover will be reported for it."""
        self._handover_to.pop(rid, None)
        self._parts.pop(rid, None)
        self._early.pop(rid, None)
        self._sources.pop(rid, None)

    def on_reset(self) -> None:
        self.leaving.clear()
        self._twins.clear()
        self._handover_to.clear()
        self._parts.clear()
        self._early.clear()
        self._sources.clear()

    def unwarranted(
        self, dep: AppState, src: str, vertex: str, rid: int, order: bytes, paced: bool = True
    ) -> bool:
        """A step of a move that does not trace to a decision this node can check (with
        operator keys: :func:`mso.protocol.warrant.refused`; ``paced``: a chain end's move
        counts against its interval here); counted by why."""
        ctx = self.ctx
        why = warrant.refused(
            dep,
            ctx.id,
            src,
            vertex,
            rid,
            order,
            ctx.failed,
            ctx.authority,
            self.orders,
            ctx.now,
            paced=paced,
        )
        if why:
            ctx.refusal(f"move_{why}")
        return bool(why)

    # -- the coordinator: asks, switches the producers, ends (a restore: retries) --------------
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

    def prepare(self, dep: AppState, reloc: Relocation) -> None:
        """Ask a move's target to prepare an instance. With operator keys the vertex's host,
        if another node, is told the move too (``Moving``), so it knows the markers that
        will come for it (:class:`mso.protocol.warrant.Leaving`)."""
        order = reloc.order
        self.ctx.send(reloc.target, placement.prepare(dep, reloc.vertex, reloc.pid, order=order))
        if self.ctx.authority.signed and reloc.source != self.ctx.id:
            moving = m.Moving(reloc.app, reloc.vertex, reloc.pid, reloc.target, order)
            self.ctx.send(reloc.source, moving)

    def on_moving(self, src: str, msg: m.Moving, now: float) -> None:
        """At a move's old host: the coordinator tells it the move, with its warrant; the
        move's markers that came first are taken now."""
        dep = self.ctx.apps.get(msg.app)
        if dep is None or msg.vertex not in dep.instances or msg.to == self.ctx.id:
            self.ctx.refusal("moving_unexpected")
            return
        # (a chain end's pace is kept by the move's target and producers, whose refusals end
        # it before or instead of its switch; the host refusing alone would stop the stream:
        # a producer switched, and the host kept the vertex)
        if self.unwarranted(dep, src, msg.vertex, msg.rid, msg.order, paced=False):
            return
        for marker in self.leaving.warranted(msg.app, msg.vertex, msg.rid, msg.to, now):
            self.dp.on_marker_msg(marker, now)

    def on_marker(self, src: str, msg: m.Marker, now: float) -> None:
        """A marker of a move of a vertex hosted here. With operator keys it hands the vertex
        over only for a move this node coordinates or was told of with a warrant; before
        that it waits (refused, counted, if none comes within the move's deadline). And only
        from its edge's producer: the host of the edge's producer in this node's view sends
        it (:meth:`on_switch`); a marker from any other node waits until the view says that
        node hosts the producer (a move of the producer this node has not heard of yet), or
        is refused, counted, at the move's deadline: a member that knew a running move's
        number and target used to end one edge's drain early."""
        dep = self.ctx.apps.get(msg.app)
        if self.ctx.authority.signed and dep is not None and 0 <= msg.edge < len(dep.app.edges):
            edge = dep.app.edges[msg.edge]
            vid = edge.dst
            hosted = vid in dep.instances and msg.to != self.ctx.id
            if hosted and dep.placed.get(edge.src) != src:
                self.leaving.stray(msg.app, vid, src, msg, now)
                return
            ours = any(
                (r.app, r.vertex, r.pid, r.target) == (msg.app, vid, msg.rid, msg.to)
                for r in self._open()
            )
            if hosted and not ours and not self.leaving.takes(msg.app, vid, msg):
                self.leaving.hold(msg.app, vid, msg, now)
                return
        self.dp.on_marker_msg(msg, now)

    def expire_held(self, now: float) -> None:
        """Markers from a node the view now places their edge's producer on are taken;
        markers whose move never got a warrant here, or that never came from their edge's
        producer, are refused, counted."""
        for sender, msg in self.leaving.strays():
            dep = self.ctx.apps.get(msg.app)
            edges = dep.app.edges if dep is not None else []
            if (
                dep is not None
                and msg.edge < len(edges)
                and dep.placed.get(edges[msg.edge].src) == sender
            ):
                self.leaving.unstray(sender, msg)
                self.on_marker(sender, msg, now)
        unwarranted, strays = self.leaving.expire(now)
        for _ in range(unwarranted):
            self.ctx.refusal("marker_no_warrant")
        for _ in range(strays):
            self.ctx.refusal("marker_not_from_its_producer")

    def moving(self, app: str, vertex: str) -> bool:
        """A relocation or restore of ``vertex`` this node coordinates is under way."""
        return any(r.app == app and r.vertex == vertex for r in self._open())

    def cannot_hand_over(self, dep: AppState, vertex: str) -> str:
        """Why a live instance of ``vertex`` cannot be moved now ("" if it can): its node, or
        the node of a producer whose marker the handover waits for, is out of reach (held
        unreachable, not failed). Its instance drains and hands over, or nothing: a move
        started anyway waits on a marker that cannot come, past its commit (seeds 5449, 8978)."""
        here, routes, failed = self.ctx.id, self.ctx.routes, self.ctx.failed
        source = dep.placed[vertex]
        if source != here and source not in routes:
            return f"{vertex!r} runs on {source}, out of reach: it cannot hand over its state"
        for e in dep.app.edges:
            node = dep.placed.get(e.src, here)
            if e.dst == vertex and node != here and node not in routes and node not in failed:
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
                # a restore that failed here (its target was held failed) prepared anyway: a
                # prepare held while the node was down reaches it when it is back. Nothing
                # will resume that instance; drop it rather than leave a twin.
                self.ctx.send(msg.node, m.Unprepare(msg.app, msg.vertex, msg.rid))
            return
        if msg.error:
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
        for e in dep.app.edges:
            if e.dst == msg.vertex:
                edge = dep.app.edges.index(e)
                switch = m.Switch(msg.app, edge, reloc.target, msg.rid, reloc.source, reloc.order)
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
            self.ctx.send(reloc.target, prepare)
        else:
            self.ctx.emit(SetTimer(Retry(reloc.pid, reloc.attempts), now + STEP_TIMEOUT_S / 4))
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
        # told of the move otherwise
        taken = dep is not None and placement.learn(
            dep, reloc.vertex, reloc.target, msg.version, now, running=False
        )
        if dep is not None and not taken:
            self.ctx.dropped()
        self._ended(reloc, "")

    def fail(self, reloc: Relocation, why: str, now: float) -> None:
        """A relocation or restore failed: whoever waits (a client, a remap) is told. If no
        producer had switched yet, the target drops the instance it prepared."""
        if reloc.state is S.PREPARING and reloc.target not in self.ctx.failed:
            self.ctx.send(reloc.target, m.Unprepare(reloc.app, reloc.vertex, reloc.pid))
        if reloc.restore:
            self._failed_restores[reloc.pid] = (reloc.app, reloc.vertex)
            while len(self._failed_restores) > MAX_FAILED_RESTORES:
                del self._failed_restores[next(iter(self._failed_restores))]
        reloc.fail(self.ctx, why)
        self.ctx.end(reloc.pid)
        self._ended(reloc, why)

    def _ended(self, reloc: Relocation, error: str) -> None:
        """Tell whoever waits for a relocation how it ended: its client, and (by an internal
        event) whoever started it: a remap, a crash restore."""
        if reloc.client is not None and error:
            self._refuse(reloc.client, m.RelocateRequest(reloc.app, reloc.vertex), error)
        elif reloc.client is not None:
            elapsed = self.ctx.elapsed_ms(reloc.started_at)
            reply = m.RelocateReply(reloc.app, reloc.vertex, True, reloc.target, elapsed)
            self.ctx.emit(Reply(reloc.client, reply))
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
        prepare = placement.prepare(dep, reloc.vertex, rid, True, reloc.resumes, reloc.order)
        self.ctx.send(reloc.target, prepare)
        self.ctx.emit(SetTimer(Retry(rid, reloc.attempts), now + STEP_TIMEOUT_S))

    def on_retry(self, key: Retry, now: float) -> None:
        """A restore's prepare was not answered in time: ask again, a few times."""
        rid = key.pid
        reloc = self._reloc(rid)
        dep = self.ctx.apps.get(reloc.app) if reloc is not None else None
        if reloc is None or dep is None:
            return
        if not reloc.restore:  # a move's target that did not hold the app (_ask_again)
            if reloc.state is S.PREPARING and key.attempt == reloc.attempts:
                prepare = placement.prepare(dep, reloc.vertex, rid, order=reloc.order)
                self.ctx.send(reloc.target, prepare)
            return
        if reloc.attempts >= STEP_ATTEMPTS or reloc.target in self.ctx.failed:
            why = f"restoring {reloc.vertex!r} on {reloc.target} did not complete"
            self.fail(reloc, why, now)
            return
        where = dep.placed[reloc.vertex]
        if where != reloc.target and reloc.vertex not in dep.lost(self.ctx.failed):
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
            return
        reloc.on(RelocationEvent.RETRY)
        if reloc.retried is not None:  # a recovery's record of what it sent again
            reloc.retried.append(f"restore {reloc.vertex} on {reloc.target}")
        self.start_restore(dep, reloc, rid, now)  # idempotent at every end: just ask again

    # -- the new host: prepares an instance, takes the handover --------------------------------
    def on_prepare(self, src: str, msg: m.Prepare) -> None:
        """At a relocation's (or restore's) target: create the new instance; it is
        Prepared once the executor has started it (or refused if its code fails)."""
        dep = self.ctx.apps.get(msg.app)
        error = ""
        vid = msg.vertex
        resumes = _resumes(dep, vid, msg.resumes) if dep is not None else set()
        if resumes is None:
            self.ctx.refusal("prepare_malformed_resumes")
            return
        if dep is None:
            error = f"{self.ctx.id} does not run app {msg.app!r}"
            self.ctx.send(src, m.Prepared(msg.app, vid, msg.rid, self.ctx.id, error, no_app=True))
            return
        if vid in dep.app.vertices and self.unwarranted(dep, src, vid, msg.rid, msg.order):
            if not msg.restore:  # its coordinator hears at once (a restore's asks again: by
                why = f"refused: {self.ctx.id} sees no warrant for moving {vid!r}"  # then we
                self.ctx.send(src, m.Prepared(msg.app, vid, msg.rid, self.ctx.id, why))
            return  # may hold the failure it follows)
        signed = self.ctx.authority.signed
        failed = self.ctx.failed if signed else None  # (a view restricted as a Moved is)
        source = dep.placed.get(vid, "")
        briefed = signed and not dep.instances and warrant.could_take(dep, src, vid)
        placement.merge(
            dep, src, msg.placed, msg.versions, msg.vanished, self.ctx.now, failed, here=self.ctx.id
        )
        if briefed and vid in dep.app.vertices:  # (a target told of none of the app's moves)
            placement.brief(dep, vid, msg.placed, msg.versions, self.ctx.now)
        if msg.restore and dep.replicas.get(vid) and not dep.replica_nodes.get(vid):
            dep.replica_nodes[vid] = list(msg.replicas[:MAX_REPLICAS])  # (as a ReplicaSet)
        if vid in dep.app.vertices and msg.restore and self._restored_since(dep, vid, src, msg):
            return
        twin = self._twins.get((msg.app, vid)) if vid in dep.awaiting else None
        if twin is not None and (twin[0] == msg.rid or vid in dep.restoring):
            twin = None  # (asked again; or a restore took the instance over)
        if twin is not None and self.ctx.now - twin[1] > SWITCH_DEADLINE_S:
            self._abandon(dep, vid, twin[0])  # its move is past its deadline: given up
            twin = None
        if vid not in dep.app.vertices:
            error = f"{self.ctx.id}: unknown vertex {vid!r}"
        elif twin is not None and not msg.restore:  # its handover would be refused here
            error = f"{self.ctx.id} holds {vid!r} prepared for another move"
        elif vid not in dep.instances and vid not in dep.awaiting:
            dep.awaiting[vid] = self.dp.host(dep, vid)
            dep.preparing[vid] = (msg.rid, src, msg.restore)
            self._handover_to[msg.rid] = src
            if not msg.restore:
                self._sources[msg.rid] = {source, msg.placed.get(vid, source)}
                self._twins[(msg.app, vid)] = (msg.rid, self.ctx.now)
            if msg.restore:
                dep.restoring[vid] = Restoring(msg.rid, src, resumes)
            return
        elif msg.restore and vid in dep.instances:  # it never went: nothing to restore
            self.ctx.send(src, m.Prepared(msg.app, vid, msg.rid, self.ctx.id, error))
            version = dep.versions.get(vid, 0)
            self.ctx.send(src, m.HandoverDone(dep.app.name, vid, msg.rid, self.ctx.id, version))
            inc = self.ctx.incarnation
            placement.announce(self.ctx, dep, vid, self.ctx.id, incarnation=inc, also=[src])
            return
        elif msg.restore and vid in dep.awaiting:  # asked again, maybe by a new
            old = dep.restoring.get(vid)  # coordinator after the first one failed
            if old is None or old.rid != msg.rid:
                dep.restoring[vid] = Restoring(msg.rid, src, resumes)
                self._handover_to[msg.rid] = src
            else:  # a retry: an end lost since (its node reset) will not resume any more; it
                old.pending &= resumes  # is restored later
            if vid in dep.preparing:  # still starting: Prepared goes to the newest asker
                dep.preparing[vid] = (msg.rid, src, True)
                return
        self.ctx.send(src, m.Prepared(msg.app, vid, msg.rid, self.ctx.id, error))
        if not error and msg.restore:  # the replacement may have no end to wait for
            self.ctx.publish(ReplacementPrepared(msg.app, vid))

    def _restored_since(self, dep: AppState, vid: str, src: str, msg: m.Prepare) -> bool:
        """A restore asked on a view older than ours: we know ``vid`` runs on a live node at
        a later move than the coordinator does (restored there since, by a coordinator it
        did not hear of). A second instance here would start without the positions the
        running one has and make its consumers drop what it sends as repeats: refused, and
        the coordinator told where it runs (its recovery is tried again on that view)."""
        where, version = dep.placed.get(vid), dep.versions.get(vid, 0)
        if (
            where is None
            or where == self.ctx.id
            or where in self.ctx.failed
            or vid in dep.vanished
            or version <= msg.versions.get(vid, 0)
        ):
            return False
        self.ctx.refusal("restore_of_a_vertex_restored_since")
        self.ctx.send(src, m.Moved(dep.app.name, vid, where, -1, version))
        why = f"{vid!r} runs on {where} since (move {version}); not restored on {self.ctx.id}"
        self.ctx.send(src, m.Prepared(dep.app.name, vid, msg.rid, self.ctx.id, why))
        return True

    def on_instance_ready(self, ev: InstanceReady) -> None:
        """A move's new instance started: the coordinator hears it is prepared."""
        dep, vid = self.ctx.apps.get(ev.app), ev.vertex
        prep = dep.preparing.pop(vid, None) if dep is not None else None
        if dep is not None and prep is not None:  # a relocation's or a restore's
            rid, coordinator, restore = prep
            self.ctx.send(coordinator, m.Prepared(dep.app.name, vid, rid, self.ctx.id, ""))
            if restore:  # the replacement may have no end to wait for
                self.ctx.publish(ReplacementPrepared(dep.app.name, vid))

    def on_instance_failed(self, ev: InstanceFailed) -> None:
        """A move's new instance failed to start: the coordinator hears why."""
        dep, vid, error = self.ctx.apps.get(ev.app), ev.vertex, ev.error
        prep = dep.preparing.pop(vid, None) if dep is not None else None
        if dep is not None and prep is not None:
            dep.restoring.pop(vid, None)
            self._handover_to.pop(prep[0], None)
            self.ctx.send(prep[1], m.Prepared(dep.app.name, vid, prep[0], self.ctx.id, error))

    def on_unprepare(self, src: str, msg: m.Unprepare, now: float) -> None:
        """At a failed move's target: drop the instance prepared for it (nothing was switched
        to it, so nothing is lost). With operator keys, only the move's coordinator says so."""
        dep = self.ctx.apps.get(msg.app)
        if dep is None:
            self.ctx.refusal("unprepare_unexpected")
            return
        h = dep.awaiting.get(msg.vertex)
        prep = dep.preparing.get(msg.vertex)
        restoring = dep.restoring.get(msg.vertex)
        ours = msg.rid in self._handover_to or (prep is not None and prep[0] == msg.rid)
        if h is None or not ours or (restoring is not None and restoring.rid != msg.rid):
            self.ctx.refusal("unprepare_unexpected")  # (another move took the instance over since)
            return
        asker = self._handover_to.get(msg.rid, prep[1] if prep is not None else src)
        if src not in (asker, self.ctx.id) and self.ctx.authority.signed:
            self.ctx.refusal("unprepare_not_by_its_coordinator")
            return
        self._abandon(dep, msg.vertex, msg.rid)

    def _abandon(self, dep: AppState, vid: str, rid: int) -> None:
        """Drop the instance of ``vid`` prepared here for move ``rid``, which failed."""
        self.dp.stop(dep.awaiting.pop(vid), "abandoned")
        dep.preparing.pop(vid, None)
        dep.restoring.pop(vid, None)
        self._twins.pop((dep.app.name, vid), None)
        self.forget(rid)
        for i, e in enumerate(dep.app.edges):
            if e.dst == vid:
                dep.stash.pop(i, None)
        self.ctx.note_event(self.ctx.now, f"dropped {vid}, prepared for a move that failed")

    def on_handover_events(self, src: str, msg: m.HandoverEvents, now: float) -> None:
        """Output events of a move, ahead of its handover: kept until it comes."""
        dep = self.ctx.apps.get(msg.app)
        ok = dep is not None and msg.vertex in dep.awaiting and 0 <= msg.edge < len(dep.app.edges)
        if not ok or dep is None or dep.app.edges[msg.edge].src != msg.vertex:
            self.ctx.refusal("handover_unexpected")
            return
        if self._not_its_source(src, msg.rid):
            return
        self._parts.setdefault(msg.rid, {}).setdefault(msg.edge, []).append((msg.first, msg.events))
        early = self._early.get(msg.rid)
        if early is not None and self._complete(early[1]):
            del self._early[msg.rid]
            self.on_handover(early[0], early[1], now)

    def _complete(self, msg: m.Handover) -> bool:
        return sum(map(len, self._parts.get(msg.rid, {}).values())) >= msg.parts

    def on_handover(self, src: str, msg: m.Handover, now: float) -> None:
        dep = self.ctx.apps.get(msg.app)
        if dep is None or msg.vertex not in dep.awaiting:
            self.ctx.refusal("handover_unexpected")
            return
        shapes = [len(v) >= 2 for v in msg.inputs.values()]
        shapes += [len(v) == 4 for v in msg.outputs.values()]
        if not all(shapes):  # (no genuine node sends one: a frame fuzzed or forged)
            self.ctx.refusal("handover_malformed")
            return
        if self._not_its_source(src, msg.rid):
            return
        if not self._complete(msg):  # (parts overtaken on the way: wait for them)
            self._early[msg.rid] = (src, msg)
            return
        parts = self._parts.pop(msg.rid, {})
        dep.moved[msg.vertex] = (now, src)
        h = dep.awaiting.pop(msg.vertex)
        self._twins.pop((msg.app, msg.vertex), None)
        h.life.on(InstanceEvent.HANDOVER)
        self.ctx.emit(fx.RestoreVertex(h.instance, msg.state))  # before any feed
        h.processed, h.emitted = msg.processed, msg.emitted
        dep.instances[msg.vertex] = h
        placement.learn(dep, msg.vertex, self.ctx.id, msg.version, now)
        dep.placed[msg.vertex] = self.ctx.id  # (first-hand, whatever news came first)
        dep.handed.pop(msg.vertex, None)
        gated = bool(dep.out_edges.get(msg.vertex))
        for i, (expected, acked, *counts) in msg.inputs.items():
            superseded, expired, missed = (*counts, 0, 0, 0)[:3]  # (absent from older nodes)
            dep.inc[i] = InChannel(
                expected=expected,
                processed=expected,
                _acked=acked,
                released=acked if gated else None,
                superseded=superseded,  # the edge's QoS counts move with its consumer
                expired=expired,
                deadline_missed=missed,
                marks=provenance.from_wire(msg.marks.get(i)),
            )
        for i, (next_seq, acked, events, positions) in msg.outputs.items():
            ch = self.dp.channel(dep, i, acked)
            for _, ahead in sorted(parts.get(i, []), key=lambda p: p[0]):
                ch.push_many(ahead, now)
            ch.push_many(events, now)
            ch.next_seq = next_seq
            ch.positions = {int(k): int(v) for k, v in positions.items()}
            dep.out[i] = ch
        if msg.gate:
            dep.gates[msg.vertex] = AckGate.from_wire(msg.gate)
        for i in msg.inputs:  # what arrived early, in order, now that positions are known
            for seq, events, ts in sorted(dep.stash.pop(i, []), key=lambda b: b[0]):
                self.dp.deliver(dep, i, seq, events, ts)
        coordinator = self._handover_to.pop(msg.rid, None)
        if coordinator is not None:
            done = m.HandoverDone(msg.app, msg.vertex, msg.rid, self.ctx.id, msg.version)
            self.ctx.send(coordinator, done)
        self.ctx.publish(Happened("hosted", msg.app, msg.vertex, f"{src} -> {self.ctx.id}"))

    def _not_its_source(self, src: str, rid: int) -> bool:
        """A move's state (or its events sent ahead) from another node than the one its
        Prepare said the vertex leaves (with operator keys): refused, counted."""
        if not self.ctx.authority.signed or src in self._sources.get(rid, ()):
            return False
        self.ctx.refusal("handover_not_from_its_host")
        return True

    # -- a producer: switches its edge, sends a marker the old way -----------------------------
    def on_switch(self, src: str, msg: m.Switch) -> None:
        """At the producer's node: new events go to the new instance; a marker goes the old way."""
        dep = self.ctx.apps.get(msg.app)
        if dep is None or not 0 <= msg.edge < len(dep.app.edges):
            self.ctx.refusal("switch_unknown_edge")
            return
        edge = dep.app.edges[msg.edge]
        if self.unwarranted(dep, src, edge.dst, msg.rid, msg.order):
            return
        old = dep.placed[edge.dst]
        if old == msg.to and msg.source:  # a merge vertex whose other input, produced here
            old = msg.source  # too, switched first: its marker goes the old way as well
        why = self._switch_refused(dep, edge.src, edge.dst, msg.to, old)
        if why:
            self.ctx.refusal(why)
            return
        key = (msg.app, msg.edge)
        batch = self.dp.outbox.pop(key, None)
        if batch is not None:  # what is already queued leaves before the marker
            data = m.Data(msg.app, msg.edge, dep.epoch, *batch)
            self.ctx.emit(Send(old, data))
        seq = self.dp.out(dep, msg.edge).next_seq
        dep.placed[edge.dst] = msg.to
        dep.vanished.discard(edge.dst)  # the move's coordinator sees to it from now on (it
        # restores it at the target if the old host went); a recovery here would make a twin
        marker = m.Marker(msg.app, msg.edge, seq, msg.rid, msg.to)
        if old == self.ctx.id:
            self.dp.enqueue(dep, edge.dst, marker)
        else:
            self.ctx.emit(Send(old, marker))

    def _switch_refused(
        self, dep: AppState, producer: str, consumer: str, to: str, old: str
    ) -> str:
        """Why a Switch cannot be part of a relocation ('' if it can): a relocation never
        moves a pinned vertex, nor to where it runs already (its instance would be handed
        over to nobody; ``old`` is where it runs, the move's source once another input of
        the vertex switched here). With operator keys, the producer must run here and ``to``
        be a node this one can reach."""
        if to == old:
            return "switch_to_where_it_runs"
        if dep.app.vertices[consumer].pinned is not None:
            return "switch_of_a_pinned_vertex"
        if self.ctx.authority.signed:
            if producer not in dep.instances:
                return "switch_not_the_producer"
            if to != self.ctx.id and to not in self.ctx.routes:
                return "switch_to_an_unknown_node"
        return ""

    # -- the old host: drains to the markers, snapshots, hands over ----------------------------
    def on_marker_reached(self, ev: MarkerReached) -> None:
        """At the old instance's node: once every input is marked, hand the state over."""
        dep, msg = self.ctx.apps.get(ev.app), ev.marker
        if dep is None:
            return
        vid = dep.app.edges[msg.edge].dst
        h = dep.instances.get(vid)
        if h is None:
            return
        marked = dep.markers.setdefault(vid, set())
        marked.add(msg.edge)
        ins = [i for i, e in enumerate(dep.app.edges) if e.dst == vid]
        if not set(ins) <= marked:
            h.life.on(InstanceEvent.MARKER)
            return
        del dep.markers[vid]
        h.life.on(InstanceEvent.ALL_MARKED)
        h.handing_over = msg  # the state is taken once everything before is processed
        self.dp.submit(h, fx.SnapshotVertex(h.instance, msg.rid))

    def on_snapshotted(self, ev: Snapshotted) -> None:
        """The old instance's state is taken: hand it and the channels over, then free it."""
        dep, vid, res = self.ctx.apps.get(ev.app), ev.vertex, ev.result
        h = dep.instances.get(vid) if dep is not None else None
        msg = h.handing_over if h is not None and h.instance == res.instance else None
        if dep is None or h is None or msg is None or res.token < 0:  # (<0: a replication's)
            return
        ins = [i for i, e in enumerate(dep.app.edges) if e.dst == vid]
        for i in ins:  # acknowledge what the old instance processed, then forget the inputs
            self.dp.ack(dep, i)
        marks = {  # what it has of a merge's inputs (mso.protocol.provenance)
            i: wire
            for i in ins
            if (ch := dep.inc.get(i)) and (wire := provenance.to_wire(ch.marks)) is not None
        }
        inputs = {
            i: [ch.expected, ch._acked, ch.superseded, ch.expired, ch.deadline_missed]
            if (ch := dep.inc.pop(i, None))
            else [0, 0]
            for i in ins
        }
        outputs: dict[int, list[Any]] = {}
        parts = 0
        for i in dep.out_edges.get(vid, []):
            out = dep.out.pop(i, None)
            if out is not None:
                events, ahead = self.dp.sf.handover_events(out)
                for first, part in ahead:  # (a backlog past one frame goes ahead in parts)
                    part_msg = m.HandoverEvents(dep.app.name, vid, msg.rid, i, first, part)
                    self.ctx.send(msg.to, part_msg)
                parts += len(ahead)
                outputs[i] = [out.next_seq, out.acked, events, out.positions]
        gate = dep.gates.pop(vid, None)
        key_batches = [k for k in self.dp.outbox if k[0] == dep.app.name and k[1] in outputs]
        for k in key_batches:  # queued output leaves from here before the handover
            batch = self.dp.outbox.pop(k)
            dst = dep.placed[dep.app.edges[k[1]].dst]
            self.ctx.emit(Send(dst, m.Data(k[0], k[1], dep.epoch, *batch)))
        h.life.on(InstanceEvent.HANDED_OVER)
        self.dp.stop(h, "moved")
        del dep.instances[vid]
        self.leaving.done(dep.app.name, vid)
        dep.placed[vid] = msg.to
        dep.handed[vid] = msg.to
        version = placement.bump(dep, vid)
        handover = m.Handover(
            dep.app.name,
            vid,
            msg.rid,
            res.state,
            inputs,
            outputs,
            h.processed,
            h.emitted,
            gate.to_wire() if gate is not None else [],
            parts,
            version,
            marks,
        )
        dep.marks.pop(vid, None)
        dep.catch_up.pop(vid, None)
        self.dp.taps.hand_over(dep.app.name, vid, msg.to, self.ctx.now)  # (asked there first)
        self.ctx.send(msg.to, handover)
        placement.announce(self.ctx, dep, vid, msg.to)  # to the app's members, not everyone


def _resumes(dep: AppState, vid: str, resumes: list[list[Any]]) -> set[tuple[int, bool]] | None:
    """A restore's ``[edge, producer?]`` pairs as a set, or None if one is malformed: not a
    pair of an int and a bool, or not an edge of ``vid`` on that side."""
    edges = dep.app.edges
    out = set()
    for r in resumes:
        if len(r) != 2 or type(r[0]) is not int or type(r[1]) is not bool:
            return None
        e, producer = r
        if not 0 <= e < len(edges) or (edges[e].dst if producer else edges[e].src) != vid:
            return None
        out.add((e, producer))
    return out


def who_asked(reloc: Relocation) -> str:
    """Who a move is for, in words for its log line: an operator's request, a step of a remap,
    a restore (a crash or a failure), else this node's rules."""
    if reloc.client is not None:
        return "operator"
    if reloc.remap is not None:
        return "remap"
    return "recovery" if reloc.restore else "rule"
