"""Twins a cut left behind: a vertex restored on both sides of a partition, one of whose hosts
reset at the heal. News of the other placement, relayed by a node that missed the reset, must
not make the node still running the vertex place it elsewhere (it ran a vertex its own view put
on a node that ran nothing: fault seed 92622); and the nodes holding that placement, its
instance gone with the reset, take the running host's word even though its version is older.

N1 - N2 - N3, no operator keys, ``pipe`` deployed: src on N1, mid on N2, sink on N3."""

from __future__ import annotations

from mso.model.network import LinkSpec, Network, NodeSpec
from mso.protocol import messages as m
from mso.protocol.effects import Send
from mso.sim.runner import Simulation
from runtime_vertices import pipe_app

APP = pipe_app(50).replace("pinned: N4", "pinned: N3")


def line() -> Simulation:
    """N1 - N2 - N3, nothing deployed."""
    return Simulation(
        Network(
            [NodeSpec("N1"), NodeSpec("N2"), NodeSpec("N3")],
            [LinkSpec("N1", "N2", delay_ms=1.0), LinkSpec("N2", "N3", delay_ms=1.0)],
        )
    )


def overlay() -> Simulation:
    sim = line()
    sim.request("N1", m.DeployRequest(APP, "app.yaml"))
    sim.run_until(1.0)
    assert any(isinstance(r, m.DeployReply) and r.ok for _, _, r in sim.replies)
    assert sim.cores["N2"].apps["pipe"].placed["mid"] == "N2"
    return sim


def test_a_relayed_later_placement_does_not_move_a_vertex_running_here() -> None:
    sim = overlay()
    core = sim.cores["N2"]
    dep = core.apps["pipe"]
    relayed = m.Moved("pipe", "mid", "N3", incarnation=-1, version=2)  # N1 passes it on
    effects = core.receive("N1", relayed, sim.now)
    assert dep.placed["mid"] == "N2" and "mid" in dep.instances  # still ours, still runs
    assert dep.versions["mid"] == 2  # as of the version the others hold
    told = {e.dst: e.said for e in effects if isinstance(e, Send) and isinstance(e.said, m.Moved)}
    assert set(told) == {"N3"}  # the node it names, whose own word settles it
    for word in told.values():
        assert (word.vertex, word.node, word.version) == ("mid", "N2", 2)
        assert word.incarnation == core.incarnation  # the host's own word


def test_the_running_hosts_word_beats_a_vanished_later_placement() -> None:
    sim = overlay()
    core, host = sim.cores["N3"], sim.cores["N2"]
    dep = core.apps["pipe"]
    dep.placed["mid"], dep.versions["mid"] = "N1", 2  # restored on N1 across a cut; N1 reset:
    dep.vanished.add("mid")  # its instance went with that incarnation
    word = m.Moved("pipe", "mid", "N2", incarnation=host.incarnation, version=1)
    core.receive("N2", word, sim.now)
    assert dep.placed["mid"] == "N2" and "mid" not in dep.vanished
    assert dep.versions["mid"] == 2  # not older than the placement it replaced
    dep.placed["mid"] = "N1"  # not vanished: a live later placement, and the old word loses
    core.receive("N2", word, sim.now)
    assert dep.placed["mid"] == "N1"


def test_a_node_that_yields_its_twin_tells_the_members_where_it_runs() -> None:
    """N2 runs mid and hears N3's own word that it runs mid at a later move: N2's instance is
    the twin and yields. The members whose view places mid on N2 (told so at its restore)
    hear from N2 that it runs on N3; unheard, they held it on N2, which runs none, and when
    N3's twin went with a reset at the heal nobody restored it (fault seed 136485)."""
    sim = overlay()
    core = sim.cores["N2"]
    inc = sim.cores["N3"].incarnation
    effects = core.receive("N3", m.Moved("pipe", "mid", "N3", incarnation=inc, version=1), sim.now)
    assert "mid" not in core.apps["pipe"].instances
    told = {e.dst: e.said for e in effects if isinstance(e, Send) and isinstance(e.said, m.Moved)}
    assert set(told) == {"N1"}  # (not N3, whose word it was)
    assert (told["N1"].vertex, told["N1"].node, told["N1"].version) == ("mid", "N3", 1)
    assert told["N1"].incarnation == inc  # the twin's host's word, passed on
    sim.apply("N2", effects)
    sim.run_until(sim.now + 0.05)
    assert sim.cores["N1"].apps["pipe"].placed["mid"] == "N3"


def restarted_n3() -> Simulation:
    """The overlay after N3's daemon restarted (N1 has heard its new incarnation); ``mid``
    runs on N2 at move 1, N1 placing it there."""
    sim = overlay()
    sim.crash("N3")
    sim.run_until(sim.now + 0.5)
    sim.revive("N3")
    sim.run_until(sim.now + 0.5)
    n1 = sim.cores["N1"]
    assert n1.incarnation_of("N3", 0) == 1
    for core in sim.cores.values():
        core.apps["pipe"].versions["mid"] = 1
    assert n1.apps["pipe"].placed["mid"] == "N2" and "mid" not in n1.apps["pipe"].vanished
    return sim


def test_the_yielders_word_of_a_twin_gone_with_a_reset_is_a_loss() -> None:
    """The other order: N1 has heard N3 restart before N2's word that it yielded mid to N3's
    twin (N3's last incarnation) comes. The word names a placement of the version N1 holds
    and an instance gone with N3's reset; from the node N1 places mid on, it is news: mid is
    held lost there and recovered (before, N1 kept mid on N2, which ran none)."""
    sim = restarted_n3()  # (move 1: N2's restore of mid, a twin of N3's)
    n1 = sim.cores["N1"]
    dep = n1.apps["pipe"]
    n1.receive("N2", m.Moved("pipe", "mid", "N3", incarnation=0, version=1), sim.now)
    assert dep.placed["mid"] == "N3" and "mid" in dep.vanished


def test_a_twin_gone_with_a_reset_heard_late_is_checked_with_the_running_host() -> None:
    """N3's last process restored ``mid`` on itself across a cut (move 2) while N2, cut off
    but alive, ran it on (move 1); that word reaches N1 after N3's reset. N1 holds ``mid``
    lost on N3 (news of an instance gone with its node) and asks the nodes its view names:
    N2 says it runs ``mid``, and its own word stands against the later placement gone. Before,
    N1, hosting nothing on ``mid``'s edges, held it lost for good while the others placed it
    on N2 (fault seed 164451)."""
    sim = restarted_n3()
    n1 = sim.cores["N1"]
    dep = n1.apps["pipe"]
    effects = n1.receive("N3", m.Moved("pipe", "mid", "N3", incarnation=0, version=2), sim.now)
    assert dep.placed["mid"] == "N3" and "mid" in dep.vanished
    asked = {e.dst for e in effects if isinstance(e, Send) and isinstance(e.said, m.PlacementQuery)}
    assert "N2" in asked
    assert dep.recovering is None  # N1 coordinates: its recovery waits for the answers
    sim.apply("N1", effects)
    sim.run_until(sim.now + 0.05)
    assert dep.placed["mid"] == "N2" and "mid" not in dep.vanished
    assert dep.versions["mid"] == 2  # (not older than the placement it replaced)


def test_a_move_handed_over_and_gone_with_a_reset_is_recovered_once_asked() -> None:
    """The other case of that news: N2 had handed ``mid`` over to N3 (move 2) and N3's
    instance went with its reset. Asked, N2 says ``mid`` runs on N3: N1, which coordinates,
    recovers it once the answers are in (seed 22392), not before."""
    sim = restarted_n3()
    n1 = sim.cores["N1"]
    dep = n1.apps["pipe"]
    effects = n1.receive("N3", m.Moved("pipe", "mid", "N3", incarnation=0, version=2), sim.now)
    assert dep.recovering is None
    (qid,) = {e.said.qid for e in effects if isinstance(e, Send) and e.dst == "N2"
              and isinstance(e.said, m.PlacementQuery)}  # fmt: skip
    placed = dict(dep.placed) | {"mid": "N3"}
    n1.receive("N2", m.PlacementReply("pipe", qid, placed, {"mid": 2}, ["mid"]), sim.now)
    n1.receive("N3", m.PlacementReply("pipe", qid, placed, {"mid": 2}, ["mid"]), sim.now)
    assert dep.placed["mid"] == "N3" and "mid" in dep.vanished
    assert dep.recovering is not None


def test_a_handover_heard_late_then_told_with_its_hosts_gone_incarnation_is_a_loss() -> None:
    """N2 handed ``mid`` over to N3 (move 2) while N1 was cut off; N3 restarted since and N1
    has heard its new incarnation. Then, at the heal, both of N2's words come, in the order
    sent: its ``Moved`` of the handover (no incarnation: an old host's) — kept and sent
    again by the control stream; before, lost in the cut — then the same move told back with
    the incarnation N3 had (:meth:`_claim_to`). The first placed ``mid`` on N3, alive by
    N1's view; the second, at the version N1 now held, was taken as nothing new, and nobody
    restored ``mid`` (fault seed 24365). It is a loss: ``mid`` vanished, checked with N3
    (whose new incarnation's own word would stand), and recovered once asked."""
    sim = restarted_n3()
    n1 = sim.cores["N1"]
    dep = n1.apps["pipe"]
    n1.receive("N2", m.Moved("pipe", "mid", "N3", incarnation=-1, version=2), sim.now)
    assert dep.placed["mid"] == "N3" and "mid" not in dep.vanished  # (where, not whose)
    effects = n1.receive("N2", m.Moved("pipe", "mid", "N3", incarnation=0, version=2), sim.now)
    assert dep.placed["mid"] == "N3" and "mid" in dep.vanished
    asked = {e.dst: e.said.qid for e in effects
             if isinstance(e, Send) and isinstance(e.said, m.PlacementQuery)}  # fmt: skip
    assert "N3" in asked
    assert dep.recovering is None  # (N1 coordinates: it waits for the answers)
    placed = dict(dep.placed)
    for src, qid in asked.items():
        n1.receive(src, m.PlacementReply("pipe", qid, placed, {"mid": 2}, ["mid"]), sim.now)
    assert dep.placed["mid"] == "N3" and "mid" in dep.vanished
    assert dep.recovering is not None


def test_a_twin_of_that_version_on_the_hosts_new_incarnation_stands_once_asked() -> None:
    """The same late word where N3's new incarnation runs ``mid`` itself at that version (a
    twin restored there): held lost until N3 answers, then N3's own word stands."""
    sim = restarted_n3()
    n1 = sim.cores["N1"]
    dep = n1.apps["pipe"]
    inc = sim.cores["N3"].incarnation
    n1.receive("N3", m.Moved("pipe", "mid", "N3", incarnation=inc, version=2), sim.now)
    assert dep.placed["mid"] == "N3" and "mid" not in dep.vanished
    effects = n1.receive("N2", m.Moved("pipe", "mid", "N3", incarnation=0, version=2), sim.now)
    assert "mid" in dep.vanished and dep.recovering is None
    (qid,) = {e.said.qid for e in effects if isinstance(e, Send) and e.dst == "N3"
              and isinstance(e.said, m.PlacementQuery)}  # fmt: skip
    n1.receive("N3", m.PlacementReply("pipe", qid, dict(dep.placed), {"mid": 2}), sim.now)
    assert dep.placed["mid"] == "N3" and "mid" not in dep.vanished


def test_a_lookup_takes_the_running_hosts_word_over_a_vanished_later_placement() -> None:
    """A lookup's answers, in either order: N2 says ``mid`` runs on N2 (move 1), N3 passes on
    a placement of ``mid`` on N3 at move 2 whose instance vanished. The running host's own
    word stands, as its ``Moved`` would (seed 92622); the answer with the higher version
    outweighed it when it came second, or came first and the own word was older (164451)."""
    for order in (("N2", "N3"), ("N3", "N2")):
        sim = restarted_n3()
        n1 = sim.cores["N1"]
        dep = n1.apps["pipe"]
        n1.lookups.on_stale("pipe", wide=False)
        look = next(p for p in n1.open() if p.name == "lookup")
        look.waiting |= {"N2", "N3"}  # (its queries go out with the core's next effects)
        placed = dict(dep.placed)
        answers = {
            "N2": m.PlacementReply("pipe", look.pid, placed, {"mid": 1}),
            "N3": m.PlacementReply("pipe", look.pid, placed | {"mid": "N3"}, {"mid": 2}, ["mid"]),
        }
        for src in order:
            n1.receive(src, answers[src], sim.now)
        assert dep.placed["mid"] == "N2" and "mid" not in dep.vanished, order
        assert dep.versions["mid"] == 2


def test_a_sync_from_a_hosts_last_incarnation_does_not_undo_a_vanishing() -> None:
    """N2's daemon restarts; N1 hears it back in its new incarnation and holds mid, which N2
    ran, vanished. Then comes a sync N2's last process sent as it went (its own incarnation
    in it, 0), saying it runs mid: first-hand, but of an incarnation gone. Taken, it undid
    the vanishing, and nobody restored mid (fault seed 142461)."""
    sim = overlay()
    sim.crash("N2")
    sim.run_until(sim.now + 0.5)
    sim.revive("N2")
    n1 = sim.cores["N1"]
    dep = n1.apps["pipe"]
    while n1.incarnation_of("N2", 0) != 1 or "mid" not in dep.vanished:
        sim.run_until(sim.now + 0.001)  # (not long enough for the recovery to be done)
    assert dep.placed["mid"] == "N2"
    sync = m.AppSync("pipe", "N1", dep.document, dep.epoch, dict(dep.placed))
    sync.incarnations = {"N1": n1.incarnation, "N2": 0, "N3": 0}
    n1.receive("N2", sync, sim.now)
    assert "mid" in dep.vanished


def test_a_view_passed_on_places_a_vanished_vertex_on_a_twin_of_its_version() -> None:
    """N3 holds mid on N1 at move 1, vanished: restored there across a cut, its instance went
    with N1's reset. N2 restored mid too, on a view that never had N1's (move 1 again), and
    N3, hosting nothing on mid's edges, was not told. A coordinator's view passed on (its
    ``Prepare``) placing mid on N2 at move 1, not vanished, is that restore: N3 takes it.
    Before, only a later move or the host's own word was taken, and N3 kept mid on N1 for
    ever (fault seed 171657). A view placing mid on N1 itself says nothing of that instance:
    mid stays vanished."""
    sim = overlay()
    core = sim.cores["N3"]
    dep = core.apps["pipe"]
    dep.placed["mid"], dep.versions["mid"] = "N1", 1
    dep.vanished.add("mid")
    placed = {"src": "N1", "mid": "N1", "sink": "N3"}

    def prepare(rid: int) -> m.Prepare:
        return m.Prepare("pipe", "sink", rid, True, [], dict(placed), {"mid": 1}, [])

    core.receive("N2", prepare(7), sim.now)  # (the restore of a sink that never went)
    assert dep.placed["mid"] == "N1" and "mid" in dep.vanished
    placed["mid"] = "N2"
    core.receive("N1", prepare(8), sim.now)  # (a coordinator's view: not N2's own word)
    assert dep.placed["mid"] == "N2" and "mid" not in dep.vanished
    assert dep.versions["mid"] == 1


def test_a_coordinators_record_of_a_restore_orders_twins_as_a_moved_does() -> None:
    """N1 coordinates a move of mid to N3; as it ends, N1's view holds a twin of the version
    the target reports (two coordinators restored mid from one view, each on another node),
    on N2, which prevails over N3 (one incarnation, the lower name). The target's
    ``HandoverDone`` is weighed as its ``Moved`` is: N1's view keeps N2. Taken whatever the
    twins, a coordinator that ran the twin that prevailed placed the vertex on the node that
    had yielded it, and its output edge dangled (fault seed 146144)."""
    sim = overlay()
    sim.request("N1", m.RelocateRequest("pipe", "mid", target="N3"))
    n1 = sim.cores["N1"]
    (rid,) = [p.pid for p in n1.open() if p.name == "relocation"]
    dep = n1.apps["pipe"]
    dep.versions["mid"] = 1  # the twin on N2, at the version the target counts
    sim.apply("N1", n1.receive("N3", m.HandoverDone("pipe", "mid", rid, "N3", 1), sim.now))
    assert dep.placed["mid"] == "N2"


CHAIN = """
name: chain
planner: paper
vertices:
  src: {code: runtime_vertices:CountingSource, pinned: N1, rate: 50,
        output: runtime_vertices:Num}
  a: {code: runtime_vertices:Double, pinned: N2, output: runtime_vertices:Num}
  b: {code: runtime_vertices:Double, output: runtime_vertices:Num}
  sink: {code: runtime_vertices:Recorder, pinned: N3}
edges: [[src, a], [a, b], [b, sink]]
"""


def test_a_producer_whose_consumer_here_yields_to_a_twin_asks_where_it_stands() -> None:
    """``a`` feeds ``b`` on its own node, and ``b`` yields to a twin restored across a cut on
    N3: ``a``'s output is numbered as the retired instance took it, not as the twin stands.
    Sent on, the twin dropped what it numbered below its own position as had (fault seed
    142356: 24 events of a restarted source). Its events wait until the twin says where it
    stands (as a producer whose consumer went with its node: ``OutChannel.consumer_lost``)."""
    sim = line()
    sim.request("N1", m.DeployRequest(CHAIN, "app.yaml"))
    sim.run_until(1.0)
    sim.request("N1", m.RelocateRequest("chain", "b", target="N2"))
    sim.run_until(sim.now + 0.5)
    core = sim.cores["N2"]
    dep = core.apps["chain"]
    assert dep.placed["b"] == "N2" and "b" in dep.instances
    out = dep.out[1]  # (a -> b)
    assert not out.unsure
    inc = sim.cores["N3"].incarnation
    word = m.Moved("chain", "b", "N3", incarnation=inc, version=dep.versions["b"] + 1)
    sim.apply("N2", core.receive("N3", word, sim.now))
    assert "b" not in dep.instances and out.unsure
    sent = out.sent
    sim.run_until(sim.now + 0.3)
    assert out.next_seq > sent and out.sent == sent  # held, not sent in the old numbering


def test_a_consumer_below_what_a_retired_twin_took_skips_there_with_its_outputs() -> None:
    """A twin of ``mid`` took events of the source's edge and passed on what it made, all
    acknowledged, then retired; the instance that stayed stands below them. The source, its
    consumer's word in doubt, hears where it stands and says where the edge is acknowledged
    to, with the positions that ack brought; the consumer skips its input there and numbers
    its output from those positions. Numbered on from its own, its next outputs took numbers
    its consumer had from the twin, and were dropped as had (fault seed 183066: 5 events)."""
    sim = overlay()
    sim.run_until(2.0)
    n1, n2 = sim.cores["N1"], sim.cores["N2"]
    out = n1.apps["pipe"].out[0]
    inc, made = n2.apps["pipe"].inc[0], n2.apps["pipe"].out[1]
    at, numbered = inc.expected, made.next_seq
    assert out.acked >= at > 10
    out.positions = {1: numbered + 7}
    out.acked = out.sent = out.positions_at = at + 5  # (as the twin's chained ack left it)
    out.consumer_lost = True
    effects = n1.receive("N2", m.Resume("pipe", 0, 1, False, at), sim.now)
    (said,) = [e.said for e in effects if isinstance(e, Send) and isinstance(e.said, m.Resume)]
    assert said.producer and (said.start, said.positions) == (at + 5, {1: numbered + 7})
    assert not out.consumer_lost
    n2.receive("N1", said, sim.now)
    assert inc.expected == at + 5
    assert n2.apps["pipe"].out[1].next_seq == numbered + 7
