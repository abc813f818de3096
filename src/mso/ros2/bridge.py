"""ROS 2 topics as mso vertices: :class:`Subscriber` (a source) and :class:`Publisher` (a sink).

They speak rmw_zenoh's wire contract (:mod:`mso.ros2.wire`) through zenoh-python, connected as
a Zenoh *client* to the router the app names (``router``: on a robot, the one ``rmw_zenohd``
runs; a Python *peer* behind it does not see ROS topics). Multicast scouting is off: the
session talks to that endpoint only.

zenoh-python calls back on Zenoh's own threads and has no asyncio API. So the Subscriber's
callback only decodes the sample and puts it in a bounded queue; the vertex is a free-running
source that mso's executor iterates in the vertex's worker thread, never on the control plane.
With ``history: keep_last`` a full queue drops its oldest message (``superseded``, counted);
with ``keep_all`` and ``reliable`` the callback waits for room (``waited``), which pushes back
through Zenoh's reliable transport. ``durability: transient_local`` uses Zenoh's advanced
publisher (a cache of the last ``depth``) and subscriber (history asked of late publishers), as
rmw_zenoh does. ``close()`` wakes any waiting callback and undeclares on a helper thread it
waits for at most :data:`CLOSE_S`, so a stuck Zenoh never holds the node.
"""

from __future__ import annotations

import collections
import contextlib
import json
import threading
import time
from typing import Any

import numpy as np

from mso.ros2 import wire
from mso.ros2.types import TypeMap, register, type_map

DEFAULT_ROUTER = "tcp/127.0.0.1:7447"  # where rmw_zenohd listens on a robot
CONNECT_MS = 5000  # how long open() tries the router before it fails
POLL_S = 0.05  # how long one next() waits for a message before it yields None
CLOSE_S = 2.0  # how long close() waits for Zenoh to undeclare and close
KEEP_ALL_BOUND = 1000  # queue bound of a keep_all subscription


def _session(router: str) -> Any:
    """A Zenoh session connected as a client to ``router`` only (no scouting)."""
    try:
        import zenoh
    except ImportError as exc:  # the optional extra is missing
        raise RuntimeError("mso.ros2 needs the ros2 extra: pip install 'mso[ros2]'") from exc
    conf = zenoh.Config()
    conf.insert_json5("mode", '"client"')
    conf.insert_json5("connect/endpoints", json.dumps([router]))
    conf.insert_json5("connect/timeout_ms", str(CONNECT_MS))
    conf.insert_json5("connect/exit_on_failure", "true")
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("timestamping/enabled", "true")  # as rmw_zenoh's (transient_local needs it)
    return zenoh.open(conf)


def _close_quietly(*things: Any) -> bool:
    """Undeclare/close ``things`` in order on a helper thread; True if done within CLOSE_S."""

    def run() -> None:
        for thing in things:
            if thing is None:
                continue
            # already closed, or the router went away: nothing to keep
            with contextlib.suppress(Exception):
                thing.undeclare() if hasattr(thing, "undeclare") else thing.close()

    helper = threading.Thread(target=run, name="mso-ros2-close", daemon=True)
    helper.start()
    helper.join(CLOSE_S)
    return not helper.is_alive()


class CdrBuffer:
    """A message's CDR bytes, serialized into one buffer kept from call to call.

    A fresh ``bytes`` of a 900 KiB Image handed to Zenoh each call cost more than the
    serializing: once Zenoh had freed a few of them on its own threads, glibc gave every new one
    fresh pages (418 page faults a message, 1.2 ms: 520 Images/s where the same calls managed
    3,000 before). Zenoh copies a ``bytearray`` as ``put`` is called, so one buffer serves every
    message of a size; it is zeroed first, since rosbags' serializer leaves CDR's padding and a
    string's terminating NUL as it finds them."""

    def __init__(self, types: TypeMap, ros_type: str) -> None:
        self.store = types.store
        self.msgdef = types.store.get_msgdef(ros_type)
        self.buf = bytearray(0)
        self.zero: Any = None  # a numpy view of buf, to zero it in place

    def encode(self, msg: Any) -> bytearray:
        """The CDR of ``msg`` (little-endian, with its encapsulation header): valid until the
        next call."""
        size = 4 + self.msgdef.getsize_cdr(0, msg, self.store)
        if len(self.buf) != size:  # a new size: a new buffer (the old one may be exported)
            self.buf = bytearray(size)
            self.zero = np.frombuffer(self.buf, dtype=np.uint8)
        else:
            self.zero.fill(0)
        view = memoryview(self.buf)
        view[1] = 1  # CDR_LE: 00 01 00 00
        self.msgdef.serialize_cdr_le(view[4:], 0, msg, self.store)
        return self.buf


class _Endpoint:
    """What a Subscriber and a Publisher share: params, type, keys and tokens."""

    kind = ""

    def __init__(
        self,
        topic: str,
        type: str,
        domain: int = 0,
        distro: str = "jazzy",
        router: str = DEFAULT_ROUTER,
        qos: Any = None,
        node: str | None = None,
        namespace: str = "",
        msgdef: str | None = None,
    ) -> None:
        self.topic = wire.fully_qualified(topic)
        if not isinstance(domain, int) or not 0 <= domain <= 232:
            raise ValueError(f"domain: expected a ROS domain id from 0 to 232, got {domain!r}")
        if msgdef is not None:
            register(type, msgdef)
        self.types: TypeMap = type_map(distro)
        self.types.check(type)
        self.ros_type = type
        self.domain = domain
        self.distro = distro
        self.router = router
        self.qos = wire.qos_from(qos)
        # samples kept for a late joiner (transient_local): rmw_zenoh's 42 for a depth of 0
        keep_last = self.qos.history == "keep_last"
        self.history = (self.qos.depth or wire.RMW_DEFAULT_DEPTH) if keep_last else KEEP_ALL_BOUND
        role = "sub" if self.kind == "MS" else "pub"
        self.node = node or f"mso_{role}_{self.topic.strip('/').replace('/', '_')}"
        self.namespace = namespace
        self.type_hash = wire.type_hash_for(distro, self.types.rihs01(type))
        self.key = wire.topic_key(domain, self.topic, type, self.type_hash)
        self.session: Any = None
        self.tokens: list[Any] = []
        self.token = ""
        self.gid = b""
        self.closed = False

    def _connect(self) -> None:
        """Open the session and name the entity (its token's key, its GID)."""
        self.session = _session(self.router)
        zid = str(self.session.zid())
        self.token = wire.entity_token(
            self.kind, self.domain, zid, 0, 1, self.node, self.topic, self.ros_type,
            self.type_hash, self.qos, namespace=self.namespace,
        )  # fmt: skip
        self.gid = wire.gid_of(self.token)

    def _announce(self) -> None:
        """Declare the node's and the entity's liveliness tokens, once the entity is declared
        (rmw_zenoh's order): a ROS node that sees the token in the graph (``ros2 topic info``,
        a wait for a subscriber's count) reaches the entity, since the router has its
        declaration first. Tokens first, a talker that waited for the graph published into
        a subscription the router did not have yet, and lost the first messages."""
        zid = str(self.session.zid())
        node = wire.node_token(self.domain, zid, 0, self.node, namespace=self.namespace)
        lv = self.session.liveliness()
        self.tokens = [lv.declare_token(node), lv.declare_token(self.token)]

    def _shut(self, *entities: Any) -> bool:
        """Undeclare in the reverse order: off the graph first, then the entity."""
        self.closed = True
        session, self.session = self.session, None
        tokens, self.tokens = self.tokens, []
        return _close_quietly(*reversed(tokens), *entities, session)


class Subscriber(_Endpoint):
    """A source: the messages of a ROS 2 topic, as the type's Struct (:mod:`mso.ros2.types`).

    Params: ``topic``, ``type`` (``std_msgs/msg/String``), ``domain`` (0), ``distro``
    (``jazzy``; ``humble`` for hash-less keys), ``router`` (a Zenoh endpoint),
    ``qos`` (``{reliability, durability, history, depth}``), ``node``, ``namespace``,
    ``msgdef`` (a custom type's ``.msg`` text).
    """

    kind = "MS"

    def __init__(self, topic: str, type: str, **params: Any) -> None:
        super().__init__(topic, type, **params)
        keep_last = self.qos.history == "keep_last"
        self.bound = max(1, self.qos.depth) if keep_last else KEEP_ALL_BOUND
        self.wait_for_room = not keep_last and self.qos.reliability == "reliable"
        self.queue: collections.deque[Any] = collections.deque()
        self.ready = threading.Condition()
        self.subscriber: Any = None
        self.counts = {"received": 0, "superseded": 0, "waited": 0, "undecodable": 0}
        self.decode_s = 0.0  # CPU time decoding on Zenoh's threads
        self.last_error = ""

    def open(self) -> None:
        self._connect()
        if self.qos.durability == "transient_local":  # a late joiner: the last samples first
            from zenoh import ext

            history = ext.HistoryConfig(detect_late_publishers=True, max_samples=self.history)
            self.subscriber = ext.declare_advanced_subscriber(
                self.session, self.key, self._on_sample, history=history
            )
        else:
            self.subscriber = self.session.declare_subscriber(self.key, self._on_sample)
        self._announce()

    def _on_sample(self, sample: Any) -> None:
        """On a Zenoh thread: decode, then queue (drop the oldest, or wait, when full). The
        decoding's CPU time is counted (``decode_ms``): the vertex's own CPU in mso status is
        its worker's, which does not decode."""
        started = time.thread_time()
        try:
            raw = sample.payload.to_bytes()
            if sample.attachment is not None:  # rmw_zenoh always sends one; check its form
                wire.Attachment.decode(sample.attachment.to_bytes())
            msg = self.types.store.deserialize_cdr(raw, self.ros_type)
            event = self.types.to_struct(self.ros_type, msg)
        except Exception as exc:  # a malformed sample is counted, never fatal
            with self.ready:
                self.counts["undecodable"] += 1
                self.last_error = f"{type(exc).__name__}: {exc}"
            return
        with self.ready:
            self.decode_s += time.thread_time() - started
            self.counts["received"] += 1
            if len(self.queue) >= self.bound and self.wait_for_room:
                self.counts["waited"] += 1
                while len(self.queue) >= self.bound and not self.closed:
                    self.ready.wait(POLL_S)
            if self.closed:
                return
            if len(self.queue) >= self.bound:
                self.queue.popleft()
                self.counts["superseded"] += 1
            self.queue.append(event)
            self.ready.notify_all()

    def __iter__(self) -> Subscriber:
        return self

    def __next__(self) -> Any:
        """The next message, or None after POLL_S without one (so the worker stays free to
        take a stop, and its credit comes back)."""
        with self.ready:
            if not self.queue:
                self.ready.wait(POLL_S)
            if not self.queue:
                return None
            event = self.queue.popleft()
            self.ready.notify_all()
            return event

    def stats(self) -> dict[str, Any]:
        with self.ready:
            decode_ms = round(self.decode_s * 1e3, 3)
            return {**self.counts, "queued": len(self.queue), "decode_ms": decode_ms,
                    "key": self.key}  # fmt: skip

    def close(self) -> None:
        with self.ready:
            self.closed = True
            self.ready.notify_all()
        subscriber, self.subscriber = self.subscriber, None
        self._shut(subscriber)


class Publisher(_Endpoint):
    """A sink: every event it consumes (the type's Struct, or a mapping of its fields) is
    published on a ROS 2 topic as CDR with rmw_zenoh's attachment. Params as
    :class:`Subscriber`'s, and ``forward``: an operator that also passes each event on (a
    tee into ROS mid-chain; off by default, so a sink does not encode what nobody reads)."""

    kind = "MP"

    def __init__(self, topic: str, type: str, forward: bool = False, **params: Any) -> None:
        super().__init__(topic, type, **params)
        if not isinstance(forward, bool):
            raise ValueError(f"forward: expected true or false, got {forward!r}")
        self.forward = forward
        self.publisher: Any = None
        self.encoder = CdrBuffer(self.types, type)
        self.seq = 0

    def open(self) -> None:
        import zenoh

        self._connect()
        reliable = self.qos.reliability == "reliable"
        Rel, Cc = zenoh.Reliability, zenoh.CongestionControl
        options: dict[str, Any] = {
            "reliability": Rel.RELIABLE if reliable else Rel.BEST_EFFORT,
            "congestion_control": Cc.BLOCK if reliable else Cc.DROP,
        }
        if self.qos.durability == "transient_local":  # keeps its last samples for late joiners
            from zenoh import ext

            self.publisher = ext.declare_advanced_publisher(
                self.session, self.key, cache=ext.CacheConfig(self.history),
                publisher_detection=True, **options,
            )  # fmt: skip
        else:
            self.publisher = self.session.declare_publisher(self.key, **options)
        self._announce()

    def __call__(self, event: Any) -> Any:
        if self.publisher is None:
            raise RuntimeError("the publisher is not open")
        payload = self.encoder.encode(self.types.to_ros(self.ros_type, event))
        self.seq += 1
        attachment = wire.Attachment(self.seq, time.time_ns(), self.gid).encode()
        self.publisher.put(payload, attachment=attachment)
        return event if self.forward else None

    def stats(self) -> dict[str, Any]:
        return {"published": self.seq, "key": self.key}

    def close(self) -> None:
        publisher, self.publisher = self.publisher, None
        self._shut(publisher)
