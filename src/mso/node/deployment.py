"""Distributed deployment (Algorithm 1) at one node.

The origin announces the app to every node; each node derives the same
:class:`~mso.planning.placement.Layout`; the node holding a ready chain's head probes toward the
chain's target hop by hop, places the chain with the shared placement code, broadcasts the
placement (which activates the chains that depended on it), and builds the chain's overlay by
asking each node on it to host its vertices. When every chain is built the origin starts the
sources. The origin's side is the :class:`~mso.protocol.procedures.deploy.Deploy` procedure,
whose deadline ends a deployment whose probe or build was lost.
"""

from __future__ import annotations

from mso.errors import MsoError
from mso.management import load_policy
from mso.model.app import App
from mso.model.appfile import loads_app
from mso.node.dataplane import RETRANSMIT_S, DataPlane
from mso.node.tables import Deployment
from mso.planning.placement import Hop, Layout
from mso.protocol import messages as m
from mso.protocol.authority import generation
from mso.protocol.effects import Reply, Send, SetTimer
from mso.protocol.procedures.deploy import Deploy
from mso.protocol.procedures.relocate import STEP_TIMEOUT_S

MAX_WAITING_PROBES = 256  # probes held at a hop whose route still goes through a failed node


class Deploying(DataPlane):
    """A node's part in deploying and undeploying apps."""

    def _deploy_request(self, client: int, req: m.DeployRequest, now: float) -> None:
        try:
            app = loads_app(req.document, file=req.file)
            load_policy(app.policy, where=f"{req.file}: policy")
        except MsoError as exc:
            self._effects.append(Reply(client, _failed_reply("", str(exc))))
            return
        revoked = self.authority.revocation(app.name, req.document)
        if revoked:
            self._effects.append(Reply(client, _failed_reply(app.name, revoked)))
            return
        if app.name in self.apps:
            reply = _failed_reply(app.name, f"an app named {app.name!r} is already deployed")
            self._effects.append(Reply(client, reply))
            return
        known = set(self.known_nodes())
        for v in app.vertices.values():
            if v.pinned is not None and v.pinned not in known:
                reason = (
                    f"vertex {v.id!r} is pinned to node {v.pinned!r}, which is not reachable "
                    f"(reachable: {', '.join(sorted(known))})"
                )
                self._effects.append(Reply(client, _failed_reply(app.name, reason)))
                return
        self._deploy_clients[app.name] = (client, now)
        self._rid += 1
        self._begin(Deploy(self._rid, now, app.name))
        epoch = self._epochs = (self._epochs + 1) & 0x7FFFFFFF
        self._broadcast(
            m.AppAnnounce(app=app.name, origin=self.id, document=req.document, epoch=epoch)
        )

    def _load_app(self, name: str, document: str) -> App:
        """An app announced (or synced) by another node, with its policy checked and loaded."""
        app = loads_app(document, file=f"<{name}>")
        self.manager.app_policy(app.name, app.policy, where=f"{self.id}: {app.name}: policy")
        return app

    def _revoked(self, src: str, app: str, document: str) -> bool:
        """An operator undeployed ``app`` after ``document`` was granted (a replay, or a node
        that missed the undeploy): refused, and the sender is told the undeploy."""
        if not self.authority.revocation(app, document):
            return False
        self._refusal("document_revoked")
        stop = self.authority.revoked.get(app)
        if stop is not None and src != self.id:
            self._send(src, stop)
        return True

    def _named(self, app: App, name: str) -> bool:
        """A document travels under its app's own name (a grant covers the document, not
        the message's ``app``), else it is refused."""
        if app.name == name:
            return True
        self._refusal("document_named_otherwise")
        return False

    def _on_announce(self, src: str, msg: m.AppAnnounce, now: float) -> None:
        if msg.app in self.apps or self._revoked(src, msg.app, msg.document):
            return
        try:
            app = self._load_app(msg.app, msg.document)
        except MsoError as exc:
            self._send(msg.origin, m.DeployFailed(app=msg.app, reason=f"{self.id}: {exc}"))
            return
        if not self._named(app, msg.app):
            return
        layout = Layout(app, msg.origin)
        dep = Deployment(
            app=app,
            layout=layout,
            origin=msg.origin,
            placed=layout.initial_placement(),
            epoch=msg.epoch,
            document=msg.document,
        )
        for i, e in enumerate(app.edges):
            dep.out_edges.setdefault(e.src, []).append(i)
        if msg.origin == self.id and msg.app in self._deploy_clients:
            dep.client, dep.requested_at = self._deploy_clients.pop(msg.app)
        self.apps[msg.app] = dep
        self._start_ready_chains(dep)
        for early in self._early.pop(msg.app, []):
            self._work.append((early[0], "", early[1]))

    def _start_ready_chains(self, dep: Deployment) -> None:
        lay = dep.layout
        for ci in lay.order:
            if ci in dep.started_chains or not lay.ready(ci, dep.placed_chains):
                continue
            head = lay.chains[ci].head
            if dep.placed.get(head) != self.id:
                continue
            dep.started_chains.add(ci)
            target, _ = lay.target(ci, dep.placed, self._distances())
            pairs = lay.probes_needed(ci, dep.placed, target)
            dep.probes[ci] = {}
            if not pairs:
                self._place(dep, ci)
                continue
            dep.probes_expected[ci] = len(pairs)
            for k, (a, b) in enumerate(pairs):
                self._send(a, m.Probe(dep.app.name, ci, k, self.id, b, [], []))

    def _on_probe(self, msg: m.Probe) -> None:
        msg.nodes.append(self.id)
        msg.capacities.append(self.capacity)
        if msg.target == self.id:
            reply = m.ProbeReply(msg.app, msg.chain, msg.segment, msg.nodes, msg.capacities)
            self._send(msg.requester, reply)
            return
        self._forward_probe(msg, self._now)

    def _forward_probe(self, msg: m.Probe, now: float) -> None:
        nxt = self.routes.get(msg.target)
        if nxt is not None and nxt[0] in self.dead:
            # our routes do not go around a failure yet (the coordinator's already do): wait
            # for them rather than lose the probe and the coordinator's STEP_TIMEOUT_S
            if len(self._probes_waiting) < MAX_WAITING_PROBES:
                self._probes_waiting.append((now + STEP_TIMEOUT_S, msg))
            return
        if nxt is None:
            reply = m.ProbeReply(msg.app, msg.chain, msg.segment, [], [])
            self._send(msg.requester, reply)
            return
        self._effects.append(Send(nxt[0], msg))  # the next hop appends itself in turn

    def _on_probe_reply(self, msg: m.ProbeReply) -> None:
        dep = self.apps.get(msg.app)
        if (
            dep is None
            or msg.chain not in dep.probes
            or not 0 <= msg.segment < dep.probes_expected.get(msg.chain, 0)
        ):
            self._refusal("probe_reply_unexpected")
            return
        got = dep.probes[msg.chain]
        got[msg.segment] = [Hop(n, c) for n, c in zip(msg.nodes, msg.capacities, strict=False)]
        if len(got) == dep.probes_expected.get(msg.chain):
            self._place(dep, msg.chain)

    def _place(self, dep: Deployment, ci: int) -> None:
        lay = dep.layout
        hops_by_pair: dict[tuple[str, str], list[Hop]] = {}
        dep.probes_expected.pop(ci, None)
        for hops in dep.probes.pop(ci, {}).values():
            if hops:
                hops_by_pair[(hops[0].node, hops[-1].node)] = hops

        def probe(a: str, b: str) -> list[Hop]:
            return hops_by_pair.get((a, b), [])

        try:
            assigned, _ = lay.place(ci, dep.placed, probe, self._distances())
        except MsoError as exc:
            self._send(dep.origin, m.DeployFailed(dep.app.name, f"{self.id}: {exc}"))
            return
        self._broadcast(m.ChainPlaced(dep.app.name, ci, assigned))

    def _on_placed(self, msg: m.ChainPlaced) -> None:
        dep = self.apps.get(msg.app)
        if dep is None or not 0 <= msg.chain < len(dep.layout.chains):
            self._refusal("chain_placed_unknown_chain")
            return
        if msg.chain in dep.placed_chains:
            self._refusal("chain_placed_again")
            return
        if set(msg.assignments) != set(dep.layout.chains[msg.chain].vertices):
            self._refusal("chain_placed_other_vertices")
            return
        dep.placed.update(msg.assignments)
        dep.placed_chains.add(msg.chain)
        chain = dep.layout.chains[msg.chain]
        if msg.assignments.get(chain.head) == self.id and msg.chain in dep.started_chains:
            by_node: dict[str, list[str]] = {}
            for v in chain.vertices:
                by_node.setdefault(msg.assignments[v], []).append(v)
            dep.parts_pending[msg.chain] = set(by_node)
            for node, verts in by_node.items():
                self._send(node, m.BuildChain(dep.app.name, msg.chain, verts))
        self._start_ready_chains(dep)

    def _on_build(self, src: str, msg: m.BuildChain) -> None:
        """Host this node's part of a chain; it is ready once every instance has started."""
        dep = self.apps.get(msg.app)
        if dep is None or not 0 <= msg.chain < len(dep.layout.chains):
            self._refusal("build_unknown_chain")
            return
        if dep.running or not set(msg.vertices) <= set(dep.layout.chains[msg.chain].vertices):
            self._refusal("build_not_of_the_chain")  # (a running app is built already)
            return
        starting = set()
        for vid in msg.vertices:
            h = dep.stones.get(vid)
            if h is None:
                h = dep.stones[vid] = self._host(dep, vid)
            if not h.started:
                starting.add(vid)
        if starting:
            dep.building[msg.chain] = (src, starting)
        else:
            self._send(src, m.ChainPartReady(msg.app, msg.chain, self.id))

    def _on_part_ready(self, msg: m.ChainPartReady) -> None:
        dep = self.apps.get(msg.app)
        if dep is None or msg.node not in dep.parts_pending.get(msg.chain, ()):
            self._refusal("part_ready_unexpected")
            return
        pending = dep.parts_pending[msg.chain]
        pending.discard(msg.node)
        if not pending:
            del dep.parts_pending[msg.chain]
            self._send(dep.origin, m.ChainBuilt(msg.app, msg.chain))

    def _on_built(self, msg: m.ChainBuilt, now: float) -> None:
        dep = self.apps.get(msg.app)
        proc = self._deploying(msg.app)
        if (
            dep is None
            or dep.origin != self.id
            or proc is None  # no deployment of it in progress here
            or msg.chain in dep.built
            or not 0 <= msg.chain < len(dep.layout.chains)
        ):
            self._refusal("chain_built_unexpected")
            return
        dep.built.add(msg.chain)
        proc.on("built")
        if len(dep.built) == len(dep.layout.chains):
            proc.on("all_built")
            self._end(proc.pid)
            self._broadcast(m.StartApp(msg.app))
            if dep.client is not None:
                elapsed = self._elapsed_ms(dep.requested_at)
                reply = m.DeployReply(msg.app, True, dict(dep.placed), elapsed)
                self._effects.append(Reply(dep.client, reply))
                dep.client = None

    def _on_deploy_failed(self, msg: m.DeployFailed, now: float) -> None:
        dep = self.apps.get(msg.app)
        if dep is None or dep.origin != self.id:
            return
        proc = self._deploying(msg.app)
        if proc is None:  # deployed (or failed) already: a failure report cannot stop it
            self._refusal("deploy_failed_after_deployment")
            return
        proc.fail(self, msg.reason)
        self._end(proc.pid)
        if dep.client is not None:
            self._effects.append(Reply(dep.client, _failed_reply(msg.app, msg.reason)))
            dep.client = None
        self._broadcast(m.StopApp(msg.app))

    def _on_start(self, msg: m.StartApp, now: float) -> None:
        dep = self.apps.get(msg.app)
        if dep is None or dep.running:
            self._refusal("start_app_running")
            return
        dep.running = True
        dep.started_at = now
        dep.placed_at = dict.fromkeys(range(len(dep.layout.chains)), now)
        for vid, h in dep.stones.items():
            if h.kind == "source":
                self._start_source(dep, vid, now)
        self._effects.append(SetTimer(("retransmit", msg.app), now + RETRANSMIT_S))

    def _undeploy_refused(self, msg: m.StopApp) -> str:
        """Why this node does not stop ``msg.app`` ('' if it does). With operator keys only
        an operator's signed undeploy stops a running app (a member's StopApp alone does
        not); a deployment that has not started may be stopped by its origin after a
        failure."""
        if not self.authority.signed:
            return ""
        dep = self.apps.get(msg.app)
        if not msg.sig and (dep is None or not dep.running):
            return ""
        return self.authority.undeploy(msg)  # (remembers the revocation)

    def _undeployed_before(self, msg: m.StopApp) -> bool:
        """An operator's undeploy older than the deployment running here (one told again to
        a node that comes into reach): it stops nothing."""
        dep = self.apps.get(msg.app)
        return bool(msg.sig) and dep is not None and generation(dep.document) > msg.at

    def _on_stop_app(self, msg: m.StopApp, now: float) -> None:
        if self._undeploy_refused(msg):
            self._refusal("stop_app_unauthorized")
            return
        if self.authority.signed and self._undeployed_before(msg):
            self._refusal("undeploy_older_than_deployment")  # (maybe told again: harmless)
            return
        gone = self.apps.pop(msg.app, None)
        if gone is not None:
            self._stop_app(gone, "undeploy")
        self._early.pop(msg.app, None)
        self.manager.forget(msg.app)

    def _instance_ready(self, dep: Deployment, vid: str) -> None:
        for ci, (asker, starting) in list(dep.building.items()):
            starting.discard(vid)
            if not starting:
                del dep.building[ci]
                self._send(asker, m.ChainPartReady(dep.app.name, ci, self.id))
        super()._instance_ready(dep, vid)

    def _instance_failed(self, dep: Deployment, vid: str, error: str) -> None:
        for ci, (_, starting) in list(dep.building.items()):
            if vid in starting:
                del dep.building[ci]
                self._send(dep.origin, m.DeployFailed(dep.app.name, error))
        super()._instance_failed(dep, vid, error)


def _failed_reply(app: str, reason: str) -> m.DeployReply:
    return m.DeployReply(app=app, ok=False, placement={}, elapsed_ms=0.0, error=reason)
