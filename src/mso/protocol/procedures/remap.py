"""Chain remap (§3.4.2), global remap (§3.4.3) and failure recovery, at the one node that
coordinates each.

A :class:`Remap` is PROBING each chain's route in dependency order (re-probed if a probe is
lost, ``Retry``) and placing it with the deployment's own placement code, then MOVING the
vertices whose node changed one at a time — each a child :class:`~.relocation.Relocation`, or a
restore for a lost instance — then FINISHED. It fails when placement fails, a probe is never
answered, a child fails, or at its deadline. A remap's probe travels as a deployment's does
(:mod:`.deploy`'s probe hops), marked by chain -1 and its segment ``pid * 1000 + k``.

**Recovery** is the rule that turns a failure into a remap, as pure decisions on the node's own
tables (:meth:`Remapper.maybe_recover`): exactly one node acts for an app — the lowest-named
surviving node that hosts part of it — and every node derives the same choice from the same
placement and failure set, so two detectors never both remap. It remaps only the chains that
lost a vertex (a chain remap, or a global one if a chain's end was lost), waits for the routing
view to route around the failure first, and parks the chains pinned to a failed node: their
edges stop carrying events (counted as dropped), so a dead sink on one branch does not hold back
the branches that still run. Membership publishes :class:`~mso.protocol.events.PeerFailed`; the
recovery goes on from there, in one direction: membership → remap → restore.
"""

from __future__ import annotations

import enum
from collections.abc import Collection
from collections.abc import Set as AbstractSet
from dataclasses import dataclass, field
from typing import Any, ClassVar

from mso.errors import MsoError
from mso.management.guard import RuleSettings
from mso.model.app import App
from mso.planning.placement import Hop, Layout, probed_hops
from mso.protocol import messages as m
from mso.protocol import warrant
from mso.protocol.context import NodeContext
from mso.protocol.dataplane import DataPlane
from mso.protocol.effects import Reply, SetTimer
from mso.protocol.events import (
    Happened,
    PeerFailed,
    PlacementStale,
    RecoverTick,
    RecoveryDue,
    RelocationEnded,
    Retry,
    RoutesChanged,
)
from mso.protocol.procedures.base import STEP_TIMEOUT_S, Phase, Procedure, Table, within_client_wait
from mso.protocol.procedures.relocation import Relocation, Relocator
from mso.protocol.state import AppState

PROBE_ATTEMPTS = 5
# how long a recovery waits for the routing view to go around a failed node. A node whose
# machine died is routed around within the routing protocol's convergence; one whose daemon
# crashed while its router lives on never is (babeld keeps its routes, the kernel forwards).
# After this the recovery goes ahead with the view as it is: the failed node only relays.
ROUTES_SETTLE_S = 2.0
# a remap takes a chain's new placement over its current one only if it saves this share of the
# chain's energy: the rules' own margin (RuleSettings.margin), so it never undoes their moves
KEEP_MARGIN = RuleSettings().margin
# a view a restarted daemon took back from its store (mso.protocol.kept) is acted on alone only
# this long after: a live holder's sync (sent as the node is heard back) comes first and
# replaces it; acting at once on a view from before a move restored the chain twice (76070)
KEPT_WAIT_S = 2.0


class S(enum.Enum):
    PROBING = "probing"
    MOVING = "moving"


class RemapEvent(enum.Enum):
    """What moves a Remap along its table."""

    PROBE = "probe"
    PLACED = "placed"
    PLACED_ALL = "placed_all"
    MOVED = "moved"
    ALL_MOVED = "all_moved"


class Remap(Procedure):
    NAME = "remap"
    INITIAL = S.PROBING
    TRANSITIONS: ClassVar[Table] = {
        S.PROBING: {
            RemapEvent.PROBE: S.PROBING,  # probes sent for the next chain (or sent again)
            RemapEvent.PLACED: S.PROBING,  # a chain placed, more to go
            RemapEvent.PLACED_ALL: S.MOVING,
        },
        S.MOVING: {RemapEvent.MOVED: S.MOVING, RemapEvent.ALL_MOVED: Phase.FINISHED},
    }

    def __init__(
        self,
        pid: int,
        now: float,
        app: str,
        chains: list[int],
        client: int | None,
        placed: dict[str, str],
        movable: set[str],
        recovery: dict[str, Any] | None = None,
        within_s: float = 0.0,
    ) -> None:
        # every chain may need its probes retried, and every vertex a move; a client's remap
        # ends before the client stops waiting
        longest = 10.0 + 5.0 * len(chains) + 0.5 * len(movable)
        super().__init__(pid, now, within_client_wait(within_s, longest))
        self.app = app
        self.chains = chains  # still to place, in dependency order
        self.client = client
        self.placed = placed  # the placement being built
        self.movable = movable  # only these are re-placed
        self.recovery = recovery  # set when this remap recovers from a failure
        self.moves: list[tuple[str, str]] = []  # (vertex, node) still to do
        self.moved: dict[str, str] = {}
        self.probes: dict[int, list[Hop]] = {}
        self.expected = 0
        self.probe_attempts = 0
        self.weights: dict[str, float] = {}  # node -> factor on its probed capacity
        # start from the current placement (not for an energy remap: the rules chose its moves)
        self.keep = True
        self.kept: dict[int, str] = {}  # chain -> why it kept its placement or took the new one
        self.order = b""  # the operator's order it carries out (mso.protocol.warrant)

    @property
    def name(self) -> str:
        return "recovery" if self.recovery is not None else self.NAME

    def refusal(self, why: str) -> m.Message:
        return m.RemapReply(self.app, False, dict(self.moved), error=why)

    def describe(self) -> dict[str, Any]:
        return super().describe() | {
            "app": self.app,
            "chains_left": list(self.chains),
            "kept": {str(c): why for c, why in self.kept.items()},
        }


class Remapper:
    """This node's part in remaps and recoveries: it coordinates them (module docstring)."""

    def __init__(self, ctx: NodeContext, dp: DataPlane, relocator: Relocator) -> None:
        self.ctx = ctx
        self.dp = dp
        self.relocator = relocator
        self._failed_at: dict[str, float] = {}  # when each failed node was declared

    def _remap(self, pid: int | None) -> Remap | None:
        proc = self.ctx.procedure(pid)
        return proc if isinstance(proc, Remap) else None

    def expire(self, remap: Remap, now: float) -> None:
        why = f"{remap.name} did not finish within {remap.deadline - remap.started_at:g} s"
        self._finish(remap.pid, now, why)

    # -- what moves a remap or a recovery on ---------------------------------------------------
    def on_relocation_ended(self, ev: RelocationEnded) -> None:
        """One of a remap's moves ended: the next one, or the remap fails and says why."""
        if ev.remap is None or self._remap(ev.remap) is None:
            return
        if ev.error:
            self._finish(ev.remap, self.ctx.now, ev.error)
        else:
            self._step(ev.remap, self.ctx.now, moved=(ev.vertex, ev.target))

    def on_peer_failed(self, ev: PeerFailed) -> None:
        self._failed_at = {n: t for n, t in self._failed_at.items() if n in self.ctx.failed}
        self._failed_at[ev.node] = self.ctx.now
        for dep in list(self.ctx.apps.values()):
            self.repin(dep)
            self.park(dep)
            self.maybe_recover(dep, self.ctx.now)

    def repin(self, dep: AppState) -> None:
        """A vertex placed by capability whose node failed goes to the next live node that
        qualified (§3.3: the choice is redone like any other placement). Every node does this
        from the same ranked list and failure set, so all agree on its new node."""
        failed = self.ctx.failed
        for v, node in list(dep.layout.resolved.items()):
            if node not in failed:
                continue
            alt = next((n for n in dep.capable.get(v, []) if n not in failed), None)
            if alt is not None:
                dep.layout.repin(v, alt)

    def on_recovery_due(self, ev: RecoveryDue) -> None:
        for dep in list(self.ctx.apps.values()):
            if ev.app is None or dep.app.name == ev.app:
                self.maybe_recover(dep, self.ctx.now)

    def on_recover_tick(self, key: RecoverTick, now: float) -> None:
        dep = self.ctx.apps.get(key.app)
        if dep is not None:
            self.maybe_recover(dep, now)

    def on_routes_changed(self, ev: RoutesChanged) -> None:
        """A route inside a chain changed (the route rule's event); a recovery waiting for
        routes around a failed node may start."""
        now = self.ctx.now
        for dep in self.ctx.apps.values():
            for c in dep.layout.chains:
                if ev.changed & {dep.placed.get(v) for v in c.vertices}:
                    dep.route_changed[c.index] = now
        for dep in list(self.ctx.apps.values()):
            if dep.running:  # chains wait for a pinned node out of reach, and run on its return
                self.unpark(dep, reached=True)
                self.park(dep)
            self.maybe_recover(dep, now)

    # -- the remap, at its coordinator: probe and place each chain, then move ------------------
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
        self.request(None, req, now, weights, place)

    def request(
        self,
        client: int | None,
        msg: m.RemapRequest,
        now: float,
        weights: dict[str, float] | None = None,
        place: dict[str, str] | None = None,
        asked_at: float | None = None,
    ) -> None:
        """``asked_at``: when the client asked, if before ``now`` (a lookup went first)."""
        dep = self.ctx.apps.get(msg.app)
        if dep is None or not dep.running:
            self._refuse(client, msg.app, f"no running app named {msg.app!r}")
            return
        lay = dep.layout
        bad = [c for c in msg.chains if not 0 <= c < len(lay.chains)]
        if bad or (not msg.chains and not msg.everything):
            reason = f"unknown chain {bad[0]}" if bad else "name the chains to remap, or all"
            reason += f" (chains 0..{len(lay.chains) - 1})"
            self._refuse(client, msg.app, reason)
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
        wait = msg.within_s if client is not None else 0.0
        if wait > 0 and asked_at is not None:  # (not NaN) the lookup's time is the client's
            wait = max(wait - (now - asked_at), 1e-3)
        remap = Remap(self.ctx.new_pid(), now, msg.app, order, client, placed, movable, None, wait)
        remap.weights = dict(weights or {})
        remap.keep = not place
        remap.order = warrant.carried(msg)
        self.ctx.begin(remap)
        self._next_chain(remap.pid, now)

    def _refuse(self, client: int | None, app: str, reason: str) -> None:
        if client is not None:
            self.ctx.emit(Reply(client, m.RemapReply(app, False, {}, error=reason)))

    def _next_chain(self, rid: int, now: float) -> None:
        remap = self._remap(rid)
        dep = self.ctx.apps.get(remap.app) if remap is not None else None
        if remap is None or dep is None:
            return
        if not remap.chains:
            remap.on(RemapEvent.PLACED_ALL)
            order = {v: i for i, v in enumerate(dep.app.topological_order())}
            moves = [
                (v, n)
                for v, n in remap.placed.items()
                if (v in remap.movable and dep.placed.get(v) != n) or v in dep.vanished
            ]
            # replacements for lost instances first (upstream first, so each one's producer
            # is running when it resumes), then the relocations of live ones
            lost = dep.lost(self.ctx.failed)
            moves.sort(key=lambda vn: (vn[0] not in lost, order[vn[0]]))
            remap.moves = moves
            self._step(rid, now)
            return
        ci = remap.chains[0]
        lay = dep.layout
        head = lay.chains[ci].head
        if head not in remap.placed:
            remap.placed[head] = self._live_home(dep, head, remap.placed)
        target, _ = lay.target(ci, remap.placed, self.ctx.distances())
        pairs = lay.probes_needed(ci, remap.placed, target)
        remap.probes, remap.expected = {}, len(pairs)
        if not pairs:
            self._place(rid, now)
            return
        remap.on(RemapEvent.PROBE)
        remap.probe_attempts += 1
        for k, (a, b) in enumerate(pairs):  # chain -1 - rid marks a remap's probe
            self.ctx.send(a, m.Probe(remap.app, -1, rid * 1000 + k, self.ctx.id, b, [], []))
        self.ctx.emit(SetTimer(Retry(rid, remap.probe_attempts), now + STEP_TIMEOUT_S))

    def _live_home(self, dep: AppState, vertex: str, placed: dict[str, str]) -> str:
        """Where a vertex stays during a remap: its node, or if that failed, its first
        predecessor's (an upstream move), or for a lost unpinned source, this node."""
        node = dep.placed[vertex]
        if node not in self.ctx.failed:
            return node
        for pred in dep.app.predecessors()[vertex]:
            home = placed.get(pred, dep.placed[pred])
            if home not in self.ctx.failed:
                return home
        return self.ctx.id

    def on_retry(self, key: Retry, now: float) -> None:
        """A probe was lost (a route through a failed node): probe again, a few times."""
        rid, attempt = key.pid, key.attempt
        remap = self._remap(rid)
        if remap is None or attempt != remap.probe_attempts or len(remap.probes) >= remap.expected:
            return
        if remap.probe_attempts >= PROBE_ATTEMPTS:
            self._finish(rid, now, "probes along the chain's route were not answered")
            return
        if remap.recovery is not None:
            remap.recovery["retried"].append(f"probe {remap.chains[0]}")
        self._next_chain(rid, now)

    def on_probe_reply(self, msg: m.ProbeReply) -> None:
        rid, k = divmod(msg.segment, 1000)
        remap = self._remap(rid)
        if (
            remap is None
            or msg.app != remap.app
            or k in remap.probes
            or not 0 <= k < remap.expected
            or remap.state is not S.PROBING
        ):
            self.ctx.refusal("probe_reply_unexpected")
            return
        remap.probes[k] = probed_hops(msg.nodes, msg.capacities, msg.power, msg.rates)
        if len(remap.probes) == remap.expected:
            self._place(rid, self.ctx.now)

    def _place(self, rid: int, now: float) -> None:
        remap = self._remap(rid)
        dep = self.ctx.apps.get(remap.app) if remap is not None else None
        if remap is None or dep is None:
            return
        remap.on(RemapEvent.PLACED)
        ci = remap.chains.pop(0)
        remap.probe_attempts = 0
        w = remap.weights
        by_pair = {
            (h[0].node, h[-1].node): [x.weighted(w.get(x.node, 1.0)) for x in h]
            for h in remap.probes.values()
            if h
        }
        try:
            assigned, _ = dep.layout.place(
                ci, remap.placed, lambda a, b: by_pair.get((a, b), []), self.ctx.distances()
            )
        except MsoError as exc:
            self._finish(rid, now, str(exc))
            return
        if remap.keep:
            assigned = self._keep_current(remap, dep, ci, assigned, by_pair)
        remap.placed.update(assigned)
        self._next_chain(rid, now)

    def _keep_current(
        self,
        remap: Remap,
        dep: AppState,
        ci: int,
        assigned: dict[str, str],
        by_pair: dict[tuple[str, str], list[Hop]],
    ) -> dict[str, str]:
        """The chain stays where it runs unless there is a reason to move it
        (:meth:`~mso.planning.placement.Layout.keep_current`): a remap never undoes a move the
        rules made for a reason that still holds."""
        walk: list[Hop] = []
        for hops in by_pair.values():
            walk.extend(hops[1:] if walk and hops and walk[-1].node == hops[0].node else hops)
        failed = self.ctx.failed
        kept, why = dep.layout.keep_current(
            ci,
            assigned,
            dep.placed,
            walk,
            alive=lambda n: n not in failed,
            others=remap.placed,
            margin=KEEP_MARGIN,
        )
        remap.kept[ci] = why
        return kept

    def _step(self, rid: int, now: float, moved: tuple[str, str] | None = None) -> None:
        """Relocate (or, if its node failed, restore) the next vertex whose node changed;
        done when none is left."""
        remap = self._remap(rid)
        dep = self.ctx.apps.get(remap.app) if remap is not None else None
        if remap is None or dep is None:
            return
        if moved is not None:
            remap.on(RemapEvent.MOVED)
            remap.moved[moved[0]] = moved[1]
        while remap.moves:
            vertex, node = remap.moves.pop(0)
            lost = dep.placed[vertex] in self.ctx.failed or vertex in dep.vanished
            if dep.placed.get(vertex) == node and not lost:
                continue
            if dep.layout.kinds[vertex] == "source" and not lost:
                continue
            if lost and remap.recovery is None:  # the failure recovery restores it (one node
                continue  # coordinates it); restored here too, it would run twice
            if lost and vertex in dep.restoring:  # being restored here: a committed move to
                continue  # this node whose old host failed, restored by its coordinator;
                # restored elsewhere too, it ran twice (fault seed 71956)
            if not lost and self.relocator.cannot_hand_over(dep, vertex):
                continue  # stays where it runs, as a relocation would be refused
            if not lost and remap.recovery is None and dep.recovering is not None:
                continue  # a failure's recovery is re-placing the app: moving a vertex beside
                # what it restores switched a restored source before its numbering was set
                # (seed 25923: 20 events lost); this remap leaves the rest where it runs
            if not lost and self.relocator.moving(remap.app, vertex):
                continue  # a move of it is under way (a rule's, an operator's): a second
                # one waited for a handover the first had taken, for ever (seed 26555)
            pid = self.ctx.new_pid()
            source = dep.placed[vertex]
            reloc = Relocation(pid, now, remap.app, vertex, source, node, None, remap=rid)
            reloc.order = remap.order
            if remap.recovery is not None:
                reloc.retried = remap.recovery["retried"]
            self.ctx.begin(reloc)
            if lost:
                self.relocator.start_restore(dep, reloc, pid, now)
            else:
                self.relocator.prepare(dep, reloc)
            return
        remap.on(RemapEvent.ALL_MOVED)
        self._finish(rid, now, "")

    def _finish(self, rid: int, now: float, error: str) -> None:
        remap = self._remap(rid)
        if remap is None:
            return
        if error:
            remap.fail(self.ctx, error)
        self.ctx.end(rid)
        elapsed = self.ctx.elapsed_ms(remap.started_at)
        remap.tell_client(self.ctx, m.RemapReply(remap.app, not error, remap.moved, elapsed, error))
        if remap.client is not None:
            by = "operator"
        elif remap.recovery is not None and remap.recovery.get("failed"):
            by = "failure of " + ",".join(remap.recovery["failed"])
        elif remap.recovery is not None:  # instances gone with an old incarnation, none failed
            by = "recovery"
        else:
            by = "rule"
        self.ctx.publish(
            Happened(
                remap.name,
                remap.app,
                detail=" ".join(f"{v}->{n}" for v, n in sorted(remap.moved.items())) or "unchanged",
                by=by,
                took_ms=round(self.ctx.elapsed_ms(remap.started_at), 3),
                error=error,
            )
        )
        dep = self.ctx.apps.get(remap.app)
        if remap.recovery is not None and dep is not None:
            remap.recovery.update(
                moved=dict(remap.moved),
                ok=not error,
                error=error,
                took_ms=round(self.ctx.elapsed_ms(remap.started_at), 3),
            )
            dep.recovering = None
            if error:  # e.g. no route yet to a node that is about to be declared failed too:
                # try again later (sooner if routes or failures change), never in a loop
                self.ctx.emit(SetTimer(RecoverTick(dep.app.name), now + STEP_TIMEOUT_S))
            else:
                self.maybe_recover(dep, now)  # another failure may have happened meanwhile

    # -- the recovery rule: who coordinates, what is touched, what parks -----------------------
    def maybe_recover(self, dep: AppState, now: float) -> None:
        """Remap the chains that lost vertices with a failed node, if this node is the one
        that coordinates it (:func:`recovery_coordinator`) and the routes already go around
        the failure; what is remapped is :func:`recovery_plan`'s."""
        if not dep.running or dep.recovering is not None:
            return
        failed, routes = self.ctx.failed, self.ctx.routes
        lost = dep.lost(failed)
        if lost & dep.checking:  # its last host, alive, is asked whether it runs it still
            return
        if not lost or lost & dep.restoring.keys():  # (one being restored here by another
            # coordinator: its end or its failure is seen at a later beat. Restoring the rest
            # beside it, a consumer started from its marks while that producer's state
            # restarted and numbered its output from 0: 22 events dropped, seed 78957)
            return
        if dep.stored and now < dep.started_at + KEPT_WAIT_S:
            if (set(dep.placed.values()) & routes.keys()) - {self.ctx.id}:
                # asking acts on nothing: at once, once a node the view names is in reach (the
                # vertices it ran may run elsewhere since, restored by nodes that do not
                # count it a holder and will not sync it: seed 92532)
                self._ask_where(dep, failed)
            self.ctx.emit(SetTimer(RecoverTick(dep.app.name), dep.started_at + KEPT_WAIT_S))
            return
        alive = {self.ctx.id, *(n for n in routes if n not in failed)}
        holding = {dep.origin, *(n for ns in dep.replica_nodes.values() for n in ns)}
        if recovery_coordinator(dep.placed, lost, alive, holding) != self.ctx.id:
            # with every instance lost, the lowest live holder (else node alive) coordinates;
            # its view (not kept up to date: it hosts nothing) names a host, maybe one a vertex
            # has left since, whose view named this one: nobody recovered (fault seed 66410).
            # It asks the nodes its view names first, once per set of losses
            alone = recovery_coordinator({}, set(), alive, holding) == self.ctx.id
            # so does a view this node's last process kept (asked at once, above)
            if (alone and not dep.hosts_part()) or dep.stored:
                self._ask_where(dep, failed)
            return
        if not dep.hosts_part() and dep.looked_up != dep.losses(failed):  # this view is not
            self.ctx.publish(PlacementStale(dep.app.name))  # kept up to date: the app may run
            return  # elsewhere now; asked once per set of losses
        if not routes_settled(routes, failed):
            # wait for the routing view to route around the failure (set_routes), but not
            # for ever: a crashed daemon on a live router is never routed around
            since = max((self._failed_at.get(n, -ROUTES_SETTLE_S) for n in failed), default=0.0)
            if now < since + ROUTES_SETTLE_S:
                self.ctx.emit(SetTimer(RecoverTick(dep.app.name), since + ROUTES_SETTLE_S))
                return
        plan = recovery_plan(dep.layout, dep.placed, lost, set(dep.parked))
        if plan is None:
            return
        lay = dep.layout
        record: dict[str, Any] = {
            "at": now,
            "failed": sorted(failed),
            # nodes whose instances were gone with an old incarnation (a restart), not failed
            "vanished_on": sorted({dep.placed[v] for v in dep.vanished if v in dep.placed}),
            "remap": plan.kind,
            "chains": [lay.chains[c].name for c in plan.chains],
            "lost": sorted(lost),
            "parked": {lay.chains[c].name: why for c, why in sorted(dep.parked.items())},
            "retried": [],  # steps sent again after STEP_TIMEOUT_S (a lost message)
        }
        dep.recoveries.append(record)
        del dep.recoveries[:-20]
        pid = self.ctx.new_pid()
        placed = plan.stays | plan.place
        remap = Remap(pid, now, dep.app.name, plan.chains, None, placed, plan.movable, record)
        self.ctx.begin(remap)
        dep.recovering = pid
        self._next_chain(pid, now)

    def _ask_where(self, dep: AppState, failed: set[str]) -> None:
        """Ask the nodes this view names where the app runs, once per set of losses."""
        if dep.looked_up != dep.losses(failed):
            self.ctx.publish(PlacementStale(dep.app.name, wide=False))

    def park(self, dep: AppState) -> None:
        """Chains with a vertex pinned to a failed node cannot run anywhere: park them (they
        are reported, and not remapped). Their edges keep what they cannot deliver, within
        each edge's bound (store and forward, :mod:`mso.protocol.delivery`), for the node's
        return."""
        away = self.away(dep)
        for ci, why in pinned_to_failed(dep.app, dep.layout, self.ctx.failed, away).items():
            if dep.parked.get(ci, OUT_OF_REACH).endswith(OUT_OF_REACH):  # (declared since)
                dep.parked[ci] = why
        for v, node in dep.layout.resolved.items():
            if node in self.ctx.failed:  # no live node qualifies (repin found none)
                for c in dep.layout.chains:
                    if v in c.vertices:
                        why = f"{v!r}: no live node has what it requires"
                        dep.parked.setdefault(c.index, why)

    def unpark(self, dep: AppState, reached: bool = False) -> None:
        """Chains parked for a pinned node that is back run again (after their restore);
        ``reached``: only those parked for a pinned node (the routes changed)."""
        away = self.away(dep)
        for ci, why in list(dep.parked.items()):
            if reached and PINNED not in why:  # (a restore that gave up: not a pin's)
                continue
            verts = dep.layout.chains[ci].vertices
            pins = {dep.app.vertices[v].pinned for v in verts}
            pins |= {dep.layout.resolved[v] for v in verts if v in dep.layout.resolved}
            if not pins & (self.ctx.failed | away):
                del dep.parked[ci]

    def away(self, dep: AppState) -> set[str]:
        """The nodes ``dep``'s vertices are pinned to that this node has no route to: a chain
        through one is parked while it is (membership holds such a node *unreachable*, not
        failed, unless re-placing what it runs would let events flow)."""
        me, routes = self.ctx.id, self.ctx.routes
        return {n for n in dep.layout.pinned.values() if n != me and n not in routes}


# -- the recovery rule, as pure functions of what every node holds ------------------------------
@dataclass(frozen=True)
class RecoveryPlan:
    """What a recovery remaps: ``chains`` in dependency order, ``stays`` (vertex -> node, kept
    where it is), ``movable`` (re-placed), and whether a chain's end was lost (``global``)."""

    chains: list[int]
    stays: dict[str, str]
    movable: set[str]
    kind: str
    # lost vertices placed by capability: re-placed, on the next node that qualified
    place: dict[str, str] = field(default_factory=dict)


def recovery_coordinator(
    placed: dict[str, str], lost: set[str], alive: set[str], holders: AbstractSet[str] = frozenset()
) -> str:
    """The one node that recovers an app: the lowest-named node that still hosts part of it,
    or if none does (every instance went at once), the lowest-named live one of ``holders``
    (its origin and replicas': only the nodes that take part in an app hold it, issue 24.1),
    else the lowest-named node alive. Every node derives the same answer from the same
    placement and failure set, so two detectors never both remap."""
    hosting = {n for v, n in placed.items() if v not in lost}
    return min(hosting or (alive & holders) or alive)


def routes_settled(routes: dict[str, tuple[str, int]], failed: set[str]) -> bool:
    """The routing view goes around every failed node: none is a destination or a next hop
    (probes and restores sent before would be lost on the way)."""
    return not any(d in routes for d in failed) and not any(
        hop in failed for hop, _ in routes.values()
    )


def recovery_plan(
    layout: Layout, placed: dict[str, str], lost: set[str], parked: set[int]
) -> RecoveryPlan | None:
    """The chains that lost a vertex and are not parked, remapped as a chain remap (§3.4.2) or,
    when one lost an end, a global remap (§3.4.3); pinned vertices and surviving ends stay.
    None when nothing is to be remapped."""
    touched = [
        ci
        for ci, c in enumerate(layout.chains)
        if ci not in parked and any(v in lost for v in c.vertices)
    ]
    if not touched:
        return None
    chains = [layout.chains[c] for c in touched]
    in_set = {v for c in chains for v in c.vertices}
    ends = {v for c in chains for v in (c.head, c.tail)}
    # a lost vertex placed by capability moves to its new node (Remapper.repin), as an anchor
    place = {v: layout.resolved[v] for v in lost & set(layout.resolved) if v in in_set}
    stays = {v for v in placed if v not in in_set or v in layout.pinned} - set(place)
    stays |= {v for v in ends if v not in lost}
    return RecoveryPlan(
        chains=[c for c in layout.order if c in touched],
        stays={v: placed[v] for v in stays},
        movable=in_set - stays,
        kind="global" if any(v in lost for v in ends) else "chain",
        place=place,
    )


OUT_OF_REACH = "out of reach"  # the end of a parked chain's reason while its pin is away
PINNED = " is pinned to "  # in the reason of a chain parked for its pinned node


def pinned_to_failed(
    app: App, layout: Layout, failed: set[str], away: Collection[str] = ()
) -> dict[int, str]:
    """The chains with a vertex pinned to a failed node, or to one out of reach (``away``)
    (chain -> why): they cannot run anywhere until that node is back, so they are parked."""
    out: dict[int, str] = {}
    for ci, chain in enumerate(layout.chains):
        for v in chain.vertices:
            pin = app.vertices[v].pinned
            if ci in out or pin is None:
                continue
            if pin in failed:
                out[ci] = f"{v!r}{PINNED}failed node {pin}"
            elif pin in away:
                out[ci] = f"{v!r}{PINNED}{pin}, {OUT_OF_REACH}"
    return out
