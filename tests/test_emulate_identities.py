"""`mso emulate --identities` (issue 27, round three): the secure configuration rehearsed on
one machine — an operator key made for the run, each node's own certified key on its links
and on what it originates, clients served only with a certified key (the user's left beside
the overlay key)."""

from __future__ import annotations

import asyncio
import json
import os
import stat
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from click.testing import CliRunner

import mso.examples
from mso.cli import main
from mso.client import Refused, request
from mso.emu.controller import Emulator
from mso.emu.overlays import identity_files
from mso.protocol import messages as m
from mso.scenario import load_scenario, loads_scenario
from runtime_vertices import pipe_app
from waits import patience, until

TESTS = Path(__file__).resolve().parent
LINE4 = Path(mso.examples.__file__).parent / "line4.yaml"  # N1 - N2 - N3 - N4


@pytest.fixture(autouse=True)
def private_run(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Iterator[None]:
    """Overlays' files in this test's own folder; node processes import the test vertices."""
    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))
    monkeypatch.setenv("TMPDIR", str(tmp_path))
    monkeypatch.setenv("MSO_RUN_DIR", str(tmp_path))
    for name in ("MSO_KEY", "MSO_CLIENT_KEY", "MSO_SIGN"):
        monkeypatch.delenv(name, raising=False)
    path = os.environ.get("PYTHONPATH", "")
    monkeypatch.setenv("PYTHONPATH", f"{TESTS}{os.pathsep}{path}" if path else str(TESTS))
    yield


def test_an_overlay_emulated_with_identities_runs_an_app_and_serves_certified_clients_only() -> (
    None
):
    def cli(*args: str) -> tuple[int, str, str]:
        result = CliRunner().invoke(main, list(args))
        return result.exit_code, result.stdout, result.stderr

    async def run() -> dict[str, Any]:
        emu = Emulator(load_scenario(LINE4), identities=True)
        await emu.start()
        seen: dict[str, Any] = {}
        try:
            assert emu.user_keys is not None
            op, you = emu.user_keys
            seen["modes"] = {stat.S_IMODE(p.stat().st_mode) for p in (op, you)}
            reply = await emu.deploy(pipe_app(200), "pipe.yaml", "N2")  # the run's operator
            assert reply.ok, reply.error
            st = await until(
                emu.status,
                lambda st: st["N4"]["apps"]["pipe"]["vertices"]["sink"]["stats"]["count"] >= 100,
                10,
                "100 events at the sink over links proven with node identities",
            )
            seen["status"] = st
            # a member with the overlay key but no client key: refused, told why
            try:
                await request(emu.address("N1"), m.StatusRequest(), key=emu.key, timeout=10)
                seen["outsider"] = "answered"
            except Refused as exc:
                seen["outsider"] = str(exc)
            # the user who started it: its commands find the client key left for it
            seen["cli"] = await asyncio.to_thread(
                cli, "status", "--json", "--overlay", str(emu.name)
            )
            seen["files"] = identity_files(str(emu.name))
        finally:
            await emu.stop()
        return seen

    seen = asyncio.run(asyncio.wait_for(run(), patience(60)))
    st = seen["status"]
    assert seen["modes"] == {0o600}
    for node in ("N1", "N2", "N3", "N4"):
        assert st[node]["authority"]["mode"] == "signed"
        assert st[node]["connections"]["identity_refused"] == 0
    sink = st["N4"]["apps"]["pipe"]["vertices"]["sink"]["stats"]
    assert sink["repeats"] == 0 and sink["out_of_order"] == 0
    assert "serves only clients with an operator-certified key" in seen["outsider"]
    code, out, err = seen["cli"]
    assert code == 0, err
    assert sorted(json.loads(out)) == ["N1", "N2", "N3", "N4"]
    assert not any(p.exists() for p in seen["files"])  # removed when the emulator stopped


RING = """
name: ring
link_defaults: {delay_ms: 0.5}
nodes: {N1: {}, N2: {}, N3: {}, N4: {}, N5: {}}
links: [[N1, N2], [N2, N3], [N3, N4], [N4, N5], [N5, N1]]
"""


def test_a_node_restarted_under_identities_is_taken_back_on_its_own_word() -> None:
    """A neighbour's NodeUp about another node is not that node's word, so with identities
    a node takes a restarted node back from its own (signed) beats: on the ring N1 - N2 -
    N3 - N4 - N5 - N1, N5 (on the stream's path N1 - N5 - N4) killed and restarted is held
    failed by nobody afterwards, N2 and N3 refused their neighbours' announcements of it,
    and the stream goes on, no event repeated or out of order."""

    def sink(st: dict[str, Any]) -> dict[str, int]:
        stats: dict[str, int] = st["N4"]["apps"]["pipe"]["vertices"]["sink"]["stats"]
        return stats

    def failed(st: dict[str, Any]) -> dict[str, list[str]]:
        return {n: s["failed_nodes"] for n, s in st.items()}

    async def run() -> tuple[int, dict[str, Any]]:
        emu = Emulator(loads_scenario(RING), identities=True, convergence_s=0.2)
        await emu.start()
        try:
            assert (await emu.deploy(pipe_app(100), "pipe.yaml", "N1")).ok
            await until(emu.status, lambda st: sink(st)["count"] >= 50, 10, "50 events")
            await emu.fail("N5")
            await until(
                emu.status,
                lambda st: all(s["failed_nodes"] == ["N5"] for s in st.values()),
                10,
                "N5 declared failed by every node",
                show=failed,
            )
            await emu.restart("N5")
            before = sink(await emu.status())
            st = await until(
                emu.status,
                lambda st: (
                    len(st) == 5
                    and not any(failed(st).values())
                    and sink(st)["count"] >= before["count"] + 50
                ),
                20,
                "N5 taken back by every node and 50 more events",
                show=failed,
            )
            return before["count"], st
        finally:
            await emu.stop()

    before, st = asyncio.run(asyncio.wait_for(run(), patience(90)))
    got = sink(st)
    assert got["count"] >= before + 50
    assert got["repeats"] == 0 and got["out_of_order"] == 0
    # N5's neighbours announced it back to theirs: not N5's word, refused there
    assert st["N2"]["traffic"]["frames_origin_refused"] >= 1
    assert st["N3"]["traffic"]["frames_origin_refused"] >= 1
