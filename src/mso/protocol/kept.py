"""The apps a node holds, kept in its durable store, so that a daemon restart keeps them.

Only the nodes that take part in an app hold it (issue 24.1): its origin, the hosts of its
vertices, its replicas' nodes. When all of them restart at once -- a robot carrying a whole
chain and the one carrying its replica, both rebooted -- nobody was left to sync the app back
to them, and it was gone from the network (fault seed 2574; before 24.1 every node held every
app and synced it back). So a node keeps what it needs to take an app again (its document,
origin, epoch, the nodes chosen by capability, its replicas' nodes) in its store when it takes
the app and as its placement changes (looked at every monitor period), and forgets it once it
lets the app go or the app is undeployed. A restarted daemon
reads them back and takes each as a sync from its last process (:meth:`~mso.protocol
.procedures.membership.sync.AppSyncing.on_app_sync`): the vertices it ran vanished with that
process and are restored; where the others run is looked up, as after any sync.

The record is an :class:`~mso.protocol.messages.AppSync`, encoded as on the wire, and read back
through the same validating decoder: a damaged store costs the app, never the node.
"""

from __future__ import annotations

import msgspec

from mso.protocol import messages as m
from mso.protocol.spill import SpillStore
from mso.protocol.state import AppState

# (a control character: no app name in a store of edges keyed ``app/epoch/edge`` starts so)
PREFIX = "\x1fheld/"


def record(
    dep: AppState, handed: dict[str, str] | None = None, incarnations: dict[str, int] | None = None
) -> m.AppSync:
    """``dep`` as a sync of the view this node has now: what taking it again needs (the
    record kept), and, for a sync sent to another node, the vertices this node handed over
    (``handed``) and the incarnations it knows of their hosts (``incarnations``)."""
    return m.AppSync(
        dep.app.name,
        dep.origin,
        dep.document,
        dep.epoch,
        dict(dep.placed),
        sorted(dep.vanished),
        handed or {},
        dict(dep.layout.resolved),
        {v: list(ns) for v, ns in dep.capable.items()},
        incarnations or {},
        {v: k for v, k in dep.versions.items() if k},
        {v: list(ns) for v, ns in dep.replica_nodes.items()},
    )


def fingerprint(dep: AppState, incarnations: dict[str, int] | None = None) -> int:
    """What a record of ``dep`` would say, as one number: kept again when it changes."""
    return hash(
        (
            dep.epoch,
            tuple(dep.placed.items()),
            tuple(dep.versions.items()),
            tuple((v, tuple(ns)) for v, ns in dep.replica_nodes.items()),
            tuple(sorted((incarnations or {}).items())),
        )
    )


def keep(spill: SpillStore, dep: AppState, incarnations: dict[str, int] | None = None) -> None:
    """This node holds ``dep`` now: keep its record (replacing an older one), with the
    ``incarnations`` it knows of the nodes its view places vertices on: a sync its next
    process sends of this view before it hears them says which incarnation ran them (fault
    seed 265408: without them, a placement on a node restarted since was taken as news)."""
    key = PREFIX + dep.app.name
    spill.drop(key)
    spill.append(key, 0, [m.encode(record(dep, incarnations=incarnations))])
    spill.note(key + "/", "epoch", dep.epoch)


def forget(spill: SpillStore, app: str) -> None:
    """This node holds ``app`` no more (let go, undeployed)."""
    key = PREFIX + app
    spill.drop(key)
    spill.forget_notes(key + "/")


def recall(spill: SpillStore) -> list[m.AppSync]:
    """The apps this node held when its last process stopped, by name; a record that does
    not decode as one is skipped."""
    out: list[m.AppSync] = []
    for name in sorted(spill.notes(PREFIX)):
        app = name.rpartition("/")[0]
        data = spill.read(PREFIX + app, 0, 1)
        if not data:
            continue
        try:
            msg = m.decode(data[0])
        except (msgspec.DecodeError, msgspec.ValidationError):
            continue
        if isinstance(msg, m.AppSync) and msg.app == app:
            out.append(msg)
    return out


__all__ = ["PREFIX", "fingerprint", "forget", "keep", "recall", "record"]
