"""The node core: a router over one node's tables. Sans-IO.

Fed ``(message, now)``, ``(timer, now)``, a client request or an executor result; returns
effects (send a message to a node, reply to a client, set or cancel a timer, start, feed or
stop a vertex instance). It never reads a clock or a socket and never runs user code: the
asyncio driver (``mso.node.driver``) supplies real time, connections and the executor; the
simulator supplies virtual ones.

This module is only the router: a message type → handler table, the timer keys, the deadline
of every procedure this node coordinates, and status. The handlers are this node's part in each
distributed procedure, one module per group, layered as :mod:`mso.node.tables` describes.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from mso.errors import MsoError
from mso.management import RuleSettings
from mso.model.network import PowerModel
from mso.node.liveness import DEAD_AFTER_S, HEARTBEAT_S
from mso.node.manager import Manager
from mso.node.membership import MONITOR_PERIOD_S, Membership
from mso.node.tables import Deployment, Hosted, crash_status
from mso.protocol import effects as fx
from mso.protocol import messages as m
from mso.protocol.effects import Effect, Reply, Send, SetTimer
from mso.protocol.procedures.base import Deadline, IllegalTransition, Procedure, Retry
from mso.protocol.procedures.deploy import Deploy
from mso.protocol.procedures.membership import Suspicion, Vouch
from mso.protocol.procedures.relocate import Relocation
from mso.protocol.procedures.remap import Remap
from mso.protocol.procedures.status import StatusFanout

__all__ = ["Deployment", "Effect", "Hosted", "NodeCore", "Reply", "Send", "SetTimer"]

REVOCATIONS_TOLD = 16  # the operator's latest undeploys told to each newly reachable node


class NodeCore(Membership):
    """One node's state machine: the router over its tables and procedures."""

    manager: Manager
    # messages that may overtake the announcement of their app: held until it arrives
    EARLY = (m.ChainPlaced, m.BuildChain, m.ChainPartReady, m.ChainBuilt, m.StartApp)
    MAX_EARLY = 1000

    def __init__(
        self,
        node_id: str,
        *,
        capacity: float = 1.0,
        window: int = 4096,
        power: PowerModel | None = None,
        battery_wh: float | None = None,
        heartbeat_s: float = HEARTBEAT_S,
        dead_after_s: float = DEAD_AFTER_S,
        policy: Any = None,
        manage: bool = True,
        rules: RuleSettings | None = None,
        incarnation: int = 0,
    ) -> None:
        super().__init__(
            node_id,
            capacity=capacity,
            window=window,
            power=power,
            battery_wh=battery_wh,
            heartbeat_s=heartbeat_s,
            dead_after_s=dead_after_s,
            incarnation=incarnation,
        )
        # the router: message type -> the handler of the procedure it belongs to
        self._handlers: dict[type, Callable[[str, Any, float], None]] = {
            m.Data: lambda src, msg, now: self._on_data(msg),
            m.Ack: lambda src, msg, now: self._on_ack(msg, now),
            m.AppAnnounce: lambda src, msg, now: self._on_announce(src, msg, now),
            m.Probe: lambda src, msg, now: self._on_probe(msg),
            m.ProbeReply: lambda src, msg, now: (
                self._on_remap_probe(msg) if msg.chain < 0 else self._on_probe_reply(msg)
            ),  # chain -1 marks a remap's probe
            m.ChainPlaced: lambda src, msg, now: self._on_placed(msg),
            m.BuildChain: lambda src, msg, now: self._on_build(src, msg),
            m.ChainPartReady: lambda src, msg, now: self._on_part_ready(msg),
            m.ChainBuilt: lambda src, msg, now: self._on_built(msg, now),
            m.StartApp: lambda src, msg, now: self._on_start(msg, now),
            m.StopApp: lambda src, msg, now: self._on_stop_app(msg, now),
            m.DeployFailed: lambda src, msg, now: self._on_deploy_failed(msg, now),
            m.StatusRequest: lambda src, msg, now: self._send(
                src, m.StatusReply(req=msg.req, nodes={self.id: self.status(now)})
            ),
            m.StatusReply: lambda src, msg, now: self._on_status_reply(msg),
            m.Marker: lambda src, msg, now: self._on_marker_msg(msg, now),
            m.RelocateRequest: lambda src, msg, now: self._on_relocate_request(msg, now),
            m.Prepare: lambda src, msg, now: self._on_prepare(src, msg),
            m.Prepared: lambda src, msg, now: self._on_prepared(msg, now),
            m.Unprepare: lambda src, msg, now: self._on_unprepare(msg, now),
            m.Switch: lambda src, msg, now: self._on_switch(msg),
            m.Handover: lambda src, msg, now: self._on_handover(src, msg, now),
            m.Moved: lambda src, msg, now: self._on_moved(msg, now),
            m.HandoverDone: lambda src, msg, now: self._on_handover_done(msg, now),
            m.ChainDelay: lambda src, msg, now: self._on_chain_delay(msg, now),
            m.Heartbeat: lambda src, msg, now: self._on_heartbeat(src, msg, now),
            m.NodeDown: lambda src, msg, now: self._on_node_down(
                msg.node, msg.detector, now, msg.incarnation
            ),
            m.NodeUp: lambda src, msg, now: self._on_node_up(msg, now),
            m.Suspect: lambda src, msg, now: self._on_suspect(src, msg, now),
            m.Hears: lambda src, msg, now: self._on_hears(src, msg, now),
            m.AppSync: lambda src, msg, now: self._on_app_sync(src, msg, now),
            m.Rewire: lambda src, msg, now: self._on_rewire(msg, now),
            m.Resume: lambda src, msg, now: self._on_resume(msg, now),
        }
        # management rules and policies (§3.5); the node policy is checked here, at start
        self.manager = Manager(self, policy, rules, enabled=manage)

    def start(self, now: float) -> list[Effect]:
        """Begin monitoring; drivers call this once when the node starts."""
        self._sample(now)
        self._effects.append(SetTimer(("monitor",), now + MONITOR_PERIOD_S))
        self._effects.append(SetTimer(("heartbeat",), now + self.liveness.period_s))
        return self._run(now)

    def set_routes(self, routes: dict[str, tuple[str, int]], now: float = 0.0) -> list[Effect]:
        """Take the routing view's current routes; returns effects (a recovery waiting for
        routes around a failed node may start)."""
        self._now = now
        old, self.routes = self.routes, {d: r for d, r in routes.items() if d != self.id}
        self.monitor.note_routes(now, self.routes)
        changed = {d for d in set(old) | set(self.routes) if old.get(d) != self.routes.get(d)}
        for dep in self.apps.values():  # a route inside a chain changed (the route rule's event)
            for c in dep.layout.chains:
                if changed & {dep.placed.get(v) for v in c.vertices}:
                    dep.route_changed[c.index] = now
        neighbours = {d for d, (hop, _) in self.routes.items() if hop == d}
        self.liveness.set_routes(now, set(self.routes) - self.dead, neighbours)
        self._back_in_reach(now)
        if set(self.routes) - set(old):  # a hello: newly reachable nodes learn our incarnation
            beat = self._beat()  # (and whom we hold failed, if a partition just healed)
            undeploys = list(self.authority.revoked.values())[-REVOCATIONS_TOLD:]
            for d in sorted(set(self.routes) - set(old)):
                self._send(d, beat)
                for stop in undeploys:  # and the operator's latest undeploys (a node that
                    self._send(d, stop)  # restarted or was cut off has not heard them)
        waiting, self._probes_waiting = self._probes_waiting, []
        for deadline, probe in waiting:
            if deadline >= now:
                self._forward_probe(probe, now)
        for dep in list(self.apps.values()):
            self._maybe_recover(dep, now)
        return self._run(now)

    def on_vertex(self, res: fx.VertexResult, now: float) -> list[Effect]:
        """A result from the executor (drivers call this, like ``receive``)."""
        self._now = now
        self._guarded(type(res).__name__, self._on_vertex, res, now)
        return self._run(now)

    def receive(self, src: str, msg: m.Message, now: float) -> list[Effect]:
        if src in self.dead:  # a node declared failed is heard only to rejoin
            if isinstance(msg, m.Heartbeat):
                self._now = now
                self._on_dead_heartbeat(src, msg, now)
                return self._run(now)
            self.dropped_messages += 1
            return []
        self.liveness.heard_from(src, now)
        self._guarded("heard", self._heard_directly, src, now)
        self._work.append((src, "", msg))
        return self._run(now)

    def request(self, client: int, msg: m.Message, now: float) -> list[Effect]:
        """A request from a client connection (CLI, API, emulator controller)."""
        self._now = now
        if isinstance(msg, m.DeployRequest):
            self._deploy_request(client, msg, now)
        elif isinstance(msg, m.StopApp):
            why = self._undeploy_refused(msg)
            if not why and self.authority.signed and self._undeployed_before(msg):
                why = f"refused: this undeploy of {msg.app!r} is older than its deployment"
            if why:
                self._refusal("stop_app_unauthorized")
                self._effects.append(Reply(client, m.Refused(why)))
                return self._run(now)
            if msg.app in self.apps:
                self._broadcast(msg)
            self._effects.append(Reply(client, m.StopApp(msg.app)))
        elif isinstance(msg, m.RelocateRequest):
            self._relocate_request(client, msg, now)
        elif isinstance(msg, m.RemapRequest):
            self._remap_request(client, msg, now)
        elif isinstance(msg, m.StatusRequest):
            self._status_request(client, msg, now)
        else:
            self.dropped_messages += 1
        return self._run(now)

    def on_timer(self, key: Any, now: float) -> list[Effect]:
        self._now = now
        self._guarded("timer", self._on_timer, key, now)
        return self._run(now)

    def _on_timer(self, key: Any, now: float) -> None:
        if isinstance(key, Deadline):
            proc = self.procedures.get(key.pid)
            if proc is not None and not proc.done and now >= proc.deadline - 1e-9:
                self._expire(proc, now)  # (a procedure may have pushed its deadline on)
            return
        if isinstance(key, Retry):
            proc = self.procedures.get(key.pid)
            if isinstance(proc, Relocation):
                self._step_timeout(key.pid, now)
            elif isinstance(proc, Remap):
                self._remap_probe_timeout(key.pid, key.attempt, now)
            return
        kind = key[0]
        if kind == "source":
            self._source_tick(key[1], key[2], now)
        elif kind == "retransmit":
            self._retransmit(key[1], now)
        elif kind == "monitor":
            self._sample(now)
            self._report_delays(now)
            self.manager.tick(now)
            self._effects.append(SetTimer(("monitor",), now + MONITOR_PERIOD_S))
        elif kind == "heartbeat":
            self._heartbeat(now)
        elif kind == "recover":
            dep = self.apps.get(key[1])
            if dep is not None:
                self._maybe_recover(dep, now)

    def _expire(self, proc: Procedure, now: float) -> None:
        """A procedure's deadline passed: its defined failure, reported to whoever waits."""
        why = f"{proc.name} did not finish within {proc.deadline - proc.started_at:g} s"
        if isinstance(proc, Relocation):
            self._reloc_failed(proc, why, now)
        elif isinstance(proc, Remap):
            self._finish_remap(proc.pid, now, why)
        elif isinstance(proc, Deploy):  # a probe or a chain build was lost: stop it everywhere
            self._on_deploy_failed(m.DeployFailed(proc.app, f"{self.id}: {why}"), now)
            self._end(proc.pid)
        elif isinstance(proc, Suspicion):  # nobody said they hear the node: it failed
            proc.expire(self)
            self._suspected(proc, now)
        elif isinstance(proc, Vouch):  # the node asked on others' behalf did not answer
            self._vouch_expired(proc)
        else:
            proc.expire(self)
            self._end(proc.pid)

    def _run(self, now: float) -> list[Effect]:
        self._now = now
        while self._work:
            src, _, msg = self._work.popleft()
            self._guarded(type(msg).__name__, self._dispatch, src, msg, now)
        self._flush()
        out, self._effects = self._effects, []
        return out

    def _guarded(self, what: str, handle: Callable[..., None], *args: Any) -> None:
        """Handle one message, timer or executor result. An event at the wrong moment is an
        illegal transition, counted; a bug costs that one event, never the link or the node.
        Tests run strict, where both raise."""
        try:
            handle(*args)
        except MsoError:
            self.dropped_messages += 1
        except IllegalTransition:
            self.illegal_transitions += 1
            if self.strict:
                raise
        except Exception as exc:
            self.handler_errors += 1
            self.last_handler_error = f"{what}: {type(exc).__name__}: {exc}"
            if self.strict:
                raise

    def _dispatch(self, src: str, msg: m.Message, now: float) -> None:
        if isinstance(msg, self.EARLY) and msg.app not in self.apps:
            held = self._early.setdefault(msg.app, [])
            if len(held) < self.MAX_EARLY and len(self._early) <= 64:
                held.append((src, msg))  # replayed when the app's announcement arrives
            else:
                self.dropped_messages += 1
            return
        handler = self._handlers.get(type(msg))
        if handler is None:
            self.dropped_messages += 1  # a client's request, or a link message, from a node
            return
        handler(src, msg, now)

    def status(self, now: float) -> dict[str, Any]:
        apps: dict[str, Any] = {}
        for name, dep in self.apps.items():
            up = max(now - dep.started_at, 1e-9) if dep.running else 0.0
            edges = {}
            for i, e in enumerate(dep.app.edges):
                if i in dep.out or i in dep.inc:
                    inc = dep.inc.get(i)
                    out = dep.out.get(i)
                    sent = out.next_seq if out else 0
                    edges[f"{e.src}->{e.dst}"] = {
                        "sent": sent,
                        "delivered": inc.expected if inc else 0,
                        "duplicates": inc.duplicates if inc else 0,
                        "in_flight": out.in_flight if out else 0,
                        "events_per_s": (sent / up) if up else 0.0,
                    }
            apps[name] = {
                "running": dep.running,
                "parked": {dep.layout.chains[c].name: why for c, why in dep.parked.items()},
                "recoveries": list(dep.recoveries),
                "dropped_parked": {
                    f"{dep.app.edges[e].src}->{dep.app.edges[e].dst}": n
                    for e, n in sorted(dep.dropped.items())
                },
                "chain_delay_ms": {
                    dep.layout.chains[c].name: round(ms, 3) for c, ms in sorted(dep.delays.items())
                },
                "slo_ms": dep.app.slo_ms,
                "origin": dep.origin,
                "placement": dict(dep.placed),
                "chains": [list(c.vertices) for c in dep.layout.chains],
                "vertices": {
                    vid: {
                        "kind": h.kind,
                        "state": h.state(now),
                        "busy_s": round(now - h.busy_since, 3) if h.busy_since else 0.0,
                        "queued": h.queued
                        + sum(len(p[1]) for p in h.pending if not isinstance(p, m.Marker)),
                        "processed": h.processed,
                        "emitted": h.emitted,
                        "calls": h.calls,
                        "ended": h.ended,  # its stream is over (a source's, or every input's)
                        "errors": h.errors,
                        "cpu_s": h.cpu_s,
                        "last_error": h.last_error,
                        "stats": h.stats,
                    }
                    | crash_status(dep.crashes.get(vid))
                    for vid, h in (dep.crashed | dep.stones).items()
                },
                "edges": edges,
            }
        extra = self.status_hook() if self.status_hook is not None else {}
        self._sample(now)
        return extra | {
            "node": self.id,
            "monitor": self.monitor.snapshot() | {"work_ms": self.work_ms, "cpu_ms": self.cpu_ms},
            "routes": {d: list(r) for d, r in sorted(self.routes.items())},
            "neighbours": sorted(n for n, (hop, _) in self.routes.items() if hop == n),
            "apps": apps,
            "dropped_messages": self.dropped_messages,
            "refusals": dict(sorted(self.refusals.items())),
            "illegal_transitions": self.illegal_transitions,
            "handler_errors": self.handler_errors,
            "last_handler_error": self.last_handler_error,
            "procedures": self.open_procedures(now),
            "failed_nodes": sorted(self.dead),
            "suspected_nodes": sorted(self._suspicions),
            "incarnation": self.incarnation,
            "management": self.manager.status(),
            "failures": list(self.failures),
            "rejoins": list(self.rejoins),
            "liveness": self.liveness.stats(),
            "heard": {
                n: {"at": t, "load": b.load, "drain_w": b.drain_w, "lifetime_s": b.lifetime_s}
                for n, (t, b) in sorted(self.liveness.heard.items())
            },
        }

    def _status_request(self, client: int, req: m.StatusRequest, now: float) -> None:
        mine = {self.id: self.status(now)}
        others = [n for n in self.known_nodes() if n != self.id]
        if not req.everywhere or not others:
            self._effects.append(Reply(client, m.StatusReply(req.req, mine)))
            return
        self._rid += 1
        fanout = StatusFanout(self._rid, now, client, mine, others)
        self._begin(fanout)
        fanout.start(self)

    def _on_status_reply(self, msg: m.StatusReply) -> None:
        fanout = self.procedures.get(msg.req)
        if isinstance(fanout, StatusFanout):
            fanout.receive(self, msg)
            if fanout.done:
                self._end(fanout.pid)
