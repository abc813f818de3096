"""A module that must never be imported by a node that did not allow it: importing it writes
the file named by ``$MSO_EVIL_MARK`` (the allowlist tests check that file never appears)."""

from __future__ import annotations

import os
from pathlib import Path

_mark = os.environ.get("MSO_EVIL_MARK")
if _mark:
    Path(_mark).write_text("imported")


def vertex(event: object) -> object:
    return event
