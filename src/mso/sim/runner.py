"""A virtual-time driver for node cores: the same procedure code as the real daemon, with an
in-memory network and a simulated clock. Deterministic; used by tests and policy studies.

Messages between nodes take the sum of the per-hop link delays of their route (plus
``hop_latency_s`` per hop); effects are applied in time order from a heap.
"""

from __future__ import annotations

import hashlib
import os
import random
from collections import deque
from collections.abc import Callable, Hashable, Sequence
from typing import Any, NamedTuple

import msgspec

from mso.management import RuleSettings
from mso.model.network import Network
from mso.net.forwarding import RouteWait
from mso.node.core import Effect, NodeCore, Reply, Send, SetTimer
from mso.protocol import effects as fx
from mso.protocol import messages as m
from mso.protocol.events import Happened
from mso.protocol.spill import MemorySpill, SpillStore
from mso.sim.agenda import Agenda
from mso.sim.census import Census
from mso.sim.executor import SimExecutor

# an event on the agenda: (kind, node, payload), in time order and, at one time, in the order
# scheduled (a dataclass with order=True in a heap cost 12-15% of a 400-node run in comparisons
# alone; tuples in a heap, 6% of a 1,000-node run: mso.sim.agenda)
_Item = tuple[str, str, Any]
# route, delay, lossy hops, and the byte counters of each hop's sender and receiver
_Path = tuple[list[str], float, tuple[tuple[int, float], ...], list[list[int]], list[list[int]]]


class _Plan(NamedTuple):
    """A broadcast's copies worked out (:meth:`Simulation._plan`)."""

    copies: list[tuple[str, list[str]]]  # (receiver, route), for the census
    hops: int  # the copies' hop transmissions
    # (a byte counter, 0 sent / 1 received, the copies that cross it, their names' bytes)
    shares: list[tuple[list[int], int, int, int]]
    groups: list[tuple[float, tuple[str, ...]]]  # (delay, the receivers it brings), in order


MAX_PATHS = 200_000  # paths kept between two link changes, at most
HAPPENED_KEPT = 4096


class Simulation:
    """Node cores on a :class:`Network`, run in virtual time."""

    def __init__(
        self,
        network: Network,
        *,
        hop_latency_s: float = 50e-6,
        window: int = 4096,
        wire: bool = True,
        policy: Any = None,
        manage: bool = True,
        rules: RuleSettings | None = None,
        model_time: bool = False,
        seed: int = 0,
        spill: Callable[[str], SpillStore] | None = None,
        proofs: bool = True,
    ) -> None:
        self.network = network
        # a member's "I hear it" carries the suspect's own answer, as with node identities
        # (``Hears.proof``): each node's answer is sealed with a key only this simulator holds,
        # standing for its signature, and a seal that does not hold is stripped on arrival
        # (False: as without identities, a member's word alone, for the rules' windows)
        self.proofs = proofs
        self._proof_key = os.urandom(32)
        self.proofs_refused = 0  # Hears whose proof did not hold (stripped)
        self.rng = random.Random(seed)  # emulated loss of data frames (a link's ``loss``)
        self.lost = 0  # data frames lost that way
        # (time, node, from, message type): every delivery, when a test or a fault run asks
        self.trace: list[tuple[float, str, str, str]] | None = None
        # control frames with no route wait for the routes to change, as a node's driver does
        self.waiting: dict[str, RouteWait[tuple[str, m.Message]]] = {
            n: RouteWait() for n in network.nodes
        }
        # vertex effects take their modelled CPU time (cost per event / node cpu), so a slow
        # vertex holds back its producers as on a device; off, their results are due at once
        self.model_time = model_time
        self._policy, self._rules = policy, rules
        self.wire = wire  # pass every message through the real encoding, as the wire does
        # (sent, its envelope as received, its body as received)
        # (sent, its frame's size without its two ends' names, its body as received)
        self._last_decoded: tuple[m.Message, int, m.Message] | None = None
        self._names: dict[str, int] = {}  # a node's name -> its length in an envelope
        self._paths: dict[tuple[str, str], _Path | None] = {}
        self._paths_version = -1
        self._hops: dict[tuple[str, str], tuple[float, float]] = {}  # (a, b) -> delay, loss
        self._uniform: tuple[float, float] | None = None  # every hop's, when all are alike
        self._sums = [0.0]
        # node -> (the links' version, receivers, its last broadcast's plan or None)
        self._plans: dict[str, tuple[int, tuple[str, ...], _Plan | None]] = {}
        # node -> its last planned broadcast: (its body encoded, the frame's size without its
        # two ends' names, the body as received)
        self._broadcast: dict[str, tuple[bytes, int, m.Message]] = {}
        self.hop_latency_s = hop_latency_s
        self.now = 0.0
        # each node's spill store outlives its restarts, as the daemon's file does
        # (``spill``: each node's own, e.g. a file, for a benchmark that measures the disk)
        self.spills: dict[str, SpillStore] = {
            n: spill(n) if spill is not None else MemorySpill() for n in network.nodes
        }
        self.cores = {
            n: NodeCore(
                n,
                capacity=spec.cpu,
                window=window,
                power=spec.power,
                battery_wh=spec.battery_wh,
                policy=policy,
                manage=manage,
                rules=rules,
                capabilities=spec.capabilities,
                spill=self.spills[n],
                link_rates=self._link_rates(n),
            )
            for n, spec in network.nodes.items()
        }
        self.bytes = {n: [0, 0] for n in network.nodes}  # sent, received (relays count both)
        self.replies: list[tuple[float, int, m.Message]] = []
        self.delivered = 0
        self._agenda: Agenda[_Item] = Agenda()
        self._timers: dict[tuple[str, Hashable], float] = {}
        self.killed: set[str] = set()  # killed nodes: they receive and do nothing
        # each node's cores before its restarts (what its old processes did, for reports)
        self.retired: dict[str, list[NodeCore]] = {}
        # (node, destination): node's routing view has no route there although the links do
        # (a routing protocol that has not converged; see :meth:`lose_route`)
        self.lost_routes: set[tuple[str, str]] = set()
        # a test's view of the network: each tap sees every message put on it (from, to,
        # message); ``drop`` loses the ones it returns True for, as a radio would (it sees the
        # message a control stream's frame carries: lost so, it is lost each time sent)
        self.taps: list[Callable[[str, str, m.Message], None]] = []
        self.drop: Callable[[str, str, m.Message], bool] | None = None
        # every message counted by type, and the control messages kept for locality tallies
        self.census = Census()
        # what each core said happened (as a daemon logs it): (time, node, event), the newest
        # few thousand
        self.happened: deque[tuple[float, str, Happened]] = deque(maxlen=HAPPENED_KEPT)
        self.executors = {n: self._executor(n) for n in network.nodes}
        self._order = {n: i for i, n in enumerate(network.nodes)}
        self._recheck = set(network.nodes)  # nodes whose whole tables to compare, once
        for n, core in self.cores.items():
            self._watch(n, core)
        self.update_routes()
        for n, core in self.cores.items():
            self.apply(n, core.start(self.now))
            core.count_traffic(self.bytes[n])  # read live from now on (started with none)

    def _link_rates(self, node: str) -> Callable[[str], float | None]:
        """What ``node`` knows of its links' rates: the scenario's ``bandwidth_mbps`` now."""

        def rate(peer: str) -> float | None:
            link = self.network.link(node, peer)
            return None if link is None else link.bandwidth_mbps

        return rate

    def _executor(self, node: str) -> SimExecutor:
        ex: SimExecutor

        def push(at: float, result: fx.VertexResult) -> None:
            self._push(at, "vertex", node, (ex, result))

        ex = SimExecutor(
            self.network.nodes[node].cpu, push, lambda: self.now, model_time=self.model_time
        )
        return ex

    def hosts(self, app: str, vertex: str) -> list[str]:
        """The live nodes that run an instance of ``vertex`` (one, unless a move is under way
        or something went wrong)."""
        return sorted(
            n for n, c in self.cores.items() if n not in self.killed and vertex in c.instances(app)
        )

    def placement(self, node: str, app: str) -> dict[str, str]:
        """Where ``node`` holds each vertex of ``app`` to run."""
        return self.cores[node].placement(app)

    def failed(self, node: str) -> set[str]:
        """The nodes ``node`` holds failed."""
        return set(self.cores[node].failed)

    def instance(self, node: str, app: str, vertex: str) -> Any:
        """The user's object behind ``vertex`` on ``node`` (tests read its own state)."""
        h = self.cores[node].instances(app)[vertex]
        return self.executors[node].instance_of(h.instance)

    def update_routes(self) -> None:
        """Give the cores their routing views of the current links: to each core only the
        routes that changed (the destinations whose trees the network dropped), so a link
        change costs what it changes, not N routing tables of N entries."""
        net = self.network
        changed = net.take_changed()
        recheck, self._recheck = self._recheck - self.killed, set()
        deltas: dict[str, dict[str, tuple[str, int] | None]] = {}
        for dst in net.nodes if recheck else sorted(changed, key=self._order.__getitem__):
            view = net.routes_to(dst)
            for n in self.cores if dst in changed else recheck:
                if n == dst or n in self.killed:
                    continue
                want = view.get(n)
                if want is not None and (n, dst) in self.lost_routes:
                    want = None
                if self.cores[n].routes.get(dst) != want:
                    deltas.setdefault(n, {})[dst] = want
        for n, core in self.cores.items():
            if n in deltas and n not in self.killed:
                self.apply(n, core.change_routes(deltas[n], self.now))
        for n, wait in self.waiting.items():
            if wait and n not in self.killed:
                wait.release(self.now, self._resender(n))

    def lose_route(self, node: str, dst: str, lost: bool = True) -> None:
        """``node``'s routing view loses (or, ``lost=False``, regains) its route to ``dst``
        while the links stay: what babeld did to one node of a mesh for 12 s after a relay
        died, while the others still heard ``dst``. Only ``node``'s own frames to ``dst`` are
        affected (they wait, as a driver's do); frames it relays are not modelled."""
        if lost:
            self.lost_routes.add((node, dst))
        else:
            self.lost_routes.discard((node, dst))
        self._recheck.add(node)
        self.update_routes()

    def _resender(self, node: str) -> Callable[[str, tuple[str, m.Message], int], bool]:
        def resend(dst: str, item: tuple[str, m.Message], kind: int) -> bool:
            return self._send(node, dst, item[1])

        return resend

    def links_changed(self, convergence_s: float = 0.0) -> None:
        """The links changed (the network already shows it): routing views follow after
        ``convergence_s``, as a routing protocol's would."""
        if convergence_s <= 0:
            self.update_routes()
        else:
            self._push(self.now + convergence_s, "routes", "", None)

    def _path(self, node: str, dst: str) -> _Path | None:
        """The route from ``node`` to ``dst``, its delay, and its hops that lose data frames
        (the index of the hop's end, the loss): kept until the links change, so a beat to a
        neighbour does not walk the network's tables every time."""
        net = self.network
        if net.version != self._paths_version or len(self._paths) > MAX_PATHS:
            self._paths.clear()
            if net.version != self._paths_version:
                self._uniform = self._uniform_hop()
            self._paths_version = net.version
            self._hops.clear()
        key = (node, dst)
        if key in self._paths:
            return self._paths[key]
        route = net.route(node, dst)
        path = None
        if route is not None:
            delay = 0.0
            lossy: list[tuple[int, float]] = []
            if self._uniform is not None:  # every hop alike: the sum of the first h hops'
                sums, (step, loss) = self._sums, self._uniform  # delays, as the loop adds them
                while len(sums) < len(route):
                    sums.append(sums[-1] + step)
                delay = sums[len(route) - 1]
                if loss > 0:
                    lossy = [(i, loss) for i in range(1, len(route))]
            else:
                hops = self._hops
                a = route[0]
                for i in range(1, len(route)):
                    b = route[i]
                    hop = hops.get((a, b))
                    if hop is None:
                        hop = hops[(a, b)] = self._hop(a, b)
                    delay += hop[0]
                    if hop[1] > 0:
                        lossy.append((i, hop[1]))
                    a = b
            count = self.bytes  # each hop's counters, looked up once per path, not per send
            senders = [count[x] for x in route[:-1]]
            path = (route, delay, tuple(lossy), senders, [count[x] for x in route[1:]])
        self._paths[key] = path
        return path

    def _uniform_hop(self) -> tuple[float, float] | None:
        """The one (delay, loss) of every hop when all links have the same (a generated
        scenario's do): then a path's delay is looked up by its length, not summed hop by
        hop (the N² paths of a start-up's hellos, each used once, were a third of it)."""
        specs = {(link.delay_ms, link.loss) for link in self.network.links.values()}
        if len(specs) != 1:
            return None
        ((delay_ms, loss),) = specs
        self._sums = [0.0]  # the delays of 0, 1, 2 ... such hops, added as _path adds them
        return self.hop_latency_s + delay_ms / 1e3, loss

    def _hop(self, a: str, b: str) -> tuple[float, float]:
        """One hop's delay (its link's and ``hop_latency_s``) and loss: kept with the paths,
        so that a path of h hops costs h lookups, not h link searches."""
        link = self.network.link(a, b)
        return (self.hop_latency_s + (link.delay_ms / 1e3 if link else 0.0)), (
            link.loss if link is not None else 0.0
        )

    def _send(self, node: str, dst: str, msg: m.Message) -> bool:
        """Put ``msg`` on the in-memory network; False when there is no route to ``dst``."""
        put = self._put(node, dst, msg)
        if put is None:
            return False
        delay, msg = put
        if delay >= 0:
            self._push(self.now + delay, "msg", dst, (node, msg))
        return True

    def _put(self, node: str, dst: str, msg: m.Message) -> tuple[float, m.Message] | None:
        """Count ``msg`` on its way to ``dst`` (census, taps, bytes at every hop) and say when
        it arrives, as received (decoded from its frame): its delay, -1 when lost on the way;
        None when there is no route."""
        path = self._path(node, dst)
        if path is None or (node, dst) in self.lost_routes:
            return None
        self.census.note(self.now, node, dst, msg, path[0])
        return self._carry(node, dst, msg, path)

    def _carry(self, node: str, dst: str, msg: m.Message, path: _Path) -> tuple[float, m.Message]:
        """:meth:`_put` past the census: taps, loss, the wire and the bytes at every hop."""
        route, delay, lossy, senders, receivers = path
        for tap in self.taps:
            tap(node, dst, msg)
        # (a test's loss sees what a control stream's frame carries)
        if self.drop is not None and self.drop(node, dst, m.carried(msg)):
            return -1.0, msg  # lost on the way
        if lossy and m.kind_of(msg) == m.DATA:
            for end, loss in lossy:
                if self.rng.random() < loss:
                    self.lost += 1  # dropped at this hop: retransmission recovers it
                    route = route[: end + 1]
                    senders, receivers = senders[:end], receivers[:end]
                    delay = -1.0
                    break
        if self.wire:  # what a real node would receive: encoded, then decoded
            last = self._last_decoded
            if last is not None and last[0] is msg:  # one message to many (a beat to every
                # neighbour): encoded and decoded once, its receivers share it as without
                # the wire (decoding it per receiver held N² copies of N-entry beats); each
                # frame is the same envelope but for its ends, so its size is the rest of the
                # first frame and the two names' encoded lengths (not encoded per copy)
                _, rest, msg = last
                names = self._names
                size = rest + (names.get(node) or self._name_bytes(node))
                size += names.get(dst) or self._name_bytes(dst)
            else:
                _, rest, msg = self._encode(node, dst, msg)
                size = rest + self._name_bytes(node) + self._name_bytes(dst)
            for c in senders:  # every hop sends and receives it
                c[0] += size
            for c in receivers:
                c[1] += size
        return delay, msg

    def _encode(self, node: str, dst: str, msg: m.Message) -> tuple[m.Message, int, m.Message]:
        """``msg`` through the wire, as ``dst`` would receive it from ``node``: encoded in its
        envelope and decoded, kept as the last decoded (sent, its frame's size without its
        two ends' names, its body as received)."""
        frame = m.wrap(node, dst, msg)
        decoded = m.decode(m.unwrap(frame).body)
        rest = len(frame) - self._name_bytes(node) - self._name_bytes(dst)
        self._last_decoded = (msg, rest, decoded)
        return self._last_decoded

    def _encode_again(
        self, node: str, dst: str, msg: m.Message
    ) -> tuple[m.Message, int, m.Message]:
        """:meth:`_encode` for ``node``'s planned broadcast (its beat, every period): a body
        byte for byte the last one's (most beats: nothing changed since) is that one's frame
        less its names, and decodes to what it decoded to; only the body is encoded then, not
        the envelope, nor decoded (both were a tenth of a beat's cost at 1,000 nodes)."""
        body = m.encode(msg)
        kept = self._broadcast.get(node)
        if kept is not None and kept[0] == body:
            self._last_decoded = (msg, kept[1], kept[2])
            return self._last_decoded
        last = self._encode(node, dst, msg)
        self._broadcast[node] = (body, last[1], last[2])
        return last

    def _name_bytes(self, name: str) -> int:
        """How many bytes ``name`` takes in an envelope (msgpack: its header and UTF-8)."""
        size = self._names.get(name)
        if size is None:
            size = self._names[name] = len(msgspec.msgpack.encode(name))
        return size

    def _cast(self, node: str, sends: list[Send]) -> None:
        """One message to several nodes (a beat to every neighbour): on a radio one local
        broadcast that every neighbour hears at once. Each copy is counted (the census in one
        call for them all), taps see it and bytes are added as for a send of its own, but the
        receivers it reaches at the same moment share one scheduled event, delivered to each
        in the order sent -- the order their own events would have had (a beat's N scheduled
        sends were a fifth of a 1,000-node run). A broadcast to the receivers of the last one
        from ``node``, over the same links, follows its plan (:meth:`_plan`)."""
        msg, now = sends[0].msg, self.now
        if self.wire and not self.taps and self.drop is None and not self.lost_routes:
            dsts = tuple([eff.dst for eff in sends])
            planned = self._plans.get(node)
            if planned is None or planned[0] != self.network.version or planned[1] != dsts:
                plan = self._plan(node, dsts)
                planned = self._plans[node] = (self.network.version, dsts, plan)
            if planned[2] is not None:
                self._cast_planned(node, msg, planned[2])
                return
        if self.network.version != self._paths_version:
            self._path(node, sends[0].dst)  # (the paths kept are of older links: dropped)
        kept, lost = self._paths, self.lost_routes
        routed: list[tuple[str, _Path]] = []
        for eff in sends:
            dst = eff.dst
            path = kept.get((node, dst)) or self._path(node, dst)
            if path is None or (lost and (node, dst) in lost):  # no route: control frames
                self.waiting[node].hold(dst, (dst, msg), m.kind_of(msg), now)  # wait
            else:
                routed.append((dst, path))
        if not routed:
            return
        self.census.note_many(now, node, msg, [(dst, path[0]) for dst, path in routed])
        group: list[str] = []
        at = -1.0
        arrived: m.Message = msg
        # with nothing to see or lose a copy (no taps, no test's drop) and the body decoded
        # already, a lossless path's copy only adds its bytes: done here, as _carry does
        plain = self.wire and not self.taps and self.drop is None
        names = self._names
        own = names.get(node) or self._name_bytes(node)  # (the sender's name, in each frame)
        for dst, path in routed:
            last = self._last_decoded
            if plain and not path[2] and last is not None and last[0] is msg:
                size = last[1] + own + (names.get(dst) or self._name_bytes(dst))
                for c in path[3]:
                    c[0] += size
                for c in path[4]:
                    c[1] += size
                delay, arrived = path[1], last[2]
            else:
                delay, arrived = self._carry(node, dst, msg, path)
            if delay < 0:
                continue
            if now + delay != at:
                if group:
                    self._push(at, "cast", node, (group, arrived))
                    group = []
                at = now + delay
            group.append(dst)
        if group:
            self._push(at, "cast", node, (group, arrived))

    def _plan(self, node: str, dsts: tuple[str, ...]) -> _Plan | None:
        """What a broadcast from ``node`` to ``dsts`` costs, worked out once for as long as
        the links stay (a beat goes to the same neighbours every period): the census's copies,
        each byte counter's share, and the receivers grouped by arrival. A copy's frame is
        the first's but for its two names (:meth:`_carry`), so a counter that ``k`` copies
        cross gains ``k`` times the rest of the frame and those copies' names. None (each copy
        carried on its own, as :meth:`_cast` does) when a receiver has no route or a hop
        loses frames."""
        copies: list[tuple[str, list[str]]] = []
        shares: dict[tuple[int, int], list[Any]] = {}  # (counter's id, end) -> its share
        groups: list[tuple[float, list[str]]] = []
        own = self._name_bytes(node)
        for dst in dsts:
            path = self._path(node, dst)
            if path is None or path[2]:
                return None
            route, delay, _, senders, receivers = path
            copies.append((dst, route))
            names = own + self._name_bytes(dst)
            for end, counters in ((0, senders), (1, receivers)):
                for c in counters:
                    share = shares.setdefault((id(c), end), [c, end, 0, 0])
                    share[2] += 1
                    share[3] += names
            if groups and groups[-1][0] == delay:
                groups[-1][1].append(dst)
            else:
                groups.append((delay, [dst]))
        return _Plan(
            copies,
            sum(len(route) - 1 for _, route in copies),
            [(c, end, k, b) for c, end, k, b in shares.values()],
            [(delay, tuple(group)) for delay, group in groups],
        )

    def _cast_planned(self, node: str, msg: m.Message, plan: _Plan) -> None:
        """:meth:`_cast` by its plan: what its loop over the copies would do, in one go."""
        now = self.now
        self.census.note_many(now, node, msg, plan.copies, plan.hops)
        last = self._last_decoded
        if last is None or last[0] is not msg:
            last = self._encode_again(node, plan.copies[0][0], msg)
        _, rest, arrived = last
        for counter, end, k, names in plan.shares:
            counter[end] += k * rest + names
        at = -1.0
        group: tuple[str, ...] = ()
        for delay, receivers in plan.groups:
            if now + delay == at:  # (different delays, one arrival: one event, as _cast)
                group += receivers
                continue
            if group:
                self._push(at, "cast", node, (group, arrived))
            at, group = now + delay, receivers
        self._push(at, "cast", node, (group, arrived))

    def _push(self, at: float, kind: str, node: str, payload: Any) -> None:
        self._agenda.push(at, (kind, node, payload))

    def apply(self, node: str, effects: list[Effect]) -> None:
        """Carry out ``effects`` as if ``node``'s core had returned them (tests inject
        messages this way)."""
        i, count = 0, len(effects)
        while i < count:
            eff = effects[i]
            i += 1
            if isinstance(eff, Send):
                j = i
                while j < count and type(nxt := effects[j]) is Send and nxt.msg is eff.msg:
                    j += 1
                if j > i:  # the same message to several nodes: one broadcast
                    self._cast(node, effects[i - 1 : j])  # type: ignore[arg-type]
                    i = j
                elif not self._send(node, eff.dst, eff.msg):  # no route: control frames wait
                    self.waiting[node].hold(
                        eff.dst, (eff.dst, eff.msg), m.kind_of(eff.msg), self.now
                    )
            elif isinstance(eff, SetTimer):
                self._timers[(node, eff.key)] = eff.at
                self._push(eff.at, "timer", node, eff.key)
            elif isinstance(eff, Reply):
                self.replies.append((self.now, eff.client, eff.msg))
            elif isinstance(eff, fx.CancelTimer):
                self._timers.pop((node, eff.key), None)
            else:
                self.executors[node].submit(eff, self.now)

    def request(self, node: str, msg: m.Message, client: int = 1) -> None:
        core = self.cores[node]
        self.apply(node, core.request(client, msg, self.now))

    def kill(self, node: str, convergence_s: float = 0.0) -> None:
        """Fail-stop ``node`` now: it falls silent and its links go; the survivors' routing
        views learn the new routes ``convergence_s`` later, as a routing protocol's would."""
        self.killed.add(node)
        self.waiting[node] = RouteWait()  # what it held died with it
        for n in list(self.network.neighbours(node)):
            self.network.remove_link(node, n)
        self._push(self.now + convergence_s, "routes", node, None)

    def crash(self, node: str) -> None:
        """Crash ``node``'s daemon only: its machine and its router live on, so its links
        stay and every routing view keeps routes to it and through it (the kernel forwards),
        while it answers nothing. :meth:`revive` restarts the daemon."""
        self.killed.add(node)
        self.waiting[node] = RouteWait()  # what it held died with it

    def _watch(self, node: str, core: NodeCore) -> None:
        """Keep what ``core`` says happened (its driver drains and logs the same)."""
        core.subscribe(Happened, lambda h: self.happened.append((self.now, node, h)))
        if self.proofs:
            core.membership.proofs = lambda: True

    def _seal(self, node: str, nonce: bytes) -> bytes:
        """What stands for ``node``'s signature on its yes to ``nonce``."""
        return hashlib.blake2b(node.encode() + b"\0" + nonce, key=self._proof_key).digest()

    def _proven(self, src: str, msg: m.Hears) -> m.Hears:
        """``msg`` as the receiving transport hands it over with identities: a node's own yes
        with its seal (the frame as it came), another's proof only if it holds."""
        if src == msg.node and msg.yes and msg.nonce:
            return msgspec.structs.replace(msg, proof=self._seal(src, msg.nonce))
        if msg.proof and (not msg.yes or msg.proof != self._seal(msg.node, msg.nonce)):
            self.proofs_refused += 1
            return msgspec.structs.replace(msg, proof=b"")
        return msg

    def revive(self, node: str) -> None:
        """Restart a killed ``node`` as a new process: a fresh core with a higher incarnation
        and no apps (add its links back first). The others restore what it hosted."""
        old = self.cores[node]
        self.retired.setdefault(node, []).append(old)
        spec = self.network.nodes[node]
        self.cores[node] = core = NodeCore(
            node,
            capacity=spec.cpu,
            window=old.window,
            power=spec.power,
            battery_wh=spec.battery_wh,
            policy=self._policy,
            manage=old.manager.enabled,
            rules=self._rules,
            incarnation=old.incarnation + 1,
            capabilities=spec.capabilities,
            spill=self.spills[node],
            link_rates=self._link_rates(node),
        )
        self.executors[node] = self._executor(node)  # the old instances went with the process
        self._watch(node, core)
        self.killed.discard(node)
        self._timers = {k: v for k, v in self._timers.items() if k[0] != node}
        self.apply(node, core.start(self.now))
        core.count_traffic(self.bytes[node])  # (it started with none, as a new process)
        self._recheck.add(node)
        self.update_routes()

    def _deliver(self, at: float, src: str, dsts: Sequence[str], msg: m.Message) -> None:
        """A broadcast's copies arriving at ``at``, at each receiver in turn."""
        cores, killed, trace = self.cores, self.killed, self.trace
        for node in dsts:
            if node in killed:
                continue
            self.delivered += 1
            if trace is not None:
                trace.append((at, node, src, m.name_of(msg)))
            # (its byte counters the core reads itself: count_traffic)
            effects = cores[node].receive(src, msg, at)
            if effects:  # (a quiet beat's none)
                self.apply(node, effects)

    def run_until(self, t: float) -> None:
        pop = self._agenda.pop
        while (due := pop(t)) is not None:
            at, (kind, node, payload) = due
            self.now = at
            if kind == "cast":  # (a beat's copies: the commonest)
                self._deliver(at, node, *payload)
                continue
            if kind == "routes":
                self.update_routes()
                continue
            if node in self.killed:
                continue
            core = self.cores[node]  # (its byte counters it reads itself: count_traffic)
            if kind == "msg":
                src, msg = payload
                if self.proofs and type(msg) is m.Hears:
                    msg = self._proven(src, msg)
                self.delivered += 1
                if self.trace is not None:
                    self.trace.append((at, node, src, m.name_of(msg)))
                self.apply(node, core.receive(src, msg, at))
            elif kind == "vertex":
                executor, result = payload
                if executor is self.executors[node]:
                    self.apply(node, core.on_vertex(result, at))
            elif self._timers.get(key := (node, payload)) == at:
                del self._timers[key]
                self.apply(node, core.on_timer(payload, at))
        self.now = max(self.now, t)
