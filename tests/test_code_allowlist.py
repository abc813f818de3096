"""A node imports vertex, format and policy code only from the modules its owner allowed; an
app naming anything else is refused with a clear error before anything is imported or run."""

from __future__ import annotations

import asyncio
import os
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest

from mso.client import Client, overlay_key
from mso.errors import AppError
from mso.model.appfile import loads_app
from mso.model.imports import DEFAULT_ALLOWED, ImportPathError, allow_code, allowed_code
from mso.node.core import NodeCore
from mso.protocol import messages as m
from mso.protocol.effects import Send

TESTS = Path(__file__).resolve().parent


def evil_app(mark: Path) -> str:
    """Vertex code, a format and a policy that would each run something if imported."""
    return (
        "name: evil\n"
        "policy: {code: 'os:system', params: {command: 'touch " + str(mark) + "'}}\n"
        "vertices:\n"
        "  A: {code: 'evil_module:vertex', pinned: N1}\n"
        "  B: {code: 'subprocess:Popen'}\n"
        "edges:\n"
        "  - [A, B]\n"
    )


@pytest.fixture
def allowlist() -> Iterator[None]:
    before = allowed_code()
    allow_code(DEFAULT_ALLOWED)
    try:
        yield
    finally:
        allow_code(before)


def test_refused_before_import(allowlist: None, tmp_path: Path) -> None:
    mark = tmp_path / "mark"
    os.environ["MSO_EVIL_MARK"] = str(mark)
    try:
        with pytest.raises(AppError) as info:
            loads_app(evil_app(mark).replace("policy:", "#"), file="evil.yaml")
    finally:
        del os.environ["MSO_EVIL_MARK"]
    assert "evil.yaml:4: vertices.A.code" in str(info.value)
    assert "not on this node's code allowlist" in str(info.value)
    assert "evil_module" not in sys.modules and not mark.exists()


def test_allowed_modules_and_submodules_only(allowlist: None) -> None:
    allow_code(("apphelpers",))
    from mso.model.imports import resolve

    assert resolve("apphelpers.formats:Scan") is not None
    with pytest.raises(ImportPathError, match="allowlist"):
        resolve("apphelperz:x")  # a prefix of a name is not its parent package
    with pytest.raises(ImportPathError, match="module name"):
        allow_code(("os; rm",))


@pytest.mark.parametrize("only_policy", [False, True])
def test_every_node_refuses_an_announced_app_and_runs_nothing(
    allowlist: None, tmp_path: Path, only_policy: bool
) -> None:
    """A deploying node with a wider allowlist (or a captured one) announces the app: each
    other node refuses it on its own and tells the origin; no code is imported or run."""
    mark = tmp_path / "mark"
    doc = evil_app(mark)
    if only_policy:  # harmless vertices: the policy alone must be refused
        doc = doc.replace("'evil_module:vertex'", "null").replace("'subprocess:Popen'", "null")
    for nid in ("N2", "N3"):
        core = NodeCore(nid)
        out = core.receive("N1", m.AppAnnounce(app="evil", origin="N1", document=doc), 0.0)
        failed = [e.msg for e in out if isinstance(e, Send) and isinstance(e.msg, m.DeployFailed)]
        assert failed and "allowlist" in failed[0].reason and failed[0].reason.startswith(nid)
        assert "evil" not in core.apps
    assert not mark.exists() and "evil_module" not in sys.modules


def test_a_node_process_refuses_os_system(tmp_path: Path) -> None:
    """``mso node`` with the default allowlist: the deploy fails with the reason, nothing ran."""
    import socket

    mark = tmp_path / "mark"
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    env = {**os.environ, "MSO_KEY": "k", "MSO_EVIL_MARK": str(mark), "MSO_ALLOW_CODE": ""}
    env["PYTHONPATH"] = os.pathsep.join(p for p in (str(TESTS), env.get("PYTHONPATH")) if p)
    node = subprocess.Popen(
        [sys.executable, "-m", "mso", "node", "--id", "N1", "--listen", f"127.0.0.1:{port}"],
        env=env,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )

    async def deploy() -> m.Message:
        for _ in range(200):  # until the node listens
            try:
                client = await Client("127.0.0.1", port, overlay_key("k")).connect(1.0)
                break
            except Exception:
                await asyncio.sleep(0.05)
        try:
            return await client.call(m.DeployRequest(evil_app(mark), "evil.yaml"))
        finally:
            await client.close()

    try:
        reply = asyncio.run(deploy())
    finally:
        node.terminate()
        node.wait(10)
    assert isinstance(reply, m.DeployReply) and not reply.ok
    assert "not on this node's code allowlist" in reply.error
    assert not mark.exists()
