"""Deployment (§3.3, Algorithm 1), every role in one place: the origin, each chain head's node,
each probe hop, each builder.

- The **origin** (the node a client asked) opens the :class:`Deploy` procedure, which holds
  the client until it is answered: WAITING while a node a vertex is pinned to is held failed
  but in reach (a restart whose first beat is on its way: the announcement would skip it and
  the deployment could only time out), then it announces the app to every node
  (``AppAnnounce``); BUILDING while chains are probed, placed and built across the nodes,
  FINISHED when every chain reports built (``ChainBuilt``) and the origin starts the app
  (``StartApp``), FAILED when a node refuses (bad code, placement impossible), the pinned node
  stays failed, the origin resets or the app is undeployed meanwhile, or at the deadline —
  then the app is stopped everywhere and the client told why, instead of waiting for ever on
  a probe or a chain build that was lost. The deadline is the client's own wait
  (``DeployRequest.within_s``) less a margin for the reply, at most ``DEADLINE_S``: the
  client hears the refusal before it gives up.
- A **chain head's node**, once every chain its chain depends on is placed, probes the route
  toward the chain's furthest pinned vertex (``Probe`` → ``ProbeReply``: each hop appends its
  capacity), places the chain in proportion to cost and capacity, and tells everyone
  (``ChainPlaced``); it then asks each node on it to build its part (``BuildChain`` →
  ``ChainPartReady``) and tells the origin the chain is built.
- A **probe hop** appends itself and forwards; one whose route still goes through a failed node
  holds the probe until its routes go around it (at most ``STEP_TIMEOUT_S``).
- A **builder** hosts its vertices and reports its part ready once every instance has started.

Undeploying (``StopApp``) is here too: with operator keys only an operator's signed undeploy
stops a running app.
"""

from __future__ import annotations

import enum
import zlib
from collections.abc import Iterable
from dataclasses import dataclass, field
from typing import Any, ClassVar, Protocol

from mso.errors import MsoError, PlanningError
from mso.management import load_policy
from mso.model.app import App
from mso.model.appfile import MAX_VERTICES, loads_app, loads_app_shared
from mso.model.capabilities import Candidate, Needs, missing, offered, parse_capabilities, resolve
from mso.planning.placement import Hop, Layout, probed_hops
from mso.protocol import messages as m
from mso.protocol.authority import generation
from mso.protocol.context import NodeContext
from mso.protocol.dataplane import RETRANSMIT_S, DataPlane
from mso.protocol.effects import Reply, Send, SetTimer
from mso.protocol.events import (
    HeldProbesDue,
    InstanceFailed,
    InstanceReady,
    PeerFailed,
    PeerRejoined,
    Retransmit,
    Retry,
    RoutesChanged,
)
from mso.protocol.procedures.base import (
    STEP_TIMEOUT_S,
    Phase,
    Procedure,
    Table,
    within_client_wait,
)
from mso.protocol.state import AppState

MAX_WAITING_PROBES = 256  # probes held at a hop whose route still goes through a failed node
PROBE_HOLD_S = STEP_TIMEOUT_S / 2  # how long they wait for routes around it (then skip it)


# how long the deploying node waits for capability answers (§3.3) from nodes that stay silent:
# it chooses as soon as every live node asked has answered or declined
CHOOSE_S = 1.0

# how long a deployment waits for a node one of its vertices is pinned to, held failed yet in
# reach, to rejoin (a daemon restarting: its first beat rejoins it within a heartbeat of its
# start) before it is refused, naming the node; announced meanwhile, the app would skip the
# node and the deployment could only time out
PINNED_WAIT_S = 5.0


class S(enum.Enum):
    WAITING = "waiting"
    CHOOSING = "choosing"
    BUILDING = "building"


class DeployEvent(enum.Enum):
    """What moves a Deploy along its table."""

    PINNED_IN = "pinned_in"  # every node a vertex is pinned to is a member: announced
    ASKED = "asked"  # ... and the capability query is out
    ANSWER = "answer"
    CHOSEN = "chosen"
    BUILT = "built"
    ALL_BUILT = "all_built"


@dataclass
class Choosing:
    """An app with vertices placed by capability, while the deploying node collects answers."""

    document: str
    needs: list[Needs]
    pinned: dict[str, str]
    asked: set[str]  # the nodes the query went to
    answers: dict[str, Candidate] = field(default_factory=dict)
    declined: set[str] = field(default_factory=set)  # nodes with none of what is required
    pins: set[str] = field(default_factory=set)  # the nodes its vertices are pinned to

    def all_in(self, failed: set[str]) -> bool:
        """Every node asked that is not held failed has answered or declined."""
        return self.asked - failed <= self.answers.keys() | self.declined


class Deploy(Procedure):
    """One deployment at its origin; ``client`` is answered exactly once, whatever ends it."""

    NAME = "deploy"
    INITIAL = S.WAITING
    DEADLINE_S = 30.0
    TRANSITIONS: ClassVar[Table] = {
        S.WAITING: {DeployEvent.PINNED_IN: S.BUILDING, DeployEvent.ASKED: S.CHOOSING},
        S.CHOOSING: {DeployEvent.ANSWER: S.CHOOSING, DeployEvent.CHOSEN: S.BUILDING},
        S.BUILDING: {DeployEvent.BUILT: S.BUILDING, DeployEvent.ALL_BUILT: Phase.FINISHED},
    }

    def __init__(
        self,
        pid: int,
        now: float,
        app: App,
        document: str,
        client: int | None = None,
        deadline_s: float | None = None,
    ) -> None:
        super().__init__(pid, now, deadline_s)
        self.app = app.name
        self.parsed: App | None = app  # until announced (WAITING holds it)
        self.document = document
        self.client = client
        self.choosing: Choosing | None = None

    def refusal(self, why: str) -> m.Message:
        return _failed_reply(self.app, why)

    def describe(self) -> dict[str, Any]:
        out = super().describe() | {"app": self.app}
        if self.choosing is not None:
            out["answers"] = sorted(self.choosing.answers)
        return out


class AppPolicies(Protocol):
    """What deployment needs of the management rules: an app's policy checked (and loaded)
    when the app arrives, and forgotten when it goes."""

    def app_policy(self, app: str, spec: Any, where: str) -> None: ...

    def forget(self, app: str) -> None: ...


class Deployer:
    """This node's part in deploying and undeploying apps, in every role (module docstring)."""

    def __init__(self, ctx: NodeContext, dp: DataPlane, policies: AppPolicies) -> None:
        self.ctx = ctx
        self.dp = dp
        self.policies = policies
        self._epochs = zlib.crc32(ctx.id.encode()) & 0xFFFF
        self._waiting_probes: list[tuple[float, m.Probe]] = []  # (give up at, probe)

    def _deploying(self, app: str) -> Deploy | None:
        for proc in self.ctx.open():
            if isinstance(proc, Deploy) and proc.app == app:
                return proc
        return None

    def on_reset(self) -> None:
        self._waiting_probes.clear()

    def load_app(self, name: str, document: str) -> App:
        """An app announced (or synced) by another node, with its policy checked and loaded."""
        app = loads_app_shared(document, f"<{name}>")  # one parse per process, not per node
        self.policies.app_policy(app.name, app.policy, where=f"{self.ctx.id}: {app.name}: policy")
        return app

    def revoked(self, src: str, app: str, document: str) -> bool:
        """An operator undeployed ``app`` after ``document`` was granted (a replay, or a node
        that missed the undeploy): refused, and the sender is told the undeploy."""
        if not self.ctx.authority.revocation(app, document):
            return False
        self.ctx.refusal("document_revoked")
        stop = self.ctx.authority.revoked.get(app)
        if stop is not None and src != self.ctx.id:
            self.ctx.send(src, stop)
        return True

    def named(self, app: App, name: str) -> bool:
        """A document travels under its app's own name (a grant covers the document, not
        the message's ``app``), else it is refused."""
        if app.name == name:
            return True
        self.ctx.refusal("document_named_otherwise")
        return False

    # -- the origin: announces, waits for every chain built, starts the app --------------------
    def deploy_request(self, client: int, req: m.DeployRequest, now: float) -> None:
        try:
            app = loads_app(req.document, file=req.file)
            load_policy(app.policy, where=f"{req.file}: policy")
        except MsoError as exc:
            self.ctx.emit(Reply(client, _failed_reply("", str(exc))))
            return
        revoked = self.ctx.authority.revocation(app.name, req.document)
        if revoked:
            self.ctx.emit(Reply(client, _failed_reply(app.name, revoked)))
            return
        if app.name in self.ctx.apps or self._deploying(app.name) is not None:
            state = "already deployed" if app.name in self.ctx.apps else "being deployed"
            reply = _failed_reply(app.name, f"an app named {app.name!r} is {state}")
            self.ctx.emit(Reply(client, reply))
            return
        known = set(self.ctx.known_nodes())
        for v in app.vertices.values():
            if v.pinned is not None and v.pinned not in known:
                reason = (
                    f"vertex {v.id!r} is pinned to node {v.pinned!r}, which is not reachable "
                    f"(reachable: {', '.join(sorted(known))})"
                )
                self.ctx.emit(Reply(client, _failed_reply(app.name, reason)))
                return
        proc = Deploy(self.ctx.new_pid(), now, app, req.document, client, _deadline_s(req))
        self.ctx.begin(proc)
        if self._pinned_failed(app):  # back soon (a restart), or refused at PINNED_WAIT_S
            self.ctx.emit(SetTimer(Retry(proc.pid, 0), now + PINNED_WAIT_S))  # (0: waiting)
            return
        self._start(proc, now)

    def _pinned_failed(self, app: App) -> dict[str, str]:
        """vertex -> the node it is pinned to, for each such node held failed."""
        failed = self.ctx.failed
        return {
            v.id: v.pinned
            for v in app.vertices.values()
            if v.pinned is not None and v.pinned in failed
        }

    def _start(self, proc: Deploy, now: float) -> None:
        """Every node a vertex is pinned to is a member: announce (or ask for capabilities)."""
        app, proc.parsed = proc.parsed, None
        assert app is not None
        needs = app.needs()
        if not needs:
            proc.on(DeployEvent.PINNED_IN)
            self._announce(app.name, proc.document, {}, {}, _pins(app))
            return
        # §3.3: the nodes with the capabilities answer, the others decline; the choice is made
        # when every live node asked has spoken, or at the deadline from the answers in
        known = set(self.ctx.known_nodes())
        pinned = {v.id: v.pinned for v in app.vertices.values() if v.pinned is not None}
        proc.choosing = Choosing(proc.document, needs, pinned, known, pins=_pins(app))
        proc.on(DeployEvent.ASKED)
        anchors = sorted(known) if any(n.near for n in needs) else []
        wanted = {n.vertex: dict(n.requires) for n in needs}
        self.ctx.broadcast(m.CapabilityQuery(app.name, proc.pid, wanted, anchors))
        self.ctx.emit(SetTimer(Retry(proc.pid, 1), now + CHOOSE_S))  # (1: choosing)

    def on_peer_rejoined(self, ev: PeerRejoined) -> None:
        """A node back: the deployments that waited for it (a vertex pinned there) go on."""
        for proc in self.ctx.open():
            if not isinstance(proc, Deploy) or proc.state is not S.WAITING:
                continue
            app = proc.parsed
            if app is not None and not self._pinned_failed(app):
                self._start(proc, self.ctx.now)

    def _refuse(self, proc: Deploy, reason: str) -> None:
        """End the deployment unsuccessfully and tell the client why; the nodes that took the
        app stop it (only a deployment of ours: another origin's of the same name is not)."""
        proc.fail(self.ctx, reason)
        self.ctx.end(proc.pid)
        proc.tell_client(self.ctx, _failed_reply(proc.app, reason))
        dep = self.ctx.apps.get(proc.app)
        if proc.parsed is None and (dep is None or dep.origin == self.ctx.id):
            self.ctx.broadcast(m.StopApp(proc.app))  # (announced or asked: not while WAITING)

    def _waited_in_vain(self, proc: Deploy) -> str:
        """Why a deployment still WAITING is refused: the pinned nodes held failed."""
        app = proc.parsed
        held = self._pinned_failed(app) if app is not None else {}
        which = ", ".join(f"vertex {v!r} is pinned to node {n!r}" for v, n in sorted(held.items()))
        return f"{self.ctx.id}: {which or 'a pinned node'}, held failed (no beat from it since)"

    def abandon(self, why: str) -> None:
        """This node resets (declared failed by a side that outranks it): every deployment it
        coordinates is refused, its client told why (then the procedures are dropped)."""
        for proc in self.ctx.open():
            if isinstance(proc, Deploy):
                self._refuse(proc, f"{self.ctx.id}: {why}")

    def _announce(
        self,
        app: str,
        document: str,
        resolved: dict[str, str],
        capable: dict[str, list[str]],
        pins: set[str],
    ) -> None:
        """To the app's first holders only (issue 24.1): this node, the nodes its vertices
        are pinned to and those chosen by capability -- the chain heads' nodes; a builder is
        sent the app by its chain head (:meth:`_build`)."""
        epoch = self._epochs = (self._epochs + 1) & 0x7FFFFFFF
        msg = m.AppAnnounce(app, self.ctx.id, document, epoch, dict(resolved), dict(capable))
        for node in sorted({self.ctx.id, *pins, *resolved.values()}):
            if node not in self.ctx.failed:
                self.ctx.send(node, msg)

    # -- every node: answers a capability query if it qualifies for a vertex -------------------
    def on_capability_query(self, src: str, msg: m.CapabilityQuery, now: float) -> None:
        offers = offered(self.ctx.capabilities, self.ctx.capacity)
        needs: list[dict[str, float]] = []
        for requires in list(msg.needs.values())[:MAX_VERTICES]:
            try:
                needs.append(parse_capabilities(requires, "needs"))
            except MsoError:
                self.ctx.refusal("capability_query_malformed")
                return
        if not any(not missing(r, offers) or set(r) & set(offers) for r in needs):
            # nothing a vertex requires: declined, so the origin need not wait for this node
            self.ctx.send(src, m.CapabilityReply(msg.app, msg.qid, self.ctx.id, {}, declined=True))
            return
        dist = self.ctx.distances()
        hops = {a: dist[a] for a in msg.anchors[:MAX_VERTICES] if a in dist}
        energy = self.ctx.figures().remaining_j
        self.ctx.send(src, m.CapabilityReply(msg.app, msg.qid, self.ctx.id, offers, energy, hops))

    # -- the origin: collects the answers, chooses, announces ----------------------------------
    def _choosing(self, pid: int) -> Deploy | None:
        proc = self.ctx.procedure(pid)
        if isinstance(proc, Deploy) and proc.choosing is not None and proc.state is S.CHOOSING:
            return proc
        return None

    def on_capability_reply(self, src: str, msg: m.CapabilityReply) -> None:
        proc = self._choosing(msg.qid)
        if proc is None or proc.app != msg.app or msg.node != src:
            self.ctx.refusal("capability_reply_unexpected")
            return
        ch = proc.choosing
        assert ch is not None
        if msg.declined:
            if src not in ch.answers:  # an answer with offers is not taken back
                ch.declined.add(src)
        else:
            try:
                offers = parse_capabilities(msg.offers, "offers")
            except MsoError:
                self.ctx.refusal("capability_reply_malformed")
                return
            energy = msg.energy_j if msg.energy_j is None or msg.energy_j >= 0 else None
            hops = {a: h for a, h in msg.hops.items() if a in ch.asked}
            ch.answers[src] = Candidate(src, offers, energy, hops)
            ch.declined.discard(src)
        proc.on(DeployEvent.ANSWER)
        if ch.all_in(self.ctx.failed):
            self._choose(proc)

    def on_peer_failed(self, ev: PeerFailed) -> None:
        """A node asked that fails will not answer: choose now if it was the last awaited."""
        for proc in self.ctx.open():
            if not isinstance(proc, Deploy) or proc.state is not S.CHOOSING:
                continue
            ch = proc.choosing
            if ch is not None and ev.node in ch.asked and ch.all_in(self.ctx.failed):
                self._choose(proc)

    def on_retry(self, key: Retry, now: float) -> None:
        """The time for capability answers is up: choose from those in. Or the pinned nodes
        did not rejoin in time: refused, naming them."""
        proc = self.ctx.procedure(key.pid)
        if key.attempt == 0 and isinstance(proc, Deploy) and proc.state is S.WAITING:
            self._refuse(proc, self._waited_in_vain(proc))
            return
        chooser = self._choosing(key.pid)
        if key.attempt == 1 and chooser is not None:
            self._choose(chooser)

    def _choose(self, proc: Deploy) -> None:
        """Each constrained vertex's node, deterministically from the answers
        (:func:`mso.model.capabilities.resolve`); refused, naming the vertex and what no node
        offers, if one cannot be met."""
        ch = proc.choosing
        assert ch is not None
        answers = [ch.answers[n] for n in sorted(ch.answers)]
        try:
            resolved, capable = resolve(ch.needs, ch.pinned, answers)
        except PlanningError as exc:
            proc.fail(self.ctx, str(exc))
            self.ctx.end(proc.pid)
            proc.tell_client(self.ctx, _failed_reply(proc.app, str(exc)))
            return
        proc.on(DeployEvent.CHOSEN)
        self._announce(proc.app, ch.document, resolved, capable, ch.pins)

    def on_built(self, msg: m.ChainBuilt, now: float) -> None:
        dep = self.ctx.apps.get(msg.app)
        proc = self._deploying(msg.app)
        if (
            dep is None
            or dep.origin != self.ctx.id
            or proc is None  # no deployment of it in progress here
            or msg.chain in dep.built
            or not 0 <= msg.chain < len(dep.layout.chains)
        ):
            self.ctx.refusal("chain_built_unexpected")
            return
        dep.built.add(msg.chain)
        self.ctx.learn_incarnations(_hosts_only(dep, msg.incarnations))
        proc.on(DeployEvent.BUILT)
        if len(dep.built) == len(dep.layout.chains):
            proc.on(DeployEvent.ALL_BUILT)
            self.ctx.end(proc.pid)
            start = m.StartApp(msg.app, self._incarnations(dep, dep.placed.values()))
            self._to_holders(dep, start)
            elapsed = self.ctx.elapsed_ms(proc.started_at)
            proc.tell_client(self.ctx, m.DeployReply(msg.app, True, dict(dep.placed), elapsed))

    def _to_holders(self, dep: AppState, msg: m.Message) -> None:
        for node in sorted(holders(dep)):
            if node not in self.ctx.failed:
                self.ctx.send(node, msg)

    def _incarnations(self, dep: AppState, nodes: Iterable[str]) -> dict[str, int]:
        """The incarnations this node knows of ``nodes`` (itself included), for the app's
        other nodes: its builders said them (``ChainPartReady``)."""
        named = set(nodes)
        out = {n: self.ctx.incarnation_of(n, -1) for n in named - {self.ctx.id}}
        if self.ctx.id in named:
            out[self.ctx.id] = self.ctx.incarnation
        return {n: i for n, i in sorted(out.items()) if i >= 0}

    def on_deploy_failed(self, msg: m.DeployFailed, now: float) -> None:
        """A node refused its part (its announcement may have been this node's own, when the
        app's layout fails here: then there is no app state, only the procedure)."""
        proc = self._deploying(msg.app)
        if proc is None:  # deployed (or failed) already: a failure report cannot stop it
            dep = self.ctx.apps.get(msg.app)
            if dep is not None and dep.origin == self.ctx.id:
                self.ctx.refusal("deploy_failed_after_deployment")
            return
        self._refuse(proc, msg.reason)

    def expire(self, proc: Deploy, now: float) -> None:
        """The deadline passed: a probe or a chain build was lost, or the pinned nodes are
        still held failed; stop it everywhere, tell the client."""
        if proc.state is S.WAITING:
            self._refuse(proc, self._waited_in_vain(proc))
            return
        why = f"{proc.name} did not finish within {proc.deadline - proc.started_at:g} s"
        self._refuse(proc, f"{self.ctx.id}: {why}")

    # -- every node: takes the app; a chain head's node probes, places, builds -----------------
    def on_announce(self, src: str, msg: m.AppAnnounce, now: float) -> None:
        if msg.app in self.ctx.apps or self.revoked(src, msg.app, msg.document):
            return
        try:
            app = self.load_app(msg.app, msg.document)
        except MsoError as exc:
            self.ctx.send(msg.origin, m.DeployFailed(app=msg.app, reason=f"{self.ctx.id}: {exc}"))
            return
        if not self.named(app, msg.app):
            return
        try:
            resolved = self._resolved(app, msg)
            layout = (
                Layout(app, msg.origin, resolved=resolved)
                if resolved
                else _layout(app, msg.origin, msg.document)
            )
        except MsoError as exc:
            self.ctx.send(msg.origin, m.DeployFailed(app=msg.app, reason=f"{self.ctx.id}: {exc}"))
            return
        dep = AppState(
            app=app,
            layout=layout,
            origin=msg.origin,
            placed=layout.initial_placement(),
            epoch=msg.epoch,
            document=msg.document,
            capable={v: list(ns) for v, ns in msg.capable.items() if v in msg.resolved},
        )
        self.ctx.apps[msg.app] = dep
        self._start_ready_chains(dep)

    @staticmethod
    def _resolved(app: App, msg: m.AppAnnounce) -> dict[str, str]:
        """The announcement's choice of node for each vertex placed by capability: exactly
        those vertices, each on a node id (the ranked candidates, if any, include it)."""
        wanted = {n.vertex for n in app.needs()}
        if set(msg.resolved) != wanted or not all(isinstance(n, str) and n for n in
                                                  msg.resolved.values()):  # fmt: skip
            raise PlanningError(
                f"the announcement chooses nodes for {sorted(msg.resolved)}, "
                f"the app places {sorted(wanted)} by capability"
            )
        return dict(msg.resolved)

    def _start_ready_chains(self, dep: AppState) -> None:
        lay = dep.layout
        for ci in lay.order:
            if ci in dep.started_chains or not lay.ready(ci, dep.placed_chains):
                continue
            head = lay.chains[ci].head
            if dep.placed.get(head) != self.ctx.id:
                continue
            dep.started_chains.add(ci)
            target, _ = lay.target(ci, dep.placed, self.ctx.distances())
            pairs = lay.probes_needed(ci, dep.placed, target)
            dep.probes[ci] = {}
            if not pairs:
                self._place(dep, ci)
                continue
            dep.probes_expected[ci] = len(pairs)
            for k, (a, b) in enumerate(pairs):
                self.ctx.send(a, m.Probe(dep.app.name, ci, k, self.ctx.id, b, [], []))

    def on_probe_reply(self, msg: m.ProbeReply) -> None:
        dep = self.ctx.apps.get(msg.app)
        if (
            dep is None
            or msg.chain not in dep.probes
            or not 0 <= msg.segment < dep.probes_expected.get(msg.chain, 0)
        ):
            self.ctx.refusal("probe_reply_unexpected")
            return
        got = dep.probes[msg.chain]
        got[msg.segment] = probed_hops(msg.nodes, msg.capacities, msg.power, msg.rates)
        if len(got) == dep.probes_expected.get(msg.chain):
            self._place(dep, msg.chain)

    def _place(self, dep: AppState, ci: int) -> None:
        lay = dep.layout
        hops_by_pair: dict[tuple[str, str], list[Hop]] = {}
        dep.probes_expected.pop(ci, None)
        for hops in dep.probes.pop(ci, {}).values():
            if hops:
                hops_by_pair[(hops[0].node, hops[-1].node)] = hops

        def probe(a: str, b: str) -> list[Hop]:
            return hops_by_pair.get((a, b), [])

        try:
            assigned, _ = lay.place(ci, dep.placed, probe, self.ctx.distances())
        except MsoError as exc:
            self.ctx.send(dep.origin, m.DeployFailed(dep.app.name, f"{self.ctx.id}: {exc}"))
            return
        announce = _announcement(dep)
        for node in sorted(holders(dep) | set(assigned.values())):
            if node in self.ctx.failed:
                continue
            if node not in holders(dep):  # a builder new to the app: the app, and what is
                self.ctx.send(node, announce)  # placed so far, ahead of this chain's place
                for cj in sorted(dep.placed_chains):
                    verts = dep.layout.chains[cj].vertices
                    self.ctx.send(
                        node, m.ChainPlaced(dep.app.name, cj, {v: dep.placed[v] for v in verts})
                    )
            self.ctx.send(node, m.ChainPlaced(dep.app.name, ci, assigned))

    def on_placed(self, msg: m.ChainPlaced) -> None:
        dep = self.ctx.apps.get(msg.app)
        if dep is None or not 0 <= msg.chain < len(dep.layout.chains):
            self.ctx.refusal("chain_placed_unknown_chain")
            return
        if msg.chain in dep.placed_chains:
            self.ctx.refusal("chain_placed_again")
            return
        if set(msg.assignments) != set(dep.layout.chains[msg.chain].vertices):
            self.ctx.refusal("chain_placed_other_vertices")
            return
        dep.placed.update(msg.assignments)
        dep.placed_chains.add(msg.chain)
        chain = dep.layout.chains[msg.chain]
        if msg.assignments.get(chain.head) == self.ctx.id and msg.chain in dep.started_chains:
            by_node: dict[str, list[str]] = {}
            for v in chain.vertices:
                by_node.setdefault(msg.assignments[v], []).append(v)
            dep.parts_pending[msg.chain] = set(by_node)
            for node, verts in by_node.items():
                self.ctx.send(node, m.BuildChain(dep.app.name, msg.chain, verts))
        self._start_ready_chains(dep)

    def on_part_ready(self, msg: m.ChainPartReady) -> None:
        dep = self.ctx.apps.get(msg.app)
        if dep is None or msg.node not in dep.parts_pending.get(msg.chain, ()):
            self.ctx.refusal("part_ready_unexpected")
            return
        pending = dep.parts_pending[msg.chain]
        pending.discard(msg.node)
        self.ctx.learn_incarnations({msg.node: msg.incarnation})
        if not pending:
            del dep.parts_pending[msg.chain]
            hosts = dep.layout.chains[msg.chain].vertices
            incarnations = self._incarnations(dep, (dep.placed[v] for v in hosts))
            self.ctx.send(dep.origin, m.ChainBuilt(msg.app, msg.chain, incarnations))

    def on_start(self, msg: m.StartApp, now: float) -> None:
        dep = self.ctx.apps.get(msg.app)
        if dep is None or dep.running:
            self.ctx.refusal("start_app_running")
            return
        dep.running = True
        self.ctx.learn_incarnations(_hosts_only(dep, msg.incarnations))
        dep.started_at = now
        dep.placed_at = dict.fromkeys(range(len(dep.layout.chains)), now)
        for vid, h in dep.instances.items():
            if h.kind == "source":
                self.dp.start_source(dep, vid, now)
        self.ctx.emit(SetTimer(Retransmit(msg.app), now + RETRANSMIT_S))

    # -- a probe hop: appends itself, forwards (or holds for routes) ---------------------------
    def on_probe(self, msg: m.Probe) -> None:
        msg.nodes.append(self.ctx.id)
        msg.capacities.append(self.ctx.capacity)
        if len(msg.power) == len(msg.nodes) - 1:  # every hop so far reported (else: none did)
            pw = self.ctx.power
            msg.power.append([pw.cpu_w, pw.tx_uj_per_byte, pw.rx_uj_per_byte])
        if msg.target == self.ctx.id:
            reply = m.ProbeReply(
                msg.app, msg.chain, msg.segment, msg.nodes, msg.capacities, msg.power, msg.rates
            )
            self.ctx.send(msg.requester, reply)
            return
        self._forward_probe(msg, self.ctx.now)

    def _forward_probe(self, msg: m.Probe, now: float) -> None:
        nxt = self.ctx.routes.get(msg.target)
        if nxt is not None and nxt[0] in self.ctx.failed and msg.target not in self.ctx.failed:
            # our routes do not go around a failure yet (the coordinator's already do): wait
            # for them rather than lose the probe and the coordinator's STEP_TIMEOUT_S; if
            # they do not change by PROBE_HOLD_S, the probe skips the hop (on_held_probes_due)
            if len(self._waiting_probes) < MAX_WAITING_PROBES:
                self._waiting_probes.append((now + PROBE_HOLD_S, msg))
                self._arm_held_probes()
            return
        if nxt is None:
            reply = m.ProbeReply(msg.app, msg.chain, msg.segment, [], [])
            self.ctx.send(msg.requester, reply)
            return
        if len(msg.rates) == len(msg.nodes) - 1:  # every link so far reported (else: none)
            msg.rates.append(self.ctx.link_rate(nxt[0]) or 0.0)
        self.ctx.emit(Send(nxt[0], msg))  # the next hop appends itself in turn

    def on_routes_changed(self, ev: RoutesChanged) -> None:
        """Probes held for routes around a failure go on."""
        now = self.ctx.now
        waiting, self._waiting_probes = self._waiting_probes, []
        for deadline, probe in waiting:
            if deadline >= now:
                self._forward_probe(probe, now)

    def on_held_probes_due(self, now: float) -> None:
        """The routes still go through a failed next hop: a daemon that crashed on a machine
        whose router lives on is never routed around. Those probes go straight to their
        target, which the transport reaches through that router; the hops they skip have
        no daemon to host anything."""
        due = [p for d, p in self._waiting_probes if d <= now]
        self._waiting_probes = [(d, p) for d, p in self._waiting_probes if d > now]
        for probe in due:
            if len(probe.rates) == len(probe.nodes) - 1:
                probe.rates.append(0.0)  # over a relay whose daemon is gone: rate not known
            self.ctx.emit(Send(probe.target, probe))
        self._arm_held_probes()

    def _arm_held_probes(self) -> None:
        """The one ``HeldProbesDue`` timer, at the first held probe's deadline."""
        if self._waiting_probes:
            first = min(d for d, _ in self._waiting_probes)
            self.ctx.emit(SetTimer(HeldProbesDue(), first))

    # -- a builder: hosts its part, says when it is ready --------------------------------------
    def on_build(self, src: str, msg: m.BuildChain) -> None:
        """Host this node's part of a chain; it is ready once every instance has started."""
        dep = self.ctx.apps.get(msg.app)
        if dep is None or not 0 <= msg.chain < len(dep.layout.chains):
            self.ctx.refusal("build_unknown_chain")
            return
        if dep.running or not set(msg.vertices) <= set(dep.layout.chains[msg.chain].vertices):
            self.ctx.refusal("build_not_of_the_chain")  # (a running app is built already)
            return
        starting = set()
        for vid in msg.vertices:
            h = dep.instances.get(vid)
            if h is None:
                h = dep.instances[vid] = self.dp.host(dep, vid)
            if not h.started:
                starting.add(vid)
        if starting:
            dep.building[msg.chain] = (src, starting)
        else:
            ready = m.ChainPartReady(msg.app, msg.chain, self.ctx.id, self.ctx.incarnation)
            self.ctx.send(src, ready)

    def on_instance_ready(self, ev: InstanceReady) -> None:
        """A builder's instance started: its part of the chain may be ready."""
        dep = self.ctx.apps.get(ev.app)
        if dep is None:
            return
        vid = ev.vertex
        for ci, (asker, starting) in list(dep.building.items()):
            starting.discard(vid)
            if not starting:
                del dep.building[ci]
                ready = m.ChainPartReady(dep.app.name, ci, self.ctx.id, self.ctx.incarnation)
                self.ctx.send(asker, ready)

    def on_instance_failed(self, ev: InstanceFailed) -> None:
        """A builder's instance failed to start: the deployment fails (at its origin)."""
        dep = self.ctx.apps.get(ev.app)
        if dep is None:
            return
        vid, error = ev.vertex, ev.error
        for ci, (_, starting) in list(dep.building.items()):
            if vid in starting:
                del dep.building[ci]
                self.ctx.send(dep.origin, m.DeployFailed(dep.app.name, error))

    # -- undeploy: with operator keys, only an operator stops a running app --------------------
    def undeploy_refused(self, msg: m.StopApp) -> str:
        """Why this node does not stop ``msg.app`` ('' if it does). With operator keys only
        an operator's signed undeploy stops a running app (a member's StopApp alone does
        not); a deployment that has not started may be stopped by its origin after a
        failure."""
        if not self.ctx.authority.signed:
            return ""
        dep = self.ctx.apps.get(msg.app)
        if not msg.sig and (dep is None or not dep.running):
            return ""
        return self.ctx.authority.undeploy(msg)  # (remembers the revocation)

    def undeployed_before(self, msg: m.StopApp) -> bool:
        """An operator's undeploy older than the deployment running here (one told again to
        a node that comes into reach): it stops nothing."""
        dep = self.ctx.apps.get(msg.app)
        return bool(msg.sig) and dep is not None and generation(dep.document) > msg.at

    def on_stop_app(self, msg: m.StopApp, now: float) -> None:
        if self.undeploy_refused(msg):
            self.ctx.refusal("stop_app_unauthorized")
            return
        if self.ctx.authority.signed and self.undeployed_before(msg):
            self.ctx.refusal("undeploy_older_than_deployment")  # (maybe told again: harmless)
            return
        gone = self.ctx.apps.pop(msg.app, None)
        if gone is not None:
            self.dp.stop_app(gone, "undeploy")
        self.policies.forget(msg.app)
        proc = self._deploying(msg.app)
        if proc is not None and proc.parsed is None:  # (announced) undeployed meanwhile
            self._refuse(proc, f"{self.ctx.id}: undeployed before the deployment finished")


# (document, origin) -> (the shared parse of the document, its Layout): see _layout
_LAYOUTS: dict[tuple[str, str], tuple[App, Layout]] = {}
LAYOUTS_KEPT = 256


def _layout(app: App, origin: str, document: str) -> Layout:
    """The Layout of ``app`` deployed from ``origin``, shared by the nodes of one process as
    the parse is (``loads_app_shared``): every node takes every app announced, and a Layout
    per node per app was 8% of a 1,000-node simulation's start-up. Only for an app without
    vertices placed by capability: nothing changes such a Layout once made (``Remapper.repin``
    changes the capability vertices' nodes in place)."""
    kept = _LAYOUTS.get((document, origin))
    if kept is not None and kept[0] is app:
        return kept[1]
    layout = Layout(app, origin)
    if len(_LAYOUTS) >= LAYOUTS_KEPT:
        _LAYOUTS.clear()
    _LAYOUTS[(document, origin)] = (app, layout)
    return layout


def _hosts_only(dep: AppState, incarnations: dict[str, int]) -> dict[str, int]:
    """Of a message's incarnations, those of nodes the app runs on (it names no others)."""
    hosts = set(dep.placed.values())
    return {n: i for n, i in incarnations.items() if n in hosts}


def _deadline_s(req: m.DeployRequest) -> float:
    """The deployment's deadline: before the client stops waiting, at most 30 s."""
    return within_client_wait(req.within_s, Deploy.DEADLINE_S)


def _failed_reply(app: str, reason: str) -> m.DeployReply:
    return m.DeployReply(app=app, ok=False, placement={}, elapsed_ms=0.0, error=reason)


def holders(dep: AppState) -> set[str]:
    """The nodes that take part in the app by this node's view (issue 24.1): its origin, its
    vertices' nodes and its replicas'."""
    reps = {r for ns in dep.replica_nodes.values() for r in ns}
    return {dep.origin, *dep.placed.values(), *dep.layout.pinned.values(), *reps}


def _pins(app: App) -> set[str]:
    return {v.pinned for v in app.vertices.values() if v.pinned is not None}


def _announcement(dep: AppState) -> m.AppAnnounce:
    """The app's announcement as its origin made it (a signed document travels verbatim)."""
    resolved = dict(dep.layout.resolved)
    return m.AppAnnounce(
        dep.app.name, dep.origin, dep.document, dep.epoch, resolved, dict(dep.capable)
    )
