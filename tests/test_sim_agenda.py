"""The simulator's agenda gives its events in a heap's (time, order put in) order, whatever
times are put in between pops: ties and times earlier than the last popped included."""

from __future__ import annotations

import heapq
import itertools

from hypothesis import given, settings
from hypothesis import strategies as st

from mso.sim.agenda import Agenda

# a step: put an item at one of a few times (ties are the point), or pop what is due by a time
_steps = st.lists(
    st.one_of(
        st.tuples(st.just("push"), st.sampled_from([0.0, 0.1, 0.10005, 0.2, 0.3, 1.0])),
        st.tuples(st.just("pop"), st.sampled_from([0.0, 0.1, 0.15, 0.2, 1.0, 2.0])),
    ),
    max_size=200,
)


@given(_steps)
@settings(max_examples=300, deadline=None)
def test_the_agenda_pops_in_a_heaps_order(steps: list[tuple[str, float]]) -> None:
    agenda: Agenda[int] = Agenda()
    heap: list[tuple[float, int]] = []
    seq = itertools.count()
    for what, t in steps:
        if what == "push":
            n = next(seq)
            agenda.push(t, n)
            heapq.heappush(heap, (t, n))
        else:
            want = heapq.heappop(heap) if heap and heap[0][0] <= t else None
            assert agenda.pop(t) == want
        assert len(agenda) == len(heap)
        assert agenda.next_at() == (heap[0][0] if heap else None)
    while heap:
        assert agenda.pop(float("inf")) == heapq.heappop(heap)
    assert not agenda and agenda.pop(float("inf")) is None
