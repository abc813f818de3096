"""Per-edge delivery settings: reliability, history, deadline, lifespan and the store-and-forward
bound with its overflow policy (docs/app-format.md, "Edge QoS").

The values live on :class:`mso.model.app.Edge`; this module holds their names, defaults and
the one check both the YAML loader and the Python builder go through.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

RELIABILITY = ("reliable", "best_effort")
OVERFLOW = ("buffer", "drop_oldest", "keep_latest")
DEFAULT_BUFFER_BYTES = 256 << 20  # per edge, memory and spill together
DEFAULT_BUFFER_AGE_S = 900.0
MAX_BUFFER_BYTES = 1 << 40
MAX_KEEP_LAST = 1 << 20
QOS_KEYS = (
    "qos",
    "keep_last",
    "deadline_ms",
    "lifespan_ms",
    "buffer_bytes",
    "buffer_age_s",
    "overflow",
)

Error = Callable[[str, str, tuple[Any, ...]], Exception]


def check_edge_qos(edge: Any, error: Error, where: str, path: tuple[Any, ...]) -> None:
    """Raise ``error(message, field, path)`` for the first bad QoS value of ``edge``."""

    def bad(key: str, expected: str) -> Exception:
        return error(
            f"expected {expected}, got {getattr(edge, key)!r}", f"{where}.{key}", (*path, key)
        )

    if edge.qos not in RELIABILITY:
        raise bad("qos", f"one of {', '.join(RELIABILITY)}")
    if edge.overflow not in OVERFLOW:
        raise bad("overflow", f"one of {', '.join(OVERFLOW)}")
    if edge.keep_last is not None and not _int_in(edge.keep_last, 1, MAX_KEEP_LAST):
        raise bad("keep_last", f"an integer from 1 to {MAX_KEEP_LAST}")
    if not _int_in(edge.buffer_bytes, 0, MAX_BUFFER_BYTES):
        raise bad("buffer_bytes", f"an integer byte count from 0 to {MAX_BUFFER_BYTES} (1 TiB)")
    for key in ("deadline_ms", "lifespan_ms", "buffer_age_s"):
        value = getattr(edge, key)
        if (value is not None or key == "buffer_age_s") and not _positive(value):
            raise bad(key, "a positive number")


def _int_in(value: Any, low: int, high: int) -> bool:
    return isinstance(value, int) and not isinstance(value, bool) and low <= value <= high


def _positive(value: Any) -> bool:
    return (
        isinstance(value, int | float)
        and not isinstance(value, bool)
        and math.isfinite(value)
        and value > 0
    )
