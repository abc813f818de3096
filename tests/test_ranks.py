"""The tie-break after a healed partition, read from one node's view and another's beat
(:mod:`mso.protocol.procedures.membership.ranks`): pure functions, each reading by itself."""

from __future__ import annotations

from mso.protocol import messages as m
from mso.protocol.procedures.membership.ranks import (
    View,
    cut_off,
    holds_more_failed,
    outranked_by,
    smaller_side,
)


def view(failed: set[str], hosting: int = 0, **incs: int) -> View:
    """N2 on a line N1 - N2 - N3 - N4 - N5, every node reachable."""
    routes = {n: (n, 1) for n in ("N1", "N3", "N4", "N5")}
    known = {n: 0 for n in routes} | incs
    return View("N2", 0, routes, frozenset(failed), known, hosting, "N1")


def beat(node: str, failed: dict[str, int], hosting: int = 1) -> m.Heartbeat:
    return m.Heartbeat(node, 0, failed, node, hosting, None, [])


def test_the_node_cut_off_holds_more_failed_than_the_larger_side() -> None:
    cut = beat("N5", {"N1": 0, "N2": 0, "N3": 0, "N4": 0})
    assert holds_more_failed(view({"N5"}), cut)
    assert not holds_more_failed(view({"N5", "N1", "N3"}), beat("N5", {"N2": 0, "N4": 0}))


def test_an_older_incarnation_held_failed_is_no_dispute() -> None:
    """N5 holds N3 and N4 failed in incarnation 0, but both restarted since (1): only its
    claim on us counts, one against our one, so it is not the smaller side."""
    stale = beat("N5", {"N2": 0, "N3": 0, "N4": 0})
    assert not holds_more_failed(view({"N5"}, N3=1, N4=1), stale)
    assert holds_more_failed(view({"N5"}), stale)


def test_a_node_we_hold_alive_that_holds_most_of_ours_failed_was_cut_off() -> None:
    assert cut_off(view(set()), beat("N5", {"N1": 0, "N2": 0, "N3": 0}))
    assert not cut_off(view(set()), beat("N5", {"N2": 0}))  # only we missed it: we yield
    assert not cut_off(view({"N5"}), beat("N5", {"N1": 0, "N2": 0, "N3": 0}))  # two-sided


def test_an_even_split_is_no_cut_off_the_sender_counts_on_its_side() -> None:
    """Fault seed 287248: a ring N1-N2-N3-N4 split {N1, N4} | {N2, N3}; N1 declared N2 and
    N3, N2 nobody. At the heal N2 hears N1 (N2 and N3 failed): two of us against N1 and N4,
    which N1 holds alive. Taken for a cut off, N2 held N1 failed and its beat counted one
    failed against N1's two: N1 reset as well, and with the other pair both sides did."""
    routes = {n: (n, 1) for n in ("N1", "N3", "N4")}
    n2 = View("N2", 0, routes, frozenset(), {n: 0 for n in routes}, 1, "N2")
    assert not cut_off(n2, beat("N1", {"N2": 0, "N3": 0}))  # a tie: N2 yields (resets)
    assert outranked_by(n2, beat("N1", {"N2": 0, "N3": 0}))
    assert cut_off(n2, beat("N1", {"N2": 0, "N3": 0, "N4": 0}))  # three of us against N1


def test_the_larger_side_stays_and_an_empty_node_yields_to_a_busy_one() -> None:
    small = beat("N5", {"N1": 0, "N2": 0, "N3": 0, "N4": 0})
    assert not outranked_by(view({"N5"}, hosting=1), small)  # we count one failed, it four
    assert outranked_by(view({"N5"}, hosting=0), small)  # we run nothing: we would yield
    assert outranked_by(view(set(), hosting=1), beat("N5", {"N2": 0}))  # one-sided: we reset
    assert not outranked_by(view(set(), hosting=1), beat("N5", {"N2": 0}, hosting=0))


def test_a_node_held_failed_that_holds_us_alive_is_the_side_cut_off_if_we_reach_most() -> None:
    """Issue 22.1: a node cut off holds the others out of reach, alive, not failed. Its beat
    holding nobody failed marks it as the smaller side when we hold most of those we reach
    alive; a node that holds most of them failed (restarted amid a partition) is the smaller
    side itself, and one that holds us failed is weighed by the counts alone."""
    cut = beat("N5", {})
    assert smaller_side(view({"N5"}), cut)  # we hold N1, N3, N4 alive
    assert not smaller_side(view({"N5", "N1", "N3"}), cut)  # we hold most of them failed
    assert not smaller_side(view(set()), cut)  # (we hold it alive: no dispute)
    assert not smaller_side(view({"N5"}), beat("N5", {"N2": 0}))  # one for one
    assert smaller_side(view({"N5"}), beat("N5", {"N2": 0, "N1": 0}))  # it holds more
