"""Failure claims: whom a suspecting node asks, when another node's claim is believed, and how
accepted claims spread. Sans-IO helpers of :mod:`.peers`.

- **Whom to ask** (SWIM's indirect probe, ``K_ASKED`` members, never every member): the
  suspect's other neighbours — its last figures named them (hops of 1) and they watch it, so
  they answer at once from their own clock; only when it named none that this node reaches,
  this node's own neighbours, then the nearest nodes it reaches (they ping it: a
  :class:`~.detector.Vouch`). What one failure costs so stays O(degree) per node. An answer
  counts as "hears it" only when it heard the suspect within half the liveness window: a live
  node beats every period, a dead one was last heard about a window ago by all its watchers.
- **When a claim is believed** (:class:`Claims`): a ``NodeDown`` from another node is acted
  on only when corroborated — it names a witness other than its detector (a node the detector
  asked that did not hear the victim either), a second detector claims the same, or this node's
  own probe agrees (it has no route to the victim, or the victim does not answer a ``Suspect``
  about itself within half the liveness window). A claim about an incarnation beyond what this
  node has seen of the victim (plus ``INCARNATION_MARGIN``) is refused: a captured member's
  ``NodeDown`` a day ahead once held its victim failed for a day. A receiver that hears the
  victim itself refuses the claim.
- **When a member's "I hear it" counts** (:class:`Vouchers`): a ``Hears`` yes keeps a suspect
  alive when it is not one member's word alone — a second member asked says yes too, or the
  one that says it is the only member asked (then every path to the suspect runs through it)
  — or, alone, for at most ``LONE_YES_WINDOWS`` liveness windows until this node hears the
  suspect itself: a routing view that lags gets that long to converge, while a captured
  member that answers yes for a dead node no longer keeps it from being declared. Members'
  word, however many, keeps it alive for at most ``MEMBERS_YES_WINDOWS`` windows (20 s at
  the defaults, past the 12 s babeld was seen to lag) until this node hears it itself: two
  captured members answering yes for a dead node kept it alive for ever.

  **With node identities** (and in the simulator, whose sources are proven as with them) none
  of that is needed: a suspicion carries a fresh challenge (``Suspect.nonce``), a member that
  hears the suspect asks it on, and its yes carries the suspect's own answer to that
  challenge as it came, signed by the suspect (``Hears.proof``, checked by the receiving
  transport: :mod:`mso.net.trust`). A dead node answers nothing, and a member cannot sign in
  its name, so a yes without the proof is set aside at once (``hears_unproven``): one captured
  member, or any number, delay a dead node's declaration by nothing more than their answers'
  round trip, and a live node whose route is missing at one asker stays alive as long as
  any member reaches it.
- **How accepted claims spread** (:class:`Gossip`): the detector sends its ``NodeDown`` only
  to the nodes that host the apps (they recover); everyone else learns it piggybacked on the
  heartbeats already sent, each claim on ``rounds(n)`` beats (O(log N)), at most ``MAX_NEWS``
  per beat — an epidemic along the neighbours, not a flood.
"""

from __future__ import annotations

import math
import zlib
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field

from mso.protocol import messages as m

K_ASKED = 3  # members asked about a suspect (SWIM's k)
MAX_NEWS = 8  # failure claims piggybacked on one beat
MAX_GOSSIP = 64  # claims waiting to be piggybacked; the oldest go first past this
MAX_PENDING = 64  # uncorroborated claims waiting for this node's own probe
INCARNATION_MARGIN = 16  # a claim may be this many incarnations (resets) ahead of what was seen
LONE_YES_WINDOWS = 4  # liveness windows one member's uncorroborated yes keeps a suspect alive
MEMBERS_YES_WINDOWS = 40  # ... and members' yes, however many (a route missing that long)
NONCE_BYTES = 8  # a suspicion's challenge, with proofs: fresh, so no earlier answer holds it


def ask_whom(
    suspect: str,
    me: str,
    suspect_figures: m.Figures | None,
    routes: Mapping[str, tuple[str, int]],
    failed: set[str],
    k: int = K_ASKED,
) -> list[str]:
    """Up to ``k`` members to ask about ``suspect``: its neighbours that this node reaches,
    then this node's neighbours, then the nearest it reaches; spread by a hash of the
    suspect's name so that two suspects do not load the same few nodes."""

    def ok(n: str) -> bool:
        return n not in (suspect, me) and n not in failed and n in routes

    def spread(ns: Iterable[str]) -> list[str]:
        return sorted(ns, key=lambda n: (zlib.crc32(f"{suspect}/{n}".encode()), n))

    theirs = (
        [n for n, h in suspect_figures.hops.items() if h == 1 and ok(n)]
        if suspect_figures is not None
        else []
    )
    out = spread(theirs)[:k]
    if out:  # they watch it: their answers are at hand (ours would have to ping it)
        return out
    if len(out) < k:
        mine = [n for n, (hop, _) in routes.items() if hop == n and ok(n) and n not in out]
        out += spread(mine)[: k - len(out)]
    if len(out) < k:
        rest = sorted((h, n) for n, (_, h) in routes.items() if ok(n) and n not in out)
        out += [n for _, n in rest[: k - len(out)]]
    return out


def rounds(n: int) -> int:
    """Beats a claim rides on: O(log N), at least 3 (a beat may be lost)."""
    return max(3, math.ceil(math.log2(n + 1)))


@dataclass
class Gossip:
    """Accepted claims waiting to be piggybacked, each with the beats it has left."""

    waiting: dict[str, tuple[m.NodeDown, int]] = field(default_factory=dict)

    def add(self, claim: m.NodeDown, beats: int) -> None:
        self.waiting.pop(claim.node, None)
        self.waiting[claim.node] = (claim, beats)
        while len(self.waiting) > MAX_GOSSIP:
            del self.waiting[next(iter(self.waiting))]

    def drop(self, node: str) -> None:
        self.waiting.pop(node, None)

    def next_beat(self) -> list[m.NodeDown]:
        """The claims for this period's beats (one beat round to every neighbour)."""
        if not self.waiting:  # (every beat: mostly nothing to tell)
            return []
        out = []
        for node, (claim, left) in list(self.waiting.items())[:MAX_NEWS]:
            out.append(claim)
            if left <= 1:
                del self.waiting[node]
            else:
                self.waiting[node] = (claim, left - 1)
        return out

    def clear(self) -> None:
        self.waiting.clear()


@dataclass
class Claims:
    """Claims this node has not yet acted on: waiting for a second detector or for its own
    probe of the victim (victim -> the claim and when it came). Bounded."""

    pending: dict[str, tuple[m.NodeDown, float]] = field(default_factory=dict)

    def corroborated(self, claim: m.NodeDown) -> bool:
        """Named a witness, or a different detector claimed the same victim before."""
        if claim.witness and claim.witness not in (claim.detector, claim.node):
            return True
        held = self.pending.get(claim.node)
        return held is not None and held[0].detector != claim.detector

    def hold(self, claim: m.NodeDown, now: float) -> bool:
        """Keep ``claim`` until this node's probe settles it; False when already probing it
        (or full)."""
        if claim.node in self.pending or len(self.pending) >= MAX_PENDING:
            return False
        self.pending[claim.node] = (claim, now)
        return True

    def due(self, now: float, wait_s: float) -> list[tuple[m.NodeDown, float]]:
        """Claims whose probe has had ``wait_s`` to be answered (removed)."""
        if not self.pending:  # (every beat: mostly none)
            return []
        out = [(c, at) for c, at in self.pending.values() if now - at >= wait_s]
        for c, _ in out:
            del self.pending[c.node]
        return out

    def drop(self, node: str) -> None:
        self.pending.pop(node, None)

    def clear(self) -> None:
        self.pending.clear()


@dataclass
class Vouchers:
    """When a member's ``Hears`` yes keeps a suspect alive (module docstring): suspect -> when
    a yes first kept it alive on one member's word alone since this node last heard it
    itself. Bounded by the suspects (membership drops an entry with its node)."""

    lone: dict[str, float] = field(default_factory=dict)
    # suspect -> when members' yes first kept it alive since this node last heard it itself
    # (or since a pause of more than ``grace_s`` between yeses: a new episode), and the last
    since: dict[str, tuple[float, float]] = field(default_factory=dict)

    def counts(
        self,
        node: str,
        yes: set[str],
        asked: int,
        now: float,
        grace_s: float,
        bound_s: float = math.inf,
    ) -> bool:
        """Whether the yes just added to ``yes`` (the members that said yes in this suspicion
        of ``node``, of ``asked`` asked) counts: within ``bound_s`` of the first yes of this
        episode (yeses no more than ``grace_s`` apart), and one member's alone within
        ``grace_s``."""
        start, last = self.since.get(node, (now, now))
        if now - last > grace_s:  # (an earlier episode, over: a node not heard directly)
            start = now
        self.since[node] = (start, now)
        if now - start > bound_s:
            return False  # members' word alone, for longer than a route takes to come back
        if len(yes) > 1:
            self.lone.pop(node, None)  # two members hear it: alive, whatever came before
            return True
        if asked == 1:
            return True
        return now - self.lone.setdefault(node, now) <= grace_s

    def heard(self, node: str) -> None:
        """This node heard ``node`` itself: its own word, not a member's."""
        self.lone.pop(node, None)
        self.since.pop(node, None)

    def clear(self) -> None:
        self.lone.clear()
        self.since.clear()
