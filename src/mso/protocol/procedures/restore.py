"""Restore, the participants' side: the surviving ends of a lost instance's edges, the
replacement, and the restart budget of an instance that crashes.

A restore replaces an instance that is gone — with a failed node (a recovery's child), with a
node's old incarnation, or with its own crashed process — at a target the coordinator chose (its
side, and the new host's prepare, are in :mod:`.relocation`)::

    coordinator          replacement (target)        surviving ends of its edges
      Prepare(restore) ─▶  host an instance
               ◀──────── Prepared
      Rewire ─────────────────────────────────────▶  producer: Resume(acked), replay unacked
                                                    consumer: Resume(expected next)
                           ◀──────────────────────  Resume (one per edge end)
                           every end resumed: runs (``activate``), Moved to all
               ◀──────── HandoverDone

Producers replay what they hold unacknowledged (acks are chained, so that is everything the
lost instance had not passed on); the replacement numbers its output from the positions its
producers' acks carried, so what it regenerates by replay carries the numbers it had and
consumers drop it as duplicates: every event reaches them once, in order. A replacement whose
consumer has nothing of its edge (restored while this one was out of reach) sends it a
``Resume`` too, outside any restore: the positions it knows, for the consumer to number its
output from (:meth:`Restorer.anchor`).

A crashed instance (``isolation: process``) is restored in place the same way, at most
``MAX_RESTARTS`` times in ``RESTART_WINDOW_S``: a vertex that crashes on an event would crash
again on its replay; then it stays crashed, its chains are reported parked and their events
stay held (unacknowledged) upstream. The replacement is fed its replay one event at a time (up
to a window per input): a child that dies on an event has returned the results of every event
before it, which a batch ending in the fatal one would have taken down with it on each replay.
"""

from __future__ import annotations

from collections.abc import Iterable

from mso.model.app import has_state
from mso.protocol import effects as fx
from mso.protocol import messages as m
from mso.protocol import provenance
from mso.protocol.channel import AckGate, InChannel, OutChannel
from mso.protocol.context import NodeContext
from mso.protocol.dataplane import REPLICA_OWNER, DataPlane
from mso.protocol.events import (
    Happened,
    InstanceCrashed,
    PeerFailed,
    PeerRejoined,
    RelocationEnded,
    ReplacementPrepared,
    Superseded,
)
from mso.protocol.procedures import placement
from mso.protocol.procedures.instance import MAX_RESTARTS, RESTART_WINDOW_S, H, InstanceEvent
from mso.protocol.procedures.relocation import Relocation, Relocator
from mso.protocol.procedures.replication import usable
from mso.protocol.provenance import Marks
from mso.protocol.state import AppState, Restoring


class Restorer:
    """The surviving ends, the replacement and the restart budget (module docstring)."""

    def __init__(self, ctx: NodeContext, dp: DataPlane, relocator: Relocator) -> None:
        self.ctx = ctx
        self.dp = dp
        self.relocator = relocator

    # -- a surviving end: says where it stands, replays ----------------------------------------
    def on_rewire(self, src: str, msg: m.Rewire, now: float) -> None:
        """At a surviving end of an edge whose other end is being replaced on ``msg.to``."""
        dep = self.ctx.apps.get(msg.app)
        if dep is None or not 0 <= msg.edge < len(dep.app.edges):
            self.ctx.refusal("rewire_unknown_edge")
            return
        edge = dep.app.edges[msg.edge]
        replaced = edge.dst if msg.producer else edge.src
        if self.relocator.unwarranted(dep, src, replaced, msg.rid, msg.order):
            return  # (the restore asks again: by then we may hold the failure too)
        pin = dep.app.vertices[replaced].pinned
        if pin is not None and msg.to != pin:
            self.ctx.refusal("rewire_a_pinned_vertex")
            return
        if self._restored_since(dep, src, replaced, msg):
            return
        ours = edge.src if msg.producer else edge.dst
        if ours not in dep.instances and ours not in dep.awaiting:
            # a view that places our end here is stale (it moved on): answering from no
            # channel said the edge starts at 0 and the replacement numbered from there,
            # below what the real end had (seed 401 with restarts: 12 events dropped); the
            # restore asks again where its view then places this end, told by us where ours
            # does (a coordinator hosting nothing of the app misses its moves: 306377)
            self.ctx.refusal("rewire_not_our_end")
            self._tell_where(dep, src, ours)
            return
        if not msg.producer and ours not in dep.instances and msg.edge not in dep.inc:
            # our end is a replacement (or a move's target) not running yet: where its input
            # starts is set when it does (its consumers' marks). Answered now, from no
            # channel, the edge started at 0 and the producer's replacement numbered from 0
            # below that start: 29 events dropped (restart seed 3605, two coordinators). The
            # restore asks again (its retry)
            self.ctx.refusal("rewire_end_not_running")
            return
        if ours in dep.instances and msg.to != self.ctx.id and msg.rid:
            # (not a producer's ``ask_where``, rid 0: it knows where this end runs)
            # the replacement's node hears first-hand where this end runs: the restore's
            # view said so only where it was a later move than the node knew of, and a twin
            # of equal version restored across a cut and gone since stayed its view (restart
            # seed 52794: the consumer's node held its producer vanished on a reset node)
            self.ctx.send(msg.to, placement.moved(dep, ours, self.ctx.id, self.ctx.incarnation))
        if msg.rid:  # a restore's: the instance where our view held it is replaced (a
            # producer's, still running cut off, sends on in its own numbering: 162674)
            dep.view.restored(replaced, msg.to)
        if msg.producer and self._made_anew(dep, ours, msg.edge):
            dep.placed[edge.dst] = msg.to
            anew = m.Resume(msg.app, msg.edge, msg.rid, True, 0, gen=self._new_generation())
            anew.fresh = True
            self.ctx.send(msg.to, anew)
        elif msg.producer:  # we produce: say where we stand, then replay what is unacked
            dep.placed[edge.dst] = msg.to
            self.dp.outbox.pop((msg.app, msg.edge), None)  # those events are in the replay
            out = self.dp.out(dep, msg.edge)
            kept = out.retained_from(REPLICA_OWNER)  # a replicated consumer: replay from
            # its newest replicated snapshot on (or from the ack, if that is earlier)
            start = min(kept, out.acked) if kept is not None else -1
            # (events made anew since the consumer's snapshot: not the ones it counted; and
            # an end not running yet, a replacement or a move's target, retains nothing of
            # what the instance before made: its channel here is new, at 0, and said so, the
            # consumer's replacement took a snapshot at 0 whose replay never came, its state
            # restarted undeclared: fault seed 277659)
            retained = -1 if msg.edge in dep.fresh_from or ours not in dep.instances else start
            resume = m.Resume(
                msg.app, msg.edge, msg.rid, True, out.acked, dict(out.positions), retained
            )
            resume.fresh = out.guessed
            resume.new = _new_past(out)
            resume.gen, resume.gens = out.gen, dict(out.gens)
            resume.remade = out.remade
            out.confirmed = True  # (a replacement: it numbers on from here)
            out.consumer_lost = False
            if out.guessed:  # its consumer's replacement takes the guess: said upstream
                self._tell_taken(dep, ours, msg.edge)
            resume.renumbered = sorted(dep.renumbered.get(edge.src, ()))
            self.ctx.send(msg.to, resume)
            out.sent = out.acked  # everything unacknowledged goes again, a window at a time
            if msg.to == self.ctx.id:
                first, events = out.unsent(out.window)
                if events:
                    self.ctx.loop_back(
                        self.ctx.id,
                        m.Data(
                            msg.app,
                            msg.edge,
                            dep.epoch,
                            first,
                            events,
                            now,
                            gens=self.dp.stamp_gens(dep, msg.edge),
                        ),
                    )
            else:
                self.dp.sf.drain(dep, msg.edge)
            out.waiting_since = now
        else:  # we consume: say which event we expect next
            dep.placed[edge.src] = msg.to
            if msg.edge not in dep.inc and edge.dst in dep.layout.stamped:
                self._nothing_of(dep, edge.dst, msg.edge, msg.rid)
            self.ctx.send(msg.to, self._standing(dep, msg.edge, msg.rid))

    @staticmethod
    def _made_anew(dep: AppState, ours: str, edge: int) -> bool:
        """Our end of ``edge``, its producer, is a replacement (or a move's target) not
        running yet with no channel of the edge (its node reset): it stands nowhere, and what
        it will make is numbered anew (its activation makes its own channel), so its answer
        to a rewire says so: a generation of its own, ``Resume.fresh``. Said from a channel
        made for the answer, at 0 in the deployment's numbering, the consumer's replacement (a
        merge, restored by a coordinator that held this producer alive) kept its consumer's
        marks of that input, of the lost producer's numbering, and dropped a restarted
        source's first 33 events as had (fault seed 363254). Not a source: what it numbers
        from is its edge carried over in the node's store (as before)."""
        return (
            ours not in dep.instances and edge not in dep.out and dep.layout.kinds[ours] != "source"
        )

    def _nothing_of(self, dep: AppState, vertex: str, edge: int, rid: int) -> None:
        """A running merge or fork holds no channel of ``edge`` (its replacement resumed its
        other inputs while this one's producer was lost too, and no marks named it then), and
        that producer's replacement asks where it stands: it stands nowhere. Its answer, 0,
        starts a numbering made anew (a generation of its own), so marks its consumers hold of
        the lost producer's numbering do not take the new events for ones they had (fault seed
        179893: a merge's forwarder, restored after, dropped a restarted source's first 21
        events as had by the sink's marks of the first numbering)."""
        anew = m.Resume(dep.app.name, edge, rid, True, 0, gen=self._new_generation())
        self._numbered_anew(dep, vertex, anew)

    def _standing(self, dep: AppState, edge: int, rid: int) -> m.Resume:
        """A consumer's word on where it stands on ``edge``: the next event it expects, in
        which numbering, its outputs there where exact and, of a stamped producer, what it
        has of each of the producer's inputs (its marks)."""
        e = dep.app.edges[edge]
        inc = dep.inc.get(edge)
        start = inc.expected if inc is not None else 0
        resume = m.Resume(dep.app.name, edge, rid, False, start)
        resume.unheld = inc is not None and inc.unheld
        resume.gen = inc.gen if inc is not None else 0
        resume.positions, down = self._outputs_at_start(dep, e.dst, edge)
        resume.gens = down | _gens(dep, resume.positions)  # (theirs further down: acks')
        if inc is not None and e.src in dep.layout.stamped:
            marks = inc.marks  # what it has of each input; a forwarder that passes on
            sent_on = dep.marks.get(e.dst)  # only what its consumer lacks drops the
            if marks is not None and sent_on:  # rest as had: its consumer's marks count
                marks = provenance.highest(marks, _merged(sent_on.values()))  # (5000)
            resume.marks = provenance.to_wire(marks)
            resume.markgens = _known(inc.markgens, marks or {})
        return resume

    def _outputs_at_start(
        self, dep: AppState, vertex: str, edge: int
    ) -> tuple[dict[int, int], dict[int, int]]:
        """Where this consumer's outputs stand at the input position it tells a producer's
        replacement (everything before it processed, nothing owed): the replacement's channel
        starts with them as an ack's positions, so that a replacement of this consumer, fed
        the replay, numbers it as this one did (restart seed 115201: a restored producer
        started at its consumer's position with none; the consumer died with the replay
        passed on, its replacement numbered it from the sink's position: an event twice).
        Empty where they are not exact (:meth:`_outputs_exact`), or events are held or in
        flight, or its start is a guess. Where every output's last ack acknowledged all it
        made, that ack's positions further down go with them (as an ack's would: fault seed
        202193, a chain lost whole behind a fork whose branch to one sink had its ack and the
        other not; the source, restarted, knew only the first vertex's position, and the
        chain's replacement numbered the replay to that sink from where it stood: 6 twice).
        With them, the generations of those further down (their acks')."""
        h = dep.instances.get(vertex)
        exact = self._outputs_exact(dep, vertex)
        if (
            h is None
            or exact is None
            or exact[0] != edge
            or h.queued
            or h.pending
            or h.jobs
            or h.handing_over is not None
            or dep.inc[edge].unheld
        ):
            return {}, {}
        there, further, gens = exact[1], dict[int, int](), dict[int, int]()
        for o in there:
            out = dep.out[o]
            if out.acked != out.next_seq or out.positions_at != out.acked:
                return there, {}  # (not known further down at this point: its own only)
            further |= out.positions
            gens |= out.gens
        return further | there, _known(gens, further)

    @staticmethod
    def _outputs_exact(dep: AppState, vertex: str) -> tuple[int, dict[int, int]] | None:
        """A vertex with one input, everything on it before the channel's next event
        processed, no marks and no guessed output: that input, and where its outputs stand,
        exactly (what an ack at the input's start carries: :meth:`_tell_start`, and a
        consumer's answer to a rewire: :meth:`_outputs_at_start`). None otherwise."""
        inputs = dep.in_edges.get(vertex, [])
        outs = dep.out_edges.get(vertex, [])
        if len(inputs) != 1 or not outs or vertex in dep.marks:
            return None
        ch = dep.inc.get(inputs[0])
        if ch is None or ch.processed != ch.expected:
            return None
        if any(o not in dep.out or dep.out[o].guessed for o in outs):
            return None
        return inputs[0], {o: dep.out[o].next_seq for o in outs}

    def _restored_since(self, dep: AppState, src: str, replaced: str, msg: m.Rewire) -> bool:
        """A restore of a view older than ours: this end knows ``replaced`` runs on a live
        node at a later move than the coordinator does (this one, perhaps). Following it
        would rewire the edge to a twin of equal version, and both would run on (restart
        seed 3316: a restarted daemon's restore of a vertex restored meanwhile on the other
        side of a cut). Refused, and the coordinator told where it runs: its retry ends the
        restore there (as the target's own check, ``Relocator._restored_since``)."""
        where, version = dep.placed.get(replaced), dep.versions.get(replaced, 0)
        if (
            msg.version < 0
            or version <= msg.version
            or where is None
            or where == msg.to
            or where in self.ctx.failed
            or replaced in dep.vanished
        ):
            return False
        self.ctx.refusal("rewire_of_a_vertex_restored_since")
        inc = self.ctx.incarnation if where == self.ctx.id else -1
        self.ctx.send(src, m.Moved(dep.app.name, replaced, where, inc, version))
        return True

    def _tell_where(self, dep: AppState, src: str, ours: str) -> None:
        """A rewire's asker placed ``ours`` here, where it runs no more: tell it where our view
        places it (a relayed ``Moved``: newer versions win). Its retry asks that node. Said
        nothing, a coordinator that hosts no part of the app, so was never told of the move
        (an announce goes to the members), asked this node for good and the replacement never
        ran (fault seed 306377: ``b`` moved off N3 just before N1's restore of its consumer
        ``k1`` on N3; N1 sent its rewires to N3 every second until the end)."""
        where = dep.placed.get(ours)
        if where is None or where == self.ctx.id or where in self.ctx.failed:
            return
        if ours in dep.vanished:  # (gone with its node's last process: no word on where)
            return
        self.ctx.send(src, placement.moved(dep, ours, where))

    # -- the replacement: runs once every surviving end has resumed it -------------------------
    def on_resume(self, src: str, msg: m.Resume, now: float) -> None:
        dep = self.ctx.apps.get(msg.app)
        if dep is None or not 0 <= msg.edge < len(dep.app.edges):
            self.ctx.refusal("resume_unexpected")
            return
        edge = dep.app.edges[msg.edge]
        vertex = edge.dst if msg.producer else edge.src
        restoring = dep.restoring.get(vertex)
        if restoring is None and msg.producer and vertex in dep.instances:
            inc = dep.inc.get(msg.edge)
            if inc is not None and inc.awaiting_replay:  # it started from a snapshot and asked
                # the producer's instance before this one for the replay: ask this one (seed
                # 29505: that node restarted, its source numbered on, the replay never came)
                producer = dep.placed[edge.src]
                self.ctx.send(producer, m.Replay(msg.app, msg.edge, inc.expected, inc.positions))
            elif not self.anchor(dep, vertex, msg):  # (a running consumer: see there)
                self.ctx.refusal("resume_unexpected")
                if inc is not None and (msg.fresh or msg.gen != inc.gen):
                    # a numbering made anew that this consumer did not take: the producer's
                    # events in it are not past what this one has. Say where it stands, so
                    # that a guessed producer renumbers from there (restart seed 138982: the
                    # rewire of a restore whose consumer another coordinator had restored
                    # first confirmed a guess from 0; the consumer, at 39 in the first
                    # numbering, dropped 39 events as had, 12 of them new)
                    self.ctx.send(src, self._standing(dep, msg.edge, msg.rid))
            return
        out = dep.out.get(msg.edge)
        # a guessed channel whose consumer stands in another numbering never took the guess
        # (its answer to a refused Resume: see above), whatever the rewire confirmed
        unsure = out is not None and (out.unsure or (out.guessed and msg.gen != out.gen))
        if restoring is None and not msg.producer and vertex in dep.instances and unsure:
            self._renumber(dep, vertex, msg, now)  # (a consumer that survived: ask_where)
            return
        if restoring is None and not msg.producer and vertex in dep.instances:
            marks = provenance.from_wire(msg.marks)
            if marks and vertex in dep.layout.merges and edge.dst in dep.layout.forwarders:
                gens = dict(msg.markgens)  # (its forwarder's activate)
                self._start_past(dep, vertex, marks, set(), gens)
            else:
                self.ctx.refusal("resume_unexpected")
            return
        if restoring is None or restoring.rid != msg.rid:
            self.ctx.refusal("resume_unexpected")
            return
        if msg.producer:
            # what came before the producer's Resume goes again after it: what an instance of
            # it before made (a lineage since restored, numbered alike) must not win (30719)
            dep.stash.pop(msg.edge, None)
            gated = bool(dep.out_edges.get(vertex))
            # a fresh instance: what it has of a stamped producer's inputs is what comes
            # from here on (its lost instance's output went on and was acknowledged)
            marks = {} if edge.src in dep.layout.stamped else None
            dep.inc[msg.edge] = InChannel.starting_at(msg.start, gated, marks, msg.gen)
            for o, pos in msg.positions.items():
                if pos >= restoring.positions.get(o, 0):
                    restoring.positions[o] = pos
                    restoring.gens[o] = msg.gens.get(o, 0)
            if msg.retained >= 0:
                restoring.retained[msg.edge] = msg.retained
            if msg.remade >= 0:
                restoring.remade[msg.edge] = msg.remade
            if msg.fresh:
                restoring.fresh.add(msg.edge)
            if msg.new:
                restoring.new.add(msg.edge)
            restoring.renumbered.update(msg.renumbered)
            restoring.resumed.add(msg.edge)
        else:
            restoring.consumer_start[msg.edge] = msg.start
            restoring.consumer_gen[msg.edge] = msg.gen
            if msg.positions:
                restoring.consumer_positions[msg.edge] = dict(msg.positions)
                restoring.consumer_gens[msg.edge] = dict(msg.gens)
            if msg.unheld:
                restoring.unheld.add(msg.edge)
            marks = provenance.from_wire(msg.marks)
            if marks is not None and vertex in dep.layout.stamped:
                restoring.consumer_marks[msg.edge] = marks
                restoring.consumer_markgens[msg.edge] = dict(msg.markgens)
        restoring.pending.discard((msg.edge, msg.producer))
        if _ready(dep, vertex, restoring):
            self.activate(dep, vertex)

    def _renumber(self, dep: AppState, vertex: str, msg: m.Resume, now: float) -> None:
        """A guessed output channel's consumer says where it stands (it survived out of reach
        of this instance's restore, held lost, and was never restored: fault seed 40939, a
        restarted source's first 18 events dropped as had). Its numbering wins: what this
        channel holds goes from there on, past the consumer's marks for a stamped vertex
        (not those of an input numbered anew: they name another numbering)."""
        old = dep.out[msg.edge]
        if msg.gen == old.gen and msg.start < old.acked == old.positions_at and old.positions:
            self._skip_ahead(dep, msg, old)
            return
        if old.spilled:  # (read off the loop only: a backlog past memory keeps its guess)
            self.ctx.note_event(now, f"{vertex}: edge {msg.edge} keeps a guessed numbering")
            old.confirmed, old.consumer_lost = True, False
            return
        _, events = old.unacked()
        marks = provenance.from_wire(msg.marks)
        if marks and vertex in dep.layout.stamped:
            marks = provenance.without(marks, dep.renumbered.get(vertex, set()))
            dep.marks.setdefault(vertex, {})[msg.edge] = marks
            events = provenance.past(events, marks)
        self.dp.outbox.pop((dep.app.name, msg.edge), None)
        new = self.dp.channel(dep, msg.edge, msg.start)
        new.push_many(events, now)
        new.confirmed = True
        new.number_as(msg.gen)  # (its consumer's numbering)
        if msg.edge in dep.fresh_from:
            dep.fresh_from[msg.edge] = msg.start
        dep.out[msg.edge] = new
        if old.made_from >= 0 and old.acked == old.origin:  # (all of it renumbered: the
            new.made_from = old.made_from  # guess's start is this numbering's)
            self._tell_taken(dep, vertex, msg.edge)
        self.dp.sf.drain(dep, msg.edge)

    def _skip_ahead(self, dep: AppState, msg: m.Resume, out: OutChannel) -> None:
        """A consumer says it stands below what this channel has acknowledged, in its very
        numbering: another instance of it (a twin, retired since) took the events between,
        and what it made of them went on, and was acknowledged, as far as the ack's positions
        say. They are gone from here; the consumer skips them, and its outputs skip the
        numbers that twin gave what it made of them (fault seed 183066: the twin's chain on
        N2 took a restarted source's first 6 events; the consumer that stayed, on N3, at 27,
        skipped to 32 by the floor and numbered its next outputs 27 on, which its consumer
        had from the twin: 5 events dropped as had)."""
        skip = m.Resume(dep.app.name, msg.edge, msg.rid, True, out.acked, dict(out.positions))
        skip.gen, skip.gens = out.gen, dict(out.gens)
        out.confirmed, out.consumer_lost = True, False
        self.ctx.send(dep.placed[dep.app.edges[msg.edge].dst], skip)
        self.dp.sf.drain(dep, msg.edge)

    def _skipped(self, dep: AppState, vertex: str, msg: m.Resume) -> bool:
        """A running consumer told by its producer to skip to where another instance of it
        had taken the edge (:meth:`_skip_ahead`): its input goes there, and each output it
        numbers on from where that instance's stood: what it holds unacknowledged below that
        its consumer has from that instance, as the ack's positions say."""
        dep.inc[msg.edge].skip_to(msg.start)
        outs = dep.out_edges.get(vertex, [])
        further = {e: p for e, p in msg.positions.items() if e not in outs}
        for o in outs:
            out, pos = dep.out.get(o), msg.positions.get(o, -1)
            if out is None or pos <= out.next_seq:
                continue
            new = self.dp.channel(dep, o, pos)
            new.number_as(out.gen)
            new.positions, new.gens = further, _known(msg.gens, further)
            new.confirmed = True
            self.dp.outbox.pop((dep.app.name, o), None)
            dep.out[o] = new
        self.dp.touch(dep.app.name)
        return True

    def anchor(self, dep: AppState, vertex: str, msg: m.Resume) -> bool:
        """A consumer restored while this edge's producer was out of reach (or before it) has
        numbered its output from where its own consumers stood, or from 0: a guess, since no
        ack said what its lost instance had made of the producer's events. The producer's
        replacement says where the edge starts and, from the last ack it knows of, the
        consumer's output positions then. A consumer that has processed nothing yet numbers
        its output from those, and tells its own consumers in turn: what it makes of the
        replay carries the numbers the lost instance gave it, and downstream drops what it
        has (seeds 80, 3040). One that has processed something keeps its guess (a merge fed
        by its other input meanwhile: counted refused)."""
        h = dep.instances[vertex]
        inc = dep.inc.get(msg.edge)
        if msg.renumbered and vertex in dep.layout.forwarders and vertex in dep.marks:
            for o, held in list(dep.marks[vertex].items()):  # (_numbered_anew at the merge)
                dep.marks[vertex][o] = provenance.without(held, msg.renumbered)
        if msg.new and inc is not None and self._new_at(dep, vertex, inc, msg):
            return self._marks_past(dep, vertex, msg)
        anew = inc is not None and (msg.fresh or msg.gen != inc.gen)
        ahead = inc is not None and not anew and msg.start > inc.expected and msg.positions
        if ahead and not (h.queued or h.pending) and vertex not in dep.layout.stamped:
            return self._skipped(dep, vertex, msg)
        if inc is not None and anew and 0 <= inc.past_marks == inc.expected:
            return self._numbered_anew(dep, vertex, msg)
        outs = dep.out_edges.get(vertex, [])
        if (
            h.processed
            or h.queued
            or h.pending
            or (inc is not None and inc.expected > 0 and not inc.unheld)
            or h.from_snapshot  # numbered from its snapshot (a restore's Rewire sent again,
            # answered after it ran: renumbered, its count repeated at the sink)
            or not all(self._placed_at(dep, vertex, inc, msg, o) for o in outs)
        ):
            return anew and self._follow(dep, vertex, msg)
        marks: Marks | None = {} if dep.app.edges[msg.edge].src in dep.layout.stamped else None
        dep.inc[msg.edge] = InChannel.starting_at(msg.start, bool(outs), marks, msg.gen)
        further = {e: p for e, p in msg.positions.items() if e not in outs}
        below = {e: g for e, g in msg.gens.items() if g and e in further}
        marked = dep.marks.get(vertex, {})
        for o in outs:
            if o in marked or msg.positions.get(o, -1) < 0:  # numbered from where its
                continue  # consumer stands, past its marks, or a guess: kept (40794, 340535)
            pos = msg.positions[o]
            self.dp.outbox.pop((dep.app.name, o), None)
            dep.out[o] = self.dp.channel(dep, o, pos)
            dep.out[o].positions, dep.out[o].gens = further, below
            dep.out[o].number_as(msg.gens.get(o, 0))
            if vertex in dep.layout.merges:
                dep.out[o].remade = pos
            if o in dep.fresh_from:  # a state restarted still makes new events
                if has_state(dep.app.vertices[vertex]):
                    dep.fresh_from[o] = pos
                else:
                    del dep.fresh_from[o]
            consumer = dep.placed[dep.app.edges[o].dst]
            resume = m.Resume(dep.app.name, o, msg.rid, True, pos, further)
            resume.gen, resume.gens = dep.out[o].gen, dict(below)
            self.ctx.send(consumer, resume)
        self.dp.touch(dep.app.name)
        return True

    @staticmethod
    def _placed_at(
        dep: AppState, vertex: str, inc: InChannel | None, msg: m.Resume, o: int
    ) -> bool:
        """Whether the anchor says where output ``o`` stands, or need not: a consumer whose
        input was started past its consumers' marks (``unheld``) keeps an output numbered
        past its consumer's marks, or on a guess (no ack said where the lost instance's
        output stood, none acknowledged since; its consumer, lost too, takes the guess or
        says where it stands): the replay the producer makes from below the marks is
        numbered there as new, and each consumer gets what it lacks. Asked for positions of
        every output, a producer's replacement that knew none of them further down (its
        source's edge restarted, knowing its own only) was refused, and the fork's consumer
        lost too never got the events below the other's marks (fault seed 340535: 6)."""
        if o in msg.positions and msg.positions[o] >= 0:
            return True
        if inc is None or not inc.unheld:
            return False
        out = dep.out.get(o)
        return o in dep.marks.get(vertex, {}) or (out is not None and out.guessed)

    def _follow(self, dep: AppState, vertex: str, msg: m.Resume) -> bool:
        """A merge that keeps its output's numbering (it has processed its other inputs'
        events) still takes this input in the numbering its producer now says, if it has
        taken nothing of it and its consumers' marks do not name it: its events carry their
        input's position and generation in their headers, not the output's numbering, so the
        frames downstream say which numbering they are of. Kept in the old one, they said
        the producer's guess while numbered as its consumers' marks were, and the sink got
        an event twice (fault seed 150917: ``b`` anchored to its source's carried numbering,
        ``m`` had processed ``a``'s replay and refused the anchor)."""
        inc = dep.inc[msg.edge]
        marked = any(msg.edge in mk for mk in dep.marks.get(vertex, {}).values())
        if vertex not in dep.layout.merges or inc.taken or marked:
            return False
        gated = bool(dep.out_edges.get(vertex))
        dep.inc[msg.edge] = InChannel.starting_at(msg.start, gated, inc.marks, msg.gen)
        self.dp.touch(dep.app.name)
        return True

    @staticmethod
    def _new_at(dep: AppState, vertex: str, inc: InChannel, msg: m.Resume) -> bool:
        """A running merge or fork hears from an input's producer, restored since, that it
        numbers that input from where this one stands, in its numbering, with new events only
        (``Resume.new``, :meth:`activate`)."""
        stamped = vertex in dep.layout.stamped
        return stamped and msg.start == inc.expected and msg.gen == inc.gen

    def _marks_past(self, dep: AppState, vertex: str, msg: m.Resume) -> bool:
        """Its consumers' marks of that input from where the producer starts on name events
        the lost producer made, which nobody makes again, at numbers its new events take: they
        go, here and held aside (fault seed 266014: kept, the fork dropped a restarted
        source's first event for one consumer as had). Those below name events made before,
        which a replay may bring again: they stay."""
        edge, start = msg.edge, msg.start
        for held in dep.marks.get(vertex, {}).values():
            if edge in held and held[edge][0] >= start:
                del held[edge]
        for aside in dep.aside.get(vertex, {}).values():
            if edge in aside and aside[edge][0][0] >= start and aside[edge][1] == msg.gen:
                del aside[edge]
        self.dp.touch(dep.app.name)
        return True

    def _numbered_anew(self, dep: AppState, vertex: str, msg: m.Resume) -> bool:
        """A fork's or merge's replacement started an input past its consumers' marks (its
        producer was held lost with it), and the producer, restored by another coordinator
        before it, numbers that edge in another numbering than the marks' (another
        generation: ``Resume.gen``; or anew with no position at all, ``Resume.fresh``), so
        its events are new ones from ``msg.start``, not past the marks: taken from there, as
        the restore would have had the Resume come in it, and the marks of that input, which
        name a numbering gone, are dropped, here and at its forwarder (restart seed 102439:
        started at 39, the replacement dropped a restarted source's first 39 events as had;
        105902: the producer numbered from positions its source carried over a reset, of a
        numbering made anew across a cut, and the merge dropped 11 events as had)."""
        edge = dep.app.edges[msg.edge]
        gated = bool(dep.out_edges.get(vertex))
        marks: provenance.Marks | None = {} if edge.src in dep.layout.stamped else None
        dep.inc[msg.edge] = InChannel.starting_at(msg.start, gated, marks, msg.gen)
        dep.renumbered.setdefault(vertex, set()).add(msg.edge)
        for o, held in list(dep.marks.get(vertex, {}).items()):
            dep.marks[vertex][o] = provenance.without(held, [msg.edge])
        for o in dep.out_edges.get(vertex, []):  # a forwarder's marks of it name it too
            if dep.app.edges[o].dst in dep.layout.forwarders:
                self._tell_renumbered(dep, o, msg.rid, sorted(dep.renumbered[vertex]))
        self.dp.touch(dep.app.name)
        return True

    def _tell_renumbered(self, dep: AppState, o: int, rid: int, inputs: list[int]) -> None:
        """Tell the forwarder on output ``o`` that ``inputs`` of this merge are numbered anew
        (``Resume.renumbered``): the marks it holds of them for its own consumer name a
        numbering gone, and kept they drop the new events as had (:meth:`anchor`)."""
        out = dep.out.get(o)
        if out is None:
            return
        told = m.Resume(dep.app.name, o, rid, True, out.acked, gen=out.gen)
        told.renumbered = inputs
        self.ctx.send(dep.placed[dep.app.edges[o].dst], told)

    def on_replacement_prepared(self, ev: ReplacementPrepared) -> None:
        """The replacement started here (or its state arrived from a replica): with no
        surviving end left to wait for, it runs now."""
        dep = self.ctx.apps.get(ev.app)
        restoring = dep.restoring.get(ev.vertex) if dep is not None else None
        if dep is not None and restoring is not None and _ready(dep, ev.vertex, restoring):
            self.activate(dep, ev.vertex)

    def activate(self, dep: AppState, vertex: str) -> None:
        """Every surviving end has resumed: the replacement runs. Its output is numbered from
        the positions of the last ack its producers got, so what it regenerates by replay
        carries the numbers it had and consumers drop it as duplicates."""
        restoring = dep.restoring.pop(vertex)
        h = dep.awaiting.pop(vertex)
        h.life.on(InstanceEvent.RESUMED)
        dep.moved[vertex] = (self.ctx.now, dep.placed[vertex])
        dep.instances[vertex] = h
        dep.placed[vertex] = self.ctx.id
        dep.handed.pop(vertex, None)
        outs = dep.out_edges.get(vertex, [])
        snap = usable(dep, vertex, restoring)
        if snap is not None:  # chain replication: from a replica's state, at its positions
            self.ctx.emit(fx.RestoreVertex(h.instance, snap.state))  # before any feed
            h.processed, h.emitted = snap.processed, snap.emitted
            h.stats = None  # (its start's, not the state's: see new_host.on_handover)
            h.from_snapshot = True
            at = {o: acked + len(events) for o, (acked, events) in snap.outputs.items()}
            # what it had made and not got acknowledged goes again below: its inputs are
            # acknowledged past their producers' acks only once that is (chained acks; an
            # ack at the snapshot's position at once lost those events with this node: 1465)
            held = outs and any(events for _, events in snap.outputs.values())
            for i, pos in snap.inputs.items():
                resumed = dep.inc.get(i)
                safe = min(pos, resumed.expected) if held and resumed is not None else pos
                dep.inc[i] = InChannel(
                    expected=pos,
                    processed=pos,
                    _acked=safe,
                    released=safe if outs else None,
                    marks=dict(snap.marks) if snap.marks is not None else None,
                    markgens=dict(snap.markgens),
                )  # its producer sends again from there (it retains them); what it sent
                # before it gets the Replay is further on, not a reason to skip ahead
                dep.inc[i].awaiting_replay = resumed is not None and pos < resumed.expected
                # what an ack at ``pos`` says; an ack held back at ``safe`` says nothing of
                # positions (those at ``pos`` sent with it numbered the events between again
                # one on, once the node reset and the source's channel came back: 57857)
                dep.inc[i].positions = dict(at) if safe == pos else {}
                producer = dep.placed[dep.app.edges[i].src]
                self.ctx.send(producer, m.Replay(dep.app.name, i, pos, at))
            if held:
                dep.gates[vertex] = gate = AckGate()
                gate.record(dict(snap.inputs), at)
        elif dep.replicas.get(vertex):  # replicated, yet no usable snapshot: said so
            why = "no replica answered" if restoring.replica is None else "replica not usable"
            self.ctx.note_event(self.ctx.now, f"{vertex}: {why}, its state restarts")
            self.ctx.publish(Happened("state_restarted", dep.app.name, vertex, why))
        starts = [c.expected for i, c in dep.inc.items() if dep.app.edges[i].dst == vertex]
        dep.marks.pop(vertex, None)
        dep.aside.pop(vertex, None)
        dep.catch_up.pop(vertex, None)
        dep.renumbered.pop(vertex, None)
        if restoring.fresh and vertex in dep.layout.stamped:
            # (an input whose numbering every consumer's marks name is not new to them)
            dep.renumbered[vertex] = set[int]().union(*(_anew(dep, restoring, o) for o in outs))
        forwarder = vertex in dep.layout.forwarders
        renew: dict[int, list[int]] = {}  # output -> inputs its forwarder's marks name anew
        # what it makes is new (a source's next events, or made of such only): none of it is
        # what its lost instance made, whose numbers may be named downstream (266014)
        ins = set(dep.in_edges.get(vertex, ()))
        new = h.kind == "source" or (snap is None and bool(ins) and ins <= restoring.new)
        for o in outs:
            if snap is None and _past_in_another(restoring, o):  # its consumer's numbering
                # wins: the acks' positions, there and further down, are of a lineage it
                # never took (fault seed 327842)
                restoring.positions = {e: p for e, p in restoring.positions.items() if e in outs}
                del restoring.positions[o]
                restoring.gens = _known(restoring.gens, restoring.positions)
            base = restoring.positions.get(o, restoring.consumer_start.get(o, 0))
            marks = restoring.consumer_marks.get(o) if snap is None or forwarder else None
            if marks:  # held by generation too: an input numbered anew below, whose marks
                # are let go, may come back to their numbering (an anchor: seed 150917)
                named = restoring.consumer_markgens.get(o, {})
                dep.aside.setdefault(vertex, {})[o] = provenance.held(marks, named)
            if marks is not None and forwarder:  # its consumer has the effects of the merge's
                # (not of an input the merge's replacement numbers anew: seed 2528)
                marks = provenance.without(marks, restoring.renumbered)
                base = restoring.consumer_start[o]  # inputs up to the marks: those first,
                dep.marks.setdefault(vertex, {})[o] = marks  # and sent on only past them
                if snap is not None:  # (mso.protocol.provenance, seed 8029)
                    (i,) = snap.inputs  # (a forwarder has one input)
                    dep.catch_up[vertex] = provenance.CatchUp(marks, self.ctx.now, i)
            elif marks is not None:  # a merge: from where its consumer stands, only what it
                base = restoring.consumer_start[o]  # lacks (mso.protocol.provenance); not
                # by an input numbered anew (its producer lost with the merge: seed 11242)
                anew = _anew(dep, restoring, o)
                if dep.app.edges[o].dst in dep.layout.forwarders:  # (its own marks of them)
                    renew[o] = sorted(anew & set(marks))
                marks = provenance.without(marks, anew)
                dep.marks.setdefault(vertex, {})[o] = marks
            elif snap is None and dep.replicas.get(vertex) and o not in restoring.positions:
                # no ack said where its output stood: a producer that replays what it retains
                # may start before the consumer's position; number from the input's start
                base = min([base, *starts])
            carried = None
            if h.kind == "source":  # after this node's reset, or its daemon's restart
                carried = self.dp.sf.carry_over(dep, o, base) or self.dp.sf.recover(dep, o, base)
            if snap is not None:  # numbered as the lost instance did after the snapshot; what
                numbered, unacked = snap.outputs.get(o, (base, []))  # not acked: again
                if marks is not None and forwarder:  # (only what its consumer lacks)
                    unacked = provenance.past(list(unacked), marks)
                else:
                    base = numbered
                dep.out[o] = self.dp.channel(dep, o, base)
                dep.out[o].push_many(list(unacked), self.ctx.now)
            else:
                dep.out[o] = carried or self.dp.channel(dep, o, base)
                known = o in restoring.positions or o in restoring.consumer_start
                dep.out[o].guessed = carried is None and not known
            if vertex in dep.layout.merges:  # what it makes from here interleaves anew
                dep.out[o].remade = dep.out[o].next_seq
                # numbered without its consumer's word (that consumer out of reach of the
                # restore, never resumed): an ack's positions say where the output stood when
                # the lost instance had taken that input so far, not what it made of the
                # other inputs after, which the consumer may have; the replay's first events
                # took those numbers and were dropped as had (fault seed 353984). They wait
                # until the consumer, asked, says where it stands and what it has
                dep.out[o].consumer_lost = o not in restoring.consumer_start
            # a source numbers on from its edges' positions: its sequence never restarts
            h.asked = max(h.asked, dep.out[o].next_seq) if h.kind == "source" else h.asked
            if _fresh(dep, vertex, h.kind, snap is not None, restoring):
                dep.fresh_from[o] = dep.out[o].next_seq
            # positions further down, for a restore of its consumer (replayed from here); a
            # source's carried channel keeps those its last ack brought (seed 1998)
            further = {e: p for e, p in restoring.positions.items() if e not in outs}
            if marks is not None and restoring.positions.get(o, base) != base:
                # numbered from where a marked consumer stands, not from the ack the positions
                # came with: they say nothing of this numbering (seed 1983, forks stamped)
                further = {}
            out = dep.out[o]
            if carried is None:
                out.number_as(self._numbering(restoring, o, base, out.guessed and snap is None))
            if further or carried is None:
                out.positions = further
                out.gens = _known(restoring.gens, further)
            told = restoring.consumer_positions.get(o)
            if (
                told
                and snap is None
                and marks is None
                and o not in restoring.positions
                and (
                    out.acked == restoring.consumer_start.get(o)
                    if carried is None
                    # a source's edge carried over with no positions at its start: the
                    # consumer, standing at or below it, gets nothing before that start (the
                    # numbers between were never used, or went with the process), so its
                    # outputs there are where they stand now (fault seed 202193)
                    else not out.positions and restoring.consumer_start.get(o, -1) <= out.acked
                )
            ):  # numbered from where its consumer stands: its outputs there, exactly
                out.positions = further | told
                out.gens = _known(restoring.gens, further) | _known(
                    restoring.consumer_gens.get(o, {}), told
                )
            if renew.get(o):  # a forwarder that survived holds its consumer's marks of
                self._tell_renumbered(dep, o, restoring.rid, renew[o])  # them: let go
            if new:
                out.new_from = out.next_seq
            if new and self._new_where_it_stands(dep, restoring, o, base, carried):
                # numbered from where its consumer, a merge or fork, stands: marks it holds of
                # that input past there name what the lost instance made at numbers the new
                # events take (fault seed 266014: a restarted source's first event dropped
                # as had); told, it lets them go
                news = m.Resume(dep.app.name, o, restoring.rid, True, out.acked, out.positions)
                news.gen, news.gens, news.new = out.gen, dict(out.gens), True
                self.ctx.send(dep.placed[dep.app.edges[o].dst], news)
            theirs = restoring.consumer_start.get(o, 0)
            guess = o in restoring.unheld and theirs > out.acked
            if (out.positions and theirs < out.acked) or guess:
                # its consumer has nothing of this edge: a replacement too, restored while
                # this one was out of reach or before it; say where its numbering stood (or
                # its start is past its consumers' marks, a guess: 40794, a fork's other
                # consumer, lost too, lacks what this one makes again below them; said with
                # no positions further down too, a source's restarted edge knowing its own
                # only: 340535)
                resume = m.Resume(dep.app.name, o, restoring.rid, True, out.acked, out.positions)
                resume.gen, resume.gens = out.gen, dict(out.gens)
                resume.renumbered = sorted(dep.renumbered.get(vertex, ()))
                self.ctx.send(dep.placed[dep.app.edges[o].dst], resume)
        if snap is None and outs:
            self._tell_start(dep, vertex, restoring, outs)
            self._guessed_from(dep, vertex, restoring, outs)
        if vertex in dep.marks:
            lowest = _merged(dep.marks[vertex].values())
            gens: dict[int, int] = {}  # (of the numberings the marks name)
            for o in dep.marks[vertex]:
                gens.update(restoring.consumer_markgens.get(o, {}))
            if not forwarder:
                self._start_past(dep, vertex, lowest, restoring.resumed, gens)
            else:  # its marks are of the merge's inputs, which start past them there if
                for i in restoring.resumed:  # their producers were lost too (seed 1996)
                    resume = m.Resume(dep.app.name, i, restoring.rid, False, dep.inc[i].expected)
                    resume.gen = dep.inc[i].gen  # (the numbering it took: not a standing in
                    resume.marks = provenance.to_wire(lowest)  # another, :meth:`on_resume`)
                    resume.markgens = _known(gens, lowest)
                    self.ctx.send(dep.placed[dep.app.edges[i].src], resume)
        for i, e in enumerate(dep.app.edges):  # what arrived early, in order
            if e.dst == vertex:
                for seq, events, ts, said in sorted(dep.stash.pop(i, []), key=lambda b: b[0]):
                    self.dp.deliver(dep, i, seq, events, ts, gens=said)
        version = placement.bump(dep, vertex)
        inc, coordinator = self.ctx.incarnation, restoring.coordinator
        # and where it ran as far as this node heard: a twin there, restored by another
        # coordinator, hears that this one is the later move and yields (on_superseded)
        also = [coordinator, dep.moved[vertex][1]]
        placement.announce(self.ctx, dep, vertex, self.ctx.id, incarnation=inc, also=also)
        self.relocator.forget(restoring.rid)
        done = m.HandoverDone(dep.app.name, vertex, restoring.rid, self.ctx.id, version)
        self.ctx.send(coordinator, done)
        if h.kind == "source":
            self.dp.start_source(dep, vertex, self.ctx.now)

    @staticmethod
    def _new_where_it_stands(
        dep: AppState, restoring: Restoring, o: int, base: int, carried: OutChannel | None
    ) -> bool:
        """A replacement whose events are all new tells the consumer of output ``o`` so: it
        numbers from where that consumer said it stands (no ack's positions, no channel
        carried over), and that consumer is a merge or fork, which keeps its consumers'
        marks."""
        return (
            carried is None
            and o not in restoring.positions
            and base == restoring.consumer_start.get(o, -1)
            and dep.app.edges[o].dst in dep.layout.stamped
        )

    def _tell_start(
        self, dep: AppState, vertex: str, restoring: Restoring, outs: list[int]
    ) -> None:
        """A replacement with one input that numbers its output from a known position tells
        its producer at once, with an ack at the input's start, where that output starts: the
        producer keeps it with the events it retains, so if this instance is lost too before
        an ack of its own came back (a partition holding the chained acks), the next
        replacement numbers what the replay makes as this one did. Without it, a producer
        restarted just before (its positions gone with its process) knew none; the next one
        guessed from 0 and its consumer's marks of this numbering were set aside (59759: an
        event of each source twice at the sink)."""
        exact = self._outputs_exact(dep, vertex)
        if exact is None or exact[0] not in restoring.resumed:
            return
        i, there = exact
        at = {e: p for e, p in restoring.positions.items() if e not in outs}
        ch = dep.inc[i]
        ch.positions = at | there
        ch.gens = _known(restoring.gens, at) | _gens(dep, there)
        ch.reack = True
        self.dp.ack(dep, i)

    @staticmethod
    def _guessed_from(dep: AppState, vertex: str, restoring: Restoring, outs: list[int]) -> None:
        """A replacement with one input and one output numbered on a guess (its consumer was
        lost too, and no ack said where the lost instance's output stood): the guess starts
        where the input does, which the output keeps (``OutChannel.made_from``) for when a
        consumer takes it (:meth:`_tell_taken`). Not a stamped vertex: its output is not one
        for one with its input's replay (it sends only what its consumers lack)."""
        inputs = dep.in_edges.get(vertex, [])
        if len(inputs) != 1 or len(outs) != 1 or vertex in dep.layout.stamped:
            return
        out, ch = dep.out[outs[0]], dep.inc.get(inputs[0])
        if ch is None or not out.guessed or inputs[0] not in restoring.resumed:
            return
        if ch.processed == ch.expected:  # (nothing taken yet: the stash comes after)
            out.made_from = ch.expected

    def _tell_taken(self, dep: AppState, vertex: str, o: int) -> None:
        """A consumer takes output ``o``'s guessed numbering (its replacement, answered from
        this channel; or one that survived, whose numbering the channel took instead:
        :meth:`_renumber`): the producer of the one input is told where that numbering
        starts, with an ack at the input's start carrying the output's position there and
        its generation, as :meth:`_tell_start` tells a start that is known. Without it the
        producer kept no position there, and this vertex, lost again before its consumer
        acknowledged anything (the chained acks held by a cut further down), had its next
        replacement number the replay from where the consumer stood, past what it had: the
        consumer took it all again (fault seed 309522: a restored source's first 3 events
        twice at the sink)."""
        out = dep.out.get(o)
        inputs = dep.in_edges.get(vertex, [])
        if out is None or out.made_from < 0 or out.acked != out.origin or len(inputs) != 1:
            return
        ch = dep.inc.get(inputs[0])
        if ch is None or ch._acked != out.made_from:  # (acknowledged since: positions went)
            return
        ch.positions = {o: out.origin}
        ch.gens = {o: out.gen} if out.gen else {}
        ch.reack = True
        self.dp.ack(dep, inputs[0])

    def _numbering(self, restoring: Restoring, o: int, base: int, guessed: bool) -> int:
        """The generation of a replacement's output ``o`` numbered from ``base``: a fresh one
        for a guess (no ack's positions, no consumer's word: a numbering made anew), else
        that of the positions it took (its producers' acks'), or of its consumer's."""
        if guessed:
            return self._new_generation()
        if o in restoring.positions and restoring.positions[o] == base:
            return restoring.gens.get(o, 0)
        if o in restoring.consumer_start:
            return restoring.consumer_gen.get(o, 0)
        return restoring.gens.get(o, 0)

    def _new_generation(self) -> int:
        """A numbering's generation no other is of (distinct across nodes, and across a
        node's incarnations)."""
        return (self.ctx.incarnation & 0x7FFFF) << 44 | self.ctx.new_pid()

    def _start_past(
        self, dep: AppState, vertex: str, marks: Marks, skip: set[int], gens: dict[int, int]
    ) -> None:
        """A merge's or fork's replacement whose producer of an input was lost too: that
        producer's replacement numbers the edge from where this one says it stands — from 0 if
        it has no channel yet, below what its consumers have of that input (their lowest
        ``marks``), so its new events were dropped as had (seeds 7472, 1996). Each input with
        no channel yet (and not in ``skip``: those whose producer resumed it) starts past the
        marks instead: what the producer makes anew is past them, and what it makes again in
        the old numbering (from its own producer's acks) comes below and is dropped as had;
        its output keeps the numbering from where its consumers stand (2678: renumbered by
        the producer's positions, one event took the number of one the sink had)."""
        gated = bool(dep.out_edges.get(vertex))
        for i, e in enumerate(dep.app.edges):
            if e.dst == vertex and i in marks and i not in skip and i not in dep.inc:
                stamped = e.src in dep.layout.stamped
                start = marks[i][0] + 1
                numbering = gens.get(i, 0)  # the marks': a producer of another is taken anew
                dep.inc[i] = InChannel.starting_at(start, gated, {} if stamped else None, numbering)
                dep.inc[i].unheld = True
                dep.inc[i].past_marks = start

    # -- a twin: a later restore placed the vertex elsewhere ------------------------------------
    def on_superseded(self, ev: Superseded) -> None:
        """Retire this instance: the ends of its edges were rewired to the later one, whose
        producers replay to it what this one had not passed on; what this one still holds
        unacknowledged is made again there, with the same numbers, so dropping it loses
        nothing and keeps every event once. A producer here fed this one, not the twin: its
        output is numbered as this one took it, and sent on to the twin, what lay below the
        twin's own position was dropped as had (fault seed 142356: 24 events of a restarted
        source). Its events wait until the twin says where it stands (``consumer_lost``, as
        for a consumer gone with its node), and go from there."""
        dep = self.ctx.apps.get(ev.app)
        h = dep.instances.get(ev.vertex) if dep is not None else None
        if dep is None or h is None or h.handing_over is not None or ev.vertex in dep.markers:
            return
        vid = ev.vertex
        self.dp.stop(h, "superseded")
        del dep.instances[vid]
        for i, e in enumerate(dep.app.edges):
            if e.dst == vid:
                dep.inc.pop(i, None)
                dep.stash.pop(i, None)
                if (out := dep.out.get(i)) is not None and e.src in dep.instances:
                    out.consumer_lost = True
        for i in dep.out_edges.get(vid, []):
            dep.out.pop(i, None)
            self.dp.outbox.pop((dep.app.name, i), None)
        dep.gates.pop(vid, None)
        self.ctx.note_event(
            self.ctx.now, f"retired {vid}: it runs on {ev.node} as move {ev.version}"
        )
        # the members told it runs here (at its restore) hear where it runs now, from the
        # node their view places it on: a twin restored across a cut may be the one that
        # goes, its host reset at the heal; held here still, nobody restored it (fault seed
        # 136485: the vertex ran nowhere)
        word = m.Moved(dep.app.name, vid, ev.node, ev.incarnation, ev.version)
        for n in sorted(placement.members(dep) - {self.ctx.id, ev.node} - self.ctx.failed):
            self.ctx.send(n, word)

    # -- a crashed instance: restored in place, within its restart budget ----------------------
    def on_instance_crashed(self, ev: InstanceCrashed) -> None:
        """Restore a crashed instance in place, as a restore after a node failure does: a
        fresh instance here; its producers replay what it had not passed on (acks are chained,
        so that is everything its outputs had not been acknowledged for) and its consumers say
        where they stand, so every event reaches them once, in order. Its own state restarts
        from its constructor. At most ``MAX_RESTARTS`` in ``RESTART_WINDOW_S``: a vertex that
        crashes on an event would crash again on its replay; then it stays crashed, its
        chains are reported parked and their events stay held (unacknowledged) upstream."""
        dep, vid, now = self.ctx.apps.get(ev.app), ev.vertex, self.ctx.now
        h = dep.instances.get(vid) if dep is not None else None
        if dep is not None and (h is None or h.instance != ev.instance):
            h = dep.awaiting.get(vid)
        if dep is None or h is None or h.instance != ev.instance:
            return
        rec = dep.crashes[vid]
        rec.times = [t for t in rec.times if now - t < RESTART_WINDOW_S]
        app = dep.app.name
        if h.life.state is not H.CRASHED or dep.instances.get(vid) is not h:
            if dep.awaiting.get(vid) is h:  # a replacement or a move's target, not fed yet:
                del dep.awaiting[vid]  # a restore's retried prepare starts another one
                dep.preparing.pop(vid, None)
                dep.restoring.pop(vid, None)
            return  # a move handing over: it ends by its deadline (docs/architecture.md)
        if h.handing_over is not None or vid in dep.markers:
            return
        if len(rec.times) > MAX_RESTARTS:
            rec.gave_up = (
                f"{vid!r} crashed {len(rec.times)} times in {RESTART_WINDOW_S:g} s on "
                f"{self.ctx.id} (last: {h.crashed}); not restarted"
            )
            for c in dep.layout.chains:
                if vid in c.vertices:
                    dep.parked.setdefault(c.index, rec.gave_up)
            return
        h.life.on(InstanceEvent.RESTART)
        del dep.instances[vid]
        dep.crashed[vid] = h
        for i, e in enumerate(dep.app.edges):  # its channels: the surviving ends resume anew
            if e.dst == vid:
                dep.inc.pop(i, None)
                dep.stash.pop(i, None)
            elif e.src == vid:
                dep.out.pop(i, None)
                self.dp.outbox.pop((app, i), None)
        dep.gates.pop(vid, None)
        dep.blocked_sources.discard(vid)
        rec.restarts += 1
        rec.restoring = self._restore_here(dep, vid, self.ctx.id, now)

    def _restore_here(self, dep: AppState, vid: str, source: str, now: float) -> int:
        """Coordinate, from this node, a restore of ``vid`` (lost on ``source``) on this
        node; its procedure id."""
        pid = self.ctx.new_pid()
        reloc = Relocation(pid, now, dep.app.name, vid, source, self.ctx.id, None)
        self.ctx.begin(reloc)
        self.relocator.start_restore(dep, reloc, pid, now)
        return pid

    def on_peer_failed(self, ev: PeerFailed) -> None:
        """A replacement waiting here for its surviving ends whose coordinator failed: this
        node coordinates its restore from here on. The others placed the vertex here at the
        coordinator's ``Rewire``, so none of them holds it lost and no recovery would ask
        again; it waited for ever, prepared and never run (fault seed 14459). Likewise a move's
        instance here awaiting a handover from ``node`` whose coordinator is gone too
        (:meth:`~.relocation.new_host.NewHost.orphaned`)."""
        node, now = ev.node, self.ctx.now
        for dep in list(self.ctx.apps.values()):
            self._consumers_lost(dep, node)
            for vid, restoring in sorted(dep.restoring.items()):
                if restoring.coordinator != node or vid not in dep.awaiting:
                    continue
                self.ctx.note_event(now, f"{vid}: its restore's coordinator {node} failed")
                lost_on = dep.placed.get(vid, node)  # (the coordinator's view, from Prepare)
                self._restore_here(dep, vid, node if lost_on == self.ctx.id else lost_on, now)
            for vid in self.relocator.orphaned(dep, node):
                self.ctx.note_event(now, f"{vid}: its move's coordinator and old host {node} went")
                self._restore_here(dep, vid, node, now)

    def on_peer_rejoined(self, ev: PeerRejoined) -> None:
        """A node heard back in a later incarnation, never held failed here: what it
        coordinated went with its last process, as with a failure (fault seed 264860: a
        restore's coordinator reset at a heal; its target, which had learnt of it from a
        sync and never held it failed, awaited the restore's surviving ends for good,
        holding an app it took no part in)."""
        if ev.restarted:
            self.on_peer_failed(PeerFailed(ev.node))

    def _consumers_lost(self, dep: AppState, node: str) -> None:
        """A stamped vertex running here whose consumer went with ``node``: its output
        channel is numbered in the lost instance's terms. The consumer's restore rewires it,
        unless that restore resumed a twin of this vertex, restored across a cut (gone since
        or not): then the consumer stands in the twin's numbering, and this one's, sent on,
        had it drop what it lacked as had (fault seed 118461: two of a source's events). So
        its events wait until a restore rewires it or the consumer, asked, says where it
        stands and what it has (its marks: :meth:`_renumber`)."""
        for edge, out in dep.out.items():
            e = dep.app.edges[edge]
            stamped = e.src in dep.instances and e.src in dep.layout.stamped
            if stamped and dep.placed.get(e.dst) == node:
                out.consumer_lost = True

    def on_relocation_ended(self, ev: RelocationEnded) -> None:
        """A restore in place after a crash ended: the vertex runs again, or stays crashed."""
        dep, error = self.ctx.apps.get(ev.app), ev.error
        rec = dep.crashes.get(ev.vertex) if dep is not None else None
        if dep is not None and rec is not None and rec.restoring == ev.pid:
            rec.restoring = None
            if error:  # no instance of it runs anywhere now: say so where it crashed
                rec.gave_up = f"restoring {ev.vertex!r} after its crash failed: {error}"
                for c in dep.layout.chains:
                    if ev.vertex in c.vertices:
                        dep.parked.setdefault(c.index, rec.gave_up)
            else:
                dep.crashed.pop(ev.vertex, None)


def _merged(marks: Iterable[Marks]) -> Marks:
    """The lowest mark of each input over several consumers' marks."""
    out: Marks = {}
    for mk in marks:
        for i, mark in mk.items():
            out[i] = min(out.get(i, mark), mark)
    return out


def _gens(dep: AppState, positions: Iterable[int]) -> dict[int, int]:
    """The generations of this node's output channels named in ``positions`` (those not 0)."""
    return {o: out.gen for o in positions if (out := dep.out.get(o)) is not None and out.gen}


def _anew(dep: AppState, restoring: Restoring, o: int) -> set[int]:
    """The inputs a replacement's producers number anew (``Resume.fresh``) that are new to
    the consumer of its output ``o``: not those whose numbering (its generation) that
    consumer's marks name -- a replacement lost before it acknowledged anything took that
    numbering, and the consumer has what it passed on (fault seed 200428: its marks set
    aside as of a numbering gone, the next replacement sent the consumer 9 events again)."""
    named = restoring.consumer_markgens.get(o, {})
    return {i for i in restoring.fresh if not (g := dep.inc[i].gen) or named.get(i) != g}


def _past_in_another(restoring: Restoring, o: int) -> bool:
    """The consumer of output ``o``, one that survived (running: it answered the rewire),
    stands past the position the producers' acks gave ``o``, in another numbering (another
    generation): those positions are of a lineage restored across a cut and lost since (a
    twin of this consumer took that numbering), which this consumer never took.
    Numbered from them, the replay and the new events took numbers below where it stands
    and it dropped them as had (fault seed 327842: ``b``, restored after a heal that reset
    its node, numbered from its source's carried positions, 10 in the lost twin's guess;
    the merge ``m``, cut off all along, stood at 18 in the first numbering and dropped a
    restarted source's first 8 events). Not a consumer whose start is a guess (past its
    consumers' marks, ``unheld``): that one takes the producer's numbering (105902)."""
    if o not in restoring.positions or o not in restoring.consumer_start:
        return False
    if o in restoring.unheld or restoring.consumer_start[o] <= restoring.positions[o]:
        return False
    return restoring.consumer_gen.get(o, 0) != restoring.gens.get(o, 0)


def _new_past(out: OutChannel) -> bool:
    """Every event of ``out`` from its ack on is new (``OutChannel.new_from``), and no ack
    since said what its consumer made of them (its positions: those name that numbering)."""
    if not 0 <= out.new_from <= out.acked:
        return False
    return not (out.positions and out.positions_at >= out.new_from)


def _known(gens: dict[int, int], positions: Iterable[int]) -> dict[int, int]:
    """Of ``gens``, those of ``positions`` (and not 0)."""
    return {e: g for e in positions if (g := gens.get(e, 0))}


def _ready(dep: AppState, vertex: str, restoring: Restoring) -> bool:
    """A replacement runs once every surviving end has resumed it and, for a replicated
    vertex, its replicas were asked for its state and one answered (or none is left)."""
    if restoring.pending or restoring.fetching:
        return False
    return restoring.fetched or not dep.replicas.get(vertex)


def _fresh(dep: AppState, vertex: str, kind: str, from_replica: bool, r: Restoring) -> bool:
    """What the replacement makes is new, not what the lost instance made again: a source's
    next events, the output of a state restarted from the constructor, or of a vertex fed by
    a producer that was lost with it (what that one makes is new in turn)."""
    if kind == "source":
        return True
    if not from_replica and has_state(dep.app.vertices[vertex]):
        return True
    ins = set(dep.in_edges.get(vertex, ()))
    return not ins <= r.resumed
