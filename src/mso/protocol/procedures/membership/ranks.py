"""Who resets after a partition heals: the tie-break between two nodes that hold each other
(or one holds the other) failed, read from this node's view and the other's beat alone.

Pure functions of :class:`View` and a :class:`~mso.protocol.messages.Heartbeat`, so the rule
is whole in one place and each reading can be tested by itself; :mod:`.peers` acts on them
(reset, wait, tell the other its view).
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import dataclass

from mso.protocol import messages as m


@dataclass(frozen=True)
class View:
    """What this node's membership holds when it weighs a beat."""

    id: str
    incarnation: int
    routes: Mapping[str, object]  # the nodes it reaches
    failed: frozenset[str]
    incarnations: Mapping[str, int]  # last incarnation heard of, per node
    hosting: int  # instances it runs
    leader: str


def outranked_by(view: View, msg: m.Heartbeat) -> bool:
    """After a partition both sides may hold the other failed. A node that runs nothing
    yields to one that runs something (it loses nothing by resetting); otherwise the side
    that counts fewer failed nodes (the larger one), then the one with the lower leader,
    then the lower-named node, stays and the other resets (two nodes of one side that
    hold each other failed — not neighbours, each cut off by other failures — would
    otherwise tie for ever). One-sided (we hold the sender alive), we reset, unless the
    sender runs nothing and we run something: it yields instead (``on_failed_heartbeat``;
    a restarted node that held everyone failed once reset every node it met).

    Only failed nodes this node can reach count (the other side of the partition): a node
    that really crashed is out of everyone's reach, and the two sides learn of it at
    different moments; counted, it once made both nodes of a tie reset, and the app was
    gone from every node."""
    if msg.node not in view.failed:
        return not (msg.hosting == 0 and view.hosting > 0)

    def rank(hosting: int, dead: int, leader: str, node: str) -> tuple[bool, int, str, str]:
        return (hosting == 0, dead, leader, node)  # the node's own name breaks a tie

    def disputed(dead: Iterable[str]) -> int:
        return sum(1 for n in dead if n == view.id or n in view.routes)

    theirs = rank(msg.hosting, disputed(msg.failed), msg.leader or msg.node, msg.node)
    return theirs < rank(view.hosting, disputed(view.failed), view.leader, view.id)


def cut_off(view: View, msg: m.Heartbeat) -> bool:
    """``msg.node``, which we hold alive, holds us failed, and with us most of the nodes
    we reach and hold alive: it was cut off from them (a partition that just healed),
    and we did not declare it because our suspicion of it had not ended yet when it came
    back into reach (others had: a confirmation takes a round trip). Resetting for it
    would make the larger side reset for the smaller one; a node that only we missed
    (it stalled, or it alone lost our routes) holds failed just us and a few, and we
    yield to it as before. Only entries for the incarnations the nodes run count.

    Our side (us and those it holds failed) must outnumber its side (it and those of ours it
    holds alive), the sender counted: on an even split a node that declared nobody (issue
    22.1) counts as ours a node of the other side it never learned was across, and once
    it held the sender failed its beat counted one failed against the sender's two, so the
    sender reset too and both sides dropped the app (fault seed 287248). A tie yields."""
    if msg.node in view.failed:
        return False
    seen = {n for n in view.routes if n not in view.failed and n != msg.node}
    ours = sum(1 for n in seen if n in msg.failed and _runs(view, n, msg.failed[n]))
    ours += msg.failed.get(view.id) == view.incarnation
    theirs = 1 + len(seen) + 1 - ours  # the sender, and those of us and ours it holds alive
    return ours > theirs


def holds_more_failed(view: View, msg: m.Heartbeat) -> bool:
    """``msg.node`` holds more of the nodes we reach failed (in the incarnations they run)
    than we do: it is on the smaller side of a partition that healed."""
    theirs = sum(
        1
        for n, inc in msg.failed.items()
        if (n == view.id and inc == view.incarnation) or (n in view.routes and _runs(view, n, inc))
    )
    return theirs > sum(1 for n in view.failed if n in view.routes)


def smaller_side(view: View, msg: m.Heartbeat) -> bool:
    """``msg.node``, which we hold failed, is the side cut off by a partition that healed,
    not we: it holds more of the nodes we reach failed than we do (:func:`holds_more_failed`),
    or it holds us alive while we hold alive most of the nodes we reach. A node out of reach
    is not declared (issue 22.1), so the node cut off holds the others *unreachable*, alive,
    while they declared it to re-place what it ran: its beat holds nobody failed, and read as
    the larger side's, every node that ran nothing reset for a relay cut off 2 s and was taken
    for a restart by the others. A node that holds most of those it reaches failed (restarted
    amid a partition, told of failures that are over) is the one to yield."""
    if msg.node not in view.failed:
        return False
    if holds_more_failed(view, msg):
        return True
    if msg.failed.get(view.id) == view.incarnation:
        return False
    seen = [n for n in view.routes if n != msg.node]
    held = sum(1 for n in seen if n in view.failed)
    return len(seen) - held > held


def _runs(view: View, node: str, incarnation: int) -> bool:
    """Whether ``node`` runs ``incarnation``, as far as this node knows: one whose incarnation
    it never heard (a node far away that shares no app with it: nobody says hello to every
    node at start) is taken to run the one the beat names."""
    return view.incarnations.get(node, incarnation) == incarnation
