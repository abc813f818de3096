"""Make modules in ``tests/`` (e.g. ``apphelpers``) importable by YAML import paths."""

from __future__ import annotations

import os
import sys
from pathlib import Path

_TESTS = str(Path(__file__).resolve().parent)
if _TESTS not in sys.path:
    sys.path.insert(0, _TESTS)

from mso.node.core import NodeCore  # noqa: E402

# node processes the tests start (the emulator's) may import the tests' own vertex modules
os.environ.setdefault(
    "MSO_ALLOW_CODE",
    "runtime_vertices,apphelpers,executor_vertices,custom_policy,test_heavy_vertex,"
    "dataplane_vertices,failure_vertices,slow_import_vertices",
)

# in tests, a message at a moment a procedure's transition table does not allow raises
NodeCore.strict = True
