"""Placement knowledge (issue 24.1): who is told where a vertex runs, and what a node that is not
told does before it acts.

The paper's claim is that a reconfiguration is local: nodes away from the change are "neither
involved in nor aware of" it. So a move is not broadcast. A :class:`~mso.protocol.messages.Moved`
goes to the nodes that host part of the app (its *members*, as the sender knows them: the
moved vertex's producers and consumers and the chains around it among them) and to the new host
— a number that depends on the app, not on the size of the network. Every member's view stays
whole, so the recovery rule (the lowest surviving member coordinates) still needs no
coordinator. A node that hosts no part of an app keeps the view it last had; before it acts on
one (a client's relocation or remap, the recovery of an app whose every instance it sees lost)
it asks (:mod:`.lookup`), and a node that becomes a member learns the placement from the
coordinator's ``Prepare``.

Each vertex carries a *version*, the number of its moves: the node that hands a vertex over
counts it and every message about the move carries it, so of two answers the older loses.
Version 0 is the deployment's placement (or a view rebuilt from a sync): news about it is taken
as before, the last word winning.

With operator keys, news that changes where a vertex runs is taken only from the node this
node's view says hosts it (it handed the vertex over), or, once that node failed or the vertex
vanished with it, from the node that restored it (:func:`may_tell`): a captured member that
hosts part of an app once moved any of its vertices — to itself, so that their inputs came to
it, or to a node that never ran them — with one ``Moved`` to the app's nodes. A refused claim
is counted (``moved_not_by_its_host``) and the placement looked up (:mod:`.lookup`), whose
answers are weighed by the same rule: a move this node missed is learnt from the old host.
Two moves of one version are two restores of one view (on either side of a cut, or by a
daemon that restarted and relearnt an older view than its old process had): the twins are
ordered by their hosts (:func:`prevails`), so every node keeps the same one and the other yields.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Set
from typing import Any

from mso.protocol import messages as m
from mso.protocol.context import NodeContext
from mso.protocol.events import AppMissing, PlacementStale, RecoveryDue, Superseded
from mso.protocol.spill import placement_notes
from mso.protocol.state import AppState

Tie = Callable[[str, str], bool]  # (node, over): a placement on node prevails at equal version


def prevails(ctx: NodeContext) -> Tie:
    """Of two placements of one vertex at one version, the one that stands: the one on a live
    node where the other's host is held failed or its instance vanished; else the one on the
    node up longer (its lower incarnation; a restarted daemon's view was relearnt from
    others'), then the lower name. Each node orders the twins alike once it has heard their
    hosts' incarnations."""

    def rank(n: str) -> tuple[int, str]:
        return (ctx.incarnation if n == ctx.id else ctx.incarnation_of(n, 0), n)

    def tie(node: str, over: str) -> bool:
        return over in ctx.failed or rank(node) < rank(over)

    return tie


def remember(ctx: NodeContext, app: str, vertex: str, node: str, inc: int, version: int) -> None:
    """Note, durably, where ``vertex`` runs as its host said itself (its incarnation, the
    move): a daemon that restarts relearns the app from others' syncs, which may be older
    than what its last process heard (:func:`recall`)."""
    ctx.spill.note(placement_notes(app, vertex), f"{inc}/{node}", version)


def recall(ctx: NodeContext, dep: AppState) -> None:
    """A node that learnt the app from a sync (its daemon restarted): a vertex the sync holds
    gone that its last process heard its host say it runs, at a later move than the sync's,
    runs there still while that host is in the same incarnation and not held failed; the
    sync's view of it is older (restart seed 7422: a sync from a node that never heard of a
    restore placed the vertex on its host's old incarnation, gone; restored here again, a
    twin of equal version, and the producer restored beside it numbered its edge from 0)."""
    for v in sorted(dep.vanished):  # (where the sync's view runs it too, it is left as is:
        # a version raised alone refused the moves of nodes that had the sync's, seed 862)
        for name, version in ctx.spill.notes(placement_notes(dep.app.name, v)).items():
            inc, _, node = name.partition("/")
            if version <= dep.versions.get(v, 0) or node == ctx.id or node in ctx.failed:
                continue
            if not inc.isdigit() or ctx.incarnation_of(node, int(inc)) != int(inc):
                continue
            dep.placed[v] = node
            dep.versions[v] = version
            dep.vanished.discard(v)


def runs_there(dep: AppState, vertex: str, node: str, version: int, now: float) -> bool:
    """``node`` says it runs ``vertex`` (its own word, in a lookup's answer) where this view
    places it on another node, vanished with that node's old incarnation: the instance said
    to run stands, at the vanished placement's version, as its host's ``Moved`` does (fault
    seed 92622). Without it, a twin restored across a cut and gone with its node's reset at
    the heal, heard of at a later move than the live instance's, outweighed every answer
    from the live instance's node, and views split for good (seed 164451). True if taken."""
    where = dep.placed.get(vertex)
    if vertex not in dep.vanished or where is None or where == node:
        return False
    if vertex in dep.instances or vertex in dep.awaiting or vertex in dep.restoring:
        return False  # (this node's own word on it is first-hand)
    return learn(dep, vertex, node, max(version, dep.versions.get(vertex, 0)), now)


def members(dep: AppState) -> set[str]:
    """The nodes this node's view says host part of the app."""
    return set(dep.placed.values())


def learn(
    dep: AppState,
    vertex: str,
    node: str,
    version: int,
    now: float,
    running: bool = True,
    tie: Tie | None = None,
) -> bool:
    """Take ``vertex`` runs on ``node`` as its ``version``-th move, unless we know of a later
    one (or, given ``tie``, of one of this version that prevails); True if taken.
    ``running``: the word of a node that runs it (a Moved), so it has not vanished with a
    node's old incarnation; a view passed on (a snapshot, a coordinator's record) says
    nothing about that."""
    known, where = dep.versions.get(vertex, 0), dep.placed.get(vertex)
    if version < known:  # (a version-0 word too: the deployment's, overtaken; 57866)
        return False
    tied = version and version == known and where not in (None, node)
    if tied and tie is not None and vertex not in dep.vanished and not tie(node, where or ""):
        return False
    if dep.placed.get(vertex) != node or version > dep.versions.get(vertex, 0):
        dep.moved_at[vertex] = now
    dep.placed[vertex] = node
    dep.versions[vertex] = max(version, dep.versions.get(vertex, 0))
    if running:
        dep.vanished.discard(vertex)
    for c in dep.layout.chains:
        if vertex in c.vertices:
            dep.placed_at[c.index] = now
    return True


def brief(
    dep: AppState, vertex: str, placed: dict[str, str], versions: dict[str, int], now: float
) -> None:
    """A move's target that runs no instance of the app (told of none of its moves) takes from
    the move's ``Prepare`` where ``vertex``'s producers and consumers run, where that is a
    later move than it knows of: with operator keys it took a placement only on the host's
    word, kept the view of when it last took part, and sent the vertex's output to a node
    the consumer had left (the stream stopped: ``bench/chain_end.py``). The caller takes
    it only from a coordinator that could move the vertex onto itself
    (:func:`mso.protocol.warrant.could_take`), which holds those edges anyway."""
    for e in dep.app.edges:
        if vertex not in (e.src, e.dst):
            continue
        other = e.dst if e.src == vertex else e.src
        node, version = placed.get(other), versions.get(other, 0)
        if node is not None and version > dep.versions.get(other, 0):
            learn(dep, other, node, version, now, running=False)


def bump(dep: AppState, vertex: str) -> int:
    """Count a move of ``vertex`` made here: its new version."""
    dep.versions[vertex] = version = dep.versions.get(vertex, 0) + 1
    return version


def may_tell(dep: AppState, vertex: str, src: str, failed: Set[str]) -> bool:
    """Whether ``src`` may tell this node (with operator keys) that ``vertex`` runs elsewhere
    than its view says: it is the vertex's host in that view (it handed the vertex over), or
    that host failed or the vertex vanished with its node (a restore, by whoever restored it)."""
    host = dep.placed.get(vertex)
    return host is None or host == src or host in failed or vertex in dep.vanished


def changes(dep: AppState, vertex: str, node: str, version: int) -> bool:
    """Whether news that ``vertex`` runs on ``node`` as its ``version``-th move would change
    this node's view."""
    return dep.placed.get(vertex) != node or version > dep.versions.get(vertex, 0)


def merge(
    dep: AppState,
    src: str,
    placed: dict[str, str],
    versions: dict[str, int],
    vanished: list[str],
    now: float,
    failed: Set[str] | None = None,
    *,
    here: str,
) -> None:
    """Take from ``src``'s view (placement, versions, vanished instances) what is strictly newer
    than ours, or as new and first-hand (``src`` says where it runs it itself), or as new on
    another node where ours vanished and that view's did not (a twin restored from the same
    view, :func:`prevails`) — except for the vertices this node runs or is taking over (its
    own word on them is first-hand), and a vertex the view places ``here`` that does not run
    here is taken as vanished (seed 24786: a restore's Prepare held while this node was down
    reached its next incarnation and placed a vertex of the last one here, alive; nothing
    restored it). Given ``failed`` (with operator keys), a change only where :func:`may_tell`
    lets ``src``."""
    ours = set(dep.instances) | set(dep.awaiting) | set(dep.restoring)
    gone = set(vanished)
    for v, n in placed.items():
        version, mine = versions.get(v, 0), dep.versions.get(v, 0)
        if v not in dep.app.vertices or v in ours:
            continue
        if failed is not None and changes(dep, v, n, version) and not may_tell(dep, v, src, failed):
            continue
        # (a twin of our placement's version, restored on a view that never had ours, while
        # ours went with its node's reset: fault seed 171657, N6 kept `a` on N8's gone
        # incarnation, hosting nothing on its edges, and no node told it of N7's restore)
        restored = (
            version == mine
            and v in dep.vanished
            and v not in gone
            and n not in (here, dep.placed.get(v))
        )
        if version > mine or (version == mine and n == src) or restored:
            learn(dep, v, n, version, now, running=False)
            if v in gone or n == here:
                dep.vanished.add(v)
            else:
                dep.vanished.discard(v)


def prepare(
    dep: AppState,
    vertex: str,
    rid: int,
    restore: bool = False,
    resumes: list[list[Any]] | None = None,
    order: bytes = b"",
) -> m.Prepare:
    """A move's (or restore's) Prepare, with the coordinator's view of the app for a target
    that hosts no part of it yet and so was not told of its moves (and the operator's order
    it carries out, if any: :mod:`mso.protocol.warrant`)."""
    snapshot = dict(dep.placed), versions(dep), sorted(dep.vanished)
    # a restore's: where to fetch its state; a move's: the replicas the new host tells when
    # it has its own (they let the snapshot, and the app, go: issue 24.1)
    replicas = list(dep.replica_nodes.get(vertex, []))
    return m.Prepare(dep.app.name, vertex, rid, restore, resumes or [], *snapshot, replicas, order)


def versions(dep: AppState) -> dict[str, int]:
    return {v: k for v, k in dep.versions.items() if k}


def announce(
    ctx: NodeContext,
    dep: AppState,
    vertex: str,
    node: str,
    *,
    incarnation: int = -1,
    also: Iterable[str] = (),
) -> None:
    """Tell the app's members (and ``also``: a coordinator that may host no part of it) that
    ``vertex`` runs on ``node``, at its current version; this node too, after the current
    input, as every receiver takes it."""
    msg = moved(dep, vertex, node, incarnation)
    for n in sorted((members(dep) | {node, ctx.id, *also}) - ctx.failed):
        ctx.send(n, msg)


def moved(dep: AppState, vertex: str, node: str, incarnation: int = -1) -> m.Moved:
    """The news that ``vertex`` runs on ``node``, at its current version."""
    return m.Moved(dep.app.name, vertex, node, incarnation, dep.versions.get(vertex, 0))


def on_moved(ctx: NodeContext, src: str, msg: m.Moved, now: float) -> None:
    """News that a vertex runs elsewhere now."""
    dep = ctx.apps.get(msg.app)
    if 0 <= msg.incarnation < ctx.incarnation_of(msg.node, msg.incarnation):
        # its instance went with that incarnation (a claim overtaken by a reset): where it
        # went is still news, as a vertex lost with it (seed 22392: a move announced while
        # this node was cut off, heard after the target's restart; it was never restored)
        v = msg.vertex
        # (or at the version held here, from the node this one places the vertex on, naming
        # another: it yielded its instance to that twin, gone since; fault seed 136485)
        handed = dep is not None and src == dep.placed.get(v) != ctx.id and src != msg.node
        known = dep.versions.get(v, 0) if dep is not None else 0
        # (or the very placement held here, alive: news without an incarnation put it there
        # — an old host's word of its handover, -1 — and this word says whose instance it
        # was. Seed 24365: the old host's first word, sent into a cut, came at the heal,
        # after the new host's restart was heard and just before this one, told back)
        same = (
            dep is not None
            and dep.placed.get(v) == msg.node
            and v not in dep.vanished
            and msg.version == known
        )
        news = (
            dep is not None
            and msg.node != ctx.id
            and v in dep.placed
            and not _runs_here(dep, v)
            and (msg.version > known or (handed and msg.version == known) or same)
        )
        if news and dep is not None and not _moved_refused(ctx, dep, src, msg):
            was = None if v in dep.vanished else dep.placed[v]
            learn(dep, v, msg.node, msg.version, now, running=False)
            dep.vanished.add(v)
            if same and msg.node not in ctx.failed:
                # (that placement may be the node's new incarnation's own word, a twin restored
                # there at this version: asked, its word stands, as below)
                dep.checking.add(v)
                ctx.publish(PlacementStale(msg.app, wide=False, also=(msg.node,)))
            elif was not in (None, ctx.id, msg.node) and was not in ctx.failed:
                # it ran on a live node by this view: the placement gone may have been a twin
                # restored across a cut (that node cut off, not failed), the instance there
                # the one left. Asked, that node's own word stands (:func:`runs_there`);
                # its view of a move it handed over does not (fault seed 164451)
                # (a recovery waits for the answers: restored at once elsewhere, it would be
                # that instance's twin)
                dep.checking.add(v)
                ctx.publish(PlacementStale(msg.app, wide=False, also=(was,)))
            ctx.publish(RecoveryDue(msg.app))
        return
    why = _moved_refused(ctx, dep, src, msg) if dep is not None else "moved_unknown_app"
    if why:
        ctx.refusal(why)
        if why == "moved_not_by_its_host":  # a move we missed, or a lie: its host will say
            ctx.publish(PlacementStale(msg.app))
        return
    known = dep is not None and msg.vertex in dep.placed
    tie = prevails(ctx)
    mine = dep.versions.get(msg.vertex, 0) if dep is not None else 0
    # a later move placed it elsewhere while it runs here, or one of this version that
    # prevails over this node's (a twin restored from the same view)
    twin = (
        dep is not None
        and msg.node != ctx.id
        and (msg.version > mine or (msg.version == mine > 0 and tie(msg.node, ctx.id)))
        and _runs_here(dep, msg.vertex)
    )
    # only its host's word says it runs (un-vanishes it); an old host's news of a move it
    # handed over, or a relayed later placement, says where, not that it survived a restart
    # of that node (seed 24380: such news, sent as a node came back in reach, undid the
    # vanishing of a vertex whose new host had restarted since; nothing restored it)
    running = src == msg.node
    v, node, version = msg.vertex, msg.node, msg.version
    if running and known and dep is not None and v in dep.vanished and dep.placed[v] != node:
        # the one instance said to run, against a later placement whose instance went with
        # its node's old incarnation: that placement's version says nothing live (fault seed
        # 92622: a twin restored across a cut, the other side's host reset at the heal)
        version = max(version, dep.versions.get(v, 0))
    # (a relayed later placement while it runs here is not taken: fault seed 92622, this
    # node ran a vertex it placed elsewhere, on a node that had reset since)
    # the node this one places the vertex on says it handed it over: no twin to order (an
    # equal version here is one counted on another placement: a twin's, vanished since, its
    # version kept with the host's first-hand word of the one before; seed 101043)
    handed = dep is not None and src == dep.placed.get(v) != node and src != ctx.id
    relayed_twin = twin and not running
    taken = (
        known
        and dep is not None
        and not relayed_twin
        and learn(dep, v, node, version, now, running, None if handed else tie)
    )
    if relayed_twin and dep is not None:
        # a relayed word (a node that missed ours): the twin it names may be gone with a
        # reset this node has not heard of yet, and retiring this one left the vertex running
        # nowhere (fault seed 65198). Its node is told of this one, as of the version the
        # relayer holds: if it still runs the twin and prevails, its answer is its own word,
        # and this one yields then; if its instance went, it takes this one. (Not the relayer
        # too: while that node's word is out, the two would pass the two placements back and
        # forth.)
        ctx.dropped()
        dep.versions[v] = max(mine, version)
        word = moved(dep, v, ctx.id, ctx.incarnation)
        ctx.send(msg.node, word)
    elif known and dep is not None and not taken:
        ctx.dropped()  # an older move's news, overtaken
        newer = dep.placed[msg.vertex]
        # (not a later move onto this node whose instance is gone: said in this node's own
        # name, it retired the one instance left, the sender's: a daemon restarted with the
        # app kept, its vertex vanished, fault seed 1353)
        gone = newer == ctx.id and not _runs_here(dep, msg.vertex)
        if newer != msg.node and msg.node != ctx.id and msg.node not in ctx.failed and not gone:
            # the node it names may still run it (a move it missed while cut off): tell it
            # the later one, so that it yields rather than run a twin
            inc = ctx.incarnation if newer == ctx.id else -1
            version = dep.versions.get(msg.vertex, 0)
            ctx.send(msg.node, m.Moved(msg.app, msg.vertex, newer, inc, version))
    elif twin and running:  # this one yields, to the twin's host's own word
        ctx.publish(Superseded(msg.app, msg.vertex, msg.node, msg.version, msg.incarnation))
    if taken and running and msg.incarnation >= 0 and version and msg.node != ctx.id:
        remember(ctx, msg.app, v, node, msg.incarnation, version)


def _runs_here(dep: AppState, vertex: str) -> bool:
    """An instance of ``vertex`` runs here and is not being handed over."""
    h = dep.instances.get(vertex)
    return h is not None and h.handing_over is None and vertex not in dep.markers


def _moved_refused(ctx: NodeContext, dep: AppState, src: str, msg: m.Moved) -> str:
    """Why news that ``msg.vertex`` runs on ``msg.node`` is not taken ('' if it is): a vertex
    not in the app; a pinned vertex anywhere but on its node. With operator keys also a vertex
    this node runs itself (and is not handing over): its own view is first-hand; and a change
    told by a node that may not tell it (:func:`may_tell`)."""
    if msg.vertex not in dep.app.vertices:
        return "moved_unknown_vertex"
    pin = dep.app.vertices[msg.vertex].pinned
    if pin is not None and msg.node != pin:
        return "moved_a_pinned_vertex"
    if ctx.authority.signed:
        if msg.node != ctx.id and _runs_here(dep, msg.vertex):
            return "moved_a_vertex_running_here"
        if changes(dep, msg.vertex, msg.node, msg.version) and not may_tell(
            dep, msg.vertex, src, ctx.failed
        ):
            return "moved_not_by_its_host"
    return ""


def from_member(ctx: NodeContext, src: str, app: str) -> bool:
    """With operator keys, whether an app's events or acks from ``src`` are taken: it hosts
    part of the app in this node's view (or is this node). Any node used to be able to send
    any edge events, or ack them, in its own name — a relay that hosts nothing of the app
    among them; its frames in others' names are stopped by their end-to-end tags
    (:mod:`mso.protocol.dataseal`). One from a new host this node has not heard of yet is
    dropped and resent by its channel."""
    dep = ctx.apps.get(app)
    if not ctx.authority.signed or dep is None or src == ctx.id or src in dep.placed.values():
        return True
    ctx.refusal("data_not_from_a_member")
    return False


def reply(ctx: NodeContext, src: str, msg: m.PlacementQuery) -> None:
    """Answer a lookup with this node's view of the app (nothing if it does not hold it)."""
    dep = ctx.apps.get(msg.app)
    if dep is None:  # an empty answer: the asker need not wait for it
        ctx.send(src, m.PlacementReply(msg.app, msg.qid, {}))
        return
    if msg.fetch:  # the asker holds none of it: the app first (issue 24.1)
        ctx.publish(AppMissing(msg.app, src, ahead=True))
    snapshot = dict(dep.placed), versions(dep), sorted(dep.vanished)
    ctx.send(src, m.PlacementReply(msg.app, msg.qid, *snapshot))


__all__ = [
    "announce",
    "bump",
    "changes",
    "from_member",
    "learn",
    "may_tell",
    "members",
    "merge",
    "on_moved",
    "prepare",
    "recall",
    "remember",
    "reply",
    "runs_there",
    "versions",
]
