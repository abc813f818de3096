"""Declaring a peer failed, in one place: this node's own detector's word, or another's claim
believed only when plausible and corroborated (:mod:`.claims`)."""

from __future__ import annotations

from mso.protocol import messages as m
from mso.protocol.events import Happened, PeerFailed
from mso.protocol.procedures.membership.claims import INCARNATION_MARGIN, rounds
from mso.protocol.procedures.membership.detector import PeerEvent, Suspicion
from mso.protocol.procedures.membership.tables import PeerTables


class Declaring(PeerTables):
    """Membership's layer that declares (and ends a suspicion, which declaring does too)."""

    def _unsuspect(self, node: str, event: PeerEvent | None) -> None:
        """End ``node``'s open suspicion, if any (``event``: why, by the peer's table; None
        to leave the peer's state to the caller)."""
        pid = self._suspicions.pop(node, None)
        if pid is None:
            return
        proc = self.ctx.procedure(pid)
        if isinstance(proc, Suspicion):
            proc.end()
            self.ctx.end(pid)
        if event:
            self._move(node, event)

    def on_node_down(
        self,
        node: str,
        detector: str,
        now: float,
        incarnation: int | None = None,
        witness: str = "",
        tell: bool = True,
    ) -> None:
        """A claim that ``node`` failed: this node's own (its detector's word), or another's,
        acted on only when plausible and corroborated (:mod:`.claims`). ``tell``: False when
        the node is back already (a restart seen in its beat: its rejoin follows at once, and
        the nodes that need it learn of that, not of a failure that is over)."""
        if node in self.failed or node == self.ctx.id:
            return
        if not self.heard_of_node(node) or not self.admits(node, self._failed_incarnation):
            self.ctx.refusal("node_down_unknown")  # nobody it ever heard of: no such node
            return
        seen = self._incarnations.get(node)
        known = 0 if seen is None else seen
        if incarnation is not None and incarnation < known:
            return  # that incarnation failed, and a newer one is already back
        if seen is not None and incarnation is not None and incarnation > seen + INCARNATION_MARGIN:
            self.ctx.refusal("node_down_implausible_incarnation")  # never seen: not believed
            return
        inc = known if incarnation is None else incarnation
        claim = m.NodeDown(node, detector, inc, witness)
        if detector != self.ctx.id and not self._believe(claim, now):
            return
        self._declare(claim, now, tell)

    def _believe(self, claim: m.NodeDown, now: float) -> bool:
        """Another node's claim: refused if this node hears the victim itself; acted on when
        it names a witness, a second detector agrees, or this node's own probe does (no route
        to the victim, or no answer to a ``Suspect`` within half the window: then
        ``heartbeat`` declares it)."""
        node = claim.node
        if self.liveness.hears(node, now, within=self.liveness.dead_after_s / 2):
            self.ctx.refusal("node_down_heard")  # we hear it: it lives
            return False
        if self._claims.corroborated(claim) or node not in self.ctx.routes:
            return True
        if self._claims.hold(claim, now):
            self.ctx.send(node, m.Suspect(node, 0))  # our own probe: does it answer?
        return False

    def _declare(self, claim: m.NodeDown, now: float, tell: bool = True) -> None:
        """``claim.node`` failed, by this node's detector or a claim it believes: the one
        place a peer is declared."""
        node, detector = claim.node, claim.detector
        self._claims.drop(node)
        self._vouchers.heard(node)
        self._unsuspect(node, None)
        if detector != self.ctx.id:
            self._move(node, PeerEvent.REPORTED_DOWN)
        else:  # our own word: confirmed by the nodes we asked (or nobody left to ask), or
            # a node cut off that holds most of those we reach failed (``ranks.cut_off``)
            self._move(node, PeerEvent.CONFIRMED)
        self._failed_incarnation[node] = claim.incarnation
        self._ran[node] = {  # what it ran, by our views: restored now, next to nodes that
            a: {v for v, n in dep.placed.items() if n == node}  # may be out of reach
            for a, dep in self.ctx.apps.items()
        }
        self.liveness.forget(node)
        self.failures.append({"node": node, "detector": detector, "at": now})
        del self.failures[:-50]
        self.ctx.note_event(now, f"node {node} failed (detected by {detector})")
        self.ctx.publish(Happened("peer_failed", subject=node, by=detector))
        # it spreads on our next beats; the nodes that host the apps (one of them coordinates
        # the recovery) are told at once
        self._gossip.add(claim, rounds(len(self.ctx.routes) + 1))
        if detector == self.ctx.id and tell:
            for n in sorted(self._hosts() - self.failed - {self.ctx.id}):
                self.ctx.send(n, claim)
        # moves that needed it fail or become restores; the chains it touched are recovered
        self.ctx.publish(PeerFailed(node))
