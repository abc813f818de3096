"""What a node's management rules see and what they may ask for (paper §3.5). Pure data.

The node core builds a :class:`Snapshot` from its monitor, the monitors of the neighbours it has
heard from, and the placement it holds; the rules turn it into :data:`Action` s. Nothing here
reads a clock: every time is the node's ``now`` when the snapshot was built.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from dataclasses import dataclass

from mso.model.network import PowerModel

ActionKey = tuple[str | int, ...]
"""Identity of an action without its reason: the same move proposed twice is the same action."""


@dataclass(frozen=True, slots=True)
class NodeView:
    """A node as this node last heard of it (its own monitor, or a neighbour's report)."""

    id: str
    cpu: float  # relative speed, 1.0 = reference
    power: PowerModel
    load: float  # modelled CPU utilisation now, 0..1 (more when overloaded)
    drain_w: float  # smoothed power draw, idle included
    remaining_j: float | None  # None: wall powered
    lifetime_s: float | None  # remaining / drain; None if wall powered or not yet known
    heard_at: float  # when this information was produced
    # hops from this node to each node it routes to, as it last said (empty: not known)
    hops: Mapping[str, int] = dataclasses.field(default_factory=dict)

    @property
    def battery(self) -> bool:
        return self.remaining_j is not None


@dataclass(frozen=True, slots=True)
class VertexView:
    """A vertex hosted on this node, with the traffic and work it has been seen to cause.

    ``upstream``/``downstream`` are where an upstream/downstream relocation would take it (its
    predecessor's node / its successor's node or the next node toward the chain's tail), None
    when that relocation is not possible. ``moved_from`` is the node it left when it last moved
    (with ``moved_at``): it lets the node it moved to refuse to send it straight back.
    """

    app: str
    id: str
    node: str  # host
    chain: int
    cost: float  # ms of CPU per event on a cpu-1.0 node
    rate: float  # events/s it processes, smoothed
    in_bytes_per_s: float
    out_bytes_per_s: float
    state_bytes: int  # encoded state: what a move must transfer
    upstream: str | None
    downstream: str | None
    movable: bool  # False for chain heads/tails and pinned vertices (§3.4.1)
    moved_at: float | None = None
    moved_from: str | None = None
    pinned: bool = False  # pinned by the app: no relocation or remap ever moves it

    @property
    def key(self) -> str:
        """``app/id``: vertex ids are unique within an app only (one app may be deployed twice)."""
        return f"{self.app}/{self.id}"


@dataclass(frozen=True, slots=True)
class ChainView:
    """A chain that touches this node: its vertices, their hosts and how it is doing.

    ``placed_at`` is when the chain's current mapping was made (deployment or last remap), if the
    node knows it: a route change older than the mapping needs no remap.
    """

    app: str
    index: int
    vertices: tuple[str, ...]  # head first, tail last
    nodes: tuple[str, ...]  # host of each vertex, same order
    delay_ms: float | None  # measured end-to-end delay, smoothed; None if unknown
    slo_ms: float | None  # the app's delay objective
    route_changed_at: float | None  # last change of a route between the chain's nodes
    coordinator: bool  # this node may remap the chain (it holds the head)
    placed_at: float | None = None

    @property
    def key(self) -> tuple[str, int]:
        return (self.app, self.index)


@dataclass(frozen=True, slots=True)
class Snapshot:
    """Everything one evaluation of the rules looks at. Treat the mappings as read-only."""

    now: float
    here: str
    nodes: Mapping[str, NodeView]  # this node and the neighbours it has heard from
    vertices: tuple[VertexView, ...]  # the vertices hosted here
    chains: tuple[ChainView, ...]  # the chains that touch this node
    busy: frozenset[str] = frozenset()  # apps with a relocation or remap this node coordinates
    # nodes that run a pinned vertex of an app this node holds: work there cannot move, and the
    # app stops for good when such a node dies
    pinned_hosts: frozenset[str] = frozenset()
    # when a vertex instance last started on this node (deployment, a move here, a remap, a
    # restore): its drain and load include that start-up work for a while (RuleSettings.warmup_s)
    last_start: float | None = None
    # app -> the nodes that take part in it as this node sees them: its vertices' hosts and
    # this node's next hops toward them (the relays of its edges here). An app not listed:
    # not known (every node in view may take part)
    app_nodes: Mapping[str, frozenset[str]] = dataclasses.field(default_factory=dict)

    def vertex(self, key: str) -> VertexView | None:
        """The hosted vertex with ``key`` (``app/id``), if any."""
        for v in self.vertices:
            if v.key == key:
                return v
        return None

    def chain(self, app: str, index: int) -> ChainView | None:
        for c in self.chains:
            if c.app == app and c.index == index:
                return c
        return None

    def apps(self) -> list[str]:
        """Apps with a vertex or a chain here, sorted."""
        return sorted({v.app for v in self.vertices} | {c.app for c in self.chains})

    def for_app(self, app: str) -> Snapshot:
        """The same snapshot with only ``app``'s vertices and chains (all nodes kept)."""
        return dataclasses.replace(
            self,
            vertices=tuple(v for v in self.vertices if v.app == app),
            chains=tuple(c for c in self.chains if c.app == app),
        )

    def with_nodes(self, ids: frozenset[str] | set[str]) -> Snapshot:
        """The same snapshot seeing only the nodes in ``ids`` (those with a view)."""
        return dataclasses.replace(
            self, nodes={n: self.nodes[n] for n in sorted(ids) if n in self.nodes}
        )


@dataclass(frozen=True, slots=True)
class Relocate:
    """Move one vertex onto ``target`` (an upstream or downstream relocation, §3.4.1)."""

    app: str
    vertex: str
    target: str
    reason: str = ""

    @property
    def key(self) -> ActionKey:
        return ("relocate", self.app, self.vertex, self.target)

    @property
    def vertex_key(self) -> str:
        return f"{self.app}/{self.vertex}"

    def __str__(self) -> str:
        why = f" ({self.reason})" if self.reason else ""
        return f"relocate {self.app}/{self.vertex} -> {self.target}{why}"


@dataclass(frozen=True, slots=True)
class RemapChain:
    """Re-place one chain along a freshly probed route, head and tail kept (§3.4.2)."""

    app: str
    chain: int
    reason: str = ""

    @property
    def key(self) -> ActionKey:
        return ("remap", self.app, self.chain)

    def __str__(self) -> str:
        why = f" ({self.reason})" if self.reason else ""
        return f"remap {self.app} chain {self.chain}{why}"


@dataclass(frozen=True, slots=True)
class RemapChains:
    """Re-place several chains together, e.g. every chain that ends or starts at a join or fork
    vertex, which relocation never moves (an energy remap). Each vertex in ``place`` goes to the
    node given (the planner anchors it there); the planner places the rest seeing each node's
    probed capacity times its weight in ``weights`` (nodes not listed: 1), so a weight of 0
    keeps them off that node."""

    app: str
    chains: tuple[int, ...]
    weights: tuple[tuple[str, float], ...] = ()
    reason: str = ""
    place: tuple[tuple[str, str], ...] = ()

    @property
    def key(self) -> ActionKey:
        return ("remap-chains", self.app, *self.chains)

    def __str__(self) -> str:
        why = f" ({self.reason})" if self.reason else ""
        shown = ", ".join(str(c) for c in self.chains)
        return f"remap {self.app} chains {shown}{why}"


Action = Relocate | RemapChain | RemapChains
