"""The daemon's durable spill store (``mso.daemon.spill``): events and positions survive a
reopen, drained edges give their disk space back, and a damaged, foreign or shared file is a
clear error at start (exit code 2), never a crash."""

from __future__ import annotations

import asyncio
import contextlib
import sqlite3
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest

from mso.daemon.spill import FILE, VACUUM_PAGES, SqliteSpill, keep_tidy
from mso.errors import MsoError
from mso.protocol.channel import OutChannel
from mso.protocol.spill import MemorySpill, placement_notes
from waits import holds, patience


def test_events_and_positions_survive_a_reopen(tmp_path: Path) -> None:
    s = SqliteSpill(tmp_path)
    s.append("a/1/0", 10, [b"x" * 5, b"y" * 6])
    s.append("a/1/0", 12, [b"z"])
    s.append("a/1/0", 7, [b"p", b"q", b"r"])  # before the first: a held edge's memory moved in
    s.save_position("a/1/0", 13)
    s.close()
    s = SqliteSpill(tmp_path)
    assert s.span("a/1/0") == (7, 13) and s.position("a/1/0") == 13
    assert s.read("a/1/0", 9, 3) == [b"r", b"x" * 5, b"y" * 6]
    assert s.size("a/1/0") == 3 + 5 + 6 + 1
    s.trim("a/1/0", 11)
    assert s.read("a/1/0", 0, 10) == [b"y" * 6, b"z"] and s.size("a/1/0") == 7
    s.drop("a/1/0")
    assert s.span("a/1/0") is None and s.position("a/1/0") is None and s.size("a/1/0") == 0
    s.close()


@pytest.mark.parametrize("kind", ["sqlite", "memory"])
def test_placement_notes_keep_one_a_vertex_and_survive_a_reopen(tmp_path: Path, kind: str) -> None:
    """Where a vertex runs as its host said (placement.remember): one note a vertex, the
    newest, kept across a restart; an app's notes go with it, not its edges' positions."""
    s: Any = SqliteSpill(tmp_path) if kind == "sqlite" else MemorySpill()
    s.save_position("a/1/0", 13)
    s.note(placement_notes("a", "j"), "0/N1", 1)
    s.note(placement_notes("a", "j"), "1/N2", 2)  # a later move: the one kept
    s.note(placement_notes("a", "j2"), "0/N3", 1)
    if kind == "sqlite":
        s.close()
        s = SqliteSpill(tmp_path)
    assert s.notes(placement_notes("a", "j")) == {"1/N2": 2}
    assert s.notes(placement_notes("a", "j2")) == {"0/N3": 1}
    s.forget_notes(placement_notes("a"))
    assert s.notes(placement_notes("a", "j")) == {} and s.position("a/1/0") == 13


def free_pages(path: Path) -> int:
    """The store file's free pages, as another connection sees them."""
    with contextlib.closing(sqlite3.connect(path / FILE)) as db:
        return int(db.execute("PRAGMA freelist_count").fetchone()[0])


def test_a_drained_edge_gives_its_disk_space_back_a_bounded_step_at_a_time(
    tmp_path: Path,
) -> None:
    """The node's loop makes every call: the trim that drains an edge gives nothing back
    itself (all of 300 MB at once stopped the loop for 3.6-5.7 s, past the failure detector),
    each tidy gives back at most VACUUM_PAGES pages, and tidying on gets the file small."""
    s = SqliteSpill(tmp_path)
    s.append("k", 0, [bytes(50_000)] * 200)  # 10 MB held
    full = s.disk_bytes()
    assert full > 10_000_000 and s.held_bytes() == 10_000_000
    s.trim("k", 200)
    free = free_pages(tmp_path)
    assert s.held_bytes() == 0 and s.owed and free > 4 * VACUUM_PAGES
    steps = 0
    while s.tidy():
        steps += 1
        now = free_pages(tmp_path)
        assert 0 < free - now <= VACUUM_PAGES
        free = now
    assert free_pages(tmp_path) == 0 and steps >= 4 and s.disk_bytes() < full // 10
    assert not s.tidy()  # nothing owed any more
    s.close()


def test_keep_tidy_gives_the_pages_back_and_checkpoints_on_its_thread(tmp_path: Path) -> None:
    """Beside the daemon's node: the log is checkpointed off the loop (not by a commit on it,
    short of its safety bound), and a drained store ends about empty on disk."""
    s = SqliteSpill(tmp_path)

    async def run() -> None:
        tidy = asyncio.create_task(keep_tidy(s, period=0.01))
        try:
            await asyncio.sleep(0)  # (it starts: checkpoints apart from here on)
            s.append("k", 0, [bytes(50_000)] * 200)
            full = s.disk_bytes()
            s.trim("k", 200)
            deadline = asyncio.get_running_loop().time() + patience(10)
            while s.disk_bytes() > full // 10 or s.owed:
                assert asyncio.get_running_loop().time() < deadline, s.disk_bytes()
                await asyncio.sleep(0.01)
        finally:
            tidy.cancel()

    asyncio.run(run())
    assert free_pages(tmp_path) == 0
    s.close()


def test_span_does_not_read_every_event_of_its_edge(tmp_path: Path) -> None:
    """``span`` (a restarted source's edge) looks up each end in the primary key: one select
    of MIN and MAX together scanned every row (0.5 s on the loop for 300 MB)."""
    s = SqliteSpill(tmp_path)
    s.append("a", 3, [b"x"] * 5)
    s.append("b", 0, [b"y"] * 2)
    assert s.span("a") == (3, 8) and s.span("b") == (0, 2) and s.span("c") is None

    def steps(events: int) -> int:
        s.append("k", 0, [b"z"] * events)
        ops = [0]

        def count() -> int:
            ops[0] += 1
            return 0

        s._db.set_progress_handler(count, 1)  # one call per virtual machine instruction
        assert s.span("k") == (0, events)
        s._db.set_progress_handler(None, 1)
        s.drop("k")
        return ops[0]

    assert steps(5000) == steps(10)  # not one more step for 500 times the rows
    s.close()


def test_a_channel_spills_into_it_and_recovers_after_a_restart(tmp_path: Path) -> None:
    """A source's edge held for an unreachable consumer, its process gone: the next one
    numbers on from the saved position and still holds what was held."""
    s = SqliteSpill(tmp_path)
    ch = OutChannel(window=4, store=s, key="app/0/0", persist=True)
    for i in range(10):
        ch.push(b"%d" % i)
    ch.on_ack(3)
    ch.make_durable()
    ch.push(b"10")
    s.close()
    s = SqliteSpill(tmp_path)
    back = OutChannel.recover(s, "app/0/0", 3, 4, 0.0)
    assert back is not None and back.next_seq == 11 and back.acked == 3
    first, events = back.events_from(3)
    assert first == 3 and events == [b"%d" % i for i in range(3, 11)]
    back.on_ack(11)
    assert s.size("app/0/0") == 0 and s.position("app/0/0") >= 11
    s.close()


def test_an_edge_that_held_nothing_numbers_on_past_what_the_consumer_saw(tmp_path: Path) -> None:
    s = SqliteSpill(tmp_path)
    ch = OutChannel(window=64, store=s, key="k", persist=True)
    ch.push_many([b"e"] * 20)  # in memory only: in flight to a reachable consumer, then gone
    s.close()
    s = SqliteSpill(tmp_path)
    back = OutChannel.recover(s, "k", 12, 64, 0.0)
    assert back is not None and back.acked == back.next_seq >= 20, "never reuses 12..19"
    assert OutChannel.recover(s, "other", 0, 64, 0.0) is None
    s.close()


@pytest.mark.parametrize(
    "content, expected",
    [
        (b"not a database at all, just text" * 100, "not a usable mso spill store"),
        (None, "not mso-spill (tables: t)"),  # another program's SQLite file
    ],
)
def test_a_damaged_or_foreign_file_is_refused_clearly(
    tmp_path: Path, content: bytes | None, expected: str
) -> None:
    path = tmp_path / FILE
    if content is None:
        db = sqlite3.connect(path)
        db.execute("CREATE TABLE t (x)")
        db.commit()
        db.close()
    else:
        path.write_bytes(content)
    with pytest.raises(MsoError, match=expected.replace("(", r"\(").replace(")", r"\)")):
        SqliteSpill(tmp_path)


def test_a_newer_format_is_refused(tmp_path: Path) -> None:
    SqliteSpill(tmp_path).close()
    db = sqlite3.connect(tmp_path / FILE)
    db.execute("UPDATE meta SET value = '9' WHERE name = 'version'")
    db.commit()
    db.close()
    with pytest.raises(MsoError, match="version '9', expected 'mso-spill' version '1'"):
        SqliteSpill(tmp_path)


def test_two_nodes_cannot_share_a_state_directory(tmp_path: Path) -> None:
    first = SqliteSpill(tmp_path)
    with pytest.raises(MsoError, match="in use by another mso node"):
        SqliteSpill(tmp_path)
    first.close()
    SqliteSpill(tmp_path).close()  # free again


def test_mso_node_with_a_damaged_store_exits_2_with_one_line(tmp_path: Path) -> None:
    (tmp_path / FILE).write_bytes(b"\x00garbage" * 512)
    proc = subprocess.run(
        [sys.executable, "-m", "mso", "node", "--id", "N1", "--listen", "127.0.0.1:0",
         "--state-dir", str(tmp_path)],
        capture_output=True, text=True, timeout=60,
    )  # fmt: skip
    assert proc.returncode == 2, proc.stderr
    assert "not a usable mso spill store" in proc.stderr and "Traceback" not in proc.stderr


@pytest.mark.parametrize("store_kind", ["memory", "sqlite"])
def test_a_source_edge_holding_draining_and_holding_again_keeps_its_events_in_order(
    tmp_path: Path, store_kind: str
) -> None:
    """Random pushes, acks, outages (everything made durable) and drains: what the channel
    holds from its ack on is always exactly the events pushed, in order (found by the fault
    schedules: a second outage once wrote events at the wrong numbers)."""
    import random

    from mso.protocol.spill import MemorySpill, SpillStore

    rng = random.Random(5)
    store: SpillStore = MemorySpill() if store_kind == "memory" else SqliteSpill(tmp_path)
    ch = OutChannel(window=8, store=store, key="k", persist=True, mem_limit=40)
    pushed: list[bytes] = []
    for step in range(600):
        op = rng.random()
        if op < 0.5:
            batch = [b"%05d" % (len(pushed) + i) for i in range(rng.randint(1, 4))]
            ch.push_many(batch)
            pushed += batch
        elif op < 0.8:
            ch.on_ack(rng.randint(ch.acked, ch.next_seq))
        else:
            ch.make_durable()
        first, events = ch.events_from(ch.acked)
        assert first == ch.acked and events == pushed[ch.acked :], step
        assert not pushed or store.position("k") >= ch.next_seq


def test_a_held_source_edge_comes_back_acknowledged_where_its_last_ack_was(
    tmp_path: Path,
) -> None:
    """A source's edge into a replicated consumer keeps what it holds in the store, acked or
    retained: after a restart it comes back acknowledged up to its last ack, with the output
    positions that ack brought (a replacement numbers its replay from them; before, the
    retained events came back unacknowledged and positionless: seed 1088, 14 events twice),
    the acknowledged ones retained again only for a replica."""
    s = SqliteSpill(tmp_path)
    ch = OutChannel(window=64, store=s, key="app/0/0", persist=True)
    ch.retain("replica", 0)
    ch.push_many([b"%d" % i for i in range(10)])
    ch.make_durable()
    ch.on_ack(6)
    ch.note_positions(6, {1: 6, 2: 5})
    s.close()
    s = SqliteSpill(tmp_path)
    assert s.saved_positions("app/0/0") == (6, {1: 6, 2: 5})
    back = OutChannel.recover(s, "app/0/0", 0, 64, 0.0, retain="replica")
    assert back is not None and (back.acked, back.next_seq) == (6, 10)
    assert back.positions == {1: 6, 2: 5} and back.retained("replica") == (
        0,
        [b"%d" % i for i in range(10)],
    )
    plain = OutChannel.recover(s, "app/0/0", 0, 64, 0.0)
    assert plain is not None and plain.base == plain.acked == 6 and plain.kept == 4
    s.drop("app/0/0")
    assert s.saved_positions("app/0/0") is None and s.position("app/0/0") is None
    s.close()


def test_a_held_edge_whose_consumer_stands_past_its_last_known_positions_keeps_them(
    tmp_path: Path,
) -> None:
    """The consumer's ack past the last one whose positions were saved was lost (a
    partition, then the daemon's restart): the restored source says where it stands from
    that saved ack, retaining the events past it, so a replacement of the consumer numbers
    what their replay makes as the lost instance did, and the live consumer drops what it
    has. Started at the consumer's position with no positions, a forwarder's replacement
    numbered the replay from its own consumer's position: 12 events twice (seed 106785)."""
    s = SqliteSpill(tmp_path)
    ch = OutChannel(window=64, store=s, key="app/0/2", persist=True)
    ch.push_many([b"%d" % i for i in range(20)])
    ch.on_ack(19)
    ch.note_positions(19, {3: 19, 4: 37})
    ch.make_durable()  # event 19 held: the consumer went out of reach; its ack of 20 lost
    ch.push_many([b"%d" % i for i in range(20, 31)])
    s.close()
    s = SqliteSpill(tmp_path)
    back = OutChannel.recover(s, "app/0/2", 20, 64, 0.0)  # the consumer stands at 20
    assert back is not None and (back.acked, back.next_seq) == (19, 31)
    assert back.positions == {3: 19, 4: 37}
    assert back.events_from(19) == (19, [b"%d" % i for i in range(19, 31)])
    s.close()


def loop_steps(store: SqliteSpill) -> Callable[[], int]:
    """SQLite's virtual-machine steps on the loop's connection (hundreds), counted: how much
    work a store call does there, as a count (not a time)."""
    steps = [0]

    def step() -> int:
        steps[0] += 1
        return 0

    store._db.set_progress_handler(step, 100)
    return lambda: steps[0]


async def drain_backlog(
    store: SqliteSpill, n: int, size: int
) -> tuple[list[bytes], dict[str, list[int]]]:
    """A source's edge held ``n`` events of ``size`` bytes (all in the store), then drains
    as a node does: what is at hand goes in frames of 4 within 64 unacknowledged, each frame
    acked, and the store's word that more is in drains on. Returns what arrived, in order,
    and the SQLite steps each store call made on the loop's connection, by name."""
    loop = asyncio.get_running_loop()
    more = asyncio.Event()
    store.read_apart(loop.call_soon_threadsafe, lambda key: more.set())
    ch = OutChannel(window=64, store=store, key="app/0/0", persist=True, mem_limit=0)
    pushed = [i.to_bytes(4, "big") * (size // 4) for i in range(n)]
    ch.push_many(pushed[:1])
    ch.make_durable()
    ch.push_many(pushed[1:])
    steps, got = loop_steps(store), []
    per_call: dict[str, list[int]] = {}

    def counted(name: str, call: Callable[..., Any]) -> Callable[..., Any]:
        def call_counted(*args: Any) -> Any:
            before = steps()
            out = call(*args)
            per_call.setdefault(name, []).append(steps() - before)
            return out

        return call_counted

    for name in ("ready", "read", "trim", "append", "span", "save_position", "save_positions"):
        setattr(store, name, counted(name, getattr(store, name)))
    deadline = loop.time() + patience(20)
    while ch.acked < n:
        first, events = ch.unsent(4)
        if not events:
            more.clear()
            await asyncio.wait_for(more.wait(), deadline - loop.time())
            continue
        assert first == len(got)
        got += events
        ch.on_ack(first + len(events))
    return got, per_call


def test_a_drain_reads_its_backlog_off_the_loop_in_order_exactly_once(tmp_path: Path) -> None:
    """A backlog of 600 events of 20 KB (12 MB, three read-aheads) drains in order, each
    event once, and no ``ready`` call does SQLite work on the loop (the reader thread's):
    before, each drain read its 4 MB window there (18 ms, to 100 ms under load). The only
    other calls a drain makes there, the acks' trims, each do a bounded amount (a count of
    SQLite's steps: a few hundred, whatever the backlog)."""
    s = SqliteSpill(tmp_path)
    got, per_call = asyncio.run(drain_backlog(s, 600, 20_000))
    assert [int.from_bytes(e[:4], "big") for e in got] == list(range(600))
    assert set(per_call) == {"ready", "trim"} and s.reads_apart >= 3
    assert len(per_call["ready"]) > 150 and max(per_call["ready"]) == 0
    assert len(per_call["trim"]) >= 150 and max(per_call["trim"]) <= 10
    s.close()
    # the same store read on the loop (no reader thread) does its reads there
    s = SqliteSpill(tmp_path / "inline")
    s.append("k", 0, [bytes(20_000)] * 50)
    steps = loop_steps(s)
    assert len(s.ready("k", 0, 50)) == 50 and steps() > 0
    s.close()


def test_read_ahead_forgets_what_was_trimmed_dropped_or_rewritten_meanwhile(
    tmp_path: Path,
) -> None:
    """What the reader thread read comes back to the loop later: if the edge was trimmed past
    it, or dropped and numbered anew meanwhile, it is not served (an event twice, or another
    edge's event under the same number)."""
    s = SqliteSpill(tmp_path)
    calls: list[Callable[[], None]] = []
    told: list[str] = []
    s.read_apart(calls.append, told.append)

    def handed_back() -> None:
        async def wait() -> None:
            await holds(lambda: calls, 10, "the reader thread's result")

        asyncio.run(wait())
        calls.pop(0)()

    s.append("k", 0, [b"a", b"b", b"c", b"d"])
    assert s.ready("k", 0, 2) == []  # asked: nothing at hand yet
    handed_back()
    assert told == ["k"] and s.ready("k", 0, 2) == [b"a", b"b"]
    s.append("k", 4, [b"e"])
    assert s.ready("k", 4, 1) == []  # read on from 4
    s.trim("k", 5)  # ... but 4 was acked meanwhile
    handed_back()
    assert s.ready("k", 5, 1) == [] and told == ["k"]
    s.drop("k")
    s.append("k", 0, [b"x", b"y"])  # the same numbers, other events
    assert s.ready("k", 0, 2) == []
    s.drop("k")
    s.append("k", 0, [b"p", b"q"])
    handed_back()  # the read of the dropped key's x, y: not served
    assert s.ready("k", 0, 2) == []
    handed_back()
    assert s.ready("k", 0, 2) == [b"p", b"q"]
    s.close()


def test_an_edge_carried_over_a_reset_whose_consumer_stands_past_its_last_ack_keeps_it() -> None:
    """As above, for a node that reset (no restart): the source's channel is carried over
    (``StoreAndForward.carry_over``). Moved up to where the consumer stands, its ack named a
    point its positions were not from: a replacement of the consumer numbered the replay one
    ack off. It starts from that ack now, its positions with it."""
    from types import SimpleNamespace

    from mso.protocol.forward import StoreAndForward

    ch = OutChannel(window=64)
    ch.push_many([b"%d" % i for i in range(30)])
    ch.on_ack(19)
    ch.note_positions(19, {3: 19, 4: 37})  # (the consumer's ack of 25 was lost)
    sf = StoreAndForward(SimpleNamespace(now=5.0), None)  # type: ignore[arg-type]
    dep = SimpleNamespace(app=SimpleNamespace(name="app"), epoch=0)
    sf.carried[("app", 0, 2)] = ch
    back = sf.carry_over(dep, 2, 25)  # type: ignore[arg-type]
    assert back is ch and (ch.acked, ch.sent, ch.positions_at) == (19, 19, 19)
    assert ch.positions == {3: 19, 4: 37}
    assert ch.events_from(19) == (19, [b"%d" % i for i in range(19, 30)])
    sf.carried[("app", 0, 2)] = other = OutChannel(window=64)
    other.push_many([b"%d" % i for i in range(30)])
    other.on_ack(19)  # an ack with no positions (the consumer's outputs unknown): moved up
    assert sf.carry_over(dep, 2, 25) is other and (other.acked, other.sent) == (25, 25)  # type: ignore[arg-type]


@pytest.mark.parametrize("kind", ["sqlite", "memory"])
def test_saved_positions_keep_the_generation_of_their_numbering(tmp_path: Path, kind: str) -> None:
    """A held source edge's saved positions keep the generation of each numbering they are
    of (``OutChannel.gens``; 0, the deployment's, not written), and the edge its own: a
    source's edge numbers on in the same numbering after a restart; a consumer's replacement
    restored after a restart says which numbering it numbers from, and a merge started past
    marks of another takes its events as new (seed 105902: 7 events dropped as had)."""
    s: SqliteSpill | MemorySpill = SqliteSpill(tmp_path) if kind == "sqlite" else MemorySpill()
    ch = OutChannel(window=64, store=s, key="app/0/0", persist=True)
    ch.number_as(9)  # its own (a source restored with a guess numbers anew)
    ch.push_many([b"%d" % i for i in range(10)])
    ch.on_ack(6)
    ch.note_positions(6, {1: 6, 2: 5}, {1: 1 << 50, 2: 0, 7: 3})  # (7: no position of it)
    ch.make_durable()
    assert ch.gens == {1: 1 << 50}
    if isinstance(s, SqliteSpill):
        s.close()
        s = SqliteSpill(tmp_path)
    assert s.saved_positions("app/0/0") == (6, {1: 6, 2: 5})
    back = OutChannel.recover(s, "app/0/0", 6, 64, 0.0)
    assert back is not None and back.positions == {1: 6, 2: 5} and back.gens == {1: 1 << 50}
    assert back.gen == 9
    s.drop("app/0/0")
    assert s.saved_gens("app/0/0") == {}
    if isinstance(s, SqliteSpill):
        s.close()
