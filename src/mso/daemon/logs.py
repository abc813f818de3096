"""The daemon's log: one logfmt line a record (``ts=… level=info node=N1 event=relocation
app=convoy vertex=odom_filter from=N1 to=N2 by=rule took_ms=1.3``).

logfmt rather than JSON lines: ``journalctl -u mso-node`` and ``tail -f`` stay readable by eye
on a robot's console, ``grep event=relocation`` finds every move, and every value is still a
``key=value`` a log shipper parses without a schema (docs/fleet.md).
"""

from __future__ import annotations

import logging
import sys
import time
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


class LogfmtFormatter(logging.Formatter):
    """Wall-clock UTC time, level, node, then the record's fields (``extra={"kv": …}``) or its
    message as ``msg=``; an exception's traceback folds into ``exc=`` so a record stays one
    line."""

    def __init__(self, node_id: str) -> None:
        super().__init__()
        self.node_id = node_id

    def format(self, record: logging.LogRecord) -> str:
        fields: dict[str, Any] = {
            "ts": time.strftime("%Y-%m-%dT%H:%M:%S", time.gmtime(record.created))
            + f".{int(record.msecs):03d}Z",
            "level": record.levelname.lower(),
            "node": self.node_id,
        }
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
    handler.setFormatter(LogfmtFormatter(node_id))
    root = logging.getLogger()
    for old in list(root.handlers):
        root.removeHandler(old)
    root.addHandler(handler)
    root.setLevel(logging.DEBUG if verbose else logging.INFO)
    # each connection attempt and refused frame is debugging material (status counts them)
    logging.getLogger("mso.net").setLevel(logging.NOTSET if verbose else logging.WARNING)
