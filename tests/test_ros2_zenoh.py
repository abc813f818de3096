"""Round trips through an in-process Zenoh router on 127.0.0.1 against an independent talker
and listener written the way rmw_zenoh documents (tests/ros2_helpers.py): what a ROS 2 node
publishes reaches an mso Subscriber typed, what an mso Publisher publishes a ROS 2 node reads,
both sides see each other's liveliness tokens, and closing never hangs."""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator
from typing import Any

import pytest
from zenoh import ext as zenoh_ext

from mso.ros2 import Publisher, Subscriber, bridge
from mso.ros2.bridge import CLOSE_S
from mso.ros2.types import struct_for
from ros2_helpers import (
    STRING_HASH,
    Listener,
    attachment,
    cdr_string,
    chatter_key,
    decode_string,
    free_port,
    ros_peer,
    routed,
    router,
    tokens,
    wait_for,
)
from waits import patience

String = struct_for("std_msgs/msg/String")


@pytest.fixture
def net() -> Iterator[tuple[str, Any]]:
    """A router on a free loopback port and a ROS-side peer session connected to it."""
    port = free_port()
    r = router(port)
    peer = ros_peer(port)
    try:
        yield f"tcp/127.0.0.1:{port}", peer
    finally:
        peer.close()
        r.close()


def drain(sub: Subscriber, want: int, timeout: float = 10.0) -> list[Any]:
    out: list[Any] = []
    end = time.monotonic() + patience(timeout)
    while len(out) < want and time.monotonic() < end:
        ev = next(sub)
        if ev is not None:
            out.append(ev)
    return out


def test_a_ros_talker_reaches_an_mso_subscriber_typed(net: tuple[str, Any]) -> None:
    endpoint, peer = net
    sub = Subscriber("/chatter", "std_msgs/msg/String", router=endpoint)
    sub.open()
    try:
        zid = str(sub.session.zid())
        assert wait_for(lambda: any("/MS/" in t for t in tokens(peer)))
        seen = tokens(peer)
        assert f"@ros2_lv/0/{zid}/0/0/NN/%/%/mso_sub_chatter" in seen
        assert (
            f"@ros2_lv/0/{zid}/0/1/MS/%/%/mso_sub_chatter/%chatter/"
            f"std_msgs::msg::dds_::String_/{STRING_HASH}/::,10:,:,:,,"
        ) in seen
        talker = peer.declare_publisher(chatter_key())
        gid = bytes(range(16))
        for i in range(5):
            talker.put(cdr_string(f"hello world {i}"), attachment=attachment(i + 1, gid))
        got = drain(sub, 5)
        assert got == [String(data=f"hello world {i}") for i in range(5)]
        assert all(type(e) is String for e in got)
        assert sub.stats()["received"] == 5 and sub.stats()["undecodable"] == 0
        assert sub.stats()["decode_ms"] > 0  # (on Zenoh's thread: counted apart)
        talker.undeclare()
    finally:
        sub.close()
    assert not any("mso_sub" in t for t in tokens(peer))  # its tokens went with it


class _SlowToDeclare:
    """A Zenoh session whose subscriptions are declared late: until the test says it has
    published, or a second has passed (a loaded machine between two declarations)."""

    def __init__(self, session: Any, published: threading.Event) -> None:
        self._session = session
        self._published = published

    def __getattr__(self, name: str) -> Any:
        return getattr(self._session, name)

    def declare_subscriber(self, *args: Any, **kwargs: Any) -> Any:
        self._published.wait(1.0)
        return self._session.declare_subscriber(*args, **kwargs)


def test_a_talker_that_waits_for_the_graph_reaches_a_subscriber_slow_to_declare(
    net: tuple[str, Any], monkeypatch: pytest.MonkeyPatch
) -> None:
    """The graph shows an mso subscription only once it is declared (its token comes after
    it, as rmw_zenoh's do): a ROS talker that waits for the subscriber in the graph and then
    publishes reaches it. Tokens first, the talker published into nothing (CI, run 2)."""
    endpoint, peer = net
    published = threading.Event()
    real = bridge._session
    monkeypatch.setattr(bridge, "_session", lambda r: _SlowToDeclare(real(r), published))
    sub = Subscriber("/chatter", "std_msgs/msg/String", router=endpoint)
    opener = threading.Thread(target=sub.open, daemon=True)
    opener.start()
    try:
        assert wait_for(lambda: any("/MS/" in t for t in tokens(peer)))
        talker = peer.declare_publisher(chatter_key())
        talker.put(cdr_string("first"), attachment=attachment(1, bytes(16)))
        published.set()
        assert drain(sub, 1) == [String(data="first")]
        talker.undeclare()
    finally:
        opener.join(patience(10.0))
        sub.close()


def test_an_mso_publisher_reaches_a_ros_listener(net: tuple[str, Any]) -> None:
    endpoint, peer = net
    listener = Listener(peer, chatter_key())
    pub = Publisher("chatter", "std_msgs/msg/String", router=endpoint, qos={"depth": 7})
    pub.open()
    try:
        zid = str(pub.session.zid())
        mp = (
            f"@ros2_lv/0/{zid}/0/1/MP/%/%/mso_pub_chatter/%chatter/"
            f"std_msgs::msg::dds_::String_/{STRING_HASH}/::,7:,:,:,,"
        )
        assert wait_for(lambda: mp in tokens(peer))
        assert routed(pub.session, pub.key)  # its session knows the listener's subscription
        before = time.time_ns()
        for i in range(5):
            pub(String(data=f"from mso {i}") if i % 2 else {"data": f"from mso {i}"})
        assert wait_for(lambda: len(listener.texts()) == 5)
    finally:
        pub.close()
    assert listener.texts() == [f"from mso {i}" for i in range(5)] and listener.bad == 0
    assert [g[1] for g in listener.got] == [1, 2, 3, 4, 5]  # sequence numbers from 1
    assert all(before <= g[2] <= time.time_ns() for g in listener.got)
    assert {g[3] for g in listener.got} == {pub.gid} and len(pub.gid) == 16


def test_a_forwarding_publisher_is_an_operator_that_publishes_and_passes_on(
    net: tuple[str, Any],
) -> None:
    endpoint, peer = net
    listener = Listener(peer, chatter_key())
    tee = Publisher("chatter", "std_msgs/msg/String", router=endpoint, forward=True)
    sink = Publisher("chatter", "std_msgs/msg/String", router=endpoint, node="mso_sink")
    tee.open()
    sink.open()
    try:
        assert routed(tee.session, tee.key) and routed(sink.session, sink.key)
        event = String(data="tee")
        assert tee(event) is event and sink(event) is None
        assert wait_for(lambda: listener.texts() == ["tee", "tee"])
    finally:
        tee.close()
        sink.close()
    with pytest.raises(ValueError, match="forward"):
        Publisher("chatter", "std_msgs/msg/String", forward="yes")


def test_humble_keys_and_another_domain(net: tuple[str, Any]) -> None:
    endpoint, peer = net
    listener = Listener(peer, chatter_key(domain=3, hash_="TypeHashNotSupported"))
    pub = Publisher("/chatter", "std_msgs/msg/String", router=endpoint, distro="humble", domain=3)
    pub.open()
    try:
        assert pub.key == "3/chatter/std_msgs::msg::dds_::String_/TypeHashNotSupported"
        assert routed(pub.session, pub.key)
        pub(String(data="humble"))
        assert wait_for(lambda: listener.texts() == ["humble"])
    finally:
        pub.close()


def test_keep_last_keeps_the_newest_and_counts_the_rest(net: tuple[str, Any]) -> None:
    endpoint, peer = net
    sub = Subscriber("chatter", "std_msgs/msg/String", router=endpoint, qos={"depth": 2})
    sub.open()
    try:
        assert wait_for(lambda: any("/MS/" in t for t in tokens(peer)))
        talker = peer.declare_publisher(chatter_key())
        for i in range(6):
            talker.put(cdr_string(f"m{i}"), attachment=attachment(i + 1, bytes(16)))
        assert wait_for(lambda: sub.stats()["received"] == 6)
        assert drain(sub, 2) == [String(data="m4"), String(data="m5")]
        assert sub.stats()["superseded"] == 4
        talker.put(b"\x00\x01\x00\x00\xff", attachment=attachment(7, bytes(16)))  # not CDR
        assert wait_for(lambda: sub.stats()["undecodable"] == 1)
        talker.undeclare()
    finally:
        sub.close()


def test_a_full_reliable_keep_all_queue_waits_and_close_never_hangs(net: tuple[str, Any]) -> None:
    endpoint, peer = net
    sub = Subscriber("chatter", "std_msgs/msg/String", router=endpoint, qos={"history": "keep_all"})
    sub.bound = 3  # a small queue, so that the Zenoh callback has to wait for room
    sub.open()
    try:
        assert wait_for(lambda: any("/MS/" in t for t in tokens(peer)))
        talker = peer.declare_publisher(chatter_key())
        for i in range(5):
            talker.put(cdr_string(f"m{i}"), attachment=attachment(i + 1, bytes(16)))
        assert wait_for(lambda: sub.stats()["waited"] >= 1)
        assert drain(sub, 5) == [String(data=f"m{i}") for i in range(5)]  # none lost
        for i in range(5, 10):  # fill it again and leave a callback waiting
            talker.put(cdr_string(f"m{i}"), attachment=attachment(i + 1, bytes(16)))
        assert wait_for(lambda: sub.stats()["waited"] >= 2)
        talker.undeclare()
    finally:
        t0 = time.monotonic()
        sub.close()
        assert time.monotonic() - t0 < CLOSE_S + 1.0


def test_transient_local_gives_a_late_joiner_the_last_samples(net: tuple[str, Any]) -> None:
    """transient_local as rmw_zenoh serves it (Zenoh's advanced publisher with a cache of
    ``depth`` and publisher detection; a late subscription asks it for its history): an mso
    Publisher's last 3 reach a listener that joins after them; an mso Subscriber that joins
    after a ROS talker's 5 gets its last 3, then what comes next; a volatile one nothing old."""
    endpoint, peer = net
    durable = {"durability": "transient_local", "depth": 3}
    pub = Publisher("chatter", "std_msgs/msg/String", router=endpoint, qos=durable)
    pub.open()
    on_time = Listener(peer, chatter_key())
    try:
        assert routed(pub.session, pub.key)  # the listener on time is known to it
        for i in range(5):
            pub(String(data=f"mso {i}"))
        assert wait_for(lambda: len(on_time.texts()) == 5)  # (they are past the router)
        got: list[str] = []
        history = zenoh_ext.HistoryConfig(detect_late_publishers=True, max_samples=3)
        late = zenoh_ext.declare_advanced_subscriber(
            peer, chatter_key(), lambda s: got.append(decode_string(s)), history=history
        )
        assert wait_for(lambda: len(got) >= 3)
        pub(String(data="mso 5"))  # live, after the history: nothing else came between
        assert wait_for(lambda: "mso 5" in got)
        assert got == ["mso 2", "mso 3", "mso 4", "mso 5"]
        late.undeclare()
    finally:
        pub.close()
    cache = zenoh_ext.CacheConfig(3)
    talker = zenoh_ext.declare_advanced_publisher(
        peer, chatter_key(), cache=cache, publisher_detection=True
    )
    for i in range(5):
        talker.put(cdr_string(f"ros {i}"), attachment=attachment(i + 1, bytes(16)))
    assert wait_for(lambda: len(on_time.texts()) == 11)
    sub = Subscriber("chatter", "std_msgs/msg/String", router=endpoint, qos=durable)
    volatile = Subscriber("chatter", "std_msgs/msg/String", router=endpoint, node="plain")
    sub.open()
    volatile.open()
    try:
        assert drain(sub, 3) == [String(data=f"ros {i}") for i in (2, 3, 4)]
        # a token is declared after its subscription (rmw_zenoh's order): once the graph
        # shows both, the router routes to both
        assert wait_for(lambda: sum("/MS/" in t for t in tokens(peer)) == 2)
        talker.put(cdr_string("ros 5"), attachment=attachment(6, bytes(16)))
        assert drain(sub, 1) == [String(data="ros 5")]
        assert drain(volatile, 1) == [String(data="ros 5")]  # and nothing before it
        assert volatile.stats()["received"] == 1
    finally:
        sub.close()
        volatile.close()
        talker.undeclare()


def test_an_unreachable_router_fails_open_in_bounded_time() -> None:
    """The open fails (it does not hang waiting for a router that never comes): a deadline
    far past the connect timeout bounds the wait, not a speed the machine must make."""
    sub = Subscriber("chatter", "std_msgs/msg/String", router=f"tcp/127.0.0.1:{free_port()}")
    failed: list[BaseException] = []

    def open_it() -> None:
        try:
            sub.open()
        except Exception as exc:  # what a vertex's open() raises to its node
            failed.append(exc)

    opener = threading.Thread(target=open_it, daemon=True)
    opener.start()
    opener.join(60.0)
    assert not opener.is_alive(), "open() still waiting for the router"
    assert failed and "connect" in str(failed[0]).lower(), failed
    sub.close()


def test_params_are_checked_when_the_vertex_is_made() -> None:
    with pytest.raises(ValueError, match="type store"):
        Subscriber("chatter", "std_msgs/msg/Nope")
    with pytest.raises(ValueError, match="domain"):
        Publisher("chatter", "std_msgs/msg/String", domain=999)
    with pytest.raises(ValueError, match="distro"):
        Publisher("chatter", "std_msgs/msg/String", distro="ardent")
    custom = "int32 count\nstring label\n"
    pub = Publisher("blobs", "mso_test/msg/Blob", msgdef=custom)
    assert pub.key.startswith("0/blobs/mso_test::msg::dds_::Blob_/RIHS01_")
