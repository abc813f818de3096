"""Make modules in ``tests/`` (e.g. ``apphelpers``) importable by YAML import paths."""

from __future__ import annotations

import os
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

_TESTS = str(Path(__file__).resolve().parent)
if _TESTS not in sys.path:
    sys.path.insert(0, _TESTS)

from mso.model.imports import allow_code, allowed_code  # noqa: E402
from mso.node.core import NodeCore  # noqa: E402

# node processes the tests start (the emulator's) may import the tests' own vertex modules
os.environ.setdefault(
    "MSO_ALLOW_CODE",
    "runtime_vertices,apphelpers,custom_policy,test_heavy_vertex,slow_import_vertices,"
    "ros2_vertices",
)

# in tests, a message at a moment a procedure's transition table does not allow raises
NodeCore.strict = True


@pytest.fixture(scope="session", autouse=True)
def _overlays_of_this_session(tmp_path_factory: pytest.TempPathFactory) -> Iterator[None]:
    """Running emulators are found under /tmp/mso-UID whatever $TMPDIR says: the suite keeps
    its own (another user's emulator, or another suite running beside, stays out of sight)."""
    old = os.environ.get("MSO_RUN_DIR")
    os.environ["MSO_RUN_DIR"] = str(tmp_path_factory.mktemp("run"))
    yield
    if old is None:
        os.environ.pop("MSO_RUN_DIR", None)
    else:
        os.environ["MSO_RUN_DIR"] = old


@pytest.fixture(scope="session", autouse=True)
def _convoy_log_in_pytests_tmp(tmp_path_factory: pytest.TempPathFactory) -> Iterator[None]:
    """The convoy's storage vertex writes $MSO_CONVOY_DB, else mso-convoy.sqlite in the
    system's temp dir: a test that deploys the convoy without saying where would leave that
    file behind. Tests that set it themselves still do."""
    old = os.environ.get("MSO_CONVOY_DB")
    if old is None:
        os.environ["MSO_CONVOY_DB"] = str(tmp_path_factory.mktemp("convoy") / "convoy.sqlite")
    yield
    if old is None:
        os.environ.pop("MSO_CONVOY_DB", None)


@pytest.fixture
def keep_allowlist() -> Iterator[None]:
    """settle() restricts this process's code imports, as a daemon's must: undone after."""
    before = allowed_code()
    try:
        yield
    finally:
        allow_code(before)


# Modules whose tests start node processes (an emulator), a netns testbed, Ray or a browser:
# seconds each, most of the suite's CPU. `make test` runs the rest (every behaviour is also tested
# in one process or the simulator); `make test-all`, SLOW=1 and CI (CI=true) run these too. A
# test elsewhere that starts node processes or namespaces takes @pytest.mark.slow.
SLOW_MODULES = frozenset(
    {
        "test_cli_live",
        "test_convoy_emulated",
        "test_daemon_log",
        "test_emulate_identities",
        "test_emulate_keys",
        "test_emulator",
        "test_emulator_cleanup",
        "test_emulator_faults",
        "test_heavy_vertex",
        "test_isolation",
        "test_lifetime_study",
        "test_metrics",
        "test_netns",
        "test_overlays",
        "test_ros2_emulated",
        "test_slow_import",
        "test_sweep",
    }
)


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """Mark the end-to-end modules' tests ``slow`` (see SLOW_MODULES)."""
    for item in items:
        if item.path.stem in SLOW_MODULES:
            item.add_marker(pytest.mark.slow)


_slow_left_out = 0  # end-to-end tests `-m "not slow"` deselected (each xdist worker counts all)


def pytest_deselected(items: list[pytest.Item]) -> None:
    """Count the end-to-end tests left out (by ``-m "not slow"``: see pytest_unconfigure)."""
    global _slow_left_out
    _slow_left_out += sum(1 for item in items if item.get_closest_marker("slow"))


def pytest_sessionfinish(session: pytest.Session) -> None:
    output = getattr(session.config, "workeroutput", None)  # an xdist worker: tell the controller
    if output is not None:
        output["slow_left_out"] = _slow_left_out


@pytest.hookimpl(optionalhook=True)
def pytest_testnodedown(node: Any, error: object) -> None:
    """xdist's controller collects nothing itself: it takes the workers' count."""
    global _slow_left_out
    _slow_left_out = max(_slow_left_out, getattr(node, "workeroutput", {}).get("slow_left_out", 0))


def pytest_unconfigure(config: pytest.Config) -> None:
    """Say last what `-m "not slow"` left out, so a green fast run is not taken for the whole
    suite (after pytest's own closing line: it is the last line `make test` prints)."""
    reporter = config.pluginmanager.get_plugin("terminalreporter")
    left_out = "slow" in (config.option.markexpr or "") and _slow_left_out
    if left_out and reporter is not None and not hasattr(config, "workeroutput"):
        reporter.write_line(
            f"not run: {_slow_left_out} end-to-end tests (marked slow: node processes, netns, "
            "a browser); `make test-all` or `SLOW=1 make test` runs them too, as CI does"
        )
