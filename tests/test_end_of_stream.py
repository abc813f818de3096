"""End of stream: a finite source's end travels the data plane behind its last event, each
vertex's ``end()`` runs once every input has ended (a sink flushes there), in order."""

from __future__ import annotations

from mso.protocol import effects as fx
from mso.sim.runner import Simulation
from test_runtime_sim import deploy, line

APP = """
name: finite
vertices:
  src: {code: "runtime_vertices:numbers", params: {count: 300}, pinned: N1,
        output: runtime_vertices:Num}
  sum: {code: runtime_vertices:Summing, output: runtime_vertices:Num}
  sink: {code: runtime_vertices:Flushing, pinned: N3}
edges: [[src, sum], [sum, sink]]
"""


def test_a_finite_stream_ends_at_every_vertex_in_order() -> None:
    sim = Simulation(line(3))
    assert deploy(sim, APP).ok
    sim.run_until(sim.now + 3.0)
    sink = sim.instance("N3", "finite", "sink")
    assert sink.ends == 1  # end() once, after everything before the marker
    assert sink.flushed == list(range(300)) and sink.buffer == []
    assert sink.total == str(sum(range(300))).encode()  # the operator's end() output came first
    status = {
        n: c.status(sim.now)["apps"]["finite"]["vertices"]
        for n, c in sim.cores.items()
        if "finite" in c.apps
    }
    vertices = {v: s for n in status.values() for v, s in n.items()}
    assert all(v["ended"] for v in vertices.values()), vertices
    assert vertices["src"]["emitted"] == 300  # the marker is not counted as an event
    assert vertices["sum"]["processed"] == 300 and vertices["sum"]["emitted"] == 301
    assert vertices["sink"]["processed"] == 301 and vertices["sink"]["errors"] == 0


def test_the_marker_is_not_an_event() -> None:
    assert fx.events_in([b"a", b"b", fx.END_OF_STREAM]) == 2
    assert fx.events_in([b"a"]) == 1 and fx.events_in([]) == 0
