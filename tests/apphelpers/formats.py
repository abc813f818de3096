"""Formats and code that test apps name as ``apphelpers.formats:...``."""

from __future__ import annotations

import msgspec


class Scan(msgspec.Struct):
    seq: int
    ranges: list[float] = []


class Pose(msgspec.Struct):
    x: float
    y: float


class NotAStruct:
    """A plain class: naming it as a format is an error."""


CONSTANT = 42  # not callable: naming it as code is an error


def scan_source(seq: int, now: float) -> Scan:
    return Scan(seq=seq)


def to_pose(event: Scan) -> Pose:
    return Pose(x=float(event.seq), y=0.0)


def store(event: Pose) -> None:
    return None
