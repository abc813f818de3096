"""Relocation (§3.4.1) and restore at one node: the coordinator, the producer, the old host
and the new host.

A relocation moves a running vertex with its state and loses no event. The coordinator (the
:class:`~mso.protocol.procedures.relocate.Relocation` procedure) asks the target to prepare a
new instance; once it is ready, each producer switches its edge to the new node and sends a
marker the old way; the old instance, when every input is marked and everything before the
markers is processed, is snapshotted and handed over with its channels; the new host restores
the state, delivers what it stashed meanwhile, and reports the handover done.

A restore replaces an instance lost with a failed node: the target prepares it, every surviving
end of its edges is rewired to it and says where it stands (producers replay what is unacked,
consumers say what they expect next), and it runs once every end has resumed.
"""

from __future__ import annotations

from typing import Any

from mso.errors import MsoError
from mso.node.deployment import Deploying
from mso.node.tables import Deployment, Hosted, Restoring
from mso.protocol import effects as fx
from mso.protocol import messages as m
from mso.protocol.channel import AckGate, InChannel, OutChannel
from mso.protocol.effects import Reply, Send
from mso.protocol.procedures.base import Deadline
from mso.protocol.procedures.relocate import SWITCH_DEADLINE_S, Relocation, S


class Relocating(Deploying):
    """A node's part in relocations and restores."""

    def _refuse(self, client: int | None, msg: m.RelocateRequest, reason: str) -> None:
        if client is not None:
            reply = m.RelocateReply(msg.app, msg.vertex, False, error=reason)
            self._effects.append(Reply(client, reply))

    def relocation_target(self, dep: Deployment, vertex: str, direction: str = "") -> str:
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
                route = self.routes.get(tail) if here == self.id else None
                target = route[0] if route else tail
        else:
            raise MsoError(f"expected direction 'upstream' or 'downstream', got {direction!r}")
        if target == here:
            where = "predecessor's" if direction == "upstream" else "next downstream"
            raise MsoError(f"{vertex!r} already runs on its {where} node {here}")
        return target

    def relocate(self, req: m.RelocateRequest, now: float) -> None:
        """Start a relocation this node coordinates (the management rules' entry point)."""
        self._relocate_request(None, req, now)

    def _on_relocate_request(self, msg: m.RelocateRequest, now: float) -> None:
        """A relocation asked by another node. Where operator keys are configured that is a
        command a member has no authority for (a node's own rules relocate without asking)."""
        if self.authority.signed:
            self._refusal("relocate_from_member")
            return
        started = self._rid
        self._relocate_request(None, msg, now)
        if self._rid == started:  # refused (no such vertex, no route, ...): nothing began
            self._refusal("relocate_refused")

    def _relocate_request(self, client: int | None, msg: m.RelocateRequest, now: float) -> None:
        dep = self.apps.get(msg.app)
        if dep is None or not dep.running:
            self._refuse(client, msg, f"no running app named {msg.app!r}")
            return
        try:
            target = self.relocation_target(dep, msg.vertex, "" if msg.target else msg.direction)
        except MsoError as exc:
            self._refuse(client, msg, str(exc))
            return
        target = msg.target or target
        if target != self.id and target not in self.routes:
            self._refuse(client, msg, f"target node {target!r} is not reachable")
            return
        source = dep.placed[msg.vertex]
        if target == source:
            self._refuse(client, msg, f"{msg.vertex!r} already runs on {target}")
            return
        if msg.vertex in self._lost(dep):  # no instance to hand over: a recovery restores it
            why = f"node {source} failed" if source in self.dead else "its node restarted"
            self._refuse(client, msg, f"{msg.vertex!r} does not run anywhere ({why})")
            return
        if any(r.app == msg.app and r.vertex == msg.vertex for r in self._relocations()):
            self._refuse(client, msg, f"{msg.vertex!r} is already being relocated")
            return
        self._rid += 1
        self._begin(Relocation(self._rid, now, msg.app, msg.vertex, source, target, client))
        self._send(target, m.Prepare(msg.app, msg.vertex, self._rid))

    def _on_prepare(self, src: str, msg: m.Prepare) -> None:
        """At a relocation's (or restore's) target: create the new instance; it is
        Prepared once the executor has started it (or refused if its code fails)."""
        dep = self.apps.get(msg.app)
        error = ""
        vid = msg.vertex
        resumes = _resumes(dep, vid, msg.resumes) if dep is not None else set()
        if resumes is None:
            self._refusal("prepare_malformed_resumes")
            return
        if dep is None:
            error = f"{self.id} does not run app {msg.app!r}"
            self._send(src, m.Prepared(msg.app, vid, msg.rid, self.id, error, no_app=True))
            return
        if vid not in dep.app.vertices:
            error = f"{self.id}: unknown vertex {vid!r}"
        elif vid not in dep.stones and vid not in dep.awaiting:
            dep.awaiting[vid] = self._host(dep, vid)
            dep.preparing[vid] = (msg.rid, src, msg.restore)
            self._handover_to[msg.rid] = src
            if msg.restore:
                dep.restoring[vid] = Restoring(msg.rid, src, resumes)
            return
        elif msg.restore and vid in dep.stones:  # it never went: nothing to restore
            self._send(src, m.Prepared(msg.app, vid, msg.rid, self.id, error))
            self._send(src, m.HandoverDone(dep.app.name, vid, msg.rid))
            self._broadcast(m.Moved(dep.app.name, vid, self.id, self.incarnation))
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
        self._send(src, m.Prepared(msg.app, vid, msg.rid, self.id, error))
        if dep is not None and not error and msg.restore:
            restoring = dep.restoring.get(vid)
            if restoring is not None and not restoring.pending:
                self._activate(dep, vid)  # nothing to wait for (a lone vertex)

    def _reloc_failed(self, reloc: Relocation, why: str, now: float) -> None:
        """A relocation or restore failed: whoever waits (a client, a remap) is told. If no
        producer had switched yet, the target drops the instance it prepared."""
        if reloc.state is S.PREPARING and reloc.target not in self.dead:
            self._send(reloc.target, m.Unprepare(reloc.app, reloc.vertex, reloc.pid))
        reloc.fail(self, why)
        self._end(reloc.pid)
        self._relocation_ended(reloc, now, why)

    def _relocation_ended(self, reloc: Relocation, now: float, error: str) -> None:
        """Tell whoever waits for a relocation how it ended: its client (a remap, which waits
        for its own relocations, overrides this)."""
        if reloc.client is None:
            return
        if error:
            self._refuse(reloc.client, m.RelocateRequest(reloc.app, reloc.vertex), error)
            return
        elapsed = self._elapsed_ms(reloc.started_at)
        reply = m.RelocateReply(reloc.app, reloc.vertex, True, reloc.target, elapsed)
        self._effects.append(Reply(reloc.client, reply))

    def _on_prepared(self, msg: m.Prepared, now: float) -> None:
        reloc = self._reloc(msg.rid)
        dep = self.apps.get(msg.app)
        if reloc is None or dep is None or (reloc.app, reloc.vertex) != (msg.app, msg.vertex):
            self._refusal("prepared_unexpected")
            return
        if msg.error:
            if msg.no_app:  # a node that missed the app's sync: the retry will find it
                self._app_missing(dep, reloc.target)
            self._reloc_failed(reloc, msg.error, now)
            return
        reloc.on("prepared_restore" if reloc.restore else "prepared")
        if not reloc.restore:  # committed: the old instance drains what it holds, then hands
            reloc.deadline = max(reloc.deadline, now + SWITCH_DEADLINE_S)  # over; a busy
            self.set_timer(Deadline(reloc.pid), reloc.deadline)  # vertex may take a while
        if reloc.restore:  # the surviving ends of its edges resume the replacement
            edges = dep.app.edges
            for edge, producer in reloc.resumes:
                other = dep.placed[edges[edge].src if producer else edges[edge].dst]
                self._send(other, m.Rewire(msg.app, edge, reloc.target, msg.rid, producer))
            return
        for e in dep.app.edges:
            if e.dst == msg.vertex:
                edge = dep.app.edges.index(e)
                switch = m.Switch(msg.app, edge, reloc.target, msg.rid, reloc.source)
                self._send(dep.placed[e.src], switch)

    def _on_switch(self, msg: m.Switch) -> None:
        """At the producer's node: new events go to the new instance; a marker goes the old way."""
        dep = self.apps.get(msg.app)
        if dep is None or not 0 <= msg.edge < len(dep.app.edges):
            self._refusal("switch_unknown_edge")
            return
        edge = dep.app.edges[msg.edge]
        old = dep.placed[edge.dst]
        if old == msg.to and msg.source:  # a merge vertex whose other input, produced here
            old = msg.source  # too, switched first: its marker goes the old way as well
        why = self._switch_refused(dep, edge.src, edge.dst, msg.to, old)
        if why:
            self._refusal(why)
            return
        key = (msg.app, msg.edge)
        batch = self._outbox.pop(key, None)
        if batch is not None:  # what is already queued leaves before the marker
            data = m.Data(msg.app, msg.edge, dep.epoch, *batch)
            self._effects.append(Send(old, data))
        seq = self._out(dep, msg.edge).next_seq
        dep.placed[edge.dst] = msg.to
        dep.vanished.discard(edge.dst)  # the move's coordinator sees to it from now on (it
        # restores it at the target if the old host went); a recovery here would make a twin
        marker = m.Marker(msg.app, msg.edge, seq, msg.rid, msg.to)
        if old == self.id:
            self._enqueue(dep, edge.dst, marker)
        else:
            self._effects.append(Send(old, marker))

    def _switch_refused(
        self, dep: Deployment, producer: str, consumer: str, to: str, old: str
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
        if self.authority.signed:
            if producer not in dep.stones:
                return "switch_not_the_producer"
            if to != self.id and to not in self.routes:
                return "switch_to_an_unknown_node"
        return ""

    def _on_marker(self, dep: Deployment, msg: m.Marker) -> None:
        """At the old instance's node: once every input is marked, hand the state over."""
        vid = dep.app.edges[msg.edge].dst
        h = dep.stones.get(vid)
        if h is None:
            return
        marked = dep.markers.setdefault(vid, set())
        marked.add(msg.edge)
        ins = [i for i, e in enumerate(dep.app.edges) if e.dst == vid]
        if not set(ins) <= marked:
            h.life.on("marker")
            return
        del dep.markers[vid]
        h.life.on("all_marked")
        h.handing_over = msg  # the state is taken once everything before is processed
        self._submit(h, fx.SnapshotVertex(h.instance, msg.rid))

    def _snapshotted(self, dep: Deployment, vid: str, h: Hosted, res: fx.VertexSnapshot) -> None:
        """The old instance's state is taken: hand it and the channels over, then free it."""
        msg = h.handing_over
        if msg is None:
            return
        ins = [i for i, e in enumerate(dep.app.edges) if e.dst == vid]
        for i in ins:  # acknowledge what the old instance processed, then forget the inputs
            self._ack(dep, i)
        inputs = {
            i: [ch.expected, ch._acked] if (ch := dep.inc.pop(i, None)) else [0, 0] for i in ins
        }
        outputs: dict[int, list[Any]] = {}
        for i in dep.out_edges.get(vid, []):
            out = dep.out.pop(i, None)
            if out is not None:
                _, events = out.unacked()
                outputs[i] = [out.next_seq, out.acked, events, out.positions]
        gate = dep.gates.pop(vid, None)
        key_batches = [k for k in self._outbox if k[0] == dep.app.name and k[1] in outputs]
        for k in key_batches:  # queued output leaves from here before the handover
            batch = self._outbox.pop(k)
            dst = dep.placed[dep.app.edges[k[1]].dst]
            self._effects.append(Send(dst, m.Data(k[0], k[1], dep.epoch, *batch)))
        h.life.on("handed_over")
        self._stop(h, "moved")
        del dep.stones[vid]
        dep.placed[vid] = msg.to
        dep.handed[vid] = msg.to
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
        )
        self._send(msg.to, handover)
        self._broadcast(m.Moved(dep.app.name, vid, msg.to))

    def _on_handover(self, src: str, msg: m.Handover, now: float) -> None:
        dep = self.apps.get(msg.app)
        if dep is None or msg.vertex not in dep.awaiting:
            self._refusal("handover_unexpected")
            return
        dep.moved[msg.vertex] = (now, src)
        h = dep.awaiting.pop(msg.vertex)
        h.life.on("handover")
        self._effects.append(fx.RestoreVertex(h.instance, msg.state))  # before any feed
        h.processed, h.emitted = msg.processed, msg.emitted
        dep.stones[msg.vertex] = h
        dep.placed[msg.vertex] = self.id
        dep.handed.pop(msg.vertex, None)
        gated = bool(dep.out_edges.get(msg.vertex))
        for i, (expected, acked) in msg.inputs.items():
            dep.inc[i] = InChannel(
                expected=expected,
                processed=expected,
                _acked=acked,
                released=acked if gated else None,
            )
        for i, (next_seq, acked, events, positions) in msg.outputs.items():
            ch = OutChannel(window=self.window, next_seq=acked, acked=acked, waiting_since=now)
            ch.push_many(events, now)
            ch.next_seq = next_seq
            ch.positions = {int(k): int(v) for k, v in positions.items()}
            dep.out[i] = ch
        if msg.gate:
            dep.gates[msg.vertex] = AckGate.from_wire(msg.gate)
        for i in msg.inputs:  # what arrived early, in order, now that positions are known
            for seq, events in sorted(dep.stash.pop(i, []), key=lambda b: b[0]):
                self._deliver(dep, i, seq, events)
        coordinator = self._handover_to.pop(msg.rid, None)
        if coordinator is not None:
            self._send(coordinator, m.HandoverDone(msg.app, msg.vertex, msg.rid))

    def _on_handover_done(self, msg: m.HandoverDone, now: float) -> None:
        reloc = self._reloc(msg.rid)
        if reloc is None or (reloc.app, reloc.vertex) != (msg.app, msg.vertex):
            self._refusal("handover_done_unexpected")
            return
        reloc.on("handed_over")
        self._end(reloc.pid)
        if reloc.restore:
            dep = self.apps.get(reloc.app)
            if dep is not None:
                dep.placed[reloc.vertex] = reloc.target
        self._relocation_ended(reloc, now, "")

    def _on_moved(self, msg: m.Moved, now: float) -> None:
        dep = self.apps.get(msg.app)
        if 0 <= msg.incarnation < self._incarnations.get(msg.node, msg.incarnation):
            return  # its instance went with that incarnation (a claim overtaken by a reset)
        why = self._moved_refused(dep, msg) if dep is not None else "moved_unknown_app"
        if why:
            self._refusal(why)
            return
        if dep is not None and msg.vertex in dep.placed:
            dep.placed[msg.vertex] = msg.node
            dep.vanished.discard(msg.vertex)
            for c in dep.layout.chains:
                if msg.vertex in c.vertices:
                    dep.placed_at[c.index] = now

    def _moved_refused(self, dep: Deployment, msg: m.Moved) -> str:
        """Why news that ``msg.vertex`` runs on ``msg.node`` is not taken ('' if it is): a
        vertex not in the app; a pinned vertex anywhere but on its node. With operator keys
        also a vertex this node runs itself (and is not handing over): its own view is
        first-hand."""
        if msg.vertex not in dep.app.vertices:
            return "moved_unknown_vertex"
        pin = dep.app.vertices[msg.vertex].pinned
        if pin is not None and msg.node != pin:
            return "moved_a_pinned_vertex"
        h = dep.stones.get(msg.vertex)
        here = h is not None and h.handing_over is None and msg.vertex not in dep.markers
        if self.authority.signed and msg.node != self.id and here:
            return "moved_a_vertex_running_here"
        return ""

    def _on_rewire(self, msg: m.Rewire, now: float) -> None:
        """At a surviving end of an edge whose other end is being replaced on ``msg.to``."""
        dep = self.apps.get(msg.app)
        if dep is None or not 0 <= msg.edge < len(dep.app.edges):
            self._refusal("rewire_unknown_edge")
            return
        edge = dep.app.edges[msg.edge]
        replaced = edge.dst if msg.producer else edge.src
        pin = dep.app.vertices[replaced].pinned
        if pin is not None and msg.to != pin:
            self._refusal("rewire_a_pinned_vertex")
            return
        if msg.producer:  # we produce: say where we stand, then replay what is unacked
            dep.placed[edge.dst] = msg.to
            self._outbox.pop((msg.app, msg.edge), None)  # those events are in the replay
            out = self._out(dep, msg.edge)
            self._send(
                msg.to,
                m.Resume(msg.app, msg.edge, msg.rid, True, out.acked, dict(out.positions)),
            )
            first, events = out.unacked()
            if events:
                data = m.Data(msg.app, msg.edge, dep.epoch, first, events, now)
                if msg.to == self.id:
                    self._work.append((self.id, "", data))
                else:
                    self._effects.append(Send(msg.to, data))
            out.waiting_since = now
        else:  # we consume: say which event we expect next
            dep.placed[edge.src] = msg.to
            inc = dep.inc.get(msg.edge)
            start = inc.expected if inc is not None else 0
            self._send(msg.to, m.Resume(msg.app, msg.edge, msg.rid, False, start))

    def _on_resume(self, msg: m.Resume, now: float) -> None:
        dep = self.apps.get(msg.app)
        if dep is None or not 0 <= msg.edge < len(dep.app.edges):
            self._refusal("resume_unexpected")
            return
        edge = dep.app.edges[msg.edge]
        vertex = edge.dst if msg.producer else edge.src
        restoring = dep.restoring.get(vertex)
        if restoring is None or restoring.rid != msg.rid:
            self._refusal("resume_unexpected")
            return
        if msg.producer:
            gated = bool(dep.out_edges.get(vertex))
            dep.inc[msg.edge] = InChannel(
                expected=msg.start,
                processed=msg.start,
                _acked=msg.start,
                released=msg.start if gated else None,
            )
            for o, pos in msg.positions.items():
                restoring.positions[o] = max(restoring.positions.get(o, 0), pos)
        else:
            restoring.consumer_start[msg.edge] = msg.start
        restoring.pending.discard((msg.edge, msg.producer))
        if not restoring.pending:
            self._activate(dep, vertex)

    def _activate(self, dep: Deployment, vertex: str) -> None:
        """Every surviving end has resumed: the replacement runs. Its output is numbered from
        the positions of the last ack its producers got, so what it regenerates by replay
        carries the numbers it had and consumers drop it as duplicates."""
        restoring = dep.restoring.pop(vertex)
        h = dep.awaiting.pop(vertex)
        h.life.on("resumed")
        dep.moved[vertex] = (self._now, dep.placed[vertex])
        dep.stones[vertex] = h
        dep.placed[vertex] = self.id
        dep.handed.pop(vertex, None)
        outs = dep.out_edges.get(vertex, [])
        for o in outs:
            base = restoring.positions.get(o, restoring.consumer_start.get(o, 0))
            dep.out[o] = OutChannel(
                window=self.window, next_seq=base, acked=base, waiting_since=self._now
            )  # positions further down, for a restore of its consumer (replayed from here)
            dep.out[o].positions = {e: p for e, p in restoring.positions.items() if e not in outs}
        for i, e in enumerate(dep.app.edges):  # what arrived early, in order
            if e.dst == vertex:
                for seq, events in sorted(dep.stash.pop(i, []), key=lambda b: b[0]):
                    self._deliver(dep, i, seq, events)
        self._broadcast(m.Moved(dep.app.name, vertex, self.id, self.incarnation))
        self._handover_to.pop(restoring.rid, None)
        self._send(restoring.coordinator, m.HandoverDone(dep.app.name, vertex, restoring.rid))
        if h.kind == "source":
            self._start_source(dep, vertex, self._now)

    def _instance_ready(self, dep: Deployment, vid: str) -> None:
        prep = dep.preparing.pop(vid, None)
        if prep is not None:  # the new instance of a relocation or restore
            rid, coordinator, restore = prep
            self._send(coordinator, m.Prepared(dep.app.name, vid, rid, self.id, ""))
            restoring = dep.restoring.get(vid)
            if restore and restoring is not None and not restoring.pending:
                self._activate(dep, vid)  # nothing to wait for (a lone vertex)
        super()._instance_ready(dep, vid)

    def _instance_failed(self, dep: Deployment, vid: str, error: str) -> None:
        prep = dep.preparing.pop(vid, None)
        if prep is not None:
            dep.restoring.pop(vid, None)
            self._handover_to.pop(prep[0], None)
            self._send(prep[1], m.Prepared(dep.app.name, vid, prep[0], self.id, error))
        super()._instance_failed(dep, vid, error)

    def _on_unprepare(self, msg: m.Unprepare, now: float) -> None:
        """At a failed move's target: drop the instance prepared for it (nothing was switched
        to it, so nothing is lost)."""
        dep = self.apps.get(msg.app)
        if dep is None:
            self._refusal("unprepare_unexpected")
            return
        h = dep.awaiting.get(msg.vertex)
        prep = dep.preparing.get(msg.vertex)
        restoring = dep.restoring.get(msg.vertex)
        ours = msg.rid in self._handover_to or (prep is not None and prep[0] == msg.rid)
        if h is None or not ours or (restoring is not None and restoring.rid != msg.rid):
            self._refusal("unprepare_unexpected")  # (another move took the instance over since)
            return
        self._stop(h, "abandoned")
        del dep.awaiting[msg.vertex]
        dep.preparing.pop(msg.vertex, None)
        dep.restoring.pop(msg.vertex, None)
        self._handover_to.pop(msg.rid, None)
        for i, e in enumerate(dep.app.edges):
            if e.dst == msg.vertex:
                dep.stash.pop(i, None)
        self.monitor.note_event(now, f"dropped {msg.vertex}, prepared for a move that failed")


def _resumes(dep: Deployment, vid: str, resumes: list[list[Any]]) -> set[tuple[int, bool]] | None:
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
