"""A vertex instance's life at the node that hosts it: the host's part in deployment,
relocation (as old host and as new host) and restore.

The coordinator's side of a relocation is :class:`~mso.protocol.procedures.relocation.Relocation`;
this is the other end. An instance is STARTING until the executor has constructed it. One
asked for by a build then RUNS; one asked for by a relocation or restore (the *new host*) is
AWAITING until the old host's handover arrives or every surviving end of its edges has resumed
it. At the *old host* a RUNNING instance is DRAINING once a marker reached it behind the events
sent before the switch, SNAPSHOTTING once every input is marked and everything before the
markers is processed, and FINISHED when its state and channels are handed over. Any instance
may be stopped (undeploy, reset, failed construction): FAILED.

An instance in a child process of its own (``isolation: process``) may *crash*: the child dies
unasked. One that had not started yet FAILED, as a failed construction does. A RUNNING one is
CRASHED: its host restores the vertex in place (``restart``: FINISHED; a fresh instance takes
its place and the surviving ends of its edges replay, as after a node failure), at most
``MAX_RESTARTS`` times in ``RESTART_WINDOW_S``; past that it stays CRASHED and its chains are
reported parked until it is undeployed (``stop``). One that crashes while it hands over
(DRAINING, SNAPSHOTTING) or waits for a handover (AWAITING) is CRASHED and not restored: the
relocation in flight fails by its deadline (docs/architecture.md, Executor, says what is lost).

An AWAITING instance's wait ends by its coordinator: a move that fails before any producer
switched (its deadline passed with the target's answer lost, or a node it needed failed) sends
``Unprepare`` and the target stops the instance (``stop``). Once a producer has switched, the
move is committed — events for the new instance are held at the target — and the instance
waits for the handover however long the old instance's queue takes to drain; if the old host
fails meanwhile, recovery restores the vertex and reuses this instance.

A producer's part (switch an edge, send a marker the old way) and a probe hop's (append itself,
forward) are single steps with no wait, so they have no states of their own; a probe held at a
hop whose route goes through a failed node is dropped after ``STEP_TIMEOUT_S``.
"""

from __future__ import annotations

import enum
from typing import ClassVar

from mso.protocol.procedures.base import Phase, StateMachine, Table

AWAIT_NOTE = "an AWAITING instance's wait is ended by its coordinator's Unprepare"


class H(enum.Enum):
    STARTING = "starting"
    RUNNING = "running"
    AWAITING = "awaiting"
    DRAINING = "draining"
    SNAPSHOTTING = "snapshotting"
    CRASHED = "crashed"


MAX_RESTARTS = 3  # crashes of one vertex at one host restored in place within ...
RESTART_WINDOW_S = 60.0  # ... this long; one more and it stays crashed


class InstanceEvent(enum.Enum):
    """What moves a InstanceLife along its table."""

    STARTED = "started"
    STARTED_FOR_MOVE = "started_for_move"
    STOP = "stop"
    CRASH = "crash"
    HANDOVER = "handover"
    RESUMED = "resumed"
    MARKER = "marker"
    ALL_MARKED = "all_marked"
    HANDED_OVER = "handed_over"
    RESTART = "restart"


class InstanceLife(StateMachine):
    """One vertex instance's state at its host (see the module docstring)."""

    NAME = "instance"
    INITIAL = H.STARTING
    TRANSITIONS: ClassVar[Table] = {
        H.STARTING: {
            InstanceEvent.STARTED: H.RUNNING,
            InstanceEvent.STARTED_FOR_MOVE: H.AWAITING,
            InstanceEvent.STOP: Phase.FAILED,
            InstanceEvent.CRASH: Phase.FAILED,  # as a failed construction
        },
        H.AWAITING: {
            InstanceEvent.HANDOVER: H.RUNNING,  # a relocation: the old instance's state arrived
            InstanceEvent.RESUMED: H.RUNNING,  # a restore: every surviving end has resumed it
            InstanceEvent.STOP: Phase.FAILED,  # unprepared, undeployed or reset
            InstanceEvent.CRASH: H.CRASHED,
        },
        H.RUNNING: {
            InstanceEvent.MARKER: H.DRAINING,
            InstanceEvent.ALL_MARKED: H.SNAPSHOTTING,
            InstanceEvent.STOP: Phase.FAILED,
            InstanceEvent.CRASH: H.CRASHED,
        },
        H.DRAINING: {
            InstanceEvent.MARKER: H.DRAINING,
            InstanceEvent.ALL_MARKED: H.SNAPSHOTTING,
            InstanceEvent.STOP: Phase.FAILED,
            InstanceEvent.CRASH: H.CRASHED,
        },
        H.SNAPSHOTTING: {
            InstanceEvent.HANDED_OVER: Phase.FINISHED,
            InstanceEvent.STOP: Phase.FAILED,
            InstanceEvent.CRASH: H.CRASHED,
        },
        H.CRASHED: {
            InstanceEvent.RESTART: Phase.FINISHED,  # a fresh instance takes its place (in place)
            InstanceEvent.STOP: Phase.FAILED,  # undeployed or reset while it stays crashed
        },
    }

    def __init__(self, vertex: str) -> None:
        super().__init__()
        self.vertex = vertex

    @property
    def name(self) -> str:
        return f"instance of {self.vertex!r}"
