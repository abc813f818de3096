"""RouteWait: control and marker frames wait for a route (bounded in time and count)."""

from __future__ import annotations

from mso.net.base import CONTROL, DATA, MARKER
from mso.net.forwarding import RouteWait


def test_a_held_frame_leaves_when_the_routes_change() -> None:
    wait: RouteWait[str] = RouteWait(wait_s=1.0)
    assert wait.hold("N1", "probe", CONTROL, now=0.0)
    assert wait.hold("N2", "marker", MARKER, now=0.1)
    routes = {"N1"}  # only N1 is reachable yet
    sent: list[tuple[str, str, int]] = []

    def send(dst: str, item: str, kind: int) -> bool:
        if dst not in routes:
            return False
        sent.append((dst, item, kind))
        return True

    assert wait.release(0.5, send) == 1
    assert sent == [("N1", "probe", CONTROL)] and len(wait) == 1
    routes.add("N2")
    assert wait.release(0.6, send) == 1
    assert sent[-1] == ("N2", "marker", MARKER) and len(wait) == 0 and wait.dropped == 0


def test_a_frame_waits_only_so_long() -> None:
    dropped: list[str] = []
    wait: RouteWait[str] = RouteWait(wait_s=1.0, on_drop=dropped.append)
    wait.hold("N1", "a", CONTROL, now=0.0)
    wait.hold("N1", "b", CONTROL, now=0.5)
    assert wait.next_deadline() == 1.0
    assert wait.expire(1.2) == 1 and dropped == ["a"]
    # a release after the deadline gives the frame up instead of sending it
    assert wait.release(2.0, lambda *_: True) == 0
    assert dropped == ["a", "b"] and wait.dropped == 2 and len(wait) == 0


def test_holding_expires_old_frames_first() -> None:
    wait: RouteWait[int] = RouteWait(wait_s=1.0)
    wait.hold("N1", 1, CONTROL, now=0.0)
    wait.hold("N1", 2, CONTROL, now=1.5)
    assert [w.item for w in wait] == [2] and wait.dropped == 1


def test_data_frames_are_not_held() -> None:
    dropped: list[str] = []
    wait: RouteWait[str] = RouteWait(on_drop=dropped.append)
    assert not wait.hold("N1", "ack", DATA, now=0.0)
    assert len(wait) == 0 and dropped == ["ack"] and wait.dropped == 1


def test_at_most_limit_frames_wait() -> None:
    wait: RouteWait[int] = RouteWait(wait_s=1.0, limit=3)
    held = [wait.hold("N1", i, CONTROL, now=0.0) for i in range(5)]
    assert held == [True, True, True, False, False]
    assert [w.item for w in wait] == [0, 1, 2] and wait.dropped == 2
