"""A move's new host (a restore's replacement's too): prepares the instance and says so, refuses a
twin or a restore of a vertex restored since, drops the instance when the move fails, and takes
the handover (the state, the channels, the output events sent ahead of it) from the old host.
"""

from __future__ import annotations

from typing import Any

from mso.model.app import MAX_REPLICAS
from mso.protocol import effects as fx
from mso.protocol import messages as m
from mso.protocol import provenance, warrant
from mso.protocol.channel import AckGate, InChannel
from mso.protocol.context import NodeContext
from mso.protocol.dataplane import DataPlane
from mso.protocol.events import Happened, InstanceFailed, InstanceReady, ReplacementPrepared
from mso.protocol.procedures import placement
from mso.protocol.procedures.instance import InstanceEvent
from mso.protocol.procedures.relocation._role import Role
from mso.protocol.procedures.relocation._state import SWITCH_DEADLINE_S
from mso.protocol.state import AppState, Restoring

TAKEN_KEPT = 256  # handovers remembered as taken (a bound: one per recent move)


class NewHost(Role):
    """A move's (or a restore's) target: prepares an instance, takes the handover."""

    def __init__(self, ctx: NodeContext, dp: DataPlane) -> None:
        super().__init__(ctx, dp)
        self._handover_to: dict[int, str] = {}  # rid -> coordinator, at a move's new host
        # at a move's new host: output events sent ahead of the handover, and a handover that
        # came before all of them (rid -> edge -> [(first, events)]; rid -> (from, handover))
        self._parts: dict[int, dict[int, list[tuple[int, list[bytes]]]]] = {}
        self._early: dict[int, tuple[str, m.Handover]] = {}
        # at a move's new host: the node its Prepare said the vertex leaves, and the vertex's
        # host in this node's view when asked (rid -> nodes), the only ones whose handover it
        # takes (with operator keys; a target that took no part in the app since a move of
        # the vertex missed its Moved: its own view alone had the handover refused, and the
        # vertex lost)
        self._sources: dict[int, set[str]] = {}
        # at a move's new host: the move each instance awaiting a handover was prepared for,
        # and when ((app, vertex) -> (rid, since)): another move's Prepare meanwhile is refused
        self._twins: dict[tuple[str, str], tuple[int, float]] = {}
        # at a move's new host: the handovers taken lately (rid -> (app, vertex, version)), so
        # that one sent again (its HandoverDone lost, or the first copy late) is acknowledged
        # again rather than refused
        self._taken: dict[int, tuple[str, str, int]] = {}

    def forget(self, rid: int) -> None:
        """A restore's replacement ran or was dropped: no handover will be reported for it."""
        self._handover_to.pop(rid, None)
        self._parts.pop(rid, None)
        self._early.pop(rid, None)
        self._sources.pop(rid, None)

    def prepared_for(self, app: str, vertex: str, rid: int) -> bool:
        """An instance of ``vertex`` awaits here the handover of move ``rid``: prepared for
        it by this process, neither handed over nor dropped since."""
        dep = self.ctx.apps.get(app)
        twin = self._twins.get((app, vertex))
        return dep is not None and vertex in dep.awaiting and twin is not None and twin[0] == rid

    def orphaned(self, dep: AppState, node: str) -> list[str]:
        """The vertices of ``dep`` prepared here for a move whose old host ``node`` failed (or
        came back in a new incarnation, which ran none of its instances) before the handover,
        and whose coordinator is gone too (``node`` itself, or held failed): none is left to
        make the move a restore, and the vertex's producers, switched here, place it here, so
        no recovery would see it lost (fault seed 230857). Likewise where this node's own view
        still places the vertex on ``node`` (it missed the old host's ``Moved``, cut off as the
        move switched): the producers placed it here all the same, and each of this node and
        a producer's held the other the recovery's coordinator (fault seed 285674). Their
        move given up here, the caller restores them in place."""
        out = []
        here = (self.ctx.id, node)
        for (app, vid), (rid, _) in sorted(self._twins.items()):
            coordinator = self._handover_to.get(rid)
            if app != dep.app.name or vid not in dep.awaiting or vid in dep.restoring:
                continue
            if coordinator is None or coordinator == self.ctx.id:
                continue  # (coordinated here: the coordinator makes it a restore)
            gone = coordinator == node or coordinator in self.ctx.failed
            if gone and node in self._sources.get(rid, ()) and dep.placed.get(vid) in here:
                del self._twins[(app, vid)]
                self.forget(rid)
                out.append(vid)
        return out

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
        if dep.replicas.get(vid) and not dep.replica_nodes.get(vid):  # (as a ReplicaSet: a
            dep.replica_nodes[vid] = list(msg.replicas[:MAX_REPLICAS])  # move's are told, later)
        if vid in dep.app.vertices and msg.restore and self._restored_since(dep, vid, src, msg):
            return
        if vid in dep.app.vertices and msg.restore and self._end_runs_on(dep, src, msg, resumes):
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
        elif vid in dep.instances and not msg.restore:
            # a move to a node that runs the vertex already: asked on a view from before
            # the vertex came here (a coordinator that learnt the app from a node behind).
            # Prepared, it committed the move and waited for a handover from a node that
            # no longer ran the vertex, holding its remap, and the app, open for the
            # switch's 60 s (fault seed 79022): refused, and the coordinator told where
            # the vertex runs
            error = f"{vid!r} runs on {self.ctx.id} already"
            inc = self.ctx.incarnation
            self.ctx.send(src, placement.moved(dep, vid, self.ctx.id, inc))
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
        later = self._runs_later(dep, vid, msg)
        if later is None or later[0] == self.ctx.id:
            return False
        refusal, why = "restore_of_a_vertex_restored_since", f"not restored on {self.ctx.id}"
        return self._refuse_restore(dep, src, msg, vid, later, refusal, why)

    def _end_runs_on(
        self, dep: AppState, src: str, msg: m.Prepare, resumes: set[tuple[int, bool]]
    ) -> bool:
        """A restore that takes an end of the vertex's edges for lost with it (no Resume will
        come from there), where we know that end runs on a live node at a later move than
        the coordinator does (moved before the failure, and the coordinator not told: seed
        81772). The replacement would number its output from the last ack, not from where
        that end stands, and the end would drop what it makes anew by number as had:
        refused, and the coordinator told where the end runs (its recovery is tried again
        on that view, resuming the end)."""
        vid = msg.vertex
        for i, e in enumerate(dep.app.edges):
            if vid not in (e.src, e.dst) or (i, e.dst == vid) in resumes:
                continue
            end = e.src if e.dst == vid else e.dst
            later = self._runs_later(dep, end, msg)
            if later is None or (later[0] == self.ctx.id and end not in dep.instances):
                continue
            refusal, why = "restore_of_an_end_running_since", "resume it, not restore it"
            return self._refuse_restore(dep, src, msg, end, later, refusal, why)
        return False

    def _runs_later(self, dep: AppState, vid: str, msg: m.Prepare) -> tuple[str, int] | None:
        """Where ``vid`` runs by our view, if on a live node at a later move than the view
        the coordinator's ``Prepare`` carries."""
        where, version = dep.placed.get(vid), dep.versions.get(vid, 0)
        if where is None or where in self.ctx.failed or vid in dep.vanished:
            return None
        return (where, version) if version > msg.versions.get(vid, 0) else None

    def _refuse_restore(
        self,
        dep: AppState,
        src: str,
        msg: m.Prepare,
        vid: str,
        later: tuple[str, int],
        refusal: str,
        why: str,
    ) -> bool:
        """Refuse a restore, telling its coordinator where ``vid`` runs (a ``Moved`` first)."""
        where, version = later
        self.ctx.refusal(refusal)
        self.ctx.send(src, m.Moved(dep.app.name, vid, where, -1, version))
        why = f"{vid!r} runs on {where} since (move {version}): {why}"
        self.ctx.send(src, m.Prepared(dep.app.name, msg.vertex, msg.rid, self.ctx.id, why))
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
        if msg.rid in self._taken:  # (sent again with its handover, taken already)
            return
        dep = self.ctx.apps.get(msg.app)
        ok = dep is not None and msg.vertex in dep.awaiting and 0 <= msg.edge < len(dep.app.edges)
        if not ok or dep is None or dep.app.edges[msg.edge].src != msg.vertex:
            self.ctx.refusal("handover_unexpected")
            return
        if self._not_its_source(src, msg.rid):
            return
        parts = self._parts.setdefault(msg.rid, {}).setdefault(msg.edge, [])
        if all(first != msg.first for first, _ in parts):  # (a part sent again: kept once)
            parts.append((msg.first, msg.events))
        early = self._early.get(msg.rid)
        if early is not None and self._complete(early[1]):
            del self._early[msg.rid]
            self.on_handover(early[0], early[1], now)

    def _complete(self, msg: m.Handover) -> bool:
        return sum(map(len, self._parts.get(msg.rid, {}).values())) >= msg.parts

    def on_handover(self, src: str, msg: m.Handover, now: float) -> None:
        dep = self.ctx.apps.get(msg.app)
        taken = self._taken.get(msg.rid)
        if taken is not None and taken[:2] == (msg.app, msg.vertex):
            # sent again by its old host, which did not hear that it was taken
            self.ctx.send(src, m.HandoverDone(msg.app, msg.vertex, msg.rid, self.ctx.id, taken[2]))
            return
        if dep is None or msg.vertex not in dep.awaiting:
            self.ctx.refusal("handover_unexpected")
            return
        shapes = [len(v) >= 2 for v in msg.inputs.values()]
        shapes += [len(v) == 4 or _numbering(v[4:]) is not None for v in msg.outputs.values()]
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
        # its stats came with its start, before the state: a restore returns none, so until
        # its next result they are not known (a moved counter's said 0 after 600 events)
        h.stats = None
        dep.instances[msg.vertex] = h
        placement.learn(dep, msg.vertex, self.ctx.id, msg.version, now)
        dep.placed[msg.vertex] = self.ctx.id  # (first-hand, whatever news came first)
        dep.handed.pop(msg.vertex, None)
        gated = bool(dep.out_edges.get(msg.vertex))
        for i, (expected, acked, *counts) in msg.inputs.items():
            superseded, expired, missed, gen = (*counts, 0, 0, 0, 0)[:4]  # (absent: older nodes)
            dep.inc[i] = InChannel(
                expected=expected,
                processed=expected,
                _acked=acked,
                released=acked if gated else None,
                superseded=superseded,  # the edge's QoS counts move with its consumer
                expired=expired,
                deadline_missed=missed,
                marks=provenance.from_wire(msg.marks.get(i)),
                gen=gen,
                markgens=dict(msg.markgens.get(i, {})),
            )
        for i, (next_seq, acked, events, positions, *numbering) in msg.outputs.items():
            ch = self.dp.channel(dep, i, acked)
            for _, ahead in sorted(parts.get(i, []), key=lambda p: p[0]):
                ch.push_many(ahead, now)
            ch.push_many(events, now)
            ch.next_seq = next_seq
            ch.positions = {int(k): int(v) for k, v in positions.items()}
            gen, gens = _numbering(numbering) or (0, {})  # (absent from older nodes)
            ch.number_as(gen)
            ch.gens = {e: g for e, g in gens.items() if e in ch.positions}
            dep.out[i] = ch
        if msg.gate:
            dep.gates[msg.vertex] = AckGate.from_wire(msg.gate)
        lacks = {  # (of its own output edges only: a peer's word)
            o: marks
            for o, wire in msg.lacks.items()
            if o in msg.outputs and (marks := provenance.from_wire(wire))
        }
        if lacks and msg.vertex in dep.layout.stamped:
            dep.marks[msg.vertex] = lacks
        else:
            dep.marks.pop(msg.vertex, None)
        dep.aside.pop(msg.vertex, None)
        for i in msg.inputs:  # what arrived early, in order, now that positions are known
            for seq, events, ts, said in sorted(dep.stash.pop(i, []), key=lambda b: b[0]):
                self.dp.deliver(dep, i, seq, events, ts, gens=said)
        coordinator = self._handover_to.pop(msg.rid, None)
        done = m.HandoverDone(msg.app, msg.vertex, msg.rid, self.ctx.id, msg.version)
        if coordinator is not None:
            self.ctx.send(coordinator, done)
        if src != coordinator:  # the old host keeps the handover until it hears
            self.ctx.send(src, done)
        self._taken[msg.rid] = (msg.app, msg.vertex, msg.version)
        while len(self._taken) > TAKEN_KEPT:
            del self._taken[next(iter(self._taken))]
        self.ctx.publish(Happened("hosted", msg.app, msg.vertex, f"{src} -> {self.ctx.id}"))

    def _not_its_source(self, src: str, rid: int) -> bool:
        """A move's state (or its events sent ahead) from another node than the one its
        Prepare said the vertex leaves (with operator keys): refused, counted."""
        if not self.ctx.authority.signed or src in self._sources.get(rid, ()):
            return False
        self.ctx.refusal("handover_not_from_its_host")
        return True


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


def _numbering(extra: list[Any]) -> tuple[int, dict[int, int]] | None:
    """A handed-over output's generation and its positions' (after its positions), or None
    if they are not of that shape (no genuine node sends one: refused whole)."""
    if len(extra) != 2:
        return None
    gen, gens = extra
    if type(gen) is not int or not isinstance(gens, dict):
        return None
    if not all(type(k) is int and type(v) is int for k, v in gens.items()):
        return None
    return gen, gens
