"""Load an app from YAML into the same :class:`App` the Python builder makes."""

from __future__ import annotations

import functools
from pathlib import Path
from typing import Any

from mso.errors import AppError, SpecError
from mso.model.app import PLANNERS, App
from mso.model.gcpause import paused_gc
from mso.model.qos import QOS_KEYS
from mso.model.yamlfile import Located, load_yaml, load_yaml_file

APP_KEYS = {"name", "vertices", "edges", "slo_ms", "policy", "planner"}
POLICY_KEYS = {"name", "code", "params"}
VERTEX_KEYS = {
    "code",
    "cost",
    "pinned",
    "input",
    "output",
    "rate",
    "params",
    "get_state",
    "set_state",
    "isolation",
    "requires",
    "near",
    "apart_from",
    "replicas",
    "snapshot_events",
    "snapshot_s",
}
EDGE_KEYS = {"from", "to", "format", "size", *QOS_KEYS}
# an app document travels to every node, which loads and places it on its control plane: a
# bounded size keeps that well under a second (40,000 vertices took 10 s)
MAX_VERTICES = 5_000
MAX_EDGES = 20_000


def _err(doc: Located, message: str, path: tuple[str | int, ...]) -> AppError:
    field = ""
    for p in path:
        field += f"[{p}]" if isinstance(p, int) else (f".{p}" if field else str(p))
    return AppError(message, file=doc.file, line=doc.line(path), field=field or None)


def _unknown(
    doc: Located, got: dict[Any, Any], allowed: set[str], path: tuple[str | int, ...]
) -> None:
    for key in got:
        if key not in allowed:
            raise _err(
                doc,
                f"unknown attribute {key!r} (expected one of: {', '.join(sorted(allowed))})",
                (*path, key),
            )


@paused_gc()
def app_from_document(doc: Located, *, resolve_code: bool = True) -> App:
    """Build and validate an App from a parsed YAML document."""
    data = doc.data
    if not isinstance(data, dict):
        raise _err(doc, "expected a mapping with 'name', 'vertices' and 'edges'", ())
    _unknown(doc, data, APP_KEYS, ())
    name = data.get("name")
    if not isinstance(name, str) or not name:
        raise _err(doc, f"expected a non-empty string, got {name!r}", ("name",))
    vertices = data.get("vertices")
    if not isinstance(vertices, dict) or not vertices:
        raise _err(doc, "expected a non-empty mapping of vertex id to attributes", ("vertices",))
    if len(vertices) > MAX_VERTICES:
        raise _err(doc, f"more than {MAX_VERTICES:,} vertices ({len(vertices):,})", ("vertices",))
    edge_list = data.get("edges")
    if isinstance(edge_list, list) and len(edge_list) > MAX_EDGES:
        raise _err(doc, f"more than {MAX_EDGES:,} edges ({len(edge_list):,})", ("edges",))
    app = App(name=name, located=doc)
    if "slo_ms" in data:
        slo = data["slo_ms"]
        if isinstance(slo, bool) or not isinstance(slo, int | float) or slo <= 0:
            raise _err(doc, f"expected a positive number of milliseconds, got {slo!r}", ("slo_ms",))
        app.slo_ms = float(slo)
    if "policy" in data:
        app.policy = _policy(doc, data["policy"])
    if "planner" in data:
        planner = data["planner"]
        if not isinstance(planner, str) or planner not in PLANNERS:
            raise _err(doc, f"expected one of {', '.join(PLANNERS)}, got {planner!r}", ("planner",))
        app.planner = planner
    for vid, attrs in vertices.items():
        path: tuple[str | int, ...] = ("vertices", vid)
        if not isinstance(vid, str):
            raise _err(doc, f"expected a string vertex id, got {vid!r}", path)
        if attrs is None:
            attrs = {}
        if not isinstance(attrs, dict):
            raise _err(doc, f"expected a mapping of attributes, got {attrs!r}", path)
        _unknown(doc, attrs, VERTEX_KEYS, path)
        try:
            app.vertex(vid, **attrs)
        except AppError as exc:
            raise _err(doc, exc.message, exc.path or path) from None
    edges = data.get("edges", [])
    if edges is None:
        edges = []
    if not isinstance(edges, list):
        raise _err(doc, "expected a list of edges", ("edges",))
    for i, item in enumerate(edges):
        path = ("edges", i)
        if isinstance(item, list):
            if len(item) != 2 or not all(isinstance(x, str) for x in item):
                raise _err(doc, f"expected [producer, consumer], got {item!r}", path)
            app.edge(item[0], item[1])
        elif isinstance(item, dict):
            _unknown(doc, item, EDGE_KEYS, path)
            for key in ("from", "to"):
                if not isinstance(item.get(key), str):
                    raise _err(doc, f"expected a vertex id, got {item.get(key)!r}", (*path, key))
            qos = {k: item[k] for k in QOS_KEYS if k in item}
            app.edge(
                item["from"], item["to"], format=item.get("format"), size=item.get("size"), **qos
            )
        else:
            raise _err(doc, f"expected [producer, consumer] or a mapping, got {item!r}", path)
    return app.validate(resolve_code=resolve_code)


def load_app(source: str | Path, *, resolve_code: bool = True) -> App:
    """Load an app from a YAML file path."""
    return app_from_document(load_yaml_file(source), resolve_code=resolve_code)


def loads_app(text: str, *, file: str | None = None, resolve_code: bool = True) -> App:
    """Load an app from YAML text (tests, embedded examples)."""
    return app_from_document(load_yaml(text, file), resolve_code=resolve_code)


@functools.lru_cache(maxsize=256)
def loads_app_shared(text: str, file: str) -> App:
    """:func:`loads_app`, remembered: the nodes of one process (a simulation of 1,000 nodes,
    where each node loads each announced app) share one parse of a document. The App returned
    is shared, so it must not be changed (nothing changes a loaded app); errors are raised
    afresh each time, never remembered."""
    return loads_app(text, file=file)


__all__ = ["SpecError", "app_from_document", "load_app", "loads_app", "loads_app_shared"]


def _policy(doc: Located, spec: Any) -> str | dict[str, Any]:
    """The app's management policy: a shipped name, an import path, or a mapping with
    ``name`` or ``code`` and optional ``params`` (resolved on the nodes, see docs/policies.md)."""
    if isinstance(spec, str) and spec:
        return spec
    if isinstance(spec, dict):
        _unknown(doc, spec, POLICY_KEYS, ("policy",))
        if ("name" in spec) == ("code" in spec):
            raise _err(doc, "expected exactly one of 'name' or 'code'", ("policy",))
        which = "name" if "name" in spec else "code"
        if not isinstance(spec[which], str) or not spec[which]:
            raise _err(doc, f"expected a non-empty string, got {spec[which]!r}", ("policy", which))
        params = spec.get("params", {})
        if not isinstance(params, dict) or not all(isinstance(k, str) for k in params):
            raise _err(
                doc, f"expected a mapping of parameters, got {params!r}", ("policy", "params")
            )
        return {which: spec[which], "params": dict(params)}
    raise _err(
        doc,
        f"expected a policy name, an import path or {{name|code, params}}, got {spec!r}",
        ("policy",),
    )


def with_planner(text: str, planner: str, *, file: str | None = None) -> str:
    """The app document ``text`` with its ``planner:`` set to ``planner`` (``--planner`` on
    ``mso deploy`` and ``mso emulate``): every node derives its placement from the document, so
    the choice travels in it. The result is checked to load with that planner."""
    import re

    if planner not in PLANNERS:
        raise AppError(f"unknown planner {planner!r} (expected one of {', '.join(PLANNERS)})")
    line = f"planner: {planner}"
    pattern = re.compile(r"^planner:[^\n]*$", re.MULTILINE)
    out = (
        pattern.sub(line, text, count=1)
        if pattern.search(text)
        else text.rstrip("\n") + f"\n{line}\n"
    )
    if loads_app(out, file=file, resolve_code=False).planner != planner:
        raise AppError(
            "cannot set the planner in this document: give it a top-level 'planner:' key"
        )
    return out
