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
from waits import listening

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
        failed = [e.said for e in out if isinstance(e, Send) and isinstance(e.said, m.DeployFailed)]
        assert failed and "allowlist" in failed[0].reason and failed[0].reason.startswith(nid)
        assert "evil" not in core.apps
    assert not mark.exists() and "evil_module" not in sys.modules


def _deploy_to_node_process(docs: list[str], env: dict[str, str], log: Path) -> list[m.Message]:
    """Start ``mso node`` on loopback with ``env`` (its log to ``log``) and deploy each document
    over TCP, one connection each; the node is stopped (by its PID) whatever happens."""
    env = {**os.environ, "MSO_KEY": "k", **env}
    env["PYTHONPATH"] = os.pathsep.join(p for p in (str(TESTS), env.get("PYTHONPATH")) if p)
    with log.open("wb") as out:
        node = subprocess.Popen(
            [sys.executable, "-m", "mso", "node", "--id", "N1", "--listen", "127.0.0.1:0"],
            env=env,
            stdout=subprocess.DEVNULL,
            stderr=out,
        )

    async def deploy_all(port: int) -> list[m.Message]:
        replies = []
        for doc in docs:
            client = await Client("127.0.0.1", port, overlay_key("k")).connect(2.0)
            try:
                replies.append(await client.call(m.DeployRequest(doc, "app.yaml")))
            finally:
                await client.close()
        return replies

    try:
        return asyncio.run(asyncio.wait_for(deploy_all(listening(node, log)), 60))
    finally:
        node.terminate()
        node.wait(10)


@pytest.mark.slow
def test_a_node_process_refuses_os_system(tmp_path: Path) -> None:
    """``mso node`` with the default allowlist: the deploy fails with the reason, nothing ran."""
    mark = tmp_path / "mark"
    env = {"MSO_EVIL_MARK": str(mark), "MSO_ALLOW_CODE": ""}
    (reply,) = _deploy_to_node_process([evil_app(mark)], env, tmp_path / "node.log")
    assert isinstance(reply, m.DeployReply) and not reply.ok
    assert "not on this node's code allowlist" in reply.error
    assert not mark.exists()


# Every way an attribute path could reach code the owner never named, with a fragment of the
# reason the refusal gives, and the keyword arguments (a policy's params) under which it would
# run `touch MARK` if it were called.
TRICKS: list[tuple[str, str, dict[str, object]]] = [
    ("allowed_tricks:os.system", "the module 'os'", {"command": "touch MARK"}),
    ("allowed_tricks:sys.modules", "the module 'sys'", {}),
    ("allowed_tricks:builtins.eval", "the module 'builtins'", {}),
    ("allowed_tricks:subprocess.getoutput", "the module 'subprocess'", {"cmd": "touch MARK"}),
    ("allowed_tricks:Popen", "of 'subprocess', a module not on the allowlist", {}),
    ("allowed_tricks:system", "'builtin_function_or_method' object", {"command": "touch MARK"}),
    ("allowed_tricks:evaluate", "'builtin_function_or_method' object", {}),
    ("allowed_tricks:shell", "not found under its own name", {"command": "touch MARK"}),
    ("allowed_tricks:run", "'partial' object", {"args": "touch MARK"}),
    ("allowed_tricks:made", "compiled from '<string>'", {"command": "touch MARK"}),
    ("allowed_tricks:nested", "not found under its own name", {"command": "touch MARK"}),
    ("allowed_tricks:managed", "contextlib.py", {"command": "touch MARK"}),
    ("allowed_tricks:rmtree", "shutil.py", {}),
    ("allowed_tricks:Holder.runner", "'builtin_function_or_method'", {"command": "touch MARK"}),
    ("allowed_tricks:Holder.sub.getoutput", "the module 'subprocess'", {"cmd": "touch MARK"}),
    ("allowed_tricks:holder.method", "'Holder' object; a path may pass only through classes", {}),
    ("allowed_tricks:holder", "'Holder' object, not a class or function", {}),
    ("allowed_tricks:Sub.communicate", "of 'subprocess', a module not on the allowlist", {}),
    ("allowed_tricks:Holder.__init__.__globals__", "'__init__' is a special attribute", {}),
    ("allowed_tricks:__builtins__", "'__builtins__' is a special attribute", {}),
    ("allowed_tricks:whatever", "'builtin_function_or_method'", {"command": "touch MARK"}),
    (
        "mso.benchmarks.common:os.system",
        "not on this node's code allowlist",
        {"command": "touch MARK"},
    ),
    ("mso.benchmarks.common:write_results", "not on this node's code allowlist", {}),
]


@pytest.fixture
def tricks_allowed(allowlist: None) -> None:
    allow_code((*DEFAULT_ALLOWED, "allowed_tricks"))


@pytest.mark.parametrize(("path", "why", "params"), TRICKS, ids=[t[0] for t in TRICKS])
def test_every_attribute_path_trick_is_refused(
    tricks_allowed: None, path: str, why: str, params: dict[str, object]
) -> None:
    """The allowlist applies to the object the path reaches, not to the module it starts in."""
    from mso.model.imports import resolve

    with pytest.raises(ImportPathError) as info:
        resolve(path)
    assert f"import path {path!r} is refused" in str(info.value)
    assert why in str(info.value)


def test_code_defined_in_an_allowed_module_still_resolves(tricks_allowed: None) -> None:
    import allowed_tricks as t
    from mso.model.imports import path_of, resolve

    assert resolve("allowed_tricks:plain") is t.plain
    assert resolve("allowed_tricks:Holder") is t.Holder
    assert resolve("allowed_tricks:Holder.Inner") is t.Holder.Inner
    assert resolve("allowed_tricks:Holder.method") is t.Holder.method
    assert resolve("allowed_tricks:Holder.make")().__class__ is t.Holder
    assert resolve("allowed_tricks:Sub") is t.Sub  # a subclass defined here is a definition
    assert resolve("mso.examples.convoy:Storage").__module__ == "mso.examples.convoy.storage"
    assert path_of(t.Holder.Inner) == "allowed_tricks:Holder.Inner"


def _trick_app(path: str, params: dict[str, object], mark: Path, as_vertex: bool) -> str:
    shown = {k: str(v).replace("MARK", str(mark)) for k, v in params.items()}
    params_yaml = "{" + ", ".join(f"{k}: '{v}'" for k, v in shown.items()) + "}"
    if as_vertex:
        return (
            "name: tricks\nvertices:\n"
            f"  A: {{code: 'mso.sim.vertices:Source', pinned: N1}}\n"
            f"  B: {{code: '{path}', params: {params_yaml}}}\n"
            "edges:\n  - [A, B]\n"
        )
    return (
        f"name: tricks\npolicy: {{code: '{path}', params: {params_yaml}}}\n"
        "vertices:\n  A: {pinned: N1}\n  B: {}\nedges:\n  - [A, B]\n"
    )


@pytest.mark.parametrize("as_vertex", [False, True], ids=["policy", "vertex"])
@pytest.mark.parametrize(("path", "why", "params"), TRICKS, ids=[t[0] for t in TRICKS])
def test_an_announced_trick_is_refused_by_every_node(
    tricks_allowed: None,
    tmp_path: Path,
    path: str,
    why: str,
    params: dict[str, object],
    as_vertex: bool,
) -> None:
    """A member announces an app whose policy or vertex code is the trick (with params that
    would run a shell command): each node refuses it, names the path and why, runs nothing."""
    mark = tmp_path / "mark"
    doc = _trick_app(path, params, mark, as_vertex)
    for nid in ("N2", "N3"):
        core = NodeCore(nid)
        out = core.receive("N1", m.AppAnnounce(app="tricks", origin="N1", document=doc), 0.0)
        failed = [e.said for e in out if isinstance(e, Send) and isinstance(e.said, m.DeployFailed)]
        assert failed, f"{nid} accepted {path}"
        assert path in failed[0].reason and why in failed[0].reason
        assert "tricks" not in core.apps
    assert not mark.exists()


@pytest.mark.slow
def test_a_node_process_refuses_attribute_path_tricks(tmp_path: Path) -> None:
    """``mso node --allow-code allowed_tricks`` over TCP: a deploy whose policy reaches
    ``os.system`` (or a lambda or partial around it) through the allowed module is refused
    with the path and the reason, and no command runs."""
    mark = tmp_path / "mark"
    chosen = [t for t in TRICKS if t[0].startswith("allowed_tricks") and t[2]]
    docs = [_trick_app(path, params, mark, as_vertex=False) for path, _, params in chosen]
    replies = _deploy_to_node_process(
        docs, {"MSO_ALLOW_CODE": "allowed_tricks"}, tmp_path / "node.log"
    )
    for (path, why, _), reply in zip(chosen, replies, strict=True):
        assert isinstance(reply, m.DeployReply) and not reply.ok, path
        assert f"import path {path!r} is refused" in reply.error and why in reply.error
    assert not mark.exists()
