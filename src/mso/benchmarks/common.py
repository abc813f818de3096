"""Helpers every benchmark shares: which sources were measured, and percentiles."""

from __future__ import annotations

import hashlib
import math
from pathlib import Path


def src_digest() -> str:
    """sha256 over src/mso/**/*.py: which state of the sources a result was measured on."""
    h = hashlib.sha256()
    src = Path(__file__).resolve().parent.parent
    for f in sorted(src.rglob("*.py")):
        h.update(str(f.relative_to(src)).encode() + b"\0" + f.read_bytes())
    return h.hexdigest()[:16]


def percentile(values: list[float], q: float) -> float:
    """Linear-interpolated percentile (q in 0..100) of a non-empty list."""
    s = sorted(values)
    if len(s) == 1:
        return s[0]
    pos = (len(s) - 1) * q / 100.0
    lo = math.floor(pos)
    hi = min(lo + 1, len(s) - 1)
    return s[lo] + (s[hi] - s[lo]) * (pos - lo)
