"""Placement lookup: a node that hosts no part of an app asks where its vertices run before it
acts on it (issue 24.1; why such a node's view may be old: :mod:`.placement`).

A :class:`Lookup` asks the nodes its view names (they host part of the app, or did and know
where they handed it; with ``wide``, every node it reaches: a recovery that sees every instance
lost), keeps per vertex the answer with the highest version, and asks again the nodes the
answers name that it has not asked yet — at most :data:`ROUNDS` times. It ends when every asked
node has answered or at its deadline, and then does what waited: a client's relocation or
remap, or a recovery check. No coordinator: any node may look up, and a late answer is dropped.

A client's request at a node that holds none of the app costs a message to every node the
node reaches (and the holders' syncs): at most :data:`SEARCH_BURST` such searches, then
:data:`SEARCH_RATE` a second, per node, whoever asks; past that, the request is refused (the
client may ask a holder: ``mso status`` names them).
"""

from __future__ import annotations

import enum
from collections.abc import Callable
from typing import ClassVar

from mso.protocol import messages as m
from mso.protocol.context import NodeContext
from mso.protocol.events import PeerRejoined, RecoveryDue
from mso.protocol.procedures import placement
from mso.protocol.procedures.base import STEP_TIMEOUT_S, Phase, Procedure, Table
from mso.protocol.procedures.relocation import Relocator
from mso.protocol.procedures.remap import Remapper
from mso.protocol.tapwire import Tap, TapEvents

ROUNDS = 3  # rounds of asking the nodes answers name
# searches for an app this node holds none of (each asks every node it reaches): a bucket of
# SEARCH_BURST, refilled at SEARCH_RATE a second, for every client of the node together (a
# client is a connection: one per client would be one per connection it opens)
SEARCH_BURST = 8
SEARCH_RATE = 2.0


class S(enum.Enum):
    ASKING = "asking"


class LookupEvent(enum.Enum):
    """What moves a Lookup along its table."""

    ANSWER = "answer"
    ASKED_MORE = "asked_more"
    ALL_ANSWERED = "all_answered"
    DEADLINE = "deadline"


# what waits on the lookup (None: a recovery check)
Then = m.RelocateRequest | m.RemapRequest | Tap | None


class Lookup(Procedure):
    NAME = "lookup"
    INITIAL = S.ASKING
    DEADLINE_S = 2 * STEP_TIMEOUT_S
    TRANSITIONS: ClassVar[Table] = {
        S.ASKING: {
            LookupEvent.ANSWER: S.ASKING,
            LookupEvent.ASKED_MORE: S.ASKING,
            LookupEvent.ALL_ANSWERED: Phase.FINISHED,
            LookupEvent.DEADLINE: Phase.FINISHED,
        }
    }

    def __init__(self, pid: int, now: float, app: str, client: int | None, then: Then) -> None:
        super().__init__(pid, now)
        self.app = app
        self.client = client
        self.then = then
        self.asked: set[str] = set()
        self.waiting: set[str] = set()
        self.rounds = 0
        self.fetch = False  # this node held none of the app: the holders send it too
        self.quiet = False  # only to bring the view up to date: nothing waits on it
        self.own: dict[str, tuple[str, int]] = {}  # vertex -> (node, version): "it runs here"

    def refusal(self, why: str) -> m.Message | None:
        """(Its client waits for what the lookup lets go on: that request's reply.)"""
        return _refusal(self.app, self.then, why)


def _refusal(app: str, then: Then, why: str) -> m.Message | None:
    """The reply that refuses ``then``, a client's request for ``app``."""
    if isinstance(then, m.RelocateRequest):
        return m.RelocateReply(app, then.vertex, False, error=why)
    if isinstance(then, m.RemapRequest):
        return m.RemapReply(app, False, {}, error=why)
    return None


class Lookups:
    """This node's lookups, and what each one lets go on when it ends."""

    def __init__(
        self,
        ctx: NodeContext,
        relocator: Relocator,
        remapper: Remapper,
        tap: Callable[[int, Tap, float], None],
    ) -> None:
        self.ctx = ctx
        self.relocator = relocator
        self.remapper = remapper
        self.tap = tap  # the data plane's taps: a client's tap, once the app is here
        self._searches = float(SEARCH_BURST)  # searches it may start now (a token bucket)
        self._searched_at = 0.0

    def _lookup(self, pid: int) -> Lookup | None:
        proc = self.ctx.procedure(pid)
        return proc if isinstance(proc, Lookup) else None

    # -- what may have to wait for one ---------------------------------------------------------
    def relocate(self, client: int | None, msg: m.RelocateRequest, now: float) -> bool:
        """A relocation asked of this node: at once if it hosts part of the app (its view is
        kept whole), else after a lookup. False if refused at once."""
        dep = self.ctx.apps.get(msg.app)
        if dep is None and self._find(msg.app, client, msg, now):
            return True
        if dep is None or dep.hosts_part() or not dep.running:
            return self.relocator.request(client, msg, now)
        self._start(msg.app, client, msg, now, wide=False)
        return True

    def remap(self, client: int | None, msg: m.RemapRequest, now: float) -> None:
        """A remap asked of this node: as :meth:`relocate`."""
        dep = self.ctx.apps.get(msg.app)
        if dep is None and self._find(msg.app, client, msg, now):
            return
        if dep is None or dep.hosts_part() or not dep.running:
            self.remapper.request(client, msg, now)
            return
        self._start(msg.app, client, msg, now, wide=False)

    def tap_request(self, client: int, msg: Tap, now: float) -> None:
        """A client's tap: at once if this node holds the app, else after finding it."""
        if msg.app in self.ctx.apps or not self._find(msg.app, client, msg, now):
            self.tap(client, msg, now)

    def _find(self, app: str, client: int | None, then: Then, now: float) -> bool:
        """A client's request for an app this node holds none of: only the nodes that take
        part in an app hold it (issue 24.1), so it asks every node it reaches (as the status
        fan-out does, once per request), the holders send the app with their view, and the
        request goes on here as at a holder. False if nobody is there to ask."""
        if any(isinstance(p, Lookup) and p.app == app and p.fetch for p in self.ctx.open()):
            return False  # (one search at a time: the request is refused, not queued)
        if not self._may_search(now):
            self._refuse_search(app, client, then)
            return True
        look = Lookup(self.ctx.new_pid(), now, app, client, then)
        look.fetch = True
        self.ctx.begin(look)
        self._ask(look, set(self.ctx.known_nodes()))
        if not look.waiting:
            self._end(look, now)
        return True

    def _may_search(self, now: float) -> bool:
        """One more search within :data:`SEARCH_BURST` and :data:`SEARCH_RATE` (taken)."""
        elapsed = max(0.0, now - self._searched_at)
        self._searches = min(float(SEARCH_BURST), self._searches + elapsed * SEARCH_RATE)
        self._searched_at = now
        if self._searches < 1.0:
            return False
        self._searches -= 1.0
        return True

    def _refuse_search(self, app: str, client: int | None, then: Then) -> None:
        """A search past the bound: counted, and the client told why."""
        self.ctx.refusal("holder_search_over_rate")
        why = (
            f"{self.ctx.id} holds none of app {app!r} and searches for such apps at most "
            f"{SEARCH_RATE:g} a second: ask again later, or ask a node that holds it"
        )
        refusal = _refusal(app, then, why)
        if isinstance(then, Tap):
            refusal = TapEvents(0, app, then.edge, self.ctx.id, self.ctx.now, 0, 0, ended=why)
        if client is not None and refusal is not None:
            self.ctx.reply(client, refusal)

    def on_stale(
        self, app: str, wide: bool = True, sync: bool = False, also: tuple[str, ...] = ()
    ) -> None:
        """A recovery this node would coordinate on a view it was not kept up to date on (it
        sees every instance of the app lost): look the placement up first, widely; or one it
        would coordinate if that view is out of date (``wide`` False,
        :meth:`Remapper.maybe_recover`): ask the nodes it names. Or
        (``sync``) the app just came with a sync: ask the nodes it names where they run
        what (the sender may have been behind, and nobody tells this node of the moves made
        since: seed 1079, a move's coordinator that had looked the app up 2 s before).
        ``also``: nodes asked besides those (one the view placed a vertex on until just now)."""
        open_ = [p for p in self.ctx.open() if isinstance(p, Lookup) and p.app == app]
        if not open_:
            self._start(
                app, None, None, self.ctx.now, wide=wide and not sync, quiet=sync, also=also
            )
            return
        if not sync and open_[0].quiet:  # a recovery now waits on the one under way
            open_[0].quiet = False
            if wide:
                self._ask(open_[0], set(self.ctx.known_nodes()))
        self._ask(open_[0], set(also))

    # -- the lookup ------------------------------------------------------------------------------
    def _start(
        self,
        app: str,
        client: int | None,
        then: Then,
        now: float,
        wide: bool,
        quiet: bool = False,
        also: tuple[str, ...] = (),
    ) -> None:
        look = Lookup(self.ctx.new_pid(), now, app, client, then)
        look.quiet = quiet
        self.ctx.begin(look)
        dep = self.ctx.apps[app]
        first = set(self.ctx.known_nodes()) if wide else placement.members(dep)
        self._ask(look, first | set(dep.handed.values()) | set(also))
        if not look.waiting:
            self._end(look, now)

    def _ask(self, look: Lookup, nodes: set[str]) -> None:
        new = {
            n
            for n in nodes - look.asked
            if n != self.ctx.id and n not in self.ctx.failed and n in self.ctx.routes
        }
        look.asked |= new
        look.waiting |= new
        for n in sorted(new):
            self.ctx.send(n, m.PlacementQuery(look.app, look.pid, look.fetch))

    def on_reply(self, src: str, msg: m.PlacementReply, now: float) -> None:
        look = self._lookup(msg.qid)
        dep = self.ctx.apps.get(msg.app)
        if look is None or msg.app != look.app or src not in look.waiting:
            self.ctx.refusal("placement_reply_unexpected")
            return
        if dep is None and not (look.fetch and not msg.placed):
            self.ctx.refusal("placement_reply_unexpected")  # (its app sync did not come)
            return
        look.on(LookupEvent.ANSWER)
        look.waiting.discard(src)
        if dep is None:  # a node that holds none of it either
            if not look.waiting:
                look.on(LookupEvent.ALL_ANSWERED)
                self._end(look, now)
            return
        signed = self.ctx.failed if self.ctx.authority.signed else None  # (the hosts' word)
        placement.merge(
            dep, src, msg.placed, msg.versions, msg.vanished, now, signed, here=self.ctx.id
        )
        # what an answer says runs on its sender is that node's own word: it stands against a
        # placement elsewhere whose instance vanished, whichever answer came first (seed 164451)
        gone = set(msg.vanished)
        for v, n in msg.placed.items():
            if n == src and v not in gone and v in dep.app.vertices:
                look.own[v] = (src, msg.versions.get(v, 0))
        for v, (n, k) in look.own.items():
            placement.runs_there(dep, v, n, k, now)
        if look.rounds < ROUNDS:  # nodes the answers name that were not asked yet
            named = set(msg.placed.values()) - look.asked
            if named:
                look.rounds += 1
                look.on(LookupEvent.ASKED_MORE)
                self._ask(look, named)
        if not look.waiting:
            look.on(LookupEvent.ALL_ANSWERED)
            self._end(look, now)

    def on_peer_rejoined(self, ev: PeerRejoined) -> None:
        """A node a lookup waits on was held failed and is back: an answer it sent meanwhile
        was dropped (a node held failed is heard only to rejoin), so it is asked again,
        rather than waited for until the deadline (seed 110580: a restarted node's lookup
        of its kept view held the app 2 s past the answer, and so past the bound on holding
        an app it took no part in)."""
        for look in self.ctx.open():
            if isinstance(look, Lookup) and ev.node in look.waiting:
                self.ctx.send(ev.node, m.PlacementQuery(look.app, look.pid, look.fetch))

    def expire(self, look: Lookup, now: float) -> None:
        """Some node did not answer (it failed, or its answer was lost): go on with what the
        others said, the defined outcome of a lookup."""
        look.on(LookupEvent.DEADLINE)
        self._end(look, now)

    def _end(self, look: Lookup, now: float) -> None:
        if not look.done:
            look.state = Phase.FINISHED  # (nobody to ask: it ends as it starts)
        self.ctx.end(look.pid)
        dep = self.ctx.apps.get(look.app)
        if dep is not None:  # what a recovery waited on is answered (or went unanswered)
            dep.checking.clear()
        if isinstance(look.then, m.RelocateRequest):
            if not self.relocator.request(look.client, look.then, now) and look.client is None:
                self.ctx.refusal("relocate_refused")
        elif isinstance(look.then, m.RemapRequest):
            self.remapper.request(look.client, look.then, now, asked_at=look.started_at)
        elif isinstance(look.then, Tap):
            if look.client is not None:
                self.tap(look.client, look.then, now)
        elif dep is not None and not look.quiet:
            dep.looked_up = dep.losses(self.ctx.failed)
            self.ctx.publish(RecoveryDue(look.app))


__all__ = ["ROUNDS", "SEARCH_BURST", "SEARCH_RATE", "Lookup", "LookupEvent", "Lookups"]
