"""The narrow context every component of a node core acts through. Sans-IO.

The node core (:mod:`mso.node.core`) implements it; the data plane and each procedure's roles
get it at construction and never see the core itself. Through it they send, broadcast, reply,
set timers and hand out vertex effects (all become the core's effects, returned to the driver),
open and end procedures, publish internal events (:mod:`mso.protocol.events`) to the other
components, and read the node's shared tables: its apps, its routes, the peers membership holds
failed. It is what aioquic's connection is to its subsystems, as a typed interface.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Protocol

if TYPE_CHECKING:
    from collections.abc import Hashable, Iterable, Mapping

    from mso.model.network import PowerModel
    from mso.protocol import messages as m
    from mso.protocol.authority import Authority
    from mso.protocol.effects import Effect
    from mso.protocol.events import InternalEvent
    from mso.protocol.procedures.base import Procedure
    from mso.protocol.spill import SpillStore
    from mso.protocol.state import Apps


class NodeContext(Protocol):
    """What a component may do to, and read of, its node."""

    @property
    def id(self) -> str: ...

    @property
    def now(self) -> float: ...

    @property
    def incarnation(self) -> int: ...

    @property
    def apps(self) -> Apps: ...

    @property
    def routes(self) -> dict[str, tuple[str, int]]: ...

    @property
    def failed(self) -> set[str]:
        """The nodes membership holds failed (read only: membership alone changes it)."""
        ...

    @property
    def window(self) -> int: ...

    @property
    def capacity(self) -> float: ...

    @property
    def capabilities(self) -> dict[str, float]:
        """What this node offers besides its CPU (``mso node --capability``; §3.3)."""
        ...

    @property
    def power(self) -> PowerModel:
        """This node's power model: its figures travel in probes for the bytes planner."""
        ...

    def link_rate(self, neighbour: str) -> float | None:
        """The rate (Mb/s) of this node's link to ``neighbour`` as its driver knows it (the
        scenario's in a simulation or emulation, the configured ``link_mbps`` on a device;
        None: not known): probes carry it to the bytes planner."""
        ...

    @property
    def authority(self) -> Authority: ...

    @property
    def spill(self) -> SpillStore:
        """Where edges spill events they cannot deliver yet (the driver's durable log)."""
        ...

    # -- effects ---------------------------------------------------------------------------
    def send(self, dst: str, msg: m.Message) -> None:
        """To ``dst`` (to this node itself: handled after the current input)."""

    def broadcast(self, msg: m.Message) -> None: ...

    def reply(self, client: int, msg: m.Message) -> None: ...

    def emit(self, effect: Effect) -> None:
        """Any other effect: a vertex effect, or a Send that must not loop back."""

    def emit_all(self, effects: Iterable[Effect]) -> None:
        """:meth:`emit` each of ``effects``, in order (a beat's sends, in one call)."""

    def set_timer(self, key: Hashable, at: float) -> None: ...

    def loop_back(self, src: str, msg: m.Message) -> None:
        """Handle ``msg`` as if ``src`` had sent it, after the current input."""

    # -- procedures and events -------------------------------------------------------------
    def new_pid(self) -> int:
        """A fresh procedure id, distinct across the nodes."""
        ...

    def ours(self, pid: int) -> bool:
        """``pid`` is (was) a procedure of this node's: an answer to it may come late."""
        ...

    def begin(self, proc: Procedure) -> None:
        """Open ``proc`` here and arm its deadline."""

    def end(self, pid: int) -> None: ...

    def procedure(self, pid: int | None) -> Procedure | None: ...

    def open(self) -> list[Procedure]:
        """The procedures open here, oldest first."""
        ...

    def publish(self, event: InternalEvent) -> None:
        """Deliver ``event`` to the components subscribed to its type, now."""

    # -- accounting --------------------------------------------------------------------------
    def refusal(self, reason: str) -> None:
        """A message refused for its meaning: nothing changed; counted by reason."""

    def dropped(self) -> None:
        """A message dropped (stale, or for something gone): counted."""

    def note_event(self, now: float, what: str) -> None:
        """Into the monitor's recent events (status shows them)."""

    def note_start(self, now: float) -> None:
        """An instance started here: its start-up CPU is in the monitor's figures from now."""

    def elapsed_ms(self, since: float) -> float: ...

    def figures(self) -> m.Figures:
        """This node's monitored figures, as its heartbeats carry them."""
        ...

    def incarnation_of(self, node: str, default: int) -> int:
        """The last incarnation of ``node`` this node heard of (``default`` if none)."""
        ...

    def learn_incarnations(self, incarnations: Mapping[str, int]) -> None:
        """Incarnations another node found (a chain's probe, a sync), taken only for nodes
        this node knows none of."""
        ...

    # -- the routing view ---------------------------------------------------------------------
    def known_nodes(self) -> list[str]: ...

    def distances(self) -> dict[str, int]:
        """Hops to each node this node routes to, itself at 0."""
        ...
