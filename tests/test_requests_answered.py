"""Every client's request is answered, done or refused with its reason, before the client
stops waiting, whatever ends the procedure that holds it: here the node's reset (declared
failed by a side that outranks it), which drops every procedure with its state. A move, a
remap and a status fan-out were dropped unanswered; the client waited out its timeout."""

from __future__ import annotations

import msgspec
import pytest

from mso.client import waiting
from mso.node.core import NodeCore
from mso.protocol import messages as m
from mso.protocol.effects import Effect, Reply, SetTimer
from mso.protocol.events import Deadline
from mso.protocol.procedures.base import REPLY_MARGIN_S
from mso.protocol.procedures.lookup import Lookup
from mso.protocol.procedures.relocation import Relocation
from mso.protocol.procedures.remap import Remap
from mso.protocol.procedures.status import StatusFanout
from mso.sim.runner import Simulation
from test_faults import held_failed_both_ways

CLIENT = 9


def reset_by_n1(sim: Simulation) -> list[Effect]:
    """N1's beat, claiming N4 failed, makes N4 yield (the tie-break) and reset."""
    n1, n4 = sim.cores["N1"], sim.cores["N4"]
    beat1 = msgspec.structs.replace(n1.membership.beat(), failed={"N4": 0})
    effects = n4.receive("N1", beat1, sim.now)
    assert n4.incarnation == 1  # it yielded
    return effects


def replies(effects: list[Effect]) -> list[m.Message]:
    return [e.msg for e in effects if isinstance(e, Reply) and e.client == CLIENT]


def open_of(core: NodeCore, kind: type, now: float) -> list[object]:
    return [p for p in core.procedures.values() if isinstance(p, kind) and not p.done]


def asked(core: NodeCore, msg: m.Message, now: float, kind: type) -> None:
    """``msg`` asked of ``core``: held open (nothing answered yet), by a procedure of ``kind``."""
    assert replies(core.request(CLIENT, msg, now)) == []
    assert open_of(core, kind, now)


def test_a_move_the_node_coordinates_is_answered_when_it_resets() -> None:
    def move(sim: Simulation) -> None:  # (asked before N4 holds N1, src's node, failed)
        n4 = sim.cores["N4"]
        mid = n4.apps["pipe"].placed["mid"]
        target = next(n for n in ("N2", "N3") if n != mid)
        asked(n4, m.RelocateRequest("pipe", "mid", target=target), sim.now, Relocation)

    sim = held_failed_both_ways(move)
    n4, now = sim.cores["N4"], sim.now
    (reply,) = replies(reset_by_n1(sim))
    assert reply == m.RelocateReply(
        "pipe", "mid", False, error="N4: declared failed by N1, reset during the relocation"
    )
    assert n4.open_procedures(now) == []


def test_a_remap_the_node_coordinates_is_answered_when_it_resets() -> None:
    sim = held_failed_both_ways()
    n4, now = sim.cores["N4"], sim.now
    asked(n4, m.RemapRequest("pipe", [], everything=True), now, Remap)
    (reply,) = replies(reset_by_n1(sim))
    assert isinstance(reply, m.RemapReply) and not reply.ok
    assert reply.error == "N4: declared failed by N1, reset during the remap"


def test_a_status_fanout_answers_with_what_came_in_when_the_node_resets() -> None:
    sim = held_failed_both_ways()
    n4, now = sim.cores["N4"], sim.now
    asked(n4, m.StatusRequest(req=1, everywhere=True), now, StatusFanout)
    (reply,) = replies(reset_by_n1(sim))
    assert isinstance(reply, m.StatusReply) and "N4" in reply.nodes


@pytest.mark.parametrize(
    ("then", "reply"),
    [
        (m.RelocateRequest("pipe", "mid"), m.RelocateReply("pipe", "mid", False, error="why")),
        (m.RemapRequest("pipe", [0]), m.RemapReply("pipe", False, {}, error="why")),
    ],
)
def test_a_lookup_tells_its_client_what_waited_on_it(then: m.Message, reply: m.Message) -> None:
    """A node that hosts no part of the app looks the placement up before the request it
    was asked: ended unfinished, the client hears that request's refusal."""
    assert isinstance(then, m.RelocateRequest | m.RemapRequest)
    look = Lookup(1, 0.0, "pipe", CLIENT, then)
    told: list[tuple[int, m.Message]] = []

    class Ctx:
        def send(self, dst: str, msg: m.Message) -> None:
            raise AssertionError(dst)

        def reply(self, client: int, msg: m.Message) -> None:
            told.append((client, msg))

    look.abandon(Ctx(), "why")
    look.abandon(Ctx(), "again")  # once
    assert told == [(CLIENT, reply)]
    assert Lookup(2, 0.0, "pipe", None, None).refusal("why") is None  # a recovery's: nobody


@pytest.mark.parametrize(
    ("msg", "kind"),
    [
        (m.RemapRequest("pipe", [], everything=True), Remap),
        (m.RelocateRequest("pipe", "mid", target="N2"), Relocation),  # (mid on N3)
    ],
)
def test_an_undeploy_meanwhile_answers_a_move_or_remap(msg: m.Message, kind: type) -> None:
    """The app is undeployed while a move or remap of it runs: the procedure runs out its
    deadline (a remap's is past the client's 10 s), its client is told at once."""
    sim = held_failed_both_ways(lambda sim: asked(sim.cores["N4"], msg, sim.now, kind))
    n4, now = sim.cores["N4"], sim.now
    effects = n4.request(2, m.StopApp("pipe"), now)
    assert "pipe" not in n4.apps
    (reply,) = replies(effects)
    assert isinstance(reply, m.RemapReply | m.RelocateReply) and not reply.ok
    assert reply.error == f"N4: undeployed before the {kind.NAME} finished"
    assert replies(n4.receive("N3", m.StopApp("pipe"), now)) == []  # once


def test_a_remap_ends_before_its_client_stops_waiting() -> None:
    """A remap's deadline was 10 s and more (5 s a chain, 0.5 s a vertex), past the 10 s a
    client waits for it: its probes lost, it was answered when nobody listened. The client
    says how long it waits (``within_s``, filled in by ``mso.client``); the remap ends
    ``REPLY_MARGIN_S`` before, telling the client."""
    sim = held_failed_both_ways()
    n4, now = sim.cores["N4"], sim.now
    effects = n4.request(CLIENT, m.RemapRequest("pipe", [], everything=True, within_s=3.0), now)
    assert replies(effects) == []  # (its probes are never delivered)
    (remap,) = open_of(n4, Remap, now)
    assert isinstance(remap, Remap)
    assert remap.deadline == pytest.approx(now + 3.0 - REPLY_MARGIN_S)
    deadline = next(e for e in effects if isinstance(e, SetTimer) and e.key == Deadline(remap.pid))
    (reply,) = replies(n4.on_timer(deadline.key, deadline.at))
    assert isinstance(reply, m.RemapReply) and not reply.ok
    assert reply.error == "remap did not finish within 2.5 s"


def test_a_client_says_how_long_it_waits_for_a_remap() -> None:
    assert waiting(m.RemapRequest("a", [0]), 10.0).within_s == 10.0
    assert waiting(m.RemapRequest("a", [0], within_s=4.0), 10.0).within_s == 4.0
    for wait in (float("nan"), float("inf"), -1.0, 0.0):  # not said, or nothing sensible
        remap = Remap(1, 0.0, "a", [0], CLIENT, {}, set(), within_s=wait)
        assert remap.deadline == 15.0  # its own: 10 s, 5 s a chain
