"""An :class:`App` built in Python as the document every node loads: a deployment sends the app
file's text, never objects, so code and formats given as Python objects become import paths.

The text is JSON, which the YAML loader reads as it reads an app file; ``loads_app`` of it gives
an app equal to the one built (code and formats as the import paths they resolve from).
"""

from __future__ import annotations

import json
from typing import Any

from mso.errors import MsoError
from mso.model.app import App, Edge, Vertex
from mso.model.qos import DEFAULT_BUFFER_AGE_S, DEFAULT_BUFFER_BYTES

# each vertex setting with the value the builder gives it when left out (left out here too)
VERTEX_DEFAULTS: dict[str, Any] = {
    "cost": 1.0,
    "pinned": None,
    "input": None,
    "output": None,
    "rate": None,
    "params": {},
    "get_state": None,
    "set_state": None,
    "isolation": "thread",
    "requires": {},
    "near": None,
    "apart_from": None,
    "replicas": None,
    "snapshot_events": 100,
    "snapshot_s": 5.0,
}
EDGE_DEFAULTS: dict[str, Any] = {
    "format": None,
    "size": None,
    "qos": "reliable",
    "keep_last": None,
    "deadline_ms": None,
    "lifespan_ms": None,
    "buffer_bytes": DEFAULT_BUFFER_BYTES,
    "buffer_age_s": DEFAULT_BUFFER_AGE_S,
    "overflow": "buffer",
}


def import_path(obj: Any, where: str) -> str:
    """``module:qualname`` of a class or function every node can import by that path; an
    object defined in ``__main__`` or inside a function cannot be, and is refused saying so."""
    if isinstance(obj, str):
        return obj
    module = getattr(obj, "__module__", None)
    qualname = getattr(obj, "__qualname__", None)
    if not isinstance(module, str) or not isinstance(qualname, str):
        raise MsoError(f"{where}: {obj!r} has no import path (give 'package.module:attr')")
    if module == "__main__" or "<locals>" in qualname:
        place = "in __main__" if module == "__main__" else "inside a function"
        raise MsoError(
            f"{where}: {qualname} is defined {place}, so no node can import it: every node "
            "imports vertex code and formats by path; move it into a module installed on "
            "every node (pip install -e, or PYTHONPATH)"
        )
    return f"{module}:{qualname}"


def _vertex(v: Vertex) -> dict[str, Any]:
    where = f"vertices.{v.id}"
    out: dict[str, Any] = {}
    if v.code is not None:
        out["code"] = import_path(v.code, f"{where}.code")
    for key, default in VERTEX_DEFAULTS.items():
        value = getattr(v, key)
        if value == default:
            continue
        if key in ("input", "output", "get_state", "set_state"):
            value = import_path(value, f"{where}.{key}")
        out[key] = value
    return out


def _edge(e: Edge) -> dict[str, Any]:
    out: dict[str, Any] = {"from": e.src, "to": e.dst}
    for key, default in EDGE_DEFAULTS.items():
        value = getattr(e, key)
        if value != default:
            out[key] = (
                import_path(value, f"edges {e.src} -> {e.dst}.format") if key == "format" else value
            )
    return out


def app_document(app: App) -> str:
    """The app as the text of an app file (JSON, read by the YAML loader)."""
    doc: dict[str, Any] = {"name": app.name}
    for key in ("slo_ms", "policy", "planner"):
        if getattr(app, key) is not None:
            doc[key] = getattr(app, key)
    doc["vertices"] = {vid: _vertex(v) for vid, v in app.vertices.items()}
    doc["edges"] = [_edge(e) for e in app.edges]
    try:
        return json.dumps(doc, indent=1)
    except (TypeError, ValueError) as exc:  # a param that is not plain data
        raise MsoError(f"app {app.name!r}: its settings must be plain data: {exc}") from None
