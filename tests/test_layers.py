"""The layering in docs/architecture.md, checked from the source: no import points upward and
there is no cycle, counting imports under ``TYPE_CHECKING`` too."""

from __future__ import annotations

import ast
import functools
from pathlib import Path

import pytest

SRC = Path(__file__).resolve().parent.parent / "src"

# lowest first; a module may import its own layer's modules and those of lower layers only
LAYERS: list[tuple[str, tuple[str, ...]]] = [
    ("errors", ("mso.errors",)),
    ("model", ("mso.model",)),
    ("planning / management / scenario files", ("mso.planning", "mso.management", "mso.scenario")),
    ("protocol", ("mso.protocol",)),
    ("node runtime", ("mso.runtime", "mso.node")),
    ("net", ("mso.net", "mso.client")),
    ("drivers", ("mso.node.driver", "mso.node.metrics", "mso.sim", "mso.daemon")),
    # the client API finds an emulator's nodes by name (mso.emu.overlays); the emulator asks
    # its nodes through it
    ("emulator / client API", ("mso.emu", "mso.api")),
    (
        "front ends",
        (
            "mso.cli",
            "mso.cliargs",
            "mso.statusview",
            "mso.benchmarks",
            "mso.examples",
            "mso.ros2",  # vertex code, like the examples (the optional ros2 extra)
            "mso.dashboard",
            "mso.plots",
        ),
    ),
]
# inside the protocol and the node runtime: the core's pieces, lowest first (each may import
# only those before it): the procedures' shared shape, the tables, the events and the context,
# the data plane, one component per procedure (membership last: it drives recovery), then the
# node's own modules and the core that composes them
CORE_ORDER = [
    "mso.protocol.procedures.base",
    "mso.protocol.procedures.instance",
    "mso.protocol.state",
    "mso.protocol.events",
    "mso.protocol.context",
    "mso.protocol.taps",
    "mso.protocol.forward",
    "mso.protocol.dataplane",
    "mso.protocol.procedures.status",
    "mso.protocol.procedures.deploy",
    "mso.protocol.procedures.relocation._state",
    "mso.protocol.procedures.relocation._role",
    "mso.protocol.procedures.relocation.coordinator",
    "mso.protocol.procedures.relocation.new_host",
    "mso.protocol.procedures.relocation.producer",
    "mso.protocol.procedures.relocation.old_host",
    "mso.protocol.procedures.relocation.relocator",
    "mso.protocol.procedures.restore",
    "mso.protocol.procedures.remap",
    "mso.protocol.procedures.membership.liveness",
    "mso.protocol.procedures.membership.detector",
    "mso.protocol.procedures.membership.status",
    "mso.protocol.procedures.membership.claims",
    "mso.protocol.procedures.membership.sync",
    "mso.protocol.procedures.membership.tables",
    "mso.protocol.procedures.membership.declare",
    "mso.protocol.procedures.membership.suspicion",
    "mso.protocol.procedures.membership.beats",
    "mso.protocol.procedures.membership.rejoin",
    "mso.protocol.procedures.membership.peers",
    "mso.node.device",
    "mso.node.monitor",
    "mso.node.manager",
    "mso.node.moves",
    "mso.node.status",
    "mso.node.core",
]
TOP = {"mso", "mso.__main__"}  # the package facade and `python -m mso` may import anything


@functools.cache
def _modules() -> dict[str, set[str]]:
    """Every module under src/mso and the mso modules it imports (``from a import b`` counts
    ``a.b`` when that is a module). Parsed once per run (each case parsed it all: ~4 s each)."""
    found: dict[str, ast.Module] = {}
    for path in SRC.rglob("*.py"):
        name = ".".join(path.relative_to(SRC).with_suffix("").parts)
        found[name.removesuffix(".__init__")] = ast.parse(path.read_text(), str(path))
    graph: dict[str, set[str]] = {}
    for name, tree in found.items():
        deps: set[str] = set()
        for node in ast.walk(tree):
            if isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
                if node.module.startswith("mso"):
                    deps.add(node.module)
                    deps |= {f"{node.module}.{a.name}" for a in node.names}
            elif isinstance(node, ast.Import):
                deps |= {a.name for a in node.names if a.name.startswith("mso")}
        graph[name] = {d for d in deps if d in found and d != name}
    return graph


def _layer(module: str) -> int:
    best, rank = -1, -1
    for i, (_, prefixes) in enumerate(LAYERS):
        for p in prefixes:
            if (module == p or module.startswith(p + ".")) and len(p) > best:
                best, rank = len(p), i
    if rank < 0:
        raise AssertionError(f"{module} is in no layer: add it to LAYERS in {__file__}")
    return rank


def _is_package(module: str, graph: dict[str, set[str]]) -> bool:
    return any(other.startswith(module + ".") for other in graph)


def test_no_import_points_upward() -> None:
    graph = _modules()
    upward = []
    for mod, deps in sorted(graph.items()):
        if mod in TOP or _is_package(mod, graph):
            continue  # a package's __init__ re-exports its own modules
        for dep in sorted(deps):
            if _is_package(dep, graph) and dep not in TOP:
                continue  # `from mso.protocol import messages` names the module, counted too
            if _layer(dep) > _layer(mod):
                upward.append(f"{mod} ({LAYERS[_layer(mod)][0]}) imports {dep}")
            elif (
                mod in CORE_ORDER
                and dep in CORE_ORDER
                and (CORE_ORDER.index(dep) > CORE_ORDER.index(mod))
            ):
                upward.append(f"{mod} imports {dep}, a piece of the core above it")
    assert not upward, "\n".join(upward)


def test_no_import_cycle() -> None:
    graph = _modules()
    state: dict[str, int] = {}  # 1 on the stack, 2 done
    cycles: list[list[str]] = []

    def visit(mod: str, path: list[str]) -> None:
        state[mod] = 1
        for dep in sorted(graph[mod]):
            if state.get(dep) == 1:
                cycles.append([*path[path.index(dep) :], dep])
            elif dep not in state:
                visit(dep, [*path, dep])
        state[mod] = 2

    for mod in sorted(graph):
        if mod not in state and mod not in TOP:
            visit(mod, [mod])
    # a package's __init__ importing its own modules is not a cycle between layers
    real = [c for c in cycles if not any(_is_package(m, graph) for m in c)]
    assert not real, "\n".join(" -> ".join(c) for c in real)


@pytest.mark.parametrize("module", CORE_ORDER)
def test_the_core_layers_exist(module: str) -> None:
    assert module in _modules()
