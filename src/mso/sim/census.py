"""What a simulation's nodes said to each other, counted: every message by type, and the control
messages a reconfiguration or a failure costs, with the nodes they touched.

The paper claims reconfiguration is local ("other nodes in the network are neither involved in
nor aware of this remapping"); this is how the claim is checked. A *control message* is anything
but data, acks, heartbeats and the periodic monitoring reports (:data:`PERIODIC`), which flow
whether or not anything changes. A node is *involved* when it sent or was sent one; a *relay*
only forwarded one on its route. An *episode* is a burst of control messages: it ends at
quiescence, the first gap of ``quiet_s`` with none (longer than a procedure's step timeout, so
a retried step stays in its episode).
"""

from __future__ import annotations

import bisect
from collections import Counter
from collections.abc import Collection, Iterable
from dataclasses import dataclass, field
from typing import Any

from mso.protocol import messages as m

# control messages sent on a timer whatever happens (a chain's tail reports its delay to its
# head once a monitor period): not part of any reconfiguration
PERIODIC = frozenset({"ChainDelay"})
QUIET_S = 1.5  # a gap this long without control messages ends an episode
# bound on the control messages kept for tallies (a few tens of MB): beyond it the oldest go,
# and ``forgotten`` says how many, so a tally over them is known to be short
MAX_KEPT = 2_000_000
_KINDS: dict[type, tuple[str, bool]] = {}  # message type -> (its name, a control message)


@dataclass(frozen=True)
class Tally:
    """The control messages of a time window."""

    since: float
    until: float
    control_messages: int
    nodes_involved: frozenset[str]  # sent or were sent one
    relays: frozenset[str]  # forwarded one and are not among ``nodes_involved``
    by_type: dict[str, int]

    def to_json(self) -> dict[str, Any]:
        return {
            "at": round(self.since, 6),
            "until": round(self.until, 6),
            "control_messages": self.control_messages,
            "nodes_involved": len(self.nodes_involved),
            "nodes": sorted(self.nodes_involved),
            "relays": sorted(self.relays),
            "by_type": dict(sorted(self.by_type.items())),
        }


@dataclass
class Census:
    """Counts what a :class:`~mso.sim.runner.Simulation` puts on its network (it calls
    :meth:`note` for every message sent; tests read :meth:`tally` and :meth:`episodes`)."""

    by_type: Counter[str] = field(default_factory=Counter)  # messages sent, over the run
    hops_by_type: Counter[str] = field(default_factory=Counter)  # hop transmissions of them
    # (time, from, to, type, route): the control messages, in the order sent
    control: list[tuple[float, str, str, str, tuple[str, ...]]] = field(default_factory=list)
    forgotten: int = 0  # control messages dropped from ``control`` past MAX_KEPT

    def note(self, at: float, src: str, dst: str, msg: m.Message, route: list[str]) -> None:
        self.note_many(at, src, msg, ((dst, route),))

    def note_many(
        self,
        at: float,
        src: str,
        msg: m.Message,
        copies: Collection[tuple[str, list[str]]],
        hops: int | None = None,
    ) -> None:
        """``msg`` sent to each (destination, route) of ``copies``: every copy counted, as
        :meth:`note` counts one (a beat to every neighbour is counted in one call). ``hops``:
        the copies' hop transmissions, when the caller knows them (a planned broadcast)."""
        if type(msg) is m.Sequenced:  # a control stream's frame: counted as what it carries
            msg = msg.body
        kind = _KINDS.get(type(msg))
        if kind is None:  # a message's kind is its type's: looked up once per type
            name = type(msg).__name__
            control = m.kind_of(msg) in (m.CONTROL, m.MARKER) and name not in PERIODIC
            kind = _KINDS[type(msg)] = (name, control)
        name, control = kind
        if not control:
            sent = len(copies)
            if hops is None:
                hops = sum(len(route) - 1 for _, route in copies)
            if sent:
                self.by_type[name] += sent
                self.hops_by_type[name] += hops
            return
        for dst, route in copies:
            self.by_type[name] += 1
            self.hops_by_type[name] += len(route) - 1
            if len(self.control) >= MAX_KEPT:
                drop = MAX_KEPT // 4
                del self.control[:drop]
                self.forgotten += drop
            self.control.append((at, src, dst, name, tuple(route)))

    def tally(self, since: float = 0.0, until: float = float("inf")) -> Tally:
        """The control messages sent in ``[since, until)``."""
        nodes: set[str] = set()
        relays: set[str] = set()
        types: Counter[str] = Counter()
        last = since
        lo = bisect.bisect_left(self.control, since, key=_at)  # sent in time order
        hi = bisect.bisect_left(self.control, until, key=_at)
        for at, src, dst, name, route in self.control[lo:hi]:
            nodes.update((src, dst))
            relays.update(route[1:-1])
            types[name] += 1
            last = at
        return Tally(
            since,
            last if until == float("inf") else until,
            sum(types.values()),
            frozenset(nodes),
            frozenset(relays - nodes),
            dict(types),
        )

    def episodes(self, quiet_s: float = QUIET_S, cuts: Iterable[float] = ()) -> list[Tally]:
        """The bursts of control messages, each from its first message to its last: the next
        begins after a gap of at least ``quiet_s``, or at the first message at or after one
        of ``cuts`` (the times of triggers: a crash, a restart, a request)."""
        out: list[Tally] = []
        start = last = None
        pending = sorted(cuts)
        k = 0
        for at, *_ in self.control:
            cut = False
            while k < len(pending) and pending[k] <= at:
                cut = last is not None and pending[k] > last
                k += 1
            if last is not None and (cut or at - last >= quiet_s):
                assert start is not None
                out.append(self._burst(start, last))
                start = None
            start = at if start is None else start
            last = at
        if start is not None and last is not None:
            out.append(self._burst(start, last))
        return out

    def _burst(self, start: float, last: float) -> Tally:
        t = self.tally(start, last + 1e-9)
        return Tally(start, last, t.control_messages, t.nodes_involved, t.relays, t.by_type)

    def messages_json(self) -> dict[str, Any]:
        """``messages`` of ``mso simulate --json``: counts and hop transmissions by type."""
        return {
            "total": sum(self.by_type.values()),
            "by_type": dict(sorted(self.by_type.items())),
            "hops_by_type": dict(sorted(self.hops_by_type.items())),
            "control_forgotten": self.forgotten,
        }


def _at(record: tuple[float, str, str, str, tuple[str, ...]]) -> float:
    return record[0]


__all__ = ["MAX_KEPT", "PERIODIC", "QUIET_S", "Census", "Tally"]
