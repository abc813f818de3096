"""Whether a node out of reach must be declared failed: it must when re-placing a vertex it
runs would let the app's events flow again. Pure functions of the app, where its vertices run
and which nodes are out of reach (issue 22: unreachable is not failed)."""

from __future__ import annotations

from collections.abc import Mapping

from mso.model.app import App


def re_placeable(
    app: App, placed: Mapping[str, str], resolved: Mapping[str, str], vertex: str, away: set[str]
) -> bool:
    """Whether ``vertex``, its node out of reach, is re-placed: re-placing it helps
    (:func:`replacing_helps`) and no producer of it runs on another node out of reach. Such
    a producer may be feeding the instance there: a replacement here would be its twin, and
    what that producer replays after the heal would reach the consumers twice (a merge across
    a partition, fault seeds 1672, 3031, 4068)."""
    if _twin_risk(app, placed, vertex, away, set()):
        return False
    return replacing_helps(app, resolved, vertex, away, placed)


def _twin_risk(
    app: App, placed: Mapping[str, str], vertex: str, away: set[str], along: set[str]
) -> bool:
    """``vertex`` runs out of reach and is fed by a producer (not one of ``along``, re-placed
    with it) on another node out of reach, which may be feeding it there still."""
    host = placed.get(vertex)
    if host not in away:
        return False
    return any(
        placed.get(e.src) in away - {host} and e.src not in along
        for e in app.edges
        if e.dst == vertex
    )


def replacing_helps(
    app: App,
    resolved: Mapping[str, str],
    vertex: str,
    away: set[str],
    placed: Mapping[str, str] | None = None,
) -> bool:
    """Whether re-placing ``vertex`` (its node out of reach) could let events flow again: it
    is not pinned (one placed by capability may move to another capable node), and some path
    from a source through it to a sink has every pinned vertex on a node in reach and, given
    where the vertices run, passes no vertex out of reach that a producer off the path may
    feed there still: that one is not re-placed (:func:`re_placeable`), and a replacement
    would only feed it where nobody reaches it, while the node's reset on the heal loses what
    it held (seed 17236: two nodes declared 9 ms before a heal; a merge's interleaving and
    its stateful consumer's state lost with them). Otherwise the app waits for the node as it
    would for a declared one, and the node stays *unreachable*, not failed: taken back as it
    is when it is heard again, with no reset. Linear in the app's edges per vertex passed."""
    fixed = {v.id: v.pinned for v in app.vertices.values() if v.pinned and v.id not in resolved}
    if vertex in fixed:
        return False
    ins: dict[str, list[str]] = {}
    outs: dict[str, list[str]] = {}
    for e in app.edges:
        outs.setdefault(e.src, []).append(e.dst)
        ins.setdefault(e.dst, []).append(e.src)

    def reaches_end(start: str, step: dict[str, list[str]]) -> bool:
        seen, todo = {start}, [start]
        while todo:
            v = todo.pop()
            if not step.get(v):
                return True  # a source (upstream) or a sink (downstream) in reach
            for u in step[v]:
                if fixed.get(u) in away or u in seen:
                    continue
                if placed is not None and _twin_risk(app, placed, u, away, seen):
                    continue
                seen.add(u)
                todo.append(u)
        return False

    return reaches_end(vertex, ins) and reaches_end(vertex, outs)
