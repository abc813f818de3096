"""A merge's outputs carry the input event they were made from, so a replacement fed a replay
in another interleaving sends its consumer exactly what it lacks (mso.protocol.provenance)."""

from __future__ import annotations

from types import SimpleNamespace
from typing import Any

import msgspec
import pytest

from mso.model.app import Vertex
from mso.protocol import effects as fx
from mso.protocol import messages as m
from mso.protocol import provenance
from mso.protocol.channel import InChannel, OutChannel
from mso.protocol.events import PeerFailed
from mso.protocol.procedures import restore
from mso.protocol.procedures.instance import H
from mso.protocol.state import AppState, Restoring
from mso.runtime.worker import VertexWorker
from mso.sim import faults, vertices
from mso.sim.runner import Simulation
from test_failure import started, where


def test_stamps_name_the_input_event_and_strip_learns_the_last_per_input() -> None:
    # a batch of edge 3 from sequence number 10: event 0 made two outputs, event 2 one
    stamped = provenance.stamp([b"x", b"y", b"z"], 3, 10, [0, 0, 2])
    marks: provenance.Marks = {}
    assert provenance.strip(stamped, marks) == [b"x", b"y", b"z"]
    assert marks == {3: (12, 0)}
    second = provenance.stamp([b"w"], 5, 7, [0])
    provenance.strip(second, marks)
    assert marks == {3: (12, 0), 5: (7, 0)}
    # a payload too short for a header (no genuine node sends one) passes, learns nothing
    assert provenance.strip([b"ab"], marks) == [b"ab"] and marks == {3: (12, 0), 5: (7, 0)}


def test_a_replay_in_another_interleaving_sends_only_what_the_consumer_lacks() -> None:
    # first run: a10, b20, a11 reached the consumer; b21 was made and lost with the merge
    consumer = InChannel(marks={})
    first = [
        provenance.stamp([b"a10"], 0, 10, [0]),
        provenance.stamp([b"b20"], 1, 20, [0]),
        provenance.stamp([b"a11"], 0, 11, [0]),
    ]
    for batch in first:
        provenance.strip(batch, consumer.marks)
    assert consumer.marks == {0: (11, 0), 1: (20, 0)}
    # the replay comes b20, b21, a10, a11, a12: only b21 and a12 are new to the consumer
    replay = [
        provenance.stamp([b"b20", b"b21"], 1, 20, [0, 1]),
        provenance.stamp([b"a10", b"a11", b"a12"], 0, 10, [0, 1, 2]),
    ]
    lacks = [provenance.past(batch, consumer.marks) for batch in replay]
    assert [provenance.strip(b, None) for b in lacks] == [[b"b21"], [b"a12"]]
    # the k-th output of one event: the consumer had the first of two
    two = provenance.stamp([b"p", b"q"], 0, 12, [0, 0])
    assert provenance.strip(provenance.past(two, {0: (12, 0)}), None) == [b"q"]
    wire = provenance.to_wire(consumer.marks)
    assert provenance.from_wire(wire) == consumer.marks and provenance.from_wire(None) is None
    assert provenance.from_wire({0: [1]}) == {}  # malformed: never taken as a mark


def test_a_mark_holds_until_the_first_event_past_it_then_an_input_numbered_anew_passes() -> None:
    # a replacement's consumer had input 0 up to 12 and input 1 up to 20
    marks: provenance.Marks = {0: (12, 0), 1: (20, 0)}
    made = provenance.stamp([b"a12", b"a13"], 0, 12, [0, 1])
    sent = provenance.past(made, marks)
    assert provenance.strip(sent, None) == [b"a13"]
    provenance.outlived(sent, marks)  # a13 went past input 0's mark: it has done its work
    assert marks == {1: (20, 0)}
    # input 0 numbered anew from 0 (its producer restored fresh): nothing of it is dropped
    anew = provenance.stamp([b"n0", b"n1"], 0, 0, [0, 1])
    assert provenance.strip(provenance.past(anew, marks), None) == [b"n0", b"n1"]
    # an event at the mark, or below it, leaves it in place
    provenance.outlived(provenance.stamp([b"b20"], 1, 20, [0]), marks)
    assert marks == {1: (20, 0)}


BENCH = faults.Settings(start_s=1.0, faults_s=3.0, quiet_s=4.0, rate=10.0, restarts=False)


@pytest.mark.parametrize("seed", [1964, 3859, 5490, 8895, 9916])
def test_a_merge_restored_after_its_node_restarts_delivers_each_event_once(seed: int) -> None:
    """Fault schedules where the merge's node dies unseen (out of reach, or back before its
    window) and the merge is restored in place: its replay interleaves the two inputs as it
    happens to, and numbered from the producers' acks the sink got one event twice."""
    result = faults.run(seed, BENCH)
    assert not result.violations, "\n".join(map(str, result.violations))


class Num(msgspec.Struct, frozen=True):
    n: int


def fan(e: Num) -> Any:
    """0: nothing; 1: one output; 2: two; 3: one that cannot be encoded, then a good one."""
    return [None, Num(e.n), [Num(e.n), Num(e.n)], [object(), Num(e.n)]][e.n % 4]


def test_a_forwarder_passes_on_the_merge_inputs_provenance_with_its_own_count() -> None:
    merged = provenance.stamp([b"a", b"b"], 3, 10, [0, 1])  # the merge: edge 3, events 10, 11
    payloads, heads = provenance.split(merged)
    assert payloads == [b"a", b"b"] and heads == [(3, 10, 0), (3, 11, 0)]
    # the forwarder made two outputs of the first event, none of the second, one more
    out = provenance.forward([b"x", b"y"], heads, [0, 0])
    marks: provenance.Marks = {}
    assert provenance.strip(out, marks) == [b"x", b"y"]
    assert marks == {3: (10, 1)}  # (the merge's k 0, the forwarder's second output)
    assert provenance.past(out, {3: (10, 0)}) == out[1:]
    # headers missing for the batch (never expected): stamped as headerless, no exception
    assert provenance.split(provenance.forward([b"z"], [], [0]))[1] == [(0xFFFF, -1, 0)]


def test_a_forwarders_replacement_takes_what_its_consumer_saw_first_then_the_rest() -> None:
    catch_up = provenance.CatchUp({0: (5, 0), 1: (3, 0)}, now=0.0, edge=4)
    a5, a6, b2, b3, b4 = (
        provenance.stamp([x], e, s, [0])[0]
        for x, e, s in ((b"a5", 0, 5), (b"a6", 0, 6), (b"b2", 1, 2), (b"b3", 1, 3), (b"b4", 1, 4))
    )
    # the replay interleaves differently: a6 is past its mark, so it waits for b's mark
    assert catch_up.take([a5, a6, b2], now=0.1) == [a5, b2]
    assert not catch_up.done
    assert catch_up.take([b3, b4], now=0.2) == [b3, a6, b4]
    assert catch_up.done and catch_up.take([a5], now=0.3) == [a5]


def test_a_catch_up_whose_input_never_comes_lets_what_it_holds_go_at_its_deadline() -> None:
    catch_up = provenance.CatchUp({0: (5, 0), 1: (3, 0)}, now=0.0, edge=4)
    a6 = provenance.stamp([b"a6"], 0, 6, [0])[0]
    assert catch_up.take([a6], now=0.1) == [] and catch_up.due(provenance.CATCH_UP_S + 0.2)
    assert catch_up.release() == [a6] and catch_up.done


def test_a_snapshots_marks_stop_before_what_was_delivered_and_not_processed() -> None:
    later = [provenance.stamp([b"x"], 0, 7, [0])[0], provenance.stamp([b"y"], 1, 4, [0])[0]]
    later.append(provenance.stamp([b"z", b"w"], 1, 4, [0, 0])[1])  # (4, 1): not the first
    marks = {0: (9, 0), 1: (4, 1), 2: (1, 0)}
    assert provenance.processed(marks, later) == {0: (6, 0xFFFFFFFF), 1: (3, 0xFFFFFFFF), 2: (1, 0)}
    assert provenance.processed(None, later) is None


def test_a_merges_worker_says_which_event_of_the_batch_each_output_came_from() -> None:
    v = Vertex(id="m", code=fan)
    start = fx.StartVertex(
        1, "app", v, "operator", inputs={0: Num, 1: Num}, outputs={2: Num}, owners=True
    )
    worker = VertexWorker(start)
    assert worker.open().error == ""
    batch = [msgspec.msgpack.encode(Num(n)) for n in (0, 1, 2, 3, 5)]
    res = worker.feed(fx.FeedVertex(1, 0, batch, 0.0))
    assert [msgspec.msgpack.decode(p, type=Num).n for p in res.outputs] == [1, 2, 2, 3, 5]
    assert res.owners == [1, 2, 2, 3, 4] and res.errors == 1
    # a vertex whose outputs carry no provenance: nothing is tracked on its hot path
    one = VertexWorker(fx.StartVertex(2, "app", v, "operator", inputs={0: Num}))
    assert one.open().error == "" and one.feed(fx.FeedVertex(2, 0, batch, 0.0)).owners == []


MERGE = """
name: merge
planner: paper
vertices:
  s1: {code: mso.sim.vertices:Source, params: {name: s1}, rate: 20, pinned: N1,
       output: mso.sim.vertices:Ev}
  s2: {code: mso.sim.vertices:Source, params: {name: s2}, rate: 20, pinned: N2,
       output: mso.sim.vertices:Ev}
  m: {code: mso.sim.vertices:Pass, pinned: N3, output: mso.sim.vertices:Ev}
  c: {code: mso.sim.vertices:Pass, output: mso.sim.vertices:Ev}
  sink: {code: mso.sim.vertices:Sink, params: {run: provenance-moved, name: sink}, pinned: N6}
edges: [[s1, m], [s2, m], [m, c], [c, sink]]
"""


def test_a_moved_consumer_keeps_its_marks_for_the_merges_restore() -> None:
    """The merge's consumer moves (its marks go in the handover), then the merge's daemon
    crashes and restarts with its router up: the merge is restored in place from its
    producers' replays, in whatever interleaving, and the sink gets each event once."""
    vertices.RUNS.pop("provenance-moved", None)
    sim = started(MERGE)
    before = where(sim, "merge", "c")
    target = next(n for n in ("N4", "N5", "N6") if n != before)
    sim.request("N1", m.RelocateRequest("merge", "c", target=target))
    sim.run_until(sim.now + 1.0)
    assert where(sim, "merge", "c") == target
    marks = sim.cores[target].apps["merge"].inc[2].marks
    assert marks is not None and set(marks) == {0, 1}, marks  # (moved with c)
    sim.crash("N3")
    sim.run_until(sim.now + 0.3)
    sim.revive("N3")
    sim.run_until(sim.now + 4.0)
    (record,) = vertices.RUNS["provenance-moved"]
    assert {src for src, _ in record.streams} == {"s1", "s2"}
    for s in record.streams.values():
        assert s.duplicates == 0 and s.reordered == 0 and s.last - s.first + 1 == len(s.seen)
        assert s.last >= 80  # it went on after the restore


FORK = """
name: fork
planner: paper
vertices:
  s: {code: mso.sim.vertices:Source, params: {name: s}, rate: 20, pinned: N1,
      output: mso.sim.vertices:Ev}
  j: {code: mso.sim.vertices:Pass, pinned: N3, output: mso.sim.vertices:Ev}
  b: {code: mso.sim.vertices:Pass, pinned: N4, output: mso.sim.vertices:Ev}
  c: {code: mso.sim.vertices:Pass, pinned: N2, output: mso.sim.vertices:Ev}
  k1: {code: mso.sim.vertices:Sink, params: {run: provenance-fork, name: k1}, pinned: N5}
  k2: {code: mso.sim.vertices:Sink, params: {run: provenance-fork, name: k2}, pinned: N6}
edges: [[s, j], [j, b], [b, k1], [j, c], [c, k2]]
"""


def test_a_forks_consumers_each_keep_what_they_have_in_the_inputs_terms() -> None:
    """A fork's two consumers can hold outputs of different lost instances numbered alike
    (seed 5040): each keeps the marks of what it has in the fork's input's numbering, so the
    fork's replacement sends each only what it lacks. Here the fork's daemon crashes and
    restarts: it is restored in place, and each sink gets each event once."""
    vertices.RUNS.pop("provenance-fork", None)
    sim = started(FORK)
    for edge in (1, 3):  # j -> b, j -> c: marks of the input s -> j (edge 0)
        consumer = sim.cores[where(sim, "fork", "b" if edge == 1 else "c")]
        marks = consumer.apps["fork"].inc[edge].marks
        assert marks is not None and set(marks) == {0}, marks
    sim.crash("N3")
    sim.run_until(sim.now + 0.3)
    sim.revive("N3")
    sim.run_until(sim.now + 4.0)
    records = vertices.RUNS["provenance-fork"]
    assert len(records) == 2
    for record in records:
        (s,) = record.streams.values()
        assert s.duplicates == 0 and s.reordered == 0 and s.last - s.first + 1 == len(s.seen)
        assert s.last >= 80  # it went on after the restore


def test_a_replacement_moved_before_it_passed_its_consumers_marks_hands_them_over() -> None:
    """A forwarder's replacement sends its consumer only what was made past the consumer's
    marks; moved before it made anything past them (its replay not come yet), its new host
    must hold them too, or it sends on what the consumer has (seed 96201: 22 events twice)."""
    vertices.RUNS.pop("provenance-moved", None)
    sim = started(MERGE)
    before = where(sim, "merge", "c")
    far = {0: (10**6, 0), 1: (10**6, 0)}  # a consumer that has everything up to far ahead
    sim.cores[before].apps["merge"].marks["c"] = {3: dict(far)}  # (edge 3: c -> sink)
    target = next(n for n in ("N4", "N5", "N6") if n != before)
    sim.request("N1", m.RelocateRequest("merge", "c", target=target))
    sim.run_until(sim.now + 0.5)
    assert where(sim, "merge", "c") == target
    assert sim.cores[target].apps["merge"].marks.get("c") == {3: far}
    (record,) = vertices.RUNS["provenance-moved"]
    had = sum(len(s.seen) for s in record.streams.values())
    sim.run_until(sim.now + 1.0)  # what it makes now is below the marks: none sent on
    assert sum(len(s.seen) for s in record.streams.values()) == had


def test_an_input_started_past_the_marks_takes_a_producer_that_numbers_anew() -> None:
    """A fork's replacement starts an input whose producer was lost too past its consumers'
    marks; a producer restored first, by another coordinator, numbers the edge anew (a
    guess, ``Resume.fresh``) and says so after the fork runs. Its events are new: the input
    starts where it says, and the marks of that input (another numbering) are dropped. Kept
    past the marks, the fork dropped a restarted source's first 39 events (seed 102439)."""
    sim = started(FORK)
    node = where(sim, "fork", "j")
    core = sim.cores[node]
    dep = core.apps["fork"]
    old = dep.inc[0]
    dep.inc[0] = InChannel.starting_at(old.expected + 50, True, {})  # past the marks
    dep.inc[0].past_marks = dep.inc[0].expected
    dep.marks["j"] = {1: {0: (old.expected + 49, 0)}, 3: {0: (old.expected + 49, 0)}}
    resume = m.Resume("fork", 0, 1234, True, old.expected)
    resume.fresh = True
    sim.apply(node, core.receive(where(sim, "fork", "s"), resume, sim.now))
    assert dep.inc[0].expected == old.expected
    assert dep.marks["j"] == {1: {}, 3: {}} and dep.renumbered["j"] == {0}
    # a producer whose numbering is known (not fresh) leaves the input where it was started
    dep.inc[0] = InChannel.starting_at(old.expected + 50, True, {})
    dep.inc[0].past_marks = dep.inc[0].expected
    resume.fresh = False
    sim.apply(node, core.receive(where(sim, "fork", "s"), resume, sim.now))
    assert dep.inc[0].expected == old.expected + 50


def test_an_input_started_past_the_marks_takes_a_producer_of_another_generation() -> None:
    """A merge's replacement starts an input whose producer was lost too past its consumers'
    marks; the producer's replacement numbers the edge from positions its source kept, of a
    numbering the other side of a cut made anew (another generation), and says where it
    starts below the marks. Its events are new: the input starts there, and the marks of that
    input are dropped, the forwarder's too. Kept past the marks, the merge dropped a restored
    source's first 7 events as had (seed 105902). A producer of the marks' own generation
    makes again what lies below them: the input stays where it was started."""
    sim = started(MERGE)
    node, fwd = where(sim, "merge", "m"), where(sim, "merge", "c")
    core, dep = sim.cores[node], sim.cores[node].apps["merge"]
    old = dep.inc[0]

    def past_the_marks() -> None:
        dep.inc[0] = InChannel.starting_at(old.expected + 50, True, {})
        dep.inc[0].past_marks = dep.inc[0].expected
        far = (10**6, 0)  # (input 1: far ahead, so that it holds through the run)
        sim.cores[fwd].apps["merge"].marks["c"] = {3: {0: (old.expected + 49, 0), 1: far}}

    past_the_marks()
    resume = m.Resume("merge", 0, 1234, True, old.expected)  # not fresh: from positions
    resume.gen = 77  # of a numbering made anew elsewhere
    sim.apply(node, core.receive(where(sim, "merge", "s1"), resume, sim.now))
    assert dep.inc[0].expected == old.expected and dep.inc[0].gen == 77
    assert dep.renumbered["m"] == {0}
    sim.run_until(sim.now + 0.05)  # the forwarder is told, and drops its marks of input 0
    assert sim.cores[fwd].apps["merge"].marks["c"] == {3: {1: (10**6, 0)}}
    # of the marks' generation (the deployment's, 0): what lies below them is had
    past_the_marks()
    resume.gen = 0
    sim.apply(node, core.receive(where(sim, "merge", "s1"), resume, sim.now))
    assert dep.inc[0].expected == old.expected + 50


def test_marks_name_the_generation_of_the_numbering_they_are_of() -> None:
    """A merge's frames say the generations of its inputs' numberings (``Data.gens``), its
    forwarder's frames pass them on: each consumer knows what its marks are of, says so with
    them (``Resume.markgens``), and a replacement started past them takes that generation,
    so that a producer numbering from positions of it makes again what lies below them."""
    sim = started(MERGE)
    node = where(sim, "merge", "m")
    dep = sim.cores[node].apps["merge"]
    dep.inc[0].gen = 55  # (as a restore that took a numbering made anew would have it)
    sim.run_until(sim.now + 0.5)
    c = sim.cores[where(sim, "merge", "c")].apps["merge"]
    sink = sim.cores[where(sim, "merge", "sink")].apps["merge"]
    assert c.inc[2].markgens == {0: 55} and sink.inc[3].markgens == {0: 55}
    # started past marks of generation 55, the input takes a producer of 55 as the marks'
    old = dep.inc.pop(0)
    mark = old.expected + 49
    sim.cores[node].restorer._start_past(dep, "m", {0: (mark, 0)}, set(), {0: 55})
    assert dep.inc[0].gen == 55 and dep.inc[0].expected == mark + 1
    resume = m.Resume("merge", 0, 1234, True, old.expected, gen=55)
    sim.apply(node, sim.cores[node].receive(where(sim, "merge", "s1"), resume, sim.now))
    assert dep.inc[0].expected == mark + 1  # below the marks: had


def test_a_merge_whose_consumer_went_with_its_node_asks_where_it_stands_first() -> None:
    """The merge's consumer went with its node (as the merge's node hears it) and was restored
    by a restore that resumed a twin of the merge across a cut: it stands in the twin's
    numbering (here 50 past this merge's), with what it has in the inputs' terms. Sent on in
    its own numbering, the merge's next 50 events were dropped as had (seed 118461: two of a
    source's events). It holds them, asks the consumer, and sends what it lacks from there."""
    vertices.RUNS.pop("provenance-moved", None)
    sim = started(MERGE)
    node = where(sim, "merge", "c")
    core, dep = sim.cores["N3"], sim.cores["N3"].apps["merge"]
    core.publish(PeerFailed(node))
    assert dep.out[2].consumer_lost
    consumer = sim.cores[node].apps["merge"]
    inc = consumer.inc[2]
    consumer.inc[2] = InChannel.starting_at(inc.expected + 50, True, dict(inc.marks or {}))
    sim.run_until(sim.now + 2.0)
    assert not dep.out[2].consumer_lost
    (record,) = vertices.RUNS["provenance-moved"]
    for s in record.streams.values():
        assert s.duplicates == 0 and s.last - s.first + 1 == len(s.seen), s
        assert s.last >= 70  # it went on


def test_a_merges_replacement_its_consumer_did_not_resume_asks_where_it_stands_first() -> None:
    """The merge is restored in place resumed by its producers only (its consumer out of
    reach of the restore, as the coordinator holds it). ``s1``'s last ack said where the
    output stood when the lost instance had taken ``s1`` so far: 5 below where ``c`` stands
    (``s2``'s events took the numbers between). Numbered from there, the merge's next events
    took numbers ``c`` had and were dropped as had (fault seed 353984: a's replay's first
    event). The output waits until ``c``, asked, says where it stands and what it has."""
    vertices.RUNS.pop("provenance-moved", None)
    sim = started(MERGE)
    node = where(sim, "merge", "m")
    dep = sim.cores[node].apps["merge"]
    s1 = where(sim, "merge", "s1")
    out = sim.cores[s1].apps["merge"].out[0]
    out.positions = {o: p - 5 for o, p in out.positions.items()}
    h = dep.instances.pop("m")  # its replacement, here: s2's input resumed, s1's to come
    h.life.state, h.processed = H.AWAITING, 0
    dep.awaiting["m"] = h
    del dep.inc[0]
    dep.restoring["m"] = Restoring(99, node, {(0, True)}, resumed={1}, fetched=True)
    rewire = m.Rewire("merge", 0, node, 99, True)
    sim.apply(s1, sim.cores[s1].receive(node, rewire, sim.now))
    sim.run_until(sim.now + 2.0)
    assert "m" in dep.instances and not dep.out[2].consumer_lost
    (record,) = vertices.RUNS["provenance-moved"]
    for s in record.streams.values():
        assert s.duplicates == 0 and s.missing == 0 and s.first == 0, s
        assert s.last >= 70  # it went on


def test_a_replacement_keeps_its_consumers_marks_of_the_numbering_they_name() -> None:
    """A producer that numbers a fork's input anew says so (``Resume.fresh``) until an ack
    comes; a replacement of the fork lost before it acknowledged anything had taken that
    numbering, and its consumer's marks name it (their generation): the next replacement keeps
    them, and sends on only what is past them (fault seed 200428: set aside as of a numbering
    gone, 9 events reached the sink again). Marks of another numbering go, as before."""
    dep = SimpleNamespace(inc={1: InChannel.starting_at(0, True, {}, gen=7)})
    r = Restoring(1, "N1", set(), fresh={1}, consumer_marks={4: {1: (8, 0)}})
    r.consumer_markgens[4] = {1: 7}  # the numbering the producer says it makes
    assert restore._anew(dep, r, 4) == set()  # type: ignore[arg-type]
    r.consumer_markgens[4] = {1: 3}  # another numbering's
    assert restore._anew(dep, r, 4) == {1}  # type: ignore[arg-type]
    r.consumer_markgens[4] = {}  # the deployment's
    assert restore._anew(dep, r, 4) == {1}  # type: ignore[arg-type]


def test_a_forwarders_snapshot_keeps_the_generations_of_its_marks() -> None:
    """A forwarder's replica holds what it had of the merge's inputs (``Replicate.marks``)
    and the generations of those numberings (``Replicate.markgens``): restored from it, the
    forwarder tells a later merge restore which numbering its marks are of."""
    sim = started(
        MERGE.replace("c: {code: mso.sim.vertices:Pass,", "c: {code: mso.sim.vertices:Count,")
    )
    dep = sim.cores[where(sim, "merge", "m")].apps["merge"]
    dep.inc[0].gen = 55  # (as a restore that took a numbering made anew would have it)
    sim.run_until(sim.now + 1.5)
    held = [
        snap
        for core in sim.cores.values()
        if (app := core.apps.get("merge")) is not None and (snap := app.held.get("c"))
    ]
    assert held and all(s.markgens == {0: 55} for s in held), [s.markgens for s in held]


def test_marks_held_by_generation_drop_only_what_their_own_numbering_had() -> None:
    """A consumer's marks held with the generation they name: an event of that numbering at
    or below the mark is had; one of another numbering is new, and leaves the mark in place
    (the input may come back to it: seed 150917); an event of its own numbering past the
    mark lets it go."""
    held = provenance.held({0: (12, 0), 1: (20, 0)}, {1: 9})
    assert held == {0: ((12, 0), 0), 1: ((20, 0), 9)}
    made = provenance.stamp([b"a11", b"a12"], 0, 11, [0, 1])
    assert provenance.past_held(made, held, {0: 55}) == made  # another numbering: new
    assert held[0] == ((12, 0), 0)
    assert provenance.past_held(made, held, {}) == []  # its own: had, the mark stays
    assert held[0] == ((12, 0), 0)
    later = provenance.stamp([b"a12", b"a13"], 0, 12, [0, 1])
    assert provenance.strip(provenance.past_held(later, held, {1: 9}), None) == [b"a13"]
    assert held == {1: ((20, 0), 9)}  # went past: what follows is past it too


def s1_numbered_anew_past_marks(
    aside: dict[int, dict[int, tuple[tuple[int, int], int]]],
    marks: dict[int, dict[int, tuple[int, int]]] | None = None,
) -> AppState:
    """``merge`` running, its forwarder ``c`` holding the sink's ``marks`` and ``aside`` (far
    past everything): nothing is sent on while both inputs keep the marks' numbering; then
    ``s1``'s input is numbered anew and its new events pass, ``s2``'s do not. The forwarder's
    app state, to look at its marks after."""
    vertices.RUNS.pop("provenance-moved", None)
    sim = started(MERGE)
    fwd = sim.cores[where(sim, "merge", "c")].apps["merge"]
    if marks is not None:
        fwd.marks["c"] = marks
    fwd.aside["c"] = aside
    (record,) = vertices.RUNS["provenance-moved"]

    def seen() -> dict[str, int]:
        return {key[0]: len(s.seen) for key, s in record.streams.items()}

    sim.run_until(sim.now + 0.05)
    had = seen()
    sim.run_until(sim.now + 1.0)  # both inputs in the marks' numbering: nothing sent on
    assert seen() == had
    sim.cores[where(sim, "merge", "m")].apps["merge"].inc[0].gen = 55  # s1's numbered anew
    sim.run_until(sim.now + 1.0)
    now = seen()
    assert now["s1"] > had["s1"] and now["s2"] == had["s2"]
    return fwd


def test_a_forwarder_holds_its_consumers_marks_by_the_generation_they_name() -> None:
    """A forwarder's replacement let its consumer's marks of an input go as of a numbering
    gone (the merge's producer numbered it on a guess); held aside with their generation,
    they still drop what the input makes in their own numbering once it comes back to it
    (an anchor to a producer's carried positions: fault seed 150917, an event of each source
    twice at the sink), and let pass what another numbering makes."""
    far = ((10**6, 0), 0)  # the sink had everything of both inputs, of the deployment's
    fwd = s1_numbered_anew_past_marks(aside={3: {0: far, 1: far}})
    assert fwd.aside["c"] == {3: {0: far, 1: far}}  # (held: the input may come back)


def test_a_forwarders_marks_of_an_input_numbered_anew_since_let_its_new_events_pass() -> None:
    """A forwarder's replacement holds its consumer's marks of the deployment's numbering (as
    it passes on only what its consumer lacks, and aside by generation). The merge, restored
    after it with a producer that was lost too, numbers that input anew and says so only in
    its frames (``Data.gens``): the marks of that input name a numbering gone and drop
    nothing of the new one; the other input's still do (fault seed 277659: the sink's marks
    dropped a restarted source's first 12 events as had)."""
    far = (10**6, 0)  # the sink had everything of both inputs, of the deployment's numbering
    fwd = s1_numbered_anew_past_marks(
        marks={3: {0: far, 1: far}}, aside={3: {0: (far, 0), 1: (far, 0)}}
    )
    assert fwd.marks["c"] == {3: {1: far}}  # (input 1's still holds)
    assert fwd.aside["c"] == {3: {0: (far, 0), 1: (far, 0)}}  # (the input may come back)


def test_a_merge_takes_an_input_it_has_taken_nothing_of_in_its_producers_numbering() -> None:
    """A merge that has processed one input's events keeps its output's numbering when the
    other input's producer says where its numbering stands (an anchor: refused), but takes
    that input, of which it has taken nothing, in the producer's numbering: its frames say
    each input's generation, and kept in the old one they named the producer's guess while
    the events were numbered as the sink's marks were (seed 150917: an event twice)."""
    sim = started(MERGE)
    node = where(sim, "merge", "m")
    core, dep = sim.cores[node], sim.cores[node].apps["merge"]
    assert dep.instances["m"].processed
    start = dep.inc[1].expected
    dep.inc[1] = InChannel.starting_at(0, True, None, gen=55)  # a guess, nothing taken
    resume = m.Resume("merge", 1, 1234, True, start)  # (the deployment's numbering)
    sim.apply(node, core.receive(where(sim, "merge", "s2"), resume, sim.now))
    assert dep.inc[1].gen == 0 and dep.inc[1].expected == start
    taken = dep.inc[1] = InChannel.starting_at(0, True, None, gen=55)
    taken.accept(0, [b"x"])  # something of it taken: it stays in its numbering
    sim.apply(node, core.receive(where(sim, "merge", "s2"), resume, sim.now))
    assert dep.inc[1] is taken and taken.gen == 55


def test_a_forks_marks_let_go_for_an_input_numbered_anew_hold_when_it_comes_back() -> None:
    """A fork restored while its producer numbered its input anew (``Resume.fresh``: a state
    restarted, a guess) lets its consumers' marks of that input go as of a numbering gone.
    The producer then anchors to its own restored source, whose edge came back in the marks'
    numbering, and says where the input starts there: held aside by generation, the marks
    still drop what lies at or below them (fault seed 137164: the fork's output to one
    consumer kept its numbering from where that consumer stood, and the event at its mark
    reached the sink twice). Here the consumers had the next 4 events already."""
    vertices.RUNS.pop("provenance-fork", None)
    sim = started(FORK)
    node = where(sim, "fork", "j")
    core, dep = sim.cores[node], sim.cores[node].apps["fork"]
    start = dep.inc[0].expected  # the source's next event
    marks = {o: {0: (start + 3, 0)} for o in (1, 3)}  # of the deployment's numbering
    starts = {o: dep.out[o].next_seq for o in (1, 3)}
    h = dep.instances.pop("j")  # its replacement: the producer numbers its input anew
    h.life.state, h.processed = H.AWAITING, 0
    dep.awaiting["j"] = h
    dep.inc[0] = InChannel.starting_at(0, True, None, gen=7)
    dep.restoring["j"] = Restoring(
        99, "N1", set(), fresh={0}, resumed={0}, consumer_start=starts, fetched=True,
        consumer_marks=marks, consumer_markgens={1: {}, 3: {}},
    )  # fmt: skip
    core.restorer.activate(dep, "j")
    assert dep.marks["j"] == {1: {}, 3: {}} and dep.renumbered["j"] == {0}  # let go
    resume = m.Resume("fork", 0, 1234, True, start, dict(starts))  # the anchor, numbering 0
    sim.apply(node, core.receive(where(sim, "fork", "s"), resume, sim.now))
    assert dep.inc[0].expected == start and dep.inc[0].gen == 0
    sim.run_until(sim.now + 1.0)
    records = vertices.RUNS["provenance-fork"]
    assert len(records) == 2
    for record in records:
        (s,) = record.streams.values()
        assert s.duplicates == 0 and s.last > start + 4
        assert not s.seen & set(range(start, start + 4))  # had: not sent again
        assert set(range(start + 4, s.last + 1)) <= s.seen


def test_a_fork_started_past_one_consumers_marks_takes_a_start_below_with_no_positions() -> None:
    """A fork restored while its producer was lost too starts its input past the marks of the
    consumer that said where it stands (``unheld``); its other consumer, lost too, gets an
    output numbered on a guess. The producer's replacement numbers from below the marks and
    knows no positions further down: the fork takes its start all the same, keeps both
    outputs (the marked one sends only what its consumer lacks, the guess is new to its
    consumer), and the replay below the marks reaches the other consumer. Asked for every
    output's position, it refused, and the events below the marks never reached that
    consumer (fault seed 340535: 6). An output neither marked nor a guess still needs its
    position."""
    sim = started(FORK)
    node = where(sim, "fork", "j")
    core, dep = sim.cores[node], sim.cores[node].apps["fork"]
    start = dep.inc.pop(0).expected  # the source's next event: its producer lost too
    h = dep.instances.pop("j")  # its replacement
    h.life.state, h.processed = H.AWAITING, 0
    dep.awaiting["j"] = h
    dep.restoring["j"] = Restoring(
        99, "N1", set(), consumer_start={1: dep.out[1].next_seq}, fetched=True,
        consumer_marks={1: {0: (start + 5, 0)}}, consumer_markgens={1: {}},
    )  # fmt: skip
    core.restorer.activate(dep, "j")
    inc, marked, guess = dep.inc[0], dep.out[1], dep.out[3]
    assert inc.unheld and inc.expected == start + 6 and guess.guessed
    resume = m.Resume("fork", 0, 1234, True, start)  # from positions, none further down
    guess.guessed = False  # (as if numbered from somewhere: its position is needed)
    sim.apply(node, core.receive(where(sim, "fork", "s"), resume, sim.now))
    assert dep.inc[0] is inc and inc.expected == start + 6
    guess.guessed = True
    sim.apply(node, core.receive(where(sim, "fork", "s"), resume, sim.now))
    assert dep.inc[0].expected == start and not dep.inc[0].unheld
    assert dep.out[1] is marked and dep.out[3] is guess


def test_a_consumer_that_did_not_take_a_guessed_numbering_says_where_it_stands() -> None:
    """A fork's output was numbered on a guess from 0 (another generation), and a restore's
    rewire confirmed the guess; its consumer, running (another coordinator had restored it
    first), stands further on in the first numbering and refuses the producer's Resume. It
    answers where it stands, and the fork sends what it makes from there: without the answer
    the consumer dropped the guess's events below its position as had (restart seed 138982:
    12 of a restored source's first events never reached the sink)."""
    vertices.RUNS.pop("provenance-fork", None)
    sim = started(FORK)
    node, consumer = where(sim, "fork", "j"), where(sim, "fork", "c")
    core, dep = sim.cores[node], sim.cores[node].apps["fork"]
    at = sim.cores[consumer].apps["fork"].inc[3].expected
    assert at > 10
    guess = core.restorer.dp.channel(dep, 3, 0)  # (j -> c: numbered anew, from 0)
    guess.guessed, guess.gen = True, 99
    dep.out[3] = guess
    rewire = m.Rewire("fork", 3, consumer, 1234, True)  # a restore's, as of c restored there
    (record,) = [r for r in vertices.RUNS["provenance-fork"] if r.vertex == "k2"]
    (s,) = record.streams.values()
    before = s.last
    sim.apply(node, core.receive(node, rewire, sim.now))
    sim.run_until(sim.now + 3.0)  # (past where the consumer stood, at 20 events a second)
    assert dep.out[3].gen == 0 and dep.out[3].next_seq > at  # (the consumer's numbering)
    assert s.duplicates == 0 and s.last - s.first + 1 == len(s.seen), s
    assert s.last >= before + 40  # it went on


def rewire_answer(sim: Simulation, node: str, rewire: m.Rewire) -> m.Resume:
    """The ``Resume`` ``node`` answers a restore's ``rewire`` with (sent to its other end)."""
    effects = sim.cores[node].receive(node, rewire, sim.now)
    sent = [e.said for e in effects if isinstance(e, fx.Send) and e.dst == rewire.to]
    (said,) = [r for r in sent if isinstance(r, m.Resume)]
    assert said.producer == rewire.producer
    return said


def test_a_merge_that_holds_no_channel_of_an_input_answers_in_a_numbering_made_anew() -> None:
    """A running merge's replacement resumed only its other input (this one's producer was
    lost too, and no marks named it then); the producer's replacement asks where it stands.
    It stands nowhere: its answer, 0, is of a generation of its own, and the input counts as
    numbered anew, so marks its consumers hold of the lost producer's numbering do not drop
    the new events as had (fault seed 179893: 21 of a restarted source's events, dropped by
    the merge's forwarder by the sink's marks of the first numbering)."""
    sim = started(MERGE)
    node, s1 = where(sim, "merge", "m"), where(sim, "merge", "s1")
    dep = sim.cores[node].apps["merge"]

    def answer() -> m.Resume:
        return rewire_answer(sim, node, m.Rewire("merge", 0, s1, 1234, False))

    held = dep.inc[0].expected
    kept = answer()  # a channel it holds: where it stands, in the numbering it took
    assert (kept.start, kept.gen) == (held, 0) and "m" not in dep.renumbered
    del dep.inc[0]
    anew = answer()
    assert anew.start == 0 and anew.gen != 0
    assert dep.inc[0].gen == anew.gen and dep.inc[0].expected == 0
    assert dep.renumbered["m"] == {0}


def test_a_producers_replacement_not_running_answers_a_rewire_in_a_numbering_made_anew() -> None:
    """A producer's replacement not running yet holds no channel of its output (its node
    reset); the restore of its consumer, by another coordinator that held the producer alive,
    asks it where the edge stands. It stands nowhere, and what it will make is numbered anew:
    its answer is of a generation of its own, said ``fresh``, and it makes no channel for it
    (its activation makes its own). Said from a channel made for the answer, at 0 in the
    deployment's numbering, the merge's replacement kept its consumer's marks of that input
    and dropped a restarted source's first 33 events as had (fault seed 363254)."""
    vertices.RUNS.pop("provenance-fork", None)
    sim = started(FORK)
    node, sink = where(sim, "fork", "c"), where(sim, "fork", "k2")
    dep = sim.cores[node].apps["fork"]

    def answer() -> m.Resume:
        return rewire_answer(sim, node, m.Rewire("fork", 4, sink, 1234, True))

    kept = answer()  # running, with its channel: where it stands, in its numbering
    assert kept.start > 0 and kept.gen == 0 and not kept.fresh
    h = dep.instances.pop("c")  # its replacement, its node reset: no channel of its output
    h.life.state, h.processed = H.AWAITING, 0
    dep.awaiting["c"] = h
    dep.restoring["c"] = Restoring(98, node, {(3, True)}, fetched=True)
    del dep.out[4]
    anew = answer()
    assert anew.start == 0 and anew.fresh and anew.gen != 0
    assert 4 not in dep.out  # (made at its activation)


def test_a_merges_replacement_tells_a_forwarder_that_survived_which_inputs_are_new() -> None:
    """A forwarder restored earlier holds its consumer's marks of the merge's inputs until an
    event goes past them; the producer of one input was lost meanwhile, so nothing did. The
    merge's replacement, its producer numbering that input anew (``Resume.fresh``), lets those
    marks go at its own end and tells the forwarder, which drops its own (held by generation
    aside, as before): kept, they dropped the new events as had (fault seed 275195: a
    restarted source's first 13 events never reached the sink)."""
    sim = started(MERGE)
    node, fwd = where(sim, "merge", "m"), where(sim, "merge", "c")
    core, dep = sim.cores[node], sim.cores[node].apps["merge"]
    far = (10**6, 0)  # what the sink had of each input, of the deployment's numbering
    sim.cores[fwd].apps["merge"].marks["c"] = {3: {0: far, 1: far}}
    h = dep.instances.pop("m")  # its replacement, resumed by its consumer and by s2
    h.life.state, h.processed = H.AWAITING, 0
    dep.awaiting["m"] = h
    del dep.inc[0]
    dep.restoring["m"] = Restoring(
        99, "N1", {(0, True)}, resumed={1}, consumer_start={2: dep.out[2].next_seq},
        consumer_gen={2: 0}, consumer_marks={2: {0: far, 1: far}}, consumer_markgens={2: {}},
        fetched=True,
    )  # fmt: skip
    anew = m.Resume("merge", 0, 99, True, 0, gen=7)  # s1's replacement: a numbering made anew
    anew.fresh = True
    sim.apply(node, core.receive(where(sim, "merge", "s1"), anew, sim.now))
    assert "m" in dep.instances and dep.renumbered["m"] == {0}
    assert dep.marks["m"] == {2: {1: far}}
    sim.run_until(sim.now + 0.05)  # the forwarder is told, and drops its marks of input 0
    assert sim.cores[fwd].apps["merge"].marks["c"] == {3: {1: far}}


CHAIN = """
name: chain
planner: paper
vertices:
  s: {code: mso.sim.vertices:Source, params: {name: s}, rate: 20, pinned: N1,
      output: mso.sim.vertices:Ev}
  a: {code: mso.sim.vertices:Count, pinned: N1, output: mso.sim.vertices:Ev}
  j: {code: mso.sim.vertices:Pass, pinned: N3, output: mso.sim.vertices:Ev}
  b: {code: mso.sim.vertices:Pass, pinned: N4, output: mso.sim.vertices:Ev}
  c: {code: mso.sim.vertices:Pass, pinned: N2, output: mso.sim.vertices:Ev}
  k1: {code: mso.sim.vertices:Sink, params: {run: provenance-new, name: k1}, pinned: N5}
  k2: {code: mso.sim.vertices:Sink, params: {run: provenance-new, name: k2}, pinned: N6}
edges: [[s, a], [a, j], [j, b], [b, k1], [j, c], [c, k2]]
"""


def test_a_producer_restored_with_new_events_only_has_a_forks_marks_of_it_let_go() -> None:
    """The source and the counter after it restart with their node's daemon; the fork `j`
    downstream, running, holds its consumer's mark of the counter's next number (a twin of
    `j` had passed on what the lost counter made there). The restored counter, fed the
    restarted source's new events only, numbers from where `j` stands and says its events are
    new: `j` lets that mark go. Kept, it dropped the restarted source's first event for `c`
    as had (fault seed 266014: never delivered at `k2`)."""
    vertices.RUNS.pop("provenance-new", None)
    sim = started(CHAIN)
    node = where(sim, "chain", "j")
    dep = sim.cores[node].apps["chain"]
    sim.crash("N1")
    sim.run_until(sim.now + 0.05)
    at = dep.inc[1].expected
    dep.marks["j"] = {4: {1: (at, 0)}}  # (c had the lost counter's event `at`, from a twin)
    sim.run_until(sim.now + 1.0)
    sim.revive("N1")
    sim.run_until(sim.now + 2.0)
    for record in vertices.RUNS["provenance-new"]:
        (_, new) = sorted(record.streams.items())  # (the first source's, the restarted one's)
        s = new[1]
        assert s.first == 0 and s.missing == 0 and s.duplicates == 0, (record.vertex, s)
        assert s.last > 30
    assert "j" not in dep.marks


def test_a_forks_marks_go_only_past_where_a_producer_of_new_events_starts() -> None:
    """A running fork lets its consumers' marks of an input go, here and held aside, when the
    input's producer says it numbers from where the fork stands with new events only
    (``Resume.new``): those from there on, not those below (a replay may bring their events
    again); not for a producer that does not say so, nor from elsewhere, nor of another
    numbering."""
    sim = started(FORK)
    node = where(sim, "fork", "j")
    core, dep = sim.cores[node], sim.cores[node].apps["fork"]
    src = where(sim, "fork", "s")
    sim.crash(src)  # (nothing more comes on the input meanwhile)
    sim.run_until(sim.now + 0.05)
    at = dep.inc[0].expected
    below, past = (at - 3, 0), (at + 5, 0)

    def told(start: int, new: bool, gen: int = 0) -> tuple[Any, Any]:
        dep.marks["j"] = {1: {0: below}, 3: {0: past}}
        dep.aside["j"] = {1: {0: (below, 0)}, 3: {0: (past, 0)}}
        resume = m.Resume("fork", 0, 1234, True, start)
        resume.gen, resume.new = gen, new
        sim.apply(node, core.receive(src, resume, sim.now))
        return dep.marks.get("j"), dep.aside.get("j")

    kept = ({1: {0: below}, 3: {0: past}}, {1: {0: (below, 0)}, 3: {0: (past, 0)}})
    assert told(at, new=False) == kept
    assert told(at + 1, new=True) == kept
    assert told(at, new=True, gen=77) == kept
    assert told(at, new=True) == ({1: {0: below}, 3: {}}, {1: {0: (below, 0)}, 3: {}})
    assert dep.inc[0].expected == at and dep.inc[0].gen == 0


def test_a_producers_resume_says_new_only_of_events_no_ack_numbered_since() -> None:
    """``Resume.new``: every event from the ack on is new (``OutChannel.new_from``), and no
    ack since brought positions (what its consumer made of them, in their numbering)."""
    ch = OutChannel(64, 10, 10, 0.0)
    assert not restore._new_past(ch)
    ch.new_from = 10
    assert restore._new_past(ch)
    ch.push_many([b"x", b"y"], 0.0)
    ch.note_positions(12, {1: 40})
    ch.on_ack(12)
    assert not restore._new_past(ch)  # (positions of the new events' numbering)
    old = OutChannel(64, 8, 8, 0.0)
    old.push_many([b"x", b"y"], 0.0)
    old.new_from = 10  # (two events the last instance made, still unacknowledged)
    assert not restore._new_past(old)
