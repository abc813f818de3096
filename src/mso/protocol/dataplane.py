"""The data plane at one node: vertex instances in the executor, edges, acks, backpressure.

A component of the node core (:mod:`mso.node.core`), acting through its
:class:`~mso.protocol.context.NodeContext`. It never runs vertex code: it asks the executor
(``mso.runtime``) to start, feed, run, snapshot and stop instances, and takes their results in
:meth:`DataPlane.on_vertex`. Each instance has a bounded queue of events fed and not yet
processed; what is not fed is not acknowledged, so a slow consumer fills its producers' windows
and they wait (backpressure). Acks are chained: a vertex's inputs are acknowledged once its
outputs are, so what is acked upstream is safe downstream and a failure loses nothing the
survivors cannot replay.

What the procedures need to know of an instance's life it publishes as internal events
(:mod:`mso.protocol.events`): ready, failed at construction, crashed, a marker reached it, its
state was taken. Markers travel in-band with the events, so an instance meets one only after
everything sent before it.
"""

from __future__ import annotations

from collections.abc import Iterable

from mso.protocol import effects as fx
from mso.protocol import messages as m
from mso.protocol import provenance
from mso.protocol.channel import REPLICA_OWNER as REPLICA_OWNER  # (where procedures read it)
from mso.protocol.channel import AckGate, InChannel, OutChannel
from mso.protocol.context import NodeContext
from mso.protocol.effects import Send, SetTimer
from mso.protocol.events import (
    InstanceCrashed,
    InstanceFailed,
    InstanceReady,
    MarkerReached,
    Retransmit,
    SnapshotAligned,
    Snapshotted,
    SourceTick,
)
from mso.protocol.forward import MAX_BATCH_BYTES, StoreAndForward
from mso.protocol.forward import RETRANSMIT_S as RETRANSMIT_S  # (where procedures read it)
from mso.protocol.procedures.instance import InstanceEvent
from mso.protocol.state import SNAPSHOT_MARK, AppState, Crashes, HostedInstance, SnapshotMark
from mso.protocol.taps import Taps

QUEUE_EVENTS = 1024  # events fed to an instance's worker and not processed yet, at most
FEED_BATCH = 256  # events per feed at most, so markers and stops are not held behind a batch
SOURCE_RUN = 4096  # calls of a rated source per run at most
ACK_EVERY = 256  # events processed before an ack is sent without waiting for the flush
DELAY_SMOOTHING = 0.2  # weight of the newest batch in a chain's delay average


class DataPlane:
    """Vertex instances and the edges between them (see the module docstring)."""

    def __init__(self, ctx: NodeContext) -> None:
        self.ctx = ctx
        # vertex instances this node asked the executor for: id -> (app, vertex)
        self._instances: dict[int, tuple[str, str]] = {}
        self._next_instance = 0
        # per edge: (first seq, events, when the oldest entered its chain)
        self.outbox: dict[tuple[str, int], tuple[int, list[bytes], float]] = {}
        self.work_ms = 0.0  # modelled CPU work of every event processed here (cost units)
        # apps whose channels may have changed since the last flush: only theirs are looked
        # at for acks due and retransmissions to arm (all apps' after every event was 23-26%
        # of a 400-node simulation)
        self.touched: set[str] = set()
        self.armed: set[str] = set()  # apps whose retransmit timer is set
        self.cpu_ms = 0.0  # measured CPU time of the vertex code that ran here
        self.sf = StoreAndForward(ctx, self)  # the producer's side of an outage
        self.taps = Taps(ctx)  # copies of edges for clients looking at them (mso echo)
        # forwarders' replacements holding input past their consumer's marks, (app, vertex):
        # released by the deadline at a flush (AppState.catch_up holds what they hold)
        self.catching: set[tuple[str, str]] = set()

    def host(self, dep: AppState, vid: str) -> HostedInstance:
        """Ask the executor for a new instance of ``vid``."""
        self._next_instance += 1
        iid = self._next_instance
        self._instances[iid] = (dep.app.name, vid)
        edges = dep.app.edges
        inputs = {i: dep.app.edge_format(e) for i, e in enumerate(edges) if e.dst == vid}
        outputs = {i: dep.app.edge_format(e) for i, e in enumerate(edges) if e.src == vid}
        names = {i: f"{e.src} -> {e.dst}" for i, e in enumerate(edges) if vid in (e.src, e.dst)}
        h = HostedInstance(iid, dep.app.vertices[vid], dep.layout.kinds[vid])
        rec = dep.crashes.get(vid)
        if rec is not None and rec.restoring is not None:  # replaces a crashed instance:
            h.one_by_one = self.ctx.window * len(inputs)  # its replay is at most a window
        owners = vid in dep.layout.stamped
        start = fx.StartVertex(
            iid, dep.app.name, h.vertex, h.kind, inputs, None, outputs, names, owners
        )
        self.submit(h, start)
        return h

    def submit(self, h: HostedInstance, eff: fx.VertexEffect, events: int = 0) -> None:
        self.ctx.emit(eff)
        h.jobs += 1
        h.queued += events
        if h.busy_since is None:
            h.busy_since = self.ctx.now

    def stop(self, h: HostedInstance, reason: str) -> None:
        if not h.life.done:
            h.life.on(InstanceEvent.STOP)
        self._instances.pop(h.instance, None)
        self.ctx.emit(fx.StopVertex(h.instance, reason))

    def stop_app(self, dep: AppState, reason: str) -> None:
        for h in [*dep.instances.values(), *dep.awaiting.values()]:
            self.stop(h, reason)
        if reason == "undeploy":
            self.sf.forget(dep)

    def stop_all(self, reason: str) -> None:
        for dep in self.ctx.apps.values():
            if reason == "reset":  # its sources' edges outlive the reset
                self.sf.carry(dep)
            self.stop_app(dep, reason)

    def on_vertex(self, res: fx.VertexResult, now: float) -> None:
        """A result from the executor: account for it, then act on what it says."""
        owner = self._instances.get(res.instance)
        dep = self.ctx.apps.get(owner[0]) if owner is not None else None
        if owner is None or dep is None:
            return  # stopped meanwhile
        vid = owner[1]
        h = dep.instances.get(vid) or dep.awaiting.get(vid)
        if h is None or h.instance != res.instance:
            return
        if isinstance(res, fx.VertexCrashed):
            self._crashed(dep, vid, h, res, now)
            return
        h.jobs -= 1
        h.busy_since = now if h.jobs else None
        h.cpu_s += res.cpu_s
        self.cpu_ms += res.cpu_s * 1e3
        h.errors += res.errors
        h.last_error = res.last_error or h.last_error
        h.stats, h.state_size = res.stats, res.state_size
        if isinstance(res, fx.VertexStarted):
            self._started(dep, vid, h, res, now)
        elif isinstance(res, fx.VertexProcessed):
            self._processed(dep, vid, h, res, now)
        elif isinstance(res, fx.VertexEmitted):
            self._emitted(dep, vid, h, res, now)
        else:
            self.ctx.publish(Snapshotted(dep.app.name, vid, res))
            # what waited for the snapshot (a relocation's marker behind a replication's
            # snapshot: its producers have switched, no event comes to pump it) goes on now
            self.pump(dep, vid)

    def _crashed(
        self, dep: AppState, vid: str, h: HostedInstance, res: fx.VertexCrashed, now: float
    ) -> None:
        """An instance's child process died unasked. Counted and reported, never fatal: what
        it was working on is unanswered, so nothing it held was acknowledged (its producers
        still hold it). One that had not started fails as a failed construction does."""
        self._instances.pop(h.instance, None)
        self.ctx.emit(fx.StopVertex(h.instance, "crashed"))  # frees its lane
        h.jobs = h.queued = h.credit = 0
        h.busy_since = None
        h.crashed = res.reason
        rec = dep.crashes.setdefault(vid, Crashes())
        rec.count += 1
        rec.last = f"{self.ctx.id}: {res.reason}"
        rec.times.append(now)
        self.ctx.note_event(now, f"{vid} crashed ({res.reason})")
        h.life.on(InstanceEvent.CRASH)
        if not h.started:
            dep.instances.pop(vid, None)
            dep.awaiting.pop(vid, None)
            self.ctx.publish(
                InstanceFailed(
                    dep.app.name, vid, f"{self.ctx.id}: {vid!r} crashed starting ({res.reason})"
                )
            )
            return
        self.ctx.publish(InstanceCrashed(dep.app.name, vid, h.instance))

    def _started(
        self, dep: AppState, vid: str, h: HostedInstance, res: fx.VertexStarted, now: float
    ) -> None:
        self.ctx.note_start(now)  # its start-up CPU is in the figures from now on
        if res.error:  # user code failing at construction: refuse, change nothing
            self.stop(h, "failed")
            dep.instances.pop(vid, None)
            dep.awaiting.pop(vid, None)
            self.ctx.publish(InstanceFailed(dep.app.name, vid, f"{self.ctx.id}: {res.error}"))
            return
        h.started, h.mode = True, res.mode
        h.life.on(InstanceEvent.STARTED_FOR_MOVE if vid in dep.awaiting else InstanceEvent.STARTED)
        self.ctx.publish(InstanceReady(dep.app.name, vid))
        if h.kind == "source" and vid in dep.instances:
            self.start_source(dep, vid, now)

    def out(self, dep: AppState, edge: int) -> OutChannel:
        ch = dep.out.get(edge)
        if ch is None:
            ch = dep.out[edge] = self.channel(dep, edge)
        return ch

    def channel(self, dep: AppState, edge: int, start: int = 0) -> OutChannel:
        """A new producer end of ``edge`` numbering from ``start`` (store and forward's), which
        retains its events for a replicated consumer."""
        ch = self.sf.channel(dep, edge, start)
        retain_for_replica(dep, edge, ch)
        return ch

    def start_source(self, dep: AppState, vid: str, now: float) -> None:
        h = dep.instances[vid]
        if not h.started or not dep.running:
            return
        if h.mode == "loop":
            self.grant(dep, vid)
            return
        h.t0 = now - h.asked / h.rate if h.rate else now  # (restored: numbers on, see asked)
        self.ctx.emit(SetTimer(SourceTick(dep.app.name, vid), now))

    def _room(self, dep: AppState, vid: str) -> int:
        rooms = (self.sf.edge_room(dep, e) for e in dep.out_edges.get(vid, []))
        return min(rooms, default=SOURCE_RUN)

    def source_tick(self, app: str, vid: str, now: float) -> None:
        """A rated source keeps its schedule: event k is due at t0 + k / rate; a late tick
        asks for every event due since (up to the window), so the rate holds on average."""
        dep = self.ctx.apps.get(app)
        h = dep.instances.get(vid) if dep is not None else None
        if dep is None or h is None or not dep.running or not h.started or h.jobs or h.ended:
            return  # a run in flight schedules the next tick when it is done
        rate = h.rate
        due = int((now - h.t0) * rate + 1e-9) + 1 - h.asked
        room = self._room(dep, vid)
        n = min(due, room, SOURCE_RUN)
        if n <= 0:
            if room <= 0:  # backpressure: a full window holds the source until an ack
                dep.blocked_sources.add(vid)
            else:
                self.ctx.emit(SetTimer(SourceTick(app, vid), h.t0 + h.asked / rate))
            return
        self.submit(h, fx.RunSource(h.instance, h.asked, n, now))
        h.asked += n

    def grant(self, dep: AppState, vid: str) -> None:
        """A free-running source may make as many calls as its window has room for."""
        h = dep.instances[vid]
        if not h.started or h.ended or not dep.running:
            return
        room = self._room(dep, vid) - h.credit
        if room > 0 and (h.credit == 0 or room >= min(FEED_BATCH, self.ctx.window // 4)):
            h.credit += room
            self.ctx.emit(fx.Credit(h.instance, room))

    def _emitted(
        self, dep: AppState, vid: str, h: HostedInstance, res: fx.VertexEmitted, now: float
    ) -> None:
        h.calls += res.calls
        self.work_ms += h.vertex.cost * res.calls
        edges = dep.out_edges.get(vid, [])
        outputs = res.outputs
        if res.ended and not h.ended:  # the stream is over: say so on every edge, in order
            h.ended = True
            outputs = [*outputs, fx.END_OF_STREAM]
        if outputs:
            h.emitted += fx.events_in(outputs)
            h.bytes_out += self.send_events(dep, edges, outputs, now, -1) * len(edges)
        if h.mode == "loop":
            h.credit -= res.calls
            self.grant(dep, vid)
        elif dep.running and not h.ended:
            at = h.t0 + h.asked / h.rate
            self.ctx.emit(SetTimer(SourceTick(dep.app.name, vid), max(at, now)))

    def send_events(
        self, dep: AppState, edges: Iterable[int], payloads: list[bytes], ts: float, chain: int
    ) -> int:
        """Send encoded events on every edge in ``edges``; returns their size in bytes.
        ``ts`` is when they entered chain ``chain``: an edge of that chain carries it on, an
        edge that starts another chain starts it from now."""
        for e in edges:
            out = self.out(dep, e)
            seq = out.push_many(payloads, self.ctx.now)
            self.touched.add(dep.app.name)
            if out.sent != seq or self.sf.held(dep, e):  # out of reach, or a backlog to send first
                self.sf.hold(dep, e, out)
                continue
            out.sent = out.next_seq
            dst_node = dep.placed[dep.app.edges[e].dst]
            t = ts if dep.layout.edge_chain[e] == chain else self.ctx.now
            if dst_node == self.ctx.id:
                self.deliver(dep, e, seq, payloads, t, out.acked, self.stamp_gens(dep, e))
            else:
                key = (dep.app.name, e)
                batch = self.outbox.get(key)
                if batch is None:
                    self.outbox[key] = batch = (seq, list(payloads), t)
                else:
                    batch[1].extend(payloads)
                if len(batch[1]) * len(payloads[0]) >= MAX_BATCH_BYTES:  # frames stay small
                    del self.outbox[key]
                    data = m.Data(dep.app.name, e, dep.epoch, *batch, floor=out.acked)
                    data.gens = self.stamp_gens(dep, e)
                    self.ctx.emit(Send(dst_node, data))
        return sum(map(len, payloads))

    def deliver(
        self,
        dep: AppState,
        edge: int,
        seq: int,
        events: list[bytes],
        ts: float = 0.0,
        floor: int = 0,
        gens: dict[int, int] | None = None,
    ) -> None:
        """Events ``seq``... of ``edge`` to its consumer here; ``gens``: the generations of
        the numberings a stamped producer's headers name (:meth:`stamp_gens`; None: not
        said, those known stand)."""
        dst = dep.app.edges[edge].dst
        if dst in dep.awaiting:  # moving here: keep until the handover
            dep.stash.setdefault(edge, []).append((seq, list(events), ts, gens))
            return
        if dst not in dep.instances:  # placed here, not running (yet): taken, they would be
            self.ctx.dropped()  # acknowledged and lost; the producer keeps them (16310)
            return
        ch = dep.inc.get(edge)
        if ch is None:
            ch = dep.inc[edge] = InChannel(marks={})  # the edge's first events here
        fresh = ch.accept(seq, events, floor)
        self.touched.add(dep.app.name)
        whole = False  # a forwarder's input keeps its headers until fed (pump)
        if fresh and dep.app.edges[edge].src in dep.layout.stamped:
            before = dict(ch.marks or {})
            if dst in dep.layout.forwarders:
                provenance.note(fresh, ch.marks)
                whole = True
            else:
                fresh = provenance.strip(fresh, ch.marks)
            if gens is not None and ch.marks is not None:  # what the new marks are of
                for i, mark in ch.marks.items():
                    if before.get(i) != mark and gens.get(i, 0):
                        ch.markgens[i] = gens[i]
                    elif before.get(i) != mark:
                        ch.markgens.pop(i, None)
        if fresh:
            if self.taps.watched:
                seen = provenance.split(fresh)[0] if whole else fresh
                self.taps.saw(dep.app.name, edge, ch.expected - len(fresh), seen, ts)
            catch_up = dep.catch_up.get(dst)
            if catch_up is not None:
                fresh = catch_up.take(fresh, self.ctx.now)
                if catch_up.done:
                    del dep.catch_up[dst]
                else:
                    catch_up.ts = ts
                    self.catching.add((dep.app.name, dst))
            deadline = dep.app.edges[edge].deadline_ms
            now = self.ctx.now
            late = ch.last_at is not None and (now - ch.last_at) * 1e3 > (deadline or 0)
            if deadline is not None and late:
                ch.deadline_missed += 1
            ch.last_at = now
            self.enqueue(dep, dst, (edge, fresh, ts))

    def enqueue(
        self, dep: AppState, vid: str, item: tuple[int, list[bytes], float] | m.Marker
    ) -> None:
        """Events and markers for an instance, in arrival order: a marker is handled once
        everything before it has been processed."""
        h = dep.instances.get(vid)
        if isinstance(item, m.Marker) and vid in dep.catch_up:  # moving: what it held first
            catch_up = dep.catch_up.pop(vid)
            if h is not None and (held := catch_up.release()):
                h.pending.append((catch_up.edge, held, catch_up.ts))
        if h is not None:
            h.pending.append(item)
            self.pump(dep, vid)

    def pump(self, dep: AppState, vid: str) -> None:
        """Feed the instance's worker while its bounded queue has room (backpressure: what
        is not fed is not acknowledged, so the producers' windows fill and they stop)."""
        h = dep.instances.get(vid)
        while h is not None and h.pending and h.handing_over is None and not h.crashed:
            item = h.pending[0]
            if isinstance(item, SnapshotMark):  # aligned once everything fed is processed
                if h.jobs:
                    return
                h.pending.popleft()
                self.ctx.publish(SnapshotAligned(dep.app.name, vid))
                continue
            if isinstance(item, m.Marker):
                if h.jobs:
                    return
                h.pending.popleft()
                self.ctx.publish(MarkerReached(dep.app.name, item))
                continue
            if h.queued >= QUEUE_EVENTS:
                return
            qos = dep.app.edges[item[0]]
            if qos.keep_last is not None or qos.lifespan_ms is not None:
                if not h.queued and self._give_up_input(dep, vid, h):
                    continue
                if qos.keep_last is not None and h.queued:
                    return  # the newest N wait here, where newer ones can supersede them,
                    # and go to the worker together once it is idle (it then has at most N)
            edge, events, ts = item
            most = 1 if h.one_by_one > 0 else FEED_BATCH
            if len(events) > most:
                feed = events[:most]
                h.pending[0] = (edge, events[most:], ts)
            else:
                h.pending.popleft()
                feed = events
            h.one_by_one -= len(feed) if h.one_by_one > 0 else 0
            if vid in dep.layout.forwarders:
                feed, heads = provenance.split(feed)
                h.heads.append(heads)
            h.bytes_in += sum(map(len, feed))
            self.submit(h, fx.FeedVertex(h.instance, edge, feed, ts), len(feed))

    @staticmethod
    def stamp_gens(dep: AppState, edge: int) -> dict[int, int]:
        """What a stamped producer's frames on ``edge`` say of the numberings its events'
        headers name (``Data.gens``): a merge's or fork's inputs' generations, a forwarder's
        as its merge's frames said (those not 0; empty for any other producer). A vertex's
        input is numbered anew only while nothing of it is in flight, so a frame's word holds
        for the events it carries."""
        vid = dep.app.edges[edge].src
        if vid not in dep.layout.stamped:
            return {}
        ins = [
            (i, ch) for i, e in enumerate(dep.app.edges) if e.dst == vid and (ch := dep.inc.get(i))
        ]
        if vid in dep.layout.forwarders:
            return {i: g for _, ch in ins for i, g in ch.markgens.items() if g}
        return {i: ch.gen for i, ch in ins if ch.gen}

    def on_data(self, msg: m.Data, src: str = "") -> None:
        """A frame from ``src`` (the node that sent it): each edge's events to its consumer."""
        dep = self.ctx.apps.get(msg.app)
        if dep is None or msg.epoch != dep.epoch:
            self.ctx.dropped()
            return
        parts = [(msg.edge, msg.seq, msg.floor), *msg.also]
        edges = {edge for edge, _, _ in parts}
        n = len(dep.app.edges)
        if len(edges) < len(parts) or not all(0 <= e < n for e in edges):
            self.ctx.dropped()  # an edge twice, or one the app does not have
            return
        if dep.view.gone is not None and any(
            dep.view.replaced(dep.app.edges[e].src, src) for e in edges
        ):
            # from an instance of the producer that a restore replaced: cut off and held
            # failed, it ran on until its node reset, numbering in its own run; taken, its
            # event took a number the replacement sends next, dropped as had (fault seed
            # 162674: 1 lost). Frames from a node this view neither places the producer on
            # nor holds replaced (a move's old host before the switch) are taken
            self.ctx.dropped()
            return
        for i, (edge, seq, floor) in enumerate(parts):
            events = msg.events if i == 0 else list(msg.events)  # each edge its own list
            self.deliver(dep, edge, seq, events, msg.ts, floor, msg.gens)

    def _processed(
        self, dep: AppState, vid: str, h: HostedInstance, res: fx.VertexProcessed, now: float
    ) -> None:
        """A batch went through the edge's consumer: pass its outputs on, acknowledge."""
        edge = res.edge
        # a forwarder: the headers of the batch it processed (fed in order, one by one)
        heads = h.heads.popleft() if h.heads and vid in dep.layout.forwarders else []
        h.queued -= res.count
        h.processed += res.count - res.ends
        h.ended = h.ended or res.ended
        if h.snapshot_at and h.processed >= h.snapshot_at:  # a replication snapshot is due
            h.snapshot_at = 0
            h.pending.appendleft(SNAPSHOT_MARK)
        self.work_ms += h.vertex.cost * res.count
        ch = dep.inc.get(edge)
        if ch is None:
            return
        first = ch.processed  # the batch's first sequence number
        ch.mark_processed(res.count)
        self.touched.add(dep.app.name)
        chain = dep.layout.edge_chain[edge]
        ts = res.ts
        if ts > 0 and dep.layout.chains[chain].tail == vid:  # end-to-end through the chain
            ms = (now - ts) * 1e3
            old = dep.delays.get(chain)
            dep.delays[chain] = (
                ms if old is None else DELAY_SMOOTHING * ms + (1 - DELAY_SMOOTHING) * old
            )
            dep.engaged.note()  # reported from here every monitor period (report_delays)
        out_edges = dep.out_edges.get(vid, [])
        if res.outputs and out_edges:
            h.emitted += fx.events_in(res.outputs)
            outputs = res.outputs
            if vid in dep.layout.stamped:  # (module docstring of mso.protocol.provenance)
                if vid in dep.layout.forwarders:
                    outputs = provenance.forward(outputs, heads, res.owners)
                else:
                    outputs = provenance.stamp(outputs, edge, first, res.owners)
                marks, aside = dep.marks.get(vid), dep.aside.get(vid)
                if marks or aside:  # a replacement: only what each consumer lacks
                    for o in out_edges:
                        held = aside.get(o) if aside else None  # (by generation: seed 150917)
                        gens = self.stamp_gens(dep, o) if held is not None else {}
                        if marks and o in marks and held is not None:  # (seed 277659)
                            provenance.renamed(marks[o], held, gens)
                        lacks = provenance.past(outputs, marks.get(o, {})) if marks else outputs
                        if aside and held is not None:
                            lacks = provenance.past_held(lacks, held, gens)
                            if not held:
                                del aside[o]
                        if lacks:
                            h.bytes_out += self.send_events(dep, [o], lacks, ts, chain)
                        if lacks and marks and o in marks:  # held only until the first event
                            provenance.outlived(lacks, marks[o])  # past it
                            if not marks[o]:
                                del marks[o]
                    if marks is not None and not marks:
                        del dep.marks[vid]
                    if aside is not None and not aside:
                        del dep.aside[vid]
                    outputs = []
            if outputs:
                sent = self.send_events(dep, out_edges, outputs, ts, chain)
                h.bytes_out += sent * len(out_edges)
        self._input_done(dep, vid, edge, ch)
        self.pump(dep, vid)

    def _input_done(self, dep: AppState, vid: str, edge: int, ch: InChannel) -> None:
        """Events of ``edge`` are processed (or given up by its QoS): acknowledge them."""
        self.touched.add(dep.app.name)  # (a sink's ack goes at the flush)
        out_edges = dep.out_edges.get(vid, [])
        if out_edges:  # chained acks: the inputs are acked once the outputs are
            if ch.released is None:
                ch.released = ch._acked
            gate = dep.gates.get(vid)
            if gate is None:
                gate = dep.gates[vid] = AckGate()
            gate.record({edge: ch.processed}, {o: self.out(dep, o).next_seq for o in out_edges})
            self.release(dep, vid)
        elif ch.processed - ch._acked >= ACK_EVERY:
            self.ack(dep, edge)

    def _give_up_input(self, dep: AppState, vid: str, h: HostedInstance) -> bool:
        """With nothing in the worker, apply the QoS of the next waiting events' edge:
        expired ones (lifespan) and all but the newest ``keep_last`` (superseded) are counted
        and acknowledged unfed. True if any were."""
        item = h.pending[0]
        assert isinstance(item, tuple)
        edge, events, ts = item
        e, ch = dep.app.edges[edge], dep.inc.get(edge)
        if ch is None:
            return False
        if e.lifespan_ms is not None and self.ctx.now - ts > e.lifespan_ms / 1e3:
            h.pending.popleft()
            ch.expired += len(events)
            ch.mark_processed(len(events))
            self._input_done(dep, vid, edge, ch)
            return True
        if e.keep_last is None:
            return False
        waiting = 0
        for it in h.pending:
            if not isinstance(it, tuple):
                break  # (what follows a marker is the next instance's; a snapshot's, after it)
            if it[0] == edge:
                waiting += len(it[1])
        extra = waiting - e.keep_last
        if extra <= 0:
            return False
        kept: list[tuple[int, list[bytes], float] | m.Marker | SnapshotMark] = []
        left = extra
        while h.pending and left:
            it = h.pending.popleft()
            if not isinstance(it, tuple) or it[0] != edge:
                kept.append(it)
                continue
            n = min(left, len(it[1]))
            left -= n
            if n < len(it[1]):
                kept.append((edge, it[1][n:], it[2]))
        h.pending.extendleft(reversed(kept))
        ch.superseded += extra
        ch.mark_processed(extra)
        self._input_done(dep, vid, edge, ch)
        return True

    def release(self, dep: AppState, vid: str) -> None:
        """Acknowledge the inputs of ``vid`` as far as its outputs have been acknowledged."""
        gate = dep.gates.get(vid)
        if gate is None:
            return
        acked = {o: out.acked for o in dep.out_edges.get(vid, []) if (out := dep.out.get(o))}
        released = gate.release(acked, lambda outputs: self._known_below(dep, outputs))
        if released is None:
            return
        inputs, outputs = released
        further = dict(outputs)  # and, known exactly at these positions, the ones downstream
        gens = {o: out.gen for o in outputs if (out := dep.out.get(o)) and out.gen}
        for o, pos in outputs.items():
            out = dep.out.get(o)
            if out is None:
                continue
            below = out.history_gens.get(pos, {})
            for e, p in out.history.get(pos, {}).items():
                if e not in further:
                    further[e] = p
                    if below.get(e):
                        gens[e] = below[e]
        for i, pos in inputs.items():
            ch = dep.inc.get(i)
            if ch is not None:
                ch.released = max(ch.released or 0, pos)
                ch.positions, ch.gens = further, gens
                self.ack(dep, i)

    @staticmethod
    def _known_below(dep: AppState, outputs: dict[int, int]) -> bool:
        """At these output positions, an ack from each consumer with outputs of its own came
        (its positions further down are known there: :meth:`AckGate.release`)."""
        for o, pos in outputs.items():
            out = dep.out.get(o)
            if (
                out is not None
                and pos not in out.history
                and dep.out_edges.get(dep.app.edges[o].dst)
            ):
                return False
        return True

    def ack(self, dep: AppState, edge: int) -> None:
        ch = dep.inc.get(edge)
        upto = ch.ack_due() if ch is not None else None  # nothing arrived yet: nothing to ack
        if ch is None or upto is None:
            return
        producer = dep.app.edges[edge].src
        src_node = dep.placed[producer]
        if src_node == self.ctx.id:
            out = self.out(dep, edge)
            if upto > out.next_seq:  # this channel never sent that far (a fresh one after a
                self.ctx.dropped()  # move): nothing to release, never a crash
                return
            out.on_ack(upto, self.ctx.now)
            out.note_positions(upto, dict(ch.positions), ch.gens)
            self.sf.drain(dep, edge)
            self.unblock(dep, edge)
            self.release(dep, producer)
        elif src_node not in self.ctx.failed:
            self.ctx.emit(
                Send(
                    src_node,
                    m.Ack(dep.app.name, edge, dep.epoch, upto, dict(ch.positions), dict(ch.gens)),
                )
            )

    def on_ack(self, msg: m.Ack, now: float) -> None:
        dep = self.ctx.apps.get(msg.app)
        if dep is None or msg.epoch != dep.epoch or msg.edge not in dep.out:
            self.ctx.dropped()
            return
        out = dep.out[msg.edge]
        try:
            out.on_ack(msg.upto, now)
        except ValueError:
            self.ctx.dropped()
            return
        out.note_positions(msg.upto, msg.positions, msg.gens)
        self.sf.drain(dep, msg.edge)
        self.unblock(dep, msg.edge)
        self.release(dep, dep.app.edges[msg.edge].src)

    def unblock(self, dep: AppState, edge: int) -> None:
        """An ack freed room on ``edge``: wake its producer if backpressure stopped it. A
        rated source skips the time it was held (a sensor does not deliver missed samples)."""
        producer = dep.app.edges[edge].src
        h = dep.instances.get(producer)
        if h is None or h.kind != "source":
            return
        if h.mode == "loop":
            self.grant(dep, producer)
        elif producer in dep.blocked_sources:
            dep.blocked_sources.discard(producer)
            h.t0 = self.ctx.now - h.asked / h.rate
            self.ctx.emit(SetTimer(SourceTick(dep.app.name, producer), self.ctx.now))

    def flush(self) -> None:
        """Send what the outbox gathered: one frame per edge, except that edges carrying the
        same events at the same time to the same node share one (``Data.also``)."""
        if not (self.outbox or self.touched or self.catching):
            return  # (after every event the core handles: after a beat's tick, nothing)
        # (app, node, ts) -> its frames; events are compared, not hashed: the batches of one
        # emit share their payload objects, so a fork's comparison is a pointer walk
        frames: dict[tuple[str, str, float], list[m.Data]] = {}
        for (app, edge), (seq, events, ts) in self.outbox.items():
            dep = self.ctx.apps[app]
            dst = dep.placed[dep.app.edges[edge].dst]
            floor = out.acked if (out := dep.out.get(edge)) is not None else 0
            same = frames.setdefault((app, dst, ts), [])
            gens = self.stamp_gens(dep, edge)
            data = next((d for d in same if d.events == events and d.gens == gens), None)
            if data is None:
                same.append(m.Data(app, edge, dep.epoch, seq, events, ts, floor, gens=gens))
            else:
                data.also.append((edge, seq, floor))
        for (_, dst, _), datas in frames.items():
            for data in datas:
                self.ctx.emit(Send(dst, data))
        self.outbox.clear()
        if self.catching:
            self._caught_up()
        touched, self.touched = self.touched, set()
        for app in touched if len(touched) < 2 else [a for a in self.ctx.apps if a in touched]:
            touched_dep = self.ctx.apps.get(app)
            if touched_dep is None:
                continue
            for edge, ch in list(touched_dep.inc.items()):
                if ch.reack or ch.processed != ch._acked:
                    self.ack(touched_dep, edge)
            if app not in self.armed and touched_dep.running and self.unacked(touched_dep):
                self.armed.add(app)
                self.ctx.emit(SetTimer(Retransmit(app), self.ctx.now + RETRANSMIT_S))

    def _caught_up(self) -> None:
        """Input a forwarder's replacement held past its deadline goes to it now (an edge
        whose events never came: its producer out of reach; provenance.CatchUp)."""
        for app, vid in list(self.catching):
            dep = self.ctx.apps.get(app)
            catch_up = dep.catch_up.get(vid) if dep is not None else None
            if dep is None or catch_up is None:
                self.catching.discard((app, vid))
            elif catch_up.due(self.ctx.now):
                self.catching.discard((app, vid))
                del dep.catch_up[vid]
                self.ctx.note_event(
                    self.ctx.now,
                    f"{vid}: input past its consumer's marks "
                    f"held {provenance.CATCH_UP_S:g} s, processed now",
                )
                if held := catch_up.release():
                    self.enqueue(dep, vid, (catch_up.edge, held, catch_up.ts))

    def touch(self, app: str) -> None:
        """A procedure may have changed ``app``'s channels (a handover, a restore): look at
        them at the next flush."""
        self.touched.add(app)

    @staticmethod
    def unacked(dep: AppState) -> bool:
        """Whether ``app``'s retransmit timer has work: events unacknowledged (sent, held or
        stored) or a source held back."""
        return bool(dep.blocked_sources) or any(ch.in_flight > 0 for ch in dep.out.values())

    def report_delays(self, now: float) -> None:
        """Tell each chain's head node the delay measured at its tail (here)."""
        for dep in self.ctx.apps.engaged_apps():
            for chain, ms in dep.delays.items():
                head = dep.placed[dep.layout.chains[chain].head]
                if head == self.ctx.id:
                    dep.chain_delay[chain] = (ms, now)
                elif head not in self.ctx.failed:
                    self.ctx.send(head, m.ChainDelay(dep.app.name, chain, ms))

    def on_chain_delay(self, msg: m.ChainDelay, now: float) -> None:
        dep = self.ctx.apps.get(msg.app)
        chains = len(dep.layout.chains) if dep is not None else 0
        if not 0 <= msg.chain < chains or not -1e9 <= msg.delay_ms <= 1e9:  # (NaN, inf too)
            self.ctx.refusal("chain_delay_invalid")
            return
        assert dep is not None
        dep.chain_delay[msg.chain] = (msg.delay_ms, now)

    def on_marker_msg(self, msg: m.Marker, now: float) -> None:
        dep = self.ctx.apps.get(msg.app)
        if dep is None or not 0 <= msg.edge < len(dep.app.edges):
            self.ctx.refusal("marker_unknown_edge")
            return
        dst = dep.app.edges[msg.edge].dst
        if msg.to == self.ctx.id or dep.app.vertices[dst].pinned is not None:
            self.ctx.refusal("marker_of_no_relocation")  # (its state would go nowhere)
            return
        self.enqueue(dep, dst, msg)


def retain_for_replica(dep: AppState, edge: int, ch: OutChannel) -> None:
    """A new channel into a replicated vertex keeps its events from its start until the
    consumer's replicas hold a snapshot past them (``m.Release``)."""
    if dep.replicas.get(dep.app.edges[edge].dst):
        ch.retain(REPLICA_OWNER, ch.next_seq)
