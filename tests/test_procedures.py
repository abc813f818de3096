"""Every distributed procedure has explicit states, a transition table and a deadline."""

from __future__ import annotations

import pytest

from mso.protocol import messages as m
from mso.protocol.control_stream import KEEP_S
from mso.protocol.events import PeerRejoined
from mso.protocol.procedures.base import IllegalTransition, Phase, table_rows
from mso.protocol.procedures.deploy import Deploy
from mso.protocol.procedures.instance import H, InstanceEvent
from mso.protocol.procedures.lookup import Lookup
from mso.protocol.procedures.relocation import Relocation, RelocationEvent
from mso.protocol.procedures.remap import Remap, RemapEvent
from mso.protocol.procedures.status import StatusFanout
from mso.sim.runner import Simulation
from test_runtime_sim import PIPE, deploy, line, lose_first, sink_stats


def test_an_event_the_table_does_not_allow_raises() -> None:
    reloc = Relocation(1, 0.0, "app", "v", "N1", "N2", None)
    with pytest.raises(IllegalTransition, match="'moved' is not allowed in state PREPARING"):
        reloc.on(RemapEvent.MOVED)  # another machine's event is in no state of this table
    with pytest.raises(IllegalTransition, match="'handed_over' is not allowed in state PREP"):
        Relocation(3, 0.0, "app", "v", "N1", "N2", None).on(InstanceEvent.HANDED_OVER)
    reloc = Relocation(2, 0.0, "app", "v", "N1", "N2", None)
    reloc.on(RelocationEvent.PREPARED)
    with pytest.raises(IllegalTransition):
        reloc.on(RelocationEvent.PREPARED)  # a second Prepared is a protocol error
    reloc.on(RelocationEvent.HANDED_OVER)
    assert reloc.state is Phase.FINISHED and reloc.done


def test_every_procedure_table_reaches_an_end() -> None:
    for cls in (Relocation, Remap, StatusFanout, Deploy, Lookup):
        ends = {nxt for _, _, nxt in table_rows(cls)}
        assert "FINISHED" in ends, cls.NAME


def test_a_status_fan_out_answers_by_its_deadline_without_a_dead_node() -> None:
    sim = Simulation(line(3))
    sim.kill("N3", convergence_s=60.0)  # routes still point at it: its reply never comes
    sim.request("N1", m.StatusRequest(req=7, everywhere=True), client=9)
    sim.run_until(sim.now + 0.9)
    assert not [r for _, c, r in sim.replies if c == 9]  # still waiting for N3
    sim.run_until(sim.now + 0.2)
    ((_, _, reply),) = [(t, c, r) for t, c, r in sim.replies if c == 9]
    assert isinstance(reply, m.StatusReply) and set(reply.nodes) == {"N1", "N2"}
    assert sim.cores["N1"].open_procedures(sim.now) == []


def test_a_relocation_whose_target_never_answers_fails_at_its_deadline() -> None:
    sim = Simulation(line(4))
    assert deploy(sim, PIPE).ok
    mid = next(n for n, c in sim.cores.items() if "mid" in c.instances("pipe"))
    target = "N3" if mid != "N3" else "N2"
    sim.cores[target].strict = False
    sim.kill(target, convergence_s=60.0)  # its Prepared never comes, no failure is known yet
    for core in sim.cores.values():
        core.liveness.dead_after_s = 1e9  # nor is it detected: only the deadline can end it
    sim.request("N1", m.RelocateRequest("pipe", "mid", target=target), client=5)
    sim.run_until(sim.now + 1.0)
    open_ = sim.cores["N1"].open_procedures(sim.now)
    assert [p["procedure"] for p in open_] == ["relocation"] and not open_[0]["overdue"]
    sim.run_until(sim.now + 5.0)
    ((_, _, reply),) = [(t, c, r) for t, c, r in sim.replies if c == 5]
    assert isinstance(reply, m.RelocateReply) and not reply.ok
    assert "did not finish within 5 s" in reply.error
    assert sim.cores["N1"].open_procedures(sim.now) == []
    assert sim.cores["N1"].status(sim.now)["illegal_transitions"] == 0


def test_the_architecture_page_shows_the_tables_the_code_has() -> None:
    from pathlib import Path

    from mso.protocol.procedures.__main__ import markdown

    page = Path(__file__).resolve().parent.parent / "docs" / "architecture.md"
    assert markdown() in page.read_text()


def test_an_instance_moves_through_its_lifecycle_at_both_hosts() -> None:
    sim = Simulation(line(4))
    assert deploy(sim, PIPE).ok
    old = next(n for n, c in sim.cores.items() if "mid" in c.instances("pipe"))
    leaving = sim.cores[old].instances("pipe")["mid"]
    assert leaving.life.state is H.RUNNING
    target = "N3" if old != "N3" else "N2"
    sim.request("N1", m.RelocateRequest("pipe", "mid", target=target), client=5)
    sim.run_until(sim.now + 1.0)
    ((_, _, reply),) = [(t, c, r) for t, c, r in sim.replies if c == 5]
    assert isinstance(reply, m.RelocateReply) and reply.ok, reply
    assert leaving.life.state is Phase.FINISHED  # handed over, then stopped
    arrived = sim.cores[target].instances("pipe")["mid"]
    assert arrived.life.state is H.RUNNING
    with pytest.raises(IllegalTransition, match="'handover' is not allowed in state RUNNING"):
        arrived.life.on(InstanceEvent.HANDOVER)  # a second handover for a running instance


def moving_mid(dropping: type[m.Message]) -> tuple[Simulation, str, str]:
    """``pipe`` on a line of 4, ``mid`` asked to move one node on (by client 5) with every
    message of type ``dropping`` lost: the simulation, its old host and its target."""
    sim = Simulation(line(4))
    assert deploy(sim, PIPE).ok
    old = next(n for n, c in sim.cores.items() if "mid" in c.instances("pipe"))
    target = "N3" if old != "N3" else "N2"
    sim.drop = lambda node, dst, msg: isinstance(msg, dropping)
    sim.request("N1", m.RelocateRequest("pipe", "mid", target=target), client=5)
    return sim, old, target


def test_a_move_that_fails_before_any_switch_leaves_no_instance_at_its_target() -> None:
    """The coordinator's deadline passes with the target's Prepared lost: the target drops the
    instance it prepared (Unprepare) and the vertex runs on where it was, losing nothing."""
    sim, old, target = moving_mid(dropping=m.Prepared)
    sim.run_until(sim.now + 1.0)
    waiting = sim.cores[target].apps["pipe"].awaiting["mid"]
    assert waiting.life.state is H.AWAITING
    sim.run_until(sim.now + 5.0)
    ((_, _, reply),) = [(t, c, r) for t, c, r in sim.replies if c == 5]
    assert isinstance(reply, m.RelocateReply) and not reply.ok
    assert "mid" not in sim.cores[target].apps["pipe"].awaiting
    assert waiting.life.state is Phase.FAILED
    assert "mid" in sim.cores[old].instances("pipe")
    before = sim.cores[old].instances("pipe")["mid"].processed
    sim.run_until(sim.now + 1.0)
    assert sim.cores[old].instances("pipe")["mid"].processed > before


def test_a_vertex_that_has_seen_no_event_yet_moves() -> None:
    """Right after a deployment a slow source may not have emitted: the old host has no input
    channel to acknowledge, and the move must not trip over that (it left the vertex stuck)."""
    app = PIPE.replace("runtime_vertices:CountingSource", "runtime_vertices:Silent")
    sim = Simulation(line(4))
    assert deploy(sim, app).ok
    old = next(n for n, c in sim.cores.items() if "mid" in c.instances("pipe"))
    target = "N3" if old != "N3" else "N2"
    sim.request("N1", m.RelocateRequest("pipe", "mid", target=target), client=5)
    sim.run_until(sim.now + 1.0)
    ((_, _, reply),) = [(t, c, r) for t, c, r in sim.replies if c == 5]
    assert isinstance(reply, m.RelocateReply) and reply.ok, reply
    assert "mid" in sim.cores[target].instances("pipe")


def test_a_handover_lost_on_the_way_is_sent_again_until_its_target_takes_it() -> None:
    """Once the old instance is freed the handover is the vertex's only copy. Lost once (fault
    seed 274108: the target cut off just after the switch), the old host's control stream
    sends it again within its timeout, well before the move's own resend (2 s); the move ends,
    and the sink has every event once, in order; the old host forgets it once taken."""
    sim, old, target = moving_mid(dropping=m.Handover)
    lost: list[m.Message] = []
    sim.drop = lose_first(m.Handover, lost)
    sim.run_until(sim.now + 1.0)
    assert lost and sim.cores[old].streams.resent >= 1
    handed_over_well(sim, old, target, within_ms=1000.0)


def test_a_handover_its_stream_gave_up_is_sent_again_by_the_old_host() -> None:
    """A stream gives a frame up after ``KEEP_S``; the handover is then still the vertex's only
    copy, so the old host keeps it until the new host says it took it, and sends it again on
    its own backoff (2, 4, 8 s...) until then."""
    sim, old, target = moving_mid(dropping=m.Handover)
    until = sim.now + KEEP_S + 0.5  # every copy the stream sends is lost
    lost: list[m.Message] = []

    def lose_them(node: str, dst: str, msg: m.Message) -> bool:
        if isinstance(msg, m.Handover) and sim.now < until:
            lost.append(msg)
            return True
        return False

    sim.drop = lose_them
    sim.run_until(until)
    assert len(lost) > 3 and not [r for _, c, r in sim.replies if c == 5]  # not ended yet
    sim.run_until(until + 6.0)
    assert sim.cores[old].streams.given_up >= 1
    handed_over_well(sim, old, target)


def handed_over_well(
    sim: Simulation, old: str, target: str, within_ms: float = float("inf")
) -> None:
    ((_, _, reply),) = [(t, c, r) for t, c, r in sim.replies if c == 5]
    assert isinstance(reply, m.RelocateReply) and reply.ok, reply
    assert reply.elapsed_ms < within_ms, reply
    assert "mid" in sim.cores[target].instances("pipe")
    assert sim.cores[old].relocator.kept == {}
    assert sim.cores[target].status(sim.now)["refusals"] == {}
    stats = sink_stats(sim, "pipe", "sink")
    assert stats["out_of_order"] == stats["repeats"] == 0 and stats["count"] == stats["next"] > 0


def test_a_move_whose_target_is_heard_back_restarted_fails_as_on_its_failure() -> None:
    """A committed move's target restarts before the handover and its coordinator hears its
    next incarnation before any failure detector held it failed: its prepared instance went
    with its last process, so the move ends as on a failure, not at its deadline (fault seed
    230733: the remap's coordinator held the app past the quiet phase). A rejoin after a
    healed cut (no restart) leaves the move open."""
    sim, _, target = moving_mid(dropping=m.Handover)
    sim.run_until(sim.now + 0.5)
    core = sim.cores["N1"]
    (reloc,) = [p for p in core.procedures.values() if isinstance(p, Relocation)]
    assert reloc.state.name == "SWITCHING"
    core.relocator.on_peer_rejoined(PeerRejoined(target))  # (a cut healed: it ran on)
    assert reloc.state.name == "SWITCHING" and core.open_procedures(sim.now)
    core.relocator.on_peer_rejoined(PeerRejoined(target, restarted=True))
    assert core.open_procedures(sim.now) == []
