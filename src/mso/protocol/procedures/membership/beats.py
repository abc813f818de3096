"""Beats out: this node's heartbeat to its neighbours every period (the figures on one a
monitor period, failure claims piggybacked), the silent and the blocking suspected on each
tick, and the newly reachable told who this node is when routes change."""

from __future__ import annotations

from operator import attrgetter

import msgspec

from mso.protocol import messages as m
from mso.protocol.effects import Send
from mso.protocol.events import HeartbeatTick, RecoveryDue, RoutesChanged
from mso.protocol.procedures.membership.suspicion import Suspecting

REJOIN_EVERY = 10  # heartbeat periods between heartbeats to reachable nodes declared failed
MONITOR_PERIOD_S = 1.0  # how often the monitor samples on its own: its figures ride on one beat
# of each period (they change no faster)
REVOCATIONS_TOLD = 16  # the operator's latest undeploys told to each newly reachable node
_VANISHED = attrgetter("vanished")
# the one tick key (equal to any other HeartbeatTick(); one object, so the driver's timer table
# finds it by identity rather than calling the dataclass's __eq__ on every beat)
_TICK = HeartbeatTick()


class Beating(Suspecting):
    """Membership's layer that beats and watches routes."""

    def start(self, now: float) -> None:
        self.ctx.set_timer(_TICK, now + self.liveness.period_s)

    def beat(self, news: list[m.NodeDown] | None = None, figures: bool = True) -> m.Heartbeat:
        """This node's beat, with its monitor's figures unless ``figures`` is False (see
        Heartbeat)."""
        return m.Heartbeat(
            self.ctx.id,
            self.incarnation,
            dict(self._failed_incarnation),
            self._leader(),
            self._hosting(),
            self.ctx.figures() if figures else None,
            news or [],
        )

    def _slim_beat(self, news: list[m.NodeDown]) -> m.Heartbeat:
        """This period's beat without figures: the last one again when it says all this one
        would (no news; the same incarnation, nodes held failed, leader and instances hosted),
        as in most periods -- no message made, and the same sends (:meth:`heartbeat`). Sent
        messages are never changed, so one can go out again."""
        kept = self._slim
        if (
            not news
            and kept is not None
            and kept.incarnation == self.incarnation
            and kept.hosting == self._hosting()
            and kept.leader == self._leader()
            and kept.failed == self._failed_incarnation
        ):
            return kept
        slim = self.beat(news, figures=False)
        self._slim = None if news else slim
        return slim

    def heartbeat(self, now: float) -> None:
        """Tell the neighbours we live; declare the silent ones failed. Our figures go on one
        beat per monitor period, and on the first beat to a neighbour since its link came up
        (``_briefed``: the time the link came up, when it was given them)."""
        every = max(1, round(MONITOR_PERIOD_S / self.liveness.period_s))
        news = self._gossip.next_beat()
        # the figures (hops to the nodes within two hops) are made only for a beat that
        # carries them, not on every beat
        slim = self.beat(news) if self._beats % every == 0 else self._slim_beat(news)
        full = slim if slim.figures is not None else None
        neighbours, emit = self.liveness.neighbours, self.ctx.emit
        if full is None and self._briefed == neighbours and self.failed.isdisjoint(neighbours):
            # most rounds: every neighbour briefed since its link came up and none held
            # failed, so the slim beat to each, in the order the last round that changed
            # ``_briefed`` (the only one that does) put them: the last round's sends again
            # when it was this beat to these neighbours
            sends = self._sends
            if sends[0] is not self._round or sends[1] is not slim:
                sends = self._sends = (self._round, slim, [Send(n, slim) for n in self._round])
            self.ctx.emit_all(sends[2])
        else:
            for n, since in sorted(neighbours.items()):
                if n not in self.failed:
                    briefed = self._briefed.get(n) == since
                    self._briefed[n] = since
                    if not briefed and full is None:
                        full = msgspec.structs.replace(slim, figures=self.ctx.figures())
                    emit(Send(n, full if not briefed and full is not None else slim))
            if not self._briefed.keys() <= neighbours.keys():
                for n in set(self._briefed) - set(neighbours):
                    del self._briefed[n]  # bounded by the neighbours
            self._round = sorted(self._briefed)
        self._beats += 1
        if self._beats % REJOIN_EVERY == 0:  # a failed node we can reach again: a healed
            for n in sorted(self.failed):  # partition; tell it, so one side rejoins the other
                if n in self.ctx.routes:
                    if full is None:
                        full = msgspec.structs.replace(slim, figures=self.ctx.figures())
                    self.ctx.emit(Send(n, full))
        # (on every beat: mostly nobody out of reach, no claim pending, no app engaged here)
        away = set(self.liveness.unreachable(self.failed)) if self.liveness.gone else set()
        for n in self.liveness.silent(now, self.failed):  # silent with a route: suspected;
            if n in self.ctx.routes or self._needed(n, away):  # out of reach, only if the
                self._suspect(n, now)  # apps cannot progress without re-placing what it runs
        for n in self._blocking(now, away) if away else ():  # unreachable, and it runs part
            self._suspect(n, now)  # of an app we run: asked about like a silent neighbour
        pending = (
            self._claims.due(now, self.liveness.dead_after_s / 2) if self._claims.pending else ()
        )
        for claim, at in pending:
            if self.liveness.hears(claim.node, now, within=now - at):
                self.ctx.refusal("node_down_refuted")  # it answered our probe: it lives
            elif claim.node not in self.failed:
                self._declare(claim, now)  # our own probe agrees
        self._flush_syncs()
        # this node may have become an app's recovery coordinator (it runs part of it now);
        # with nothing failed and nothing vanished no app has a vertex to recover
        apps = self.ctx.apps
        if self.failed or (apps.engaged and any(map(_VANISHED, apps.engaged_apps()))):
            self.ctx.publish(RecoveryDue())
        self.ctx.set_timer(_TICK, now + self.liveness.period_s)

    def on_routes_changed(self, ev: RoutesChanged) -> None:
        """Who is a neighbour and who is reachable; a suspected node in reach again is not
        suspected; newly reachable nodes learn our incarnation (and whom we hold failed, if a
        partition just healed) and the operator's latest undeploys (a node that restarted or
        was cut off has not heard them).

        At a first start (incarnation 0: the simulator's nodes at t=0) only the neighbours
        are told, not every node: N² hellos on routes of many hops were most of a 1,000-node
        start-up. The nodes that need that incarnation learn it otherwise -- the neighbours
        from our beats, the nodes of an app we host part of from its placement
        (``ChainPlaced`` carries the incarnations its probe found) or a sync -- and the others
        know our routes, which is all a claim about us needs (:meth:`heard_of_node`). A node
        that may have run before (a daemon's incarnation is its start time; the simulator's
        revived nodes count up) tells every node, as its neighbours may not know its old
        incarnation: a node that held it out of reach learns of the restart from its hello."""
        now, routes = self.ctx.now, self.ctx.routes
        neighbours = {d for d, (hop, _) in routes.items() if hop == d}
        self.liveness.set_routes(now, routes, neighbours, self.failed)
        everyone = self._routed or self.incarnation > 0
        self._routed = self._routed or bool(routes)
        if ev.appeared:
            beat = self.beat()
            undeploys = list(self.ctx.authority.revoked.values())[-REVOCATIONS_TOLD:]
            for d in sorted(ev.appeared):
                if everyone or d in neighbours:
                    self.ctx.send(d, beat)
                for stop in undeploys:
                    self.ctx.send(d, stop)
                if d not in self.failed:  # (a failed one is synced when it rejoins)
                    self._claim_to(d)
