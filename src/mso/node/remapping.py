"""Chain remap (§3.4.2), global remap (§3.4.3) and failure recovery, at the coordinator.

A remap probes each chain again, places it with the shared placement code, then moves every
vertex whose node changed, one relocation at a time (a lost instance is restored instead). The
steps and their deadline are the :class:`~mso.protocol.procedures.remap.Remap` procedure; this
layer carries them out. Recovery is a remap of the chains a failed node touched, started by
exactly one surviving node (:meth:`Remapping._maybe_recover`).
"""

from __future__ import annotations

from typing import Any

from mso.errors import MsoError
from mso.node.relocation import Relocating
from mso.node.tables import Deployment, Hosted
from mso.planning.placement import Hop
from mso.protocol import messages as m
from mso.protocol.effects import Reply, SetTimer
from mso.protocol.procedures.base import Deadline, Retry
from mso.protocol.procedures.hosting import MAX_RESTARTS, RESTART_WINDOW_S, H
from mso.protocol.procedures.relocate import STEP_ATTEMPTS, STEP_TIMEOUT_S, Relocation
from mso.protocol.procedures.remap import PROBE_ATTEMPTS, Remap
from mso.protocol.procedures.remap import S as RemapState


class Remapping(Relocating):
    """A node's part in remaps and recoveries (it coordinates them)."""

    def remap(
        self,
        req: m.RemapRequest,
        now: float,
        weights: dict[str, float] | None = None,
        place: dict[str, str] | None = None,
    ) -> None:
        """Start a chain or global remap this node coordinates. An energy remap also says
        where some re-placed vertices go (``place``: the planner anchors them there) and
        scales each node's probed capacity for the planner (``weights``)."""
        self._remap_request(None, req, now, weights, place)

    def _remap_request(
        self,
        client: int | None,
        msg: m.RemapRequest,
        now: float,
        weights: dict[str, float] | None = None,
        place: dict[str, str] | None = None,
    ) -> None:
        dep = self.apps.get(msg.app)
        if dep is None or not dep.running:
            self._remap_refuse(client, msg.app, f"no running app named {msg.app!r}")
            return
        lay = dep.layout
        bad = [c for c in msg.chains if not 0 <= c < len(lay.chains)]
        if bad or (not msg.chains and not msg.everything):
            reason = f"unknown chain {bad[0]}" if bad else "name the chains to remap, or all"
            reason += f" (chains 0..{len(lay.chains) - 1})"
            self._remap_refuse(client, msg.app, reason)
            return
        wanted = set(range(len(lay.chains))) if msg.everything else set(msg.chains)
        order = [c for c in lay.order if c in wanted]
        # what stays: everything outside the set, pinned vertices, the heads of chains fed from
        # outside the set (sources included), and a lone chain's head and tail (§3.4.2)
        chains = [lay.chains[c] for c in order]
        in_set = {v for c in chains for v in c.vertices}
        tails = {c.tail for c in chains}
        ends = {chains[0].head, chains[0].tail} if len(chains) == 1 else set()
        stays = {v for v in dep.placed if v not in in_set or v in lay.pinned or v in ends}
        stays |= {c.head for c in chains if c.head not in tails}
        placed = {v: dep.placed[v] for v in stays}
        movable = in_set - stays
        placed |= {v: n for v, n in (place or {}).items() if v in movable}
        self._rid += 1
        remap = Remap(self._rid, now, msg.app, order, client, placed, movable)
        remap.weights = dict(weights or {})
        self._begin(remap)
        self._remap_next_chain(self._rid, now)

    def _remap_refuse(self, client: int | None, app: str, reason: str) -> None:
        if client is not None:
            self._effects.append(Reply(client, m.RemapReply(app, False, {}, error=reason)))

    def _remap_next_chain(self, rid: int, now: float) -> None:
        remap = self._remap(rid)
        dep = self.apps.get(remap.app) if remap is not None else None
        if remap is None or dep is None:
            return
        if not remap.chains:
            remap.on("placed_all")
            order = {v: i for i, v in enumerate(dep.app.topological_order())}
            moves = [
                (v, n)
                for v, n in remap.placed.items()
                if (v in remap.movable and dep.placed.get(v) != n) or v in dep.vanished
            ]
            # replacements for lost instances first (upstream first, so each one's producer
            # is running when it resumes), then the relocations of live ones
            lost = self._lost(dep)
            moves.sort(key=lambda vn: (vn[0] not in lost, order[vn[0]]))
            remap.moves = moves
            self._remap_step(rid, now)
            return
        ci = remap.chains[0]
        lay = dep.layout
        head = lay.chains[ci].head
        if head not in remap.placed:
            remap.placed[head] = self._live_home(dep, head, remap.placed)
        target, _ = lay.target(ci, remap.placed, self._distances())
        pairs = lay.probes_needed(ci, remap.placed, target)
        remap.probes, remap.expected = {}, len(pairs)
        if not pairs:
            self._remap_place(rid, now)
            return
        remap.on("probe")
        remap.probe_attempts += 1
        for k, (a, b) in enumerate(pairs):  # chain -1 - rid marks a remap's probe
            self._send(a, m.Probe(remap.app, -1, rid * 1000 + k, self.id, b, [], []))
        self._effects.append(SetTimer(Retry(rid, remap.probe_attempts), now + STEP_TIMEOUT_S))

    def _live_home(self, dep: Deployment, vertex: str, placed: dict[str, str]) -> str:
        """Where a vertex stays during a remap: its node, or if that failed, its first
        predecessor's (an upstream move), or for a lost unpinned source, this node."""
        node = dep.placed[vertex]
        if node not in self.dead:
            return node
        for pred in dep.app.predecessors()[vertex]:
            home = placed.get(pred, dep.placed[pred])
            if home not in self.dead:
                return home
        return self.id

    def _remap_probe_timeout(self, rid: int, attempt: int, now: float) -> None:
        """A probe was lost (a route through a failed node): probe again, a few times."""
        remap = self._remap(rid)
        if remap is None or attempt != remap.probe_attempts or len(remap.probes) >= remap.expected:
            return
        if remap.probe_attempts >= PROBE_ATTEMPTS:
            self._finish_remap(rid, now, "probes along the chain's route were not answered")
            return
        if remap.recovery is not None:
            remap.recovery["retried"].append(f"probe {remap.chains[0]}")
        self._remap_next_chain(rid, now)

    def _on_remap_probe(self, msg: m.ProbeReply) -> None:
        rid, k = divmod(msg.segment, 1000)
        remap = self._remap(rid)
        if (
            remap is None
            or msg.app != remap.app
            or k in remap.probes
            or not 0 <= k < remap.expected
            or remap.state is not RemapState.PROBING
        ):
            self._refusal("probe_reply_unexpected")
            return
        remap.probes[k] = [Hop(n, c) for n, c in zip(msg.nodes, msg.capacities, strict=False)]
        if len(remap.probes) == remap.expected:
            self._remap_place(rid, self._now)

    def _remap_place(self, rid: int, now: float) -> None:
        remap = self._remap(rid)
        dep = self.apps.get(remap.app) if remap is not None else None
        if remap is None or dep is None:
            return
        remap.on("placed")
        ci = remap.chains.pop(0)
        remap.probe_attempts = 0
        w = remap.weights
        by_pair = {
            (h[0].node, h[-1].node): [Hop(x.node, x.capacity * w.get(x.node, 1.0)) for x in h]
            for h in remap.probes.values()
            if h
        }
        try:
            assigned, _ = dep.layout.place(
                ci, remap.placed, lambda a, b: by_pair.get((a, b), []), self._distances()
            )
        except MsoError as exc:
            self._finish_remap(rid, now, str(exc))
            return
        remap.placed.update(assigned)
        self._remap_next_chain(rid, now)

    def _remap_step(self, rid: int, now: float, moved: tuple[str, str] | None = None) -> None:
        """Relocate (or, if its node failed, restore) the next vertex whose node changed;
        done when none is left."""
        remap = self._remap(rid)
        dep = self.apps.get(remap.app) if remap is not None else None
        if remap is None or dep is None:
            return
        if moved is not None:
            remap.on("moved")
            remap.moved[moved[0]] = moved[1]
        while remap.moves:
            vertex, node = remap.moves.pop(0)
            lost = dep.placed[vertex] in self.dead or vertex in dep.vanished
            if dep.placed.get(vertex) == node and not lost:
                continue
            if dep.layout.kinds[vertex] == "source" and not lost:
                continue
            if lost and remap.recovery is None:  # the failure recovery restores it (one node
                continue  # coordinates it); restored here too, it would run twice
            self._rid += 1
            source = dep.placed[vertex]
            reloc = Relocation(self._rid, now, remap.app, vertex, source, node, None, remap=rid)
            self._begin(reloc)
            if lost:
                self._restore(dep, reloc, self._rid, now)
            else:
                self._send(node, m.Prepare(remap.app, vertex, self._rid))
            return
        remap.on("all_moved")
        self._finish_remap(rid, now, "")

    def _finish_remap(self, rid: int, now: float, error: str) -> None:
        remap = self._remap(rid)
        if remap is None:
            return
        if error:
            remap.fail(self, error)
        self._end(rid)
        if remap.client is not None:
            elapsed = self._elapsed_ms(remap.started_at)
            reply = m.RemapReply(remap.app, not error, remap.moved, elapsed, error)
            self._effects.append(Reply(remap.client, reply))
        dep = self.apps.get(remap.app)
        if remap.recovery is not None and dep is not None:
            remap.recovery.update(
                moved=dict(remap.moved),
                ok=not error,
                error=error,
                took_ms=round(self._elapsed_ms(remap.started_at), 3),
            )
            dep.recovering = None
            if error:  # e.g. no route yet to a node that is about to be declared failed too:
                # try again later (sooner if routes or failures change), never in a loop
                key = ("recover", dep.app.name)
                self._effects.append(SetTimer(key, now + STEP_TIMEOUT_S))
            else:
                self._maybe_recover(dep, now)  # another failure may have happened meanwhile

    def _maybe_recover(self, dep: Deployment, now: float) -> None:
        """Remap the chains that lost vertices with a failed node. Exactly one node acts for
        an app: the lowest-named surviving node that hosts part of it (if none does, the
        lowest-named node alive). Every node derives the
        same choice from the same placement and failure set, so two detectors never both
        remap (a coordinator that is itself dead is skipped by the same rule)."""
        if not dep.running or dep.recovering is not None:
            return
        lost = self._lost(dep)
        if not lost:
            return
        live = {n for v, n in dep.placed.items() if v not in lost}
        if not live:  # every instance went (a node that ran them all restarted at once):
            live = {self.id, *(n for n in self.routes if n not in self.dead)}  # lowest alive
        if min(live) != self.id:
            return
        if any(d in self.routes for d in self.dead) or any(
            hop in self.dead for hop, _ in self.routes.values()
        ):
            return  # wait for the routing view to route around the failure (set_routes)
        lay = dep.layout
        touched = [
            ci
            for ci, c in enumerate(lay.chains)
            if ci not in dep.parked and any(v in lost for v in c.vertices)
        ]
        if not touched:
            return
        chains = [lay.chains[c] for c in touched]
        in_set = {v for c in chains for v in c.vertices}
        ends = {v for c in chains for v in (c.head, c.tail)}
        stays = {v for v in dep.placed if v not in in_set or v in lay.pinned}
        stays |= {v for v in ends if v not in lost}
        placed = {v: dep.placed[v] for v in stays}
        order = [c for c in lay.order if c in touched]
        kind = "global" if any(v in lost for v in ends) else "chain"
        record: dict[str, Any] = {
            "at": now,
            "failed": sorted(self.dead),
            "remap": kind,
            "chains": [lay.chains[c].name for c in order],
            "lost": sorted(lost),
            "parked": {lay.chains[c].name: why for c, why in sorted(dep.parked.items())},
            "retried": [],  # steps sent again after STEP_TIMEOUT_S (a lost message)
        }
        dep.recoveries.append(record)
        del dep.recoveries[:-20]
        self._rid += 1
        self._begin(
            Remap(self._rid, now, dep.app.name, order, None, placed, in_set - stays, record)
        )
        dep.recovering = self._rid
        self._remap_next_chain(self._rid, now)

    def _restore(self, dep: Deployment, reloc: Relocation, rid: int, now: float) -> None:
        """Start a replacement for ``reloc.vertex`` on ``reloc.target``: its surviving
        producers replay what it had not passed on, its consumers say where they stand."""
        if not reloc.restore:
            reloc.as_restore(now)
            self._effects.append(SetTimer(Deadline(rid), reloc.deadline))
        edges = dep.app.edges
        lost = self._lost(dep)
        reloc.resumes = [
            [i, True] for i, e in enumerate(edges) if e.dst == reloc.vertex and e.src not in lost
        ] + [[i, False] for i, e in enumerate(edges) if e.src == reloc.vertex and e.dst not in lost]
        reloc.attempts += 1
        prepare = m.Prepare(dep.app.name, reloc.vertex, rid, True, reloc.resumes)
        self._send(reloc.target, prepare)
        self._effects.append(SetTimer(Retry(rid, reloc.attempts), now + STEP_TIMEOUT_S))

    def _step_timeout(self, rid: int, now: float) -> None:
        reloc = self._reloc(rid)
        if reloc is None or not reloc.restore:
            return
        dep = self.apps.get(reloc.app)
        if dep is None:
            return
        if reloc.attempts >= STEP_ATTEMPTS or reloc.target in self.dead:
            why = f"restoring {reloc.vertex!r} on {reloc.target} did not complete"
            self._reloc_failed(reloc, why, now)
            return
        if reloc.vertex not in self._lost(dep):  # restored meanwhile by another coordinator
            # (its target tells only the newest one) and maybe moved since: asked again, the
            # target would start a second instance. Done; an instance prepared for this
            # restore and never resumed is dropped.
            where = dep.placed[reloc.vertex]
            if where != reloc.target:
                self._send(reloc.target, m.Unprepare(reloc.app, reloc.vertex, reloc.pid))
            reloc.on("handed_over")
            self._end(reloc.pid)
            reloc.target = where
            self._relocation_ended(reloc, now, "")
            return
        reloc.on("retry")
        remap = self._remap(reloc.remap)
        if remap is not None and remap.recovery is not None:
            remap.recovery["retried"].append(f"restore {reloc.vertex} on {reloc.target}")
        self._restore(dep, reloc, rid, now)  # idempotent at every end: just ask again

    def _instance_crashed(self, dep: Deployment, vid: str, h: Hosted, now: float) -> None:
        """Restore a crashed instance in place, as a restore after a node failure does: a
        fresh instance here; its producers replay what it had not passed on (acks are chained,
        so that is everything its outputs had not been acknowledged for) and its consumers say
        where they stand, so every event reaches them once, in order. Its own state restarts
        from its constructor. At most ``MAX_RESTARTS`` in ``RESTART_WINDOW_S``: a vertex that
        crashes on an event would crash again on its replay; then it stays crashed, its
        chains are reported parked and their events stay held (unacknowledged) upstream."""
        rec = dep.crashes[vid]
        rec.times = [t for t in rec.times if now - t < RESTART_WINDOW_S]
        app = dep.app.name
        if h.life.state is not H.CRASHED or dep.stones.get(vid) is not h:
            if dep.awaiting.get(vid) is h:  # a replacement or a move's target, not fed yet:
                del dep.awaiting[vid]  # a restore's retried prepare starts another one
                dep.preparing.pop(vid, None)
                dep.restoring.pop(vid, None)
            return  # a move handing over: it ends by its deadline (docs/architecture.md)
        if h.handing_over is not None or vid in dep.markers:
            return
        if len(rec.times) > MAX_RESTARTS:
            rec.gave_up = (
                f"{vid!r} crashed {len(rec.times)} times in {RESTART_WINDOW_S:g} s on {self.id} "
                f"(last: {h.crashed}); not restarted"
            )
            for c in dep.layout.chains:
                if vid in c.vertices:
                    dep.parked.setdefault(c.index, rec.gave_up)
            return
        h.life.on("restart")
        del dep.stones[vid]
        dep.crashed[vid] = h
        for i, e in enumerate(dep.app.edges):  # its channels: the surviving ends resume anew
            if e.dst == vid:
                dep.inc.pop(i, None)
                dep.stash.pop(i, None)
            elif e.src == vid:
                dep.out.pop(i, None)
                self._outbox.pop((app, i), None)
        dep.gates.pop(vid, None)
        dep.blocked_sources.discard(vid)
        rec.restarts += 1
        self._rid += 1
        rec.restoring = self._rid
        reloc = Relocation(self._rid, now, app, vid, self.id, self.id, None)
        self._begin(reloc)
        self._restore(dep, reloc, self._rid, now)

    def _relocation_ended(self, reloc: Relocation, now: float, error: str) -> None:
        dep = self.apps.get(reloc.app)
        rec = dep.crashes.get(reloc.vertex) if dep is not None else None
        if dep is not None and rec is not None and rec.restoring == reloc.pid:
            rec.restoring = None
            if error:  # no instance of it runs anywhere now: say so where it crashed
                rec.gave_up = f"restoring {reloc.vertex!r} after its crash failed: {error}"
                for c in dep.layout.chains:
                    if reloc.vertex in c.vertices:
                        dep.parked.setdefault(c.index, rec.gave_up)
            else:
                dep.crashed.pop(reloc.vertex, None)
            return
        if reloc.remap is not None and self._remap(reloc.remap) is not None:
            if error:  # one move failed: the remap fails, and says why
                self._finish_remap(reloc.remap, now, error)
            else:
                self._remap_step(reloc.remap, now, moved=(reloc.vertex, reloc.target))
            return
        super()._relocation_ended(reloc, now, error)
