"""Per-edge QoS across a relocation (simulator, virtual clock): a ``keep_last`` edge whose
slow consumer is moved mid-stream, and a ``lifespan_ms`` edge around a moving stateful vertex.
Every event the source made is delivered or counted, exactly; the moving vertex's state and
the markers are handed over exactly (its outputs are numbered without a gap or a repeat)."""

from __future__ import annotations

from typing import Any

from mso.model.network import LinkSpec, Network, NodeSpec
from mso.protocol import messages as m
from mso.sim.runner import Simulation


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
        int(c.status(sim.now)["apps"]["q"]["edges"].get(name, {}).get(field, 0))
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
