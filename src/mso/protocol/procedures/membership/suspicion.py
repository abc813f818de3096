"""The indirect probe at both ends: a watched node silent (or out of reach and needed) for the
liveness window is suspected and a few members asked (:class:`~.detector.Suspicion`); asked
about a node, this node answers, or asks it in turn (:class:`~.detector.Vouch`)."""

from __future__ import annotations

import os

from mso.protocol import messages as m
from mso.protocol.procedures.membership import reach
from mso.protocol.procedures.membership.claims import (
    LONE_YES_WINDOWS,
    MEMBERS_YES_WINDOWS,
    NONCE_BYTES,
    ask_whom,
)
from mso.protocol.procedures.membership.declare import Declaring
from mso.protocol.procedures.membership.detector import P, PeerEvent, Suspicion, Vouch
from mso.protocol.procedures.relocation import Relocation
from mso.protocol.procedures.remap import ROUTES_SETTLE_S


class Suspecting(Declaring):
    """Membership's layer that suspects, asks and answers; its verdicts are declared below."""

    def heard(self, src: str, now: float) -> None:
        """A message from ``src``, which this node holds alive: it lives (and if suspected,
        it reaches us though we do not reach it). Noted only within the tables' bound."""
        if self.admits(src, self.liveness.last_heard):
            self.liveness.heard_from(src, now)
        self.heard_directly(src, now)

    def heard_directly(self, src: str, now: float) -> None:
        """A message from a suspected node (it reaches us though we do not reach it): it
        lives, which is what the suspicion asked."""
        if self._vouchers.since:
            self._vouchers.heard(src)
        if src in self._suspicions:
            self._unsuspect(src, PeerEvent.VOUCHED)
            self.liveness.vouched(src, now)

    def _suspect(self, node: str, now: float) -> None:
        """``node``, which this node watches, has been silent for the liveness window. One
        node's silence is not evidence enough (a routing daemon may leave it without a route
        to a live node for seconds while the others still hear it): ask a few members
        (:func:`~.claims.ask_whom`), and declare it only if none hears it (:class:`Suspicion`)."""
        if node in self._suspicions or node in self.failed or node == self.ctx.id:
            return
        if self._peer(node).state is P.ALIVE:
            self._move(node, PeerEvent.SILENT)
        said = self.liveness.heard.get(node)
        asked = ask_whom(node, self.ctx.id, said[1] if said else None, self.ctx.routes, self.failed)
        if not asked:  # nobody left to ask: this node is cut off (its own probes agree)
            self.on_node_down(node, self.ctx.id, now)
            return
        nonce = os.urandom(NONCE_BYTES) if self.proofs() else b""
        proc = Suspicion(self.ctx.new_pid(), now, node, asked, self.liveness.dead_after_s, nonce)
        self.ctx.begin(proc)
        self._suspicions[node] = proc.pid
        proc.start(self.ctx)

    def _routes_settled(self, node: str, now: float) -> bool:
        """Whether the routing view has had :data:`~.remap.ROUTES_SETTLE_S` to converge since
        ``node``, silent, was last heard (past the liveness window): a suspicion of it that
        nobody answers is then taken as confirmed -- the asker is cut off from the suspect's
        side, or all of it died -- and not before. Silence alone is evidence only while the
        asker can ask someone; a route hole shorter than that declares nobody."""
        last = self.liveness.last_heard.get(node)
        return last is None or now - last >= self.liveness.dead_after_s + ROUTES_SETTLE_S

    def _blocking(self, now: float, away: set[str]) -> list[str]:
        """Nodes out of reach for the liveness window, not heard in it, that host a vertex of
        an app this node runs part of whose re-placing would let events flow again
        (:func:`.reach.re_placeable`): the app cannot progress otherwise, so they are
        suspected like a silent neighbour (a few asked); if nobody hears them they are
        declared, their vertices re-placed, and the incarnation rules take them back exactly
        once when they are heard again. Any other node out of reach stays unreachable (a
        robot that drove off with its pinned sink, or the node beyond it on a line that
        broke): taken back as it is, no reset."""
        if not away:
            return []
        window = self.liveness.dead_after_s
        return [
            n
            for n in sorted(away)
            if now - self._silent_since(n) > window
            and not self.liveness.hears(n, now)
            and self._needed(n, away)
        ]

    def _silent_since(self, node: str) -> float:
        """When ``node``, out of reach, fell silent: when it was last heard if that was
        within the window before it went out of reach (a host of the app we exchange events
        with, or a neighbour: declared from its last word, as a silent neighbour is -- counted
        from the route's loss, detection took a tick longer, 0.60 s against 0.50), else when
        it went (a node long unheard whose route merely flapped is not suspected at once)."""
        gone = self.liveness.gone[node]
        heard = self.liveness.last_heard.get(node)
        return heard if heard is not None and gone - heard < self.liveness.dead_after_s else gone

    def _needed(self, node: str, away: set[str]) -> bool:
        """``node`` runs a vertex of an app this node runs part of whose re-placing would let
        events flow again (:func:`.reach.re_placeable`), or one next to a vertex being restored
        (the replacement waits for every surviving end of its edges to say where it stands,
        and one out of reach cannot: it is re-placed too), or the old host of a move this node
        coordinates (its handover cannot come: declared, the move's target restores the
        vertex)."""
        restoring: set[tuple[str, str]] = set()
        for proc in self.ctx.open():
            if isinstance(proc, Relocation) and proc.source == node and not proc.restore:
                return True
            if isinstance(proc, Relocation) and proc.restore:
                restoring.add((proc.app, proc.vertex))
        for dep in self.ctx.apps.values():
            if not dep.instances:
                continue
            app, placed = dep.app.name, dep.placed
            lost = dep.lost(self.failed) | {  # what a failed node ran and is not running
                v  # again elsewhere (restored, a node next to it is no longer needed: 3238)
                for n in self.failed
                for v in self._ran.get(n, {}).get(app, ())
                if placed.get(v) == n or (app, v) in restoring
            }
            near = {e.src for e in dep.app.edges if e.dst in lost}
            near |= {e.dst for e in dep.app.edges if e.src in lost}
            for v, n in dep.placed.items():
                if n != node:
                    continue
                if v in near or reach.re_placeable(
                    dep.app, dep.placed, dep.layout.resolved, v, away
                ):
                    return True
        return False

    def on_suspect(self, src: str, msg: m.Suspect, now: float) -> None:
        """Another node lost ``msg.node``: say whether we hear it (we heard it within our
        liveness window, and do not hold it failed; asked about ourselves, we live). If we do
        not but reach it, we ask it and answer when it does or our :class:`Vouch` expires."""
        node = msg.node
        if node == self.ctx.id:
            self.ctx.send(src, m.Hears(node, msg.rid, True, 0, msg.nonce))
            return
        ago = self.liveness.ago_ms(node, now)
        hears = self.liveness.hears(node, now, self.liveness.dead_after_s / 2)
        if node in self.failed or (hears and not msg.nonce):
            self.ctx.send(src, m.Hears(node, msg.rid, node not in self.failed, ago, msg.nonce))
            return
        if (
            node not in self.ctx.routes
            or node == src
            or (node in self.liveness.neighbours and not hears)
        ):
            self.ctx.send(src, m.Hears(node, msg.rid, False, ago, msg.nonce))  # (a neighbour
            return  # we watch and have not heard: our own beats are the probe)
        # not heard lately but reached, or heard and the asker wants the proof: ask it
        proc = self.ctx.procedure(self._vouching.get(node, -1))
        if not isinstance(proc, Vouch):
            wait = min(self.liveness.dead_after_s / 2, 2 * self.liveness.period_s)
            proc = Vouch(self.ctx.new_pid(), now, node, wait)
            self.ctx.begin(proc)
            self._vouching[node] = proc.pid  # (bounded by the nodes this node reaches)
            proc.start(self.ctx)
        proc.ask(self.ctx, src, msg.rid, msg.nonce)

    def on_hears(self, src: str, msg: m.Hears, now: float) -> None:
        if msg.rid == 0 and src == msg.node:
            return  # the answer to our own probe of a claim: hearing it was the point
        proc = self.ctx.procedure(msg.rid)
        if isinstance(proc, Vouch) and src == proc.node == msg.node and msg.yes:
            proc.answered(self.ctx, msg.nonce, msg.proof)
            if proc.done:
                self._vouching.pop(proc.node, None)
                self.ctx.end(proc.pid)
            return
        if not isinstance(proc, Suspicion) or proc.node != msg.node or src not in proc.missing:
            if not self.ctx.ours(msg.rid):  # (ours: a late answer to a suspicion that ended)
                self.ctx.refusal("hears_unasked")  # no such suspicion, or not asked (or twice)
            return
        if proc.nonce and msg.yes:  # with proofs: the suspect's own word, or nothing
            if msg.proof and msg.nonce == proc.nonce:  # (the transport checked its signature)
                self.liveness.vouched(msg.node, now)  # it answered our challenge: alive now
                self._vouchers.heard(msg.node)
                proc.heard_by.add(src)
                proc.answer(src, True)
            else:
                self.ctx.refusal("hears_unproven")  # a member's word alone: not taken
                proc.set_aside(src)
            if proc.done:
                self.suspected(proc, now)
            return
        yes = msg.yes
        if yes and msg.ago_ms >= 0:  # heard then: the silence clock runs from there
            at = now - msg.ago_ms / 1e3
            self.liveness.vouched(msg.node, at)
            yes = now - at <= self.liveness.dead_after_s / 2
        if yes:
            proc.heard_by.add(src)
            grace = LONE_YES_WINDOWS * self.liveness.dead_after_s
            bound = MEMBERS_YES_WINDOWS * self.liveness.dead_after_s
            if not self._vouchers.counts(msg.node, proc.heard_by, proc.asked, now, grace, bound):
                proc.set_aside(src)  # one member's word, for too long: another's, or none
        if src in proc.missing:
            proc.answer(src, yes)
        if proc.done:
            self.suspected(proc, now)

    def suspicion_expired(self, proc: Suspicion, now: float) -> None:
        """Nobody said they hear the suspected node in time: it failed."""
        proc.expire(self.ctx)
        self.suspected(proc, now)

    def vouch_expired(self, proc: Vouch) -> None:
        """The node we asked on others' behalf did not answer: we tell them no."""
        self._vouching.pop(proc.node, None)
        proc.expire(self.ctx)
        self.ctx.end(proc.pid)

    def suspected(self, proc: Suspicion, now: float) -> None:
        """A suspicion ended with its answers or at its deadline: act on its outcome."""
        self.ctx.end(proc.pid)
        self._suspicions.pop(proc.node, None)
        if proc.outcome == "vouched":  # someone heard it lately: judged again from then
            self._move(proc.node, PeerEvent.VOUCHED)
        elif proc.outcome == "unanswered" and not self._routes_settled(proc.node, now):
            # nobody answered: this node's own routes may be what broke (babeld re-routes a
            # broken link in 1.3-2.1 s and forwards into it meanwhile). Asked again over the
            # routes as they are then, until the routing view has had time to converge
            self.ctx.refusal("suspicion_unanswered")  # (counted in status, refusals)
            self._move(proc.node, PeerEvent.VOUCHED)
        else:
            if proc.heard_by and proc.outcome == "confirmed":
                self.ctx.refusal("hears_uncorroborated")  # a member's lone yes, set aside
            self.on_node_down(proc.node, self.ctx.id, now, witness=proc.witness)
            if self._peer(proc.node).state is P.SUSPECT:  # (not declared after all)
                self._move(proc.node, PeerEvent.VOUCHED)
