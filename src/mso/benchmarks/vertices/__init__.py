"""Vertex code the benchmarks deploy: node processes import it by a module path of the package
(``mso.benchmarks.vertices.failure:GapSink``), on every node's allowlist by default, so no
benchmark sets ``PYTHONPATH`` or ``MSO_ALLOW_CODE`` for it. Each module imports only what its
vertices need (msgspec, :mod:`mso.benchmarks.common`): nodes import it while they deploy.
"""
