"""How long a test waits for something that should happen: a loaded machine (2 cores, other
suites beside) makes seconds into tens of seconds, so every deadline on a wait goes through
``patience``. A wait returns as soon as its event happens; only a failure waits the whole time.
``MSO_TEST_TIMEOUT_SCALE`` multiplies them (default 3: generous; raise it on a slower box)."""

from __future__ import annotations

import os

_DEFAULT_SCALE = 3.0


def scale() -> float:
    """The factor from ``MSO_TEST_TIMEOUT_SCALE``; a bad value is an error, not a silent 1."""
    raw = os.environ.get("MSO_TEST_TIMEOUT_SCALE", "")
    if not raw:
        return _DEFAULT_SCALE
    try:
        factor = float(raw)
    except ValueError:
        raise ValueError(f"MSO_TEST_TIMEOUT_SCALE={raw!r}: not a number") from None
    if not factor > 0:
        raise ValueError(f"MSO_TEST_TIMEOUT_SCALE={raw!r}: must be > 0")
    return factor


def patience(seconds: float) -> float:
    """The deadline for a wait that takes ``seconds`` on a quiet machine, scaled."""
    return seconds * scale()
