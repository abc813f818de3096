"""The daemon's log: one logfmt line a record (``ts=… level=info node=N1 event=relocation
app=convoy vertex=odom_filter move="N1 -> N2" by=rule took_ms=1.3 asked="the relocation rule on
N1: …"``).

logfmt rather than JSON lines: ``journalctl -u mso-node`` and ``tail -f`` stay readable by eye
on a robot's console, ``grep event=relocation`` finds every move, and every value is still a
``key=value`` a log shipper parses without a schema (docs/fleet.md).
"""

from __future__ import annotations

import datetime
import logging
import math
import os
import sys
from collections.abc import Mapping
from typing import Any

KV = "kv"  # a record's ``extra`` key holding its fields


def logfmt_value(value: Any) -> str:
    """A value as logfmt writes it: bare when it can be, else quoted with escapes."""
    if isinstance(value, float):
        text = f"{value:.6g}"
    elif isinstance(value, bool):
        text = "true" if value else "false"
    else:
        text = str(value)
    if text and not any(c in text for c in ' ="\\\n\t'):
        return text
    escaped = text.replace("\\", "\\\\").replace('"', '\\"').replace("\n", "\\n")
    return f'"{escaped}"'


def logfmt(fields: Mapping[str, Any]) -> str:
    """``key=value`` pairs in the order given; empty and None values are left out."""
    return " ".join(
        f"{k}={logfmt_value(v)}" for k, v in fields.items() if v is not None and v != ""
    )


RUN_START_ENV = "MSO_RUN_START"  # an emulator's start (wall clock): lines count from it


def run_start() -> float | None:
    """When the emulator that started this node began (None: not emulated, or unreadable)."""
    try:
        value = float(os.environ.get(RUN_START_ENV, ""))
    except ValueError:
        return None
    return value if math.isfinite(value) and value > 0 else None


class LogfmtFormatter(logging.Formatter):
    """The time, level, node, then the record's fields (``extra={"kv": …}``) or its message as
    ``msg=``; an exception's traceback folds into ``exc=`` so a record stays one line.

    One clock for every line: on a device the wall time with its UTC offset (``ts=``, local
    time, so it matches the robot's other logs); in an emulator the seconds since its start
    (``t=``), the clock its console tells everything on."""

    def __init__(self, node_id: str, run_start: float | None = None) -> None:
        super().__init__()
        self.node_id = node_id
        self.run_start = run_start

    def format(self, record: logging.LogRecord) -> str:
        fields: dict[str, Any] = {}
        if self.run_start is not None:
            fields["t"] = f"{record.created - self.run_start:.3f}"
        else:
            when = datetime.datetime.fromtimestamp(record.created).astimezone()
            fields["ts"] = when.isoformat(timespec="milliseconds")
        fields |= {"level": record.levelname.lower(), "node": self.node_id}
        kv = getattr(record, KV, None)
        if isinstance(kv, Mapping):
            fields.update(kv)
        else:
            fields["msg"] = record.getMessage()
        if record.exc_info:
            fields["exc"] = self.formatException(record.exc_info)
        return logfmt(fields)


def setup_logging(node_id: str, verbose: bool) -> None:
    """Info by default (start, deploys, moves, failures, stop), debug with ``-v``, on stderr
    (systemd's journal takes it from there)."""
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(LogfmtFormatter(node_id, run_start()))
    root = logging.getLogger()
    for old in list(root.handlers):
        root.removeHandler(old)
    root.addHandler(handler)
    root.setLevel(logging.DEBUG if verbose else logging.INFO)
    # each connection attempt and refused frame is debugging material (status counts them)
    logging.getLogger("mso.net").setLevel(logging.NOTSET if verbose else logging.WARNING)
