"""The node a vertex leaves: takes each producer's marker (with operator keys, only for a move it
coordinates or was told of with a warrant, and only from the edge's producer), drains its
instance to the markers, snapshots it and hands the state and channels over to the new host.

The handover is the vertex's only copy once the old instance is freed, and a control frame that
finds no route is given up after ``ROUTE_WAIT_S``. So the old host keeps what it sent until the
new host says it took it (``HandoverDone``, sent to the old host too) and sends it again when
the target is reachable again, and on a backoff (fault seed 274108: the target went out of
reach 2 ms after the switch for 1.7 s; the handover was given up, the move never ended and the
vertex ran nowhere). It is given up at the move's deadline or once the target is held failed:
the vertex is then lost with the target's prepared instance, and restored from its replica.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from mso.protocol import effects as fx
from mso.protocol import messages as m
from mso.protocol import provenance, warrant
from mso.protocol.context import NodeContext
from mso.protocol.dataplane import DataPlane
from mso.protocol.effects import Send
from mso.protocol.events import MarkerReached, Snapshotted
from mso.protocol.procedures import placement
from mso.protocol.procedures.instance import InstanceEvent
from mso.protocol.procedures.relocation._role import Role
from mso.protocol.procedures.relocation._state import SWITCH_DEADLINE_S

HANDOVER_AGAIN_S = 2.0
"""A kept handover not acknowledged is sent again after this long, then twice as long each time
(and at once when its target becomes reachable again)."""


@dataclass
class KeptHandover:
    """A handover sent and not yet acknowledged: the frames, in their order (the output events
    sent ahead, then the handover), and when to send them again or give them up."""

    target: str
    rid: int
    frames: list[m.Message]
    until: float
    again_at: float
    tries: int = 0


class OldHost(Role):
    """The node the vertex leaves: takes the markers (warranted), drains, hands over."""

    def __init__(self, ctx: NodeContext, dp: DataPlane) -> None:
        super().__init__(ctx, dp)
        self.leaving = warrant.Leaving()  # moves of vertices hosted here, told and warranted
        self.kept: dict[tuple[str, str], KeptHandover] = {}  # (app, vertex): not acknowledged

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
        producer, are refused, counted. Kept handovers due are sent again."""
        self.send_kept_again(now)
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
        ins = dep.in_edges.get(vid, [])
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
        ins = dep.in_edges.get(vid, [])
        for i in ins:  # acknowledge what the old instance processed, then forget the inputs
            self.dp.ack(dep, i)
        marks = {  # what it has of a merge's inputs (mso.protocol.provenance)
            i: wire
            for i in ins
            if (ch := dep.inc.get(i)) and (wire := provenance.to_wire(ch.marks)) is not None
        }
        markgens = {i: dict(ch.markgens) for i in ins if (ch := dep.inc.get(i)) and ch.markgens}
        said = {o: self.dp.stamp_gens(dep, o) for o in dep.out_edges.get(vid, [])}  # (inputs go)
        inputs = {
            i: [ch.expected, ch._acked, ch.superseded, ch.expired, ch.deadline_missed, ch.gen]
            if (ch := dep.inc.pop(i, None))
            else [0, 0]
            for i in ins
        }
        outputs: dict[int, list[Any]] = {}
        parts = 0
        frames: list[m.Message] = []
        for i in dep.out_edges.get(vid, []):
            out = dep.out.pop(i, None)
            if out is not None:
                events, ahead = self.dp.sf.handover_events(out)
                for first, part in ahead:  # (a backlog past one frame goes ahead in parts)
                    part_msg = m.HandoverEvents(dep.app.name, vid, msg.rid, i, first, part)
                    self.ctx.send(msg.to, part_msg)
                    frames.append(part_msg)
                parts += len(ahead)
                outputs[i] = [out.next_seq, out.acked, events, out.positions, out.gen, out.gens]
        gate = dep.gates.pop(vid, None)
        key_batches = [k for k in self.dp.outbox if k[0] == dep.app.name and k[1] in outputs]
        for k in key_batches:  # queued output leaves from here before the handover
            batch = self.dp.outbox.pop(k)
            dst = dep.placed[dep.app.edges[k[1]].dst]
            data = m.Data(k[0], k[1], dep.epoch, *batch)
            data.gens = said.get(k[1], {})
            self.ctx.emit(Send(dst, data))
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
            {  # a replacement's consumers' marks, not passed yet: its new host sends on
                o: wire  # only what is past them, as it would have
                for o, mk in dep.marks.pop(vid, {}).items()
                if o in outputs and (wire := provenance.to_wire(mk))
            },
            markgens,
        )
        dep.catch_up.pop(vid, None)
        dep.aside.pop(vid, None)  # (the marks it passes on are those still held whole)
        self.dp.taps.hand_over(dep.app.name, vid, msg.to, self.ctx.now)  # (asked there first)
        self.ctx.send(msg.to, handover)
        now = self.ctx.now
        self.kept[(dep.app.name, vid)] = KeptHandover(
            msg.to, msg.rid, [*frames, handover], now + SWITCH_DEADLINE_S, now + HANDOVER_AGAIN_S
        )
        placement.announce(self.ctx, dep, vid, msg.to)  # to the app's members, not everyone

    def handover_taken(self, src: str, msg: m.HandoverDone) -> bool:
        """The new host took a handover kept here: forgotten. False if none was kept."""
        kept = self.kept.get((msg.app, msg.vertex))
        if kept is None or kept.rid != msg.rid or src != kept.target:
            return False
        del self.kept[(msg.app, msg.vertex)]
        return True

    def send_kept_again(self, now: float, reachable: frozenset[str] = frozenset()) -> None:
        """Send again each kept handover whose target is ``reachable`` again or whose backoff
        is over; give up those past their move's deadline or whose target is held failed."""
        for key, kept in list(self.kept.items()):
            if now > kept.until or kept.target in self.ctx.failed:
                del self.kept[key]
                self.ctx.note_event(now, f"gave up the handover of {key[1]} to {kept.target}")
            elif kept.target in reachable or now >= kept.again_at:
                for frame in kept.frames:
                    self.ctx.send(kept.target, frame)
                kept.tries += 1
                kept.again_at = now + HANDOVER_AGAIN_S * 2**kept.tries
