"""Per-edge QoS across a relocation (simulator, virtual clock): a ``keep_last`` edge whose
slow consumer is moved mid-stream, and a ``lifespan_ms`` edge around a moving stateful vertex.
Every event the source made is delivered or counted, exactly; the moving vertex's state and
the markers are handed over exactly (its outputs are numbered without a gap or a repeat)."""

from __future__ import annotations

from typing import Any

from mso.model.network import LinkSpec, Network, NodeSpec
from mso.protocol import messages as m
from mso.sim.runner import Simulation
from runtime_vertices import SEEN


def line4() -> Network:
    nodes = [NodeSpec(f"N{i}") for i in range(1, 5)]
    return Network(nodes, [LinkSpec(f"N{i}", f"N{i + 1}", delay_ms=1.0) for i in range(1, 4)])


def app(rate: float, cost: float, qos: str) -> str:
    return f"""
name: q
vertices:
  src: {{code: runtime_vertices:CountingSource, pinned: N1, rate: {rate:g},
        output: runtime_vertices:Num}}
  counter: {{code: runtime_vertices:Counter, cost: {cost:g}, output: runtime_vertices:Num}}
  sink: {{code: runtime_vertices:Recorder, pinned: N4}}
edges: [{{from: src, to: counter, {qos}}}, [counter, sink]]
"""


def edge(sim: Simulation, name: str, field: str) -> int:
    """``field`` of edge ``name`` summed over every node's status (each end counts its own)."""
    return sum(
        int(c.status(sim.now)["apps"].get("q", {}).get("edges", {}).get(name, {}).get(field, 0))
        for c in sim.cores.values()
    )


def moved_around(text: str, moves: int) -> tuple[Simulation, dict[str, Any]]:
    sim = Simulation(line4(), model_time=True)
    sim.request("N1", m.DeployRequest(text, "q.yaml"))
    sim.run_until(1.0)
    done = 0
    for k in range(moves):
        target = ("N2", "N3", "N4", "N3", "N2")[k % 5]
        n = len(sim.replies)
        sim.request("N1", m.RelocateRequest("q", "counter", "", target))
        for _ in range(50):  # until it answers (bounded: 5 s), the stream running meanwhile
            sim.run_until(sim.now + 0.1)
            replies = [r for _, _, r in sim.replies[n:] if isinstance(r, m.RelocateReply)]
            if replies:
                done += replies[0].ok
                break
        sim.run_until(sim.now + 0.5)
    assert done >= moves, f"{done} moves"
    stats: dict[str, Any] = sim.cores["N4"].status(sim.now)["apps"]["q"]["vertices"]["sink"][
        "stats"
    ]
    return sim, stats


def test_keep_last_with_its_slow_consumer_moved_mid_stream_counts_exactly() -> None:
    """The counter takes 40 ms an event, the source makes one every 20 ms: ``keep_last: 3``
    supersedes about half. Across four moves, every event made is processed by the counter
    or counted superseded (at the producer or at the consumer, whichever end gave it up),
    and the counter's outputs reach the sink numbered 0, 1, 2, ... (its state moved)."""
    sim, stats = moved_around(app(50, 40, "keep_last: 3"), 4)
    made = edge(sim, "src->counter", "sent")  # (only the producer numbers events)
    superseded = edge(sim, "src->counter", "superseded")
    assert superseded > 50, "the consumer fell behind, and the oldest were given up"
    assert stats["repeats"] == 0 and stats["out_of_order"] == 0, stats
    assert stats["count"] == stats["next"], "state handed over exactly: no gap in its count"
    in_flight = made - superseded - stats["count"]
    assert 0 <= in_flight <= 3 + 2, (made, superseded, stats)  # the newest few still on the way


def test_lifespan_edge_around_a_moving_stateful_vertex_delivers_all_in_time() -> None:
    """Events live 5 s and the moves take milliseconds: nothing expires, nothing is lost,
    the count at the sink is exactly what the source made (but the newest in flight)."""
    sim, stats = moved_around(app(100, 2, "lifespan_ms: 5000"), 4)
    made = edge(sim, "src->counter", "sent")
    assert edge(sim, "src->counter", "expired") == 0
    assert stats["repeats"] == 0 and stats["out_of_order"] == 0
    assert stats["count"] == stats["next"] and made - 5 <= stats["count"] <= made


def test_a_backlog_past_one_frame_is_handed_over_in_parts() -> None:
    """The counter's consumer is out of reach, so its output edge holds a window of 40 KB
    events (20 MB, past the 16 MiB frame limit); the counter is moved meanwhile. Its handover
    sends that backlog ahead in parts of about a megabyte (before: one frame of all of it),
    and after the heal the sink gets every output once, in order, its count unbroken."""
    from mso.protocol.framing import MAX_FRAME

    text = app(200, 0.1, "size: 40000").replace(
        "pinned: N1, rate: 200,", "pinned: N1, rate: 200, params: {size: 40000},"
    )
    text = text.replace("{from: src, to: counter, size: 40000}", "[src, counter]")
    text = text.replace(
        "runtime_vertices:Recorder,", "runtime_vertices:SeenSink, params: {run: hand},"
    )
    SEEN.pop("hand", None)
    sim = Simulation(line4(), window=512)
    sim.request("N1", m.DeployRequest(text, "q.yaml"))
    sim.run_until(1.0)
    sim.network.remove_link("N3", "N4")
    sim.links_changed()
    sim.run_until(5.0)
    host = next(n for n, c in sim.cores.items() if "counter" in c.instances("q"))
    backlog = sim.cores[host].apps["q"].out[1]
    assert backlog.kept_bytes > MAX_FRAME, "a backlog past one frame"
    largest = [0]
    sim.taps.append(lambda a, b, msg: largest.__setitem__(0, max(largest[0], len(m.encode(msg)))))
    n = len(sim.replies)
    sim.request("N1", m.RelocateRequest("q", "counter", "", "N2" if host != "N2" else "N1"))
    sim.run_until(sim.now + 2.0)
    (reply,) = [r for _, _, r in sim.replies[n:] if isinstance(r, m.RelocateReply)]
    assert reply.ok, reply.error
    assert largest[0] < MAX_FRAME, f"a frame of {largest[0]:,} bytes"
    sim.network.add_link(LinkSpec("N3", "N4", delay_ms=1.0))
    sim.links_changed()
    sim.run_until(sim.now + 10.0)
    seen, made = SEEN["hand"], edge(sim, "src->counter", "sent")
    distinct = sorted(set(seen))
    assert distinct == list(range(len(distinct))), "none lost: the counter's state unbroken"
    assert list(dict.fromkeys(seen)) == distinct, "in order"
    # (the sink's node held the others failed and reset at the heal: its replacement may get
    # again what it had processed but not acknowledged, as tests/test_emulator.py says)
    assert len(seen) - len(distinct) <= 5 and len(distinct) >= made - 200, (len(seen), made)
