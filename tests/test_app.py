"""The app model: the Python builder and YAML agree, and every error is one located line."""

from __future__ import annotations

import textwrap
from pathlib import Path

import pytest

from apphelpers.formats import Pose, Scan
from mso.errors import AppError, SpecError
from mso.model.app import App
from mso.model.appfile import load_app, loads_app

EXAMPLES = Path(__file__).resolve().parent.parent / "src" / "mso" / "examples"
FILE = "app.yaml"


def yml(text: str) -> str:
    return textwrap.dedent(text).lstrip("\n")


def app_error(text: str, *, file: str = FILE, resolve_code: bool = True) -> SpecError:
    with pytest.raises(SpecError) as info:
        loads_app(yml(text), file=file, resolve_code=resolve_code)
    err = info.value
    assert "\n" not in str(err), "an error is one line"
    return err


def assert_at(err: SpecError, line: int | None, field: str | None, phrase: str) -> None:
    """The error renders as ``file:line: field: message`` with these parts."""
    assert (err.file, err.line, err.field) == (FILE, line, field), str(err)
    assert phrase in err.message, str(err)
    where = f"{FILE}:{line}: " if line else f"{FILE}: "
    assert str(err) == where + (f"{field}: " if field else "") + err.message


def builder_error(app: App) -> AppError:
    with pytest.raises(AppError) as info:
        app.validate()
    assert "\n" not in str(info.value)
    return info.value


# -- builder and YAML give the same App -----------------------------------------------------


def fig2_builder() -> App:
    app = App("fig2")
    pins = {"A": "N1", "E": "N4", "F": "N1", "I": "N4"}
    for v in "ABCDEFGHI":
        app.vertex(v, pinned=pins.get(v))
    for a, b in ["AB", "BC", "CD", "DE", "FG", "GD", "GH", "HI"]:
        app.edge(a, b)
    return app.validate()


def test_fig2_yaml_equals_builder() -> None:
    from_yaml = load_app(EXAMPLES / "fig2.yaml")
    built = fig2_builder()
    assert from_yaml.vertices == built.vertices
    assert from_yaml.edges == built.edges
    assert from_yaml == built
    assert from_yaml.located is not None and built.located is None
    assert from_yaml.sources() == ["A", "F"]
    assert from_yaml.sinks() == ["E", "I"]
    assert [from_yaml.kind(v) for v in "ADEG"] == ["source", "operator", "sink", "operator"]


FORMATS_YAML = """
name: scans
slo_ms: 150
vertices:
  src:
    code: apphelpers.formats:scan_source
    pinned: N1
    cost: 0.5
    rate: 5
    output: apphelpers.formats:Scan
  conv:
    code: apphelpers.formats:to_pose
    input: apphelpers.formats:Scan
    output: apphelpers.formats:Pose
    params: {scale: 2}
  sink: {code: apphelpers.formats:store, input: apphelpers.formats:Pose, pinned: N4, cost: 0}
edges:
  - [src, conv]
  - {from: conv, to: sink, format: apphelpers.formats:Pose, size: 24}
"""


def formats_builder() -> App:
    app = App("scans", slo_ms=150.0)
    app.vertex("src", "apphelpers.formats:scan_source", pinned="N1", cost=0.5, rate=5, output=Scan)
    app.vertex("conv", "apphelpers.formats:to_pose", input=Scan, output=Pose, params={"scale": 2})
    app.vertex("sink", "apphelpers.formats:store", input=Pose, pinned="N4", cost=0)
    app.edge("src", "conv")
    app.edge("conv", "sink", format=Pose, size=24)
    return app.validate()


def test_formats_yaml_equals_builder(tmp_path: Path) -> None:
    built = formats_builder()
    from_text = loads_app(yml(FORMATS_YAML), file=FILE)
    path = tmp_path / "scans.yaml"
    path.write_text(yml(FORMATS_YAML), encoding="utf-8")
    from_file = load_app(path)
    for app in (from_text, from_file):
        assert app.vertices == built.vertices
        assert app.edges == built.edges
        assert app == built
    # Import paths of formats are resolved to the Struct types themselves.
    assert from_file.vertices["src"].output is Scan
    assert from_file.vertices["conv"].input is Scan
    assert from_file.edges[1].format is Pose
    assert from_file.edge_format(from_file.edges[0]) is Scan  # the producer's output
    assert from_file.edge_format(from_file.edges[1]) is Pose
    assert from_file.located is not None and from_file.located.file == str(path)


def test_formats_without_import_stay_paths() -> None:
    app = loads_app(yml(FORMATS_YAML), file=FILE, resolve_code=False)
    assert app.vertices["src"].output == "apphelpers.formats:Scan"
    assert app.edges[1].format == "apphelpers.formats:Pose"


def test_minimal_yaml_needs_no_code_or_formats() -> None:
    text = yml(
        """
        name: fig2
        vertices:
          A: {pinned: N1}
          B: {}
        edges:
          - [A, B]
        """
    )
    app = loads_app(text, file=FILE)
    built = App("fig2")
    built.vertex("A", pinned="N1")
    built.vertex("B")
    built.edge("A", "B")
    assert app == built.validate()
    assert app.vertices["A"].code is None and app.vertices["A"].cost == 1.0
    assert app.sources() == ["A"] and app.sinks() == ["B"]
    assert app.topological_order() == ["A", "B"]


def test_null_vertex_attributes_and_no_edges() -> None:
    app = loads_app("name: one\nvertices:\n  A:\n", file=FILE)
    assert list(app.vertices) == ["A"] and app.edges == []
    assert app.kind("A") == "isolated"


# -- graph errors ---------------------------------------------------------------------------


def test_unknown_vertex_in_edge() -> None:
    err = app_error(
        """
        name: t
        vertices:
          A: {}
          B: {}
        edges:
          - [A, B]
          - [B, X]
        """
    )
    assert_at(err, 7, "edges[1]", "unknown vertex 'X' in edge B -> X")
    assert "known: A, B" in err.message
    err = app_error(
        """
        name: t
        vertices:
          A: {}
        edges:
          - {from: Y, to: A}
        """
    )
    assert_at(err, 5, "edges[0]", "unknown vertex 'Y'")


def test_unknown_vertex_in_edge_builder() -> None:
    app = App("t")
    app.vertex("A")
    app.edge("A", "Z")
    err = builder_error(app)
    assert (err.file, err.line, err.field) == (None, None, "edges[0]")
    assert str(err).startswith("edges[0]: unknown vertex 'Z' in edge A -> Z")


def test_duplicate_vertex_yaml() -> None:
    err = app_error(
        """
        name: t
        vertices:
          A: {}
          B: {}
          A: {cost: 2}
        """
    )
    assert_at(err, 5, "vertices.A", "duplicate key 'A'")


def test_duplicate_vertex_builder() -> None:
    app = App("t")
    app.vertex("A")
    with pytest.raises(AppError) as info:
        app.vertex("A", cost=2)
    assert info.value.field == "vertices.A"
    assert str(info.value) == "vertices.A: duplicate vertex id 'A'"
    assert app.vertices["A"].cost == 1.0  # the first one is kept


def test_cycle_is_named() -> None:
    err = app_error(
        """
        name: t
        vertices:
          S: {}
          A: {}
          B: {}
          C: {}
        edges:
          - [S, A]
          - [A, B]
          - [B, C]
          - [C, A]
        """
    )
    assert_at(err, 7, "edges", "the graph has a cycle: A -> B -> C -> A")


def test_cycle_builder() -> None:
    app = App("t")
    for v in "ABC":
        app.vertex(v)
    for a, b in ["AB", "BC", "CA"]:
        app.edge(a, b)
    err = builder_error(app)
    assert str(err) == "edges: the graph has a cycle: A -> B -> C -> A"
    with pytest.raises(AppError, match="cycle"):
        app.topological_order()
    two = App("t")
    two.vertex("P")
    two.vertex("Q")
    two.edge("P", "Q")
    two.edge("Q", "P")
    assert "P -> Q -> P" in str(builder_error(two))


def test_duplicate_edge() -> None:
    err = app_error(
        """
        name: t
        vertices:
          A: {}
          B: {}
        edges:
          - [A, B]
          - {from: A, to: B, size: 10}
        """
    )
    assert_at(err, 7, "edges[1]", "duplicate edge A -> B")


@pytest.mark.parametrize(
    ("size", "shown"), [("-1", "-1"), ("1.5", "1.5"), ("'big'", "'big'"), ("true", "True")]
)
def test_bad_edge_size(size: str, shown: str) -> None:
    err = app_error(
        f"""
        name: t
        vertices:
          A: {{}}
          B: {{}}
        edges:
          - from: A
            to: B
            size: {size}
        """
    )
    assert_at(
        err,
        8,
        "edges[0].size",
        f"expected a non-negative integer byte count up to 16777216 (16 MiB), got {shown}",
    )


def test_negative_edge_size_builder() -> None:
    app = App("t")
    app.vertex("A")
    app.vertex("B")
    app.edge("A", "B", size=-5)
    assert str(builder_error(app)) == (
        "edges[0].size: expected a non-negative integer byte count up to 16777216 (16 MiB), got -5"
    )


# -- formats and import paths ---------------------------------------------------------------


def test_format_mismatch_producer_consumer() -> None:
    err = app_error(
        """
        name: t
        vertices:
          A: {output: apphelpers.formats:Scan}
          B: {input: apphelpers.formats:Pose}
        edges:
          - [A, B]
        """
    )
    assert_at(
        err,
        6,
        "edges[0]",
        "format mismatch on A -> B: A produces apphelpers.formats:Scan "
        "but B consumes apphelpers.formats:Pose",
    )
    # Without importing, the paths are compared as written.
    err = app_error(
        """
        name: t
        vertices:
          A: {output: apphelpers.formats:Scan}
          B: {input: apphelpers.formats:Pose}
        edges:
          - [A, B]
        """,
        resolve_code=False,
    )
    assert_at(err, 6, "edges[0]", "format mismatch on A -> B")


def test_format_mismatch_edge_format() -> None:
    err = app_error(
        """
        name: t
        vertices:
          A: {output: apphelpers.formats:Scan}
          B: {}
        edges:
          - from: A
            to: B
            format: apphelpers.formats:Pose
        """
    )
    assert_at(err, 8, "edges[0].format", "A produces apphelpers.formats:Scan")
    assert "the edge carries apphelpers.formats:Pose" in err.message
    # The edge's format is what the consumer must accept.
    err = app_error(
        """
        name: t
        vertices:
          A: {}
          B: {input: apphelpers.formats:Scan}
        edges:
          - {from: A, to: B, format: apphelpers.formats:Pose}
        """
    )
    assert_at(err, 6, "edges[0]", "A produces apphelpers.formats:Pose but B consumes")


def test_format_mismatch_builder() -> None:
    app = App("t")
    app.vertex("A", output=Scan)
    app.vertex("B", input=Pose)
    app.edge("A", "B")
    err = builder_error(app)
    assert err.field == "edges[0]"
    assert "A produces apphelpers.formats:Scan but B consumes apphelpers.formats:Pose" in str(err)


@pytest.mark.parametrize(
    ("attr", "path", "phrase"),
    [
        ("code", "nosuch_mso_module:f", "no module named 'nosuch_mso_module'"),
        ("code", "apphelpers.formats:missing", "'apphelpers.formats' has no attribute 'missing'"),
        ("code", "apphelpers.formats.scan_source", "expected an import path"),
        ("code", "apphelpers.formats:CONSTANT", "to name a callable, got int"),
        ("get_state", "apphelpers.nosuch:dump", "no module named 'apphelpers.nosuch'"),
        ("set_state", "not a path", "expected an import path 'package.module:attr'"),
        ("output", "nosuch_mso_module:Fmt", "no module named 'nosuch_mso_module'"),
        ("input", "apphelpers.formats:Missing", "has no attribute 'Missing'"),
        ("output", "apphelpers.formats:NotAStruct", "to name a msgspec.Struct type"),
        ("input", "apphelpers.formats:scan_source", "to name a msgspec.Struct type"),
        ("output", "Scan", "expected an import path"),
    ],
)
def test_bad_import_paths(attr: str, path: str, phrase: str) -> None:
    text = f"""
        name: t
        vertices:
          A:
            pinned: N1
            {attr}: "{path}"
        """
    err = app_error(text)
    assert_at(err, 5, f"vertices.A.{attr}", phrase)
    assert repr(path) in err.message
    if attr in ("code", "get_state", "set_state") and "import path 'package" not in phrase:
        # Planning without importing accepts any well-formed path.
        loads_app(yml(text), file=FILE, resolve_code=False)


def test_bad_edge_format_path() -> None:
    err = app_error(
        """
        name: t
        vertices:
          A: {}
          B: {}
        edges:
          - {from: A, to: B, format: "apphelpers.formats:NotAStruct"}
        """
    )
    assert_at(err, 6, "edges[0].format", "to name a msgspec.Struct type")
    err = app_error(
        """
        name: t
        vertices:
          A: {}
          B: {}
        edges:
          - from: A
            to: B
            format: "nosuch_mso_module:X"
        """
    )
    assert_at(err, 8, "edges[0].format", "does not resolve")


def test_builder_non_struct_format() -> None:
    app = App("t")
    with pytest.raises(AppError) as info:  # refused at once, like a bad cost
        app.vertex("A", output=int)  # type: ignore[arg-type]
    assert str(info.value).startswith("vertices.A.output: expected an import path")
    assert "or a msgspec.Struct type, got <class 'int'>" in str(info.value)


def test_callable_code_and_state_hooks_in_builder() -> None:
    app = App("t")
    app.vertex("A", lambda seq, now: Scan(seq=seq), output=Scan, get_state=dict)
    app.vertex("B", "apphelpers.formats:to_pose", input=Scan)
    app.edge("A", "B")
    assert app.validate() is app
    with pytest.raises(AppError) as info:
        app.vertex("C", 42)  # type: ignore[arg-type]
    assert info.value.field == "vertices.C.code"


# -- values and attributes ------------------------------------------------------------------


@pytest.mark.parametrize(
    ("value", "shown"),
    [
        ("-1", "-1"),
        ("-0.5", "-0.5"),
        ("'1'", "'1'"),
        ("abc", "'abc'"),
        ("true", "True"),
        ("null", "None"),
        (".inf", "inf"),
        (".nan", "nan"),
        ("[1]", "[1]"),
    ],
)
def test_bad_cost(value: str, shown: str) -> None:
    err = app_error(
        f"""
        name: t
        vertices:
          A: {{}}
          B:
            pinned: N2
            cost: {value}
        """
    )
    assert_at(err, 6, "vertices.B.cost", f"expected a non-negative number, got {shown}")


def test_bad_cost_builder() -> None:
    app = App("t")
    for bad in (-1, "1", True, float("nan")):
        with pytest.raises(AppError) as info:
            app.vertex("A", cost=bad)  # type: ignore[arg-type]
        assert info.value.field == "vertices.A.cost"
        assert "expected a non-negative number" in str(info.value)
    assert app.vertices == {}
    assert app.vertex("A", cost=0).cost == 0


@pytest.mark.parametrize(
    ("value", "field", "phrase"),
    [
        ("{rate: 0}", "rate", "expected a positive number of events per second"),
        ("{rate: -2}", "rate", "expected a positive number of events per second"),
        ("{pinned: 5}", "pinned", "expected a node id (string), got 5"),
        ("{pinned: ''}", "pinned", "expected a node id (string)"),
        ("{code: 7}", "code", "expected an import path 'package.module:attr' or a callable"),
    ],
)
def test_bad_vertex_values(value: str, field: str, phrase: str) -> None:
    err = app_error(
        f"""
        name: t
        vertices:
          A: {value}
        """
    )
    assert_at(err, 3, f"vertices.A.{field}", phrase)


def test_unknown_attribute_app_level() -> None:
    err = app_error(
        """
        name: t
        vertices:
          A: {}
        sinks: [A]
        """
    )
    assert_at(err, 4, "sinks", "unknown attribute 'sinks'")
    assert "(expected one of: edges, name, planner, policy, slo_ms, vertices)" in err.message


def test_unknown_attribute_vertex_level() -> None:
    err = app_error(
        """
        name: t
        vertices:
          A:
            pinned: N1
            costs: 2
        """
    )
    assert_at(err, 5, "vertices.A.costs", "unknown attribute 'costs'")
    expected = (
        "apart_from, code, cost, get_state, input, isolation, near, output, params, pinned, "
        "rate, replicas, requires, set_state, snapshot_events, snapshot_s"
    )
    assert expected in err.message


def test_unknown_attribute_edge_level() -> None:
    err = app_error(
        """
        name: t
        vertices:
          A: {}
          B: {}
        edges:
          - from: A
            to: B
            fmt: x
        """
    )
    assert_at(err, 8, "edges[0].fmt", "unknown attribute 'fmt'")
    assert (
        "(expected one of: buffer_age_s, buffer_bytes, deadline_ms, format, from, " in err.message
    )


@pytest.mark.parametrize("text", ["", "\n\n", "# only a comment\n"])
def test_empty_file(text: str) -> None:
    with pytest.raises(AppError) as info:
        loads_app(text, file=FILE)
    assert str(info.value) == f"{FILE}: expected a mapping with 'name', 'vertices' and 'edges'"


@pytest.mark.parametrize("text", ["- A\n- B\n", "just a string\n", "42\n"])
def test_file_not_a_mapping(text: str) -> None:
    with pytest.raises(AppError) as info:
        loads_app(text, file=FILE)
    assert str(info.value) == f"{FILE}:1: expected a mapping with 'name', 'vertices' and 'edges'"


@pytest.mark.parametrize(
    ("text", "line", "field", "phrase"),
    [
        ("vertices:\n  A: {}\n", 1, "name", "expected a non-empty string, got None"),
        ("name: ''\nvertices:\n  A: {}\n", 1, "name", "expected a non-empty string"),
        ("name: t\n", 1, "vertices", "expected a non-empty mapping"),
        ("name: t\nvertices: {}\n", 2, "vertices", "expected a non-empty mapping"),
        ("name: t\nvertices: [A]\n", 2, "vertices", "expected a non-empty mapping"),
        ("name: t\nvertices:\n  A: 3\n", 3, "vertices.A", "expected a mapping of attributes"),
        ("name: t\nvertices:\n  A:\nedges: {A: B}\n", 4, "edges", "expected a list of edges"),
        ("name: t\nvertices:\n  A:\nedges:\n  - [A]\n", 5, "edges[0]", "[producer, consumer]"),
        ("name: t\nvertices:\n  A:\nedges:\n  - A\n", 5, "edges[0]", "[producer, consumer]"),
        ("name: t\nvertices:\n  A:\nedges:\n  - {to: A}\n", 5, "edges[0].from", "vertex id"),
        ("name: t\nslo_ms: 0\nvertices:\n  A:\n", 2, "slo_ms", "positive number"),
        ("name: t\npolicy: 5\nvertices:\n  A:\n", 2, "policy", "expected a policy name"),
        ("name: t\npolicy: {}\nvertices:\n  A:\n", 2, "policy", "one of 'name' or 'code'"),
        ("name: t\npolicy: {name: x, fast: 1}\nvertices:\n  A:\n", 2, "policy.fast", "unknown"),
        ("name: t\npolicy: {code: 3}\nvertices:\n  A:\n", 2, "policy.code", "non-empty"),
        (
            "name: t\npolicy: {name: x, params: [1]}\nvertices:\n  A:\n",
            2,
            "policy.params",
            "a mapping of parameters",
        ),
        ("name: t\nvertices:\n  3: {}\n", 3, "vertices[3]", "expected a string vertex id"),
    ],
)
def test_structure_errors(text: str, line: int, field: str, phrase: str) -> None:
    with pytest.raises(AppError) as info:
        loads_app(text, file=FILE)
    assert_at(info.value, line, field, phrase)


# -- malformed YAML -------------------------------------------------------------------------


def test_malformed_yaml_unclosed_bracket() -> None:
    err = app_error(
        """
        name: t
        vertices:
          A: {}
          B: {}
        edges:
          - [A, B
          - [B, A]
        """
    )
    # The parser notices the missing ']' on the next line.
    assert_at(err, 7, None, "malformed YAML: ")
    assert "expected ',' or ']'" in err.message


def test_malformed_yaml_bad_indentation() -> None:
    err = app_error(
        """
        name: t
        vertices:
          A: {}
         B: {}
        """
    )
    assert err.file == FILE and err.line == 4 and "malformed YAML" in err.message


def test_malformed_yaml_unclosed_bracket_at_end_names_its_line() -> None:
    text = "name: t\nvertices:\n  A: {}\n  B: {}\nedges:\n  - [A, B\n"
    with pytest.raises(SpecError) as info:
        loads_app(text, file=FILE)
    err = info.value
    assert err.line == 6 or "line 6" in err.message, str(err)


# -- bugs found earlier, fixed: these keep them fixed ----------------------------------------


@pytest.mark.parametrize("params", ["[1, 2]", "abc"])
def test_params_not_a_mapping(params: str) -> None:
    err = app_error(
        f"""
        name: t
        vertices:
          A:
            params: {params}
        """
    )
    assert_at(err, 4, "vertices.A.params", "expected a mapping of parameters")


def test_params_list_of_pairs_is_rejected() -> None:
    err = app_error(
        """
        name: t
        vertices:
          A:
            params: [[k, 1]]
        """
    )
    assert_at(err, 4, "vertices.A.params", "expected a mapping of parameters")


def test_yaml_edge_format_must_be_a_path() -> None:
    err = app_error(
        """
        name: t
        vertices:
          A: {}
          B: {}
        edges:
          - {from: A, to: B, format: 5}
        """
    )
    assert err.field == "edges[0].format" and err.line == 6


def test_builder_edge_format_must_be_struct() -> None:
    app = App("t")
    app.vertex("A")
    app.vertex("B")
    app.edge("A", "B", format=int)  # type: ignore[arg-type]
    err = builder_error(app)
    assert err.field == "edges[0].format"


def test_non_string_format_without_import_is_an_app_error() -> None:
    err = app_error(
        """
        name: t
        vertices:
          A: {output: apphelpers.formats:Scan}
          B: {input: 5}
        edges:
          - [A, B]
        """,
        resolve_code=False,
    )
    assert err.field == "vertices.B.input"


def test_vertex_id_with_dot_points_at_its_line() -> None:
    err = app_error(
        """
        name: t
        vertices:
          a.b: {cost: -1}
        """
    )
    assert_at(err, 3, "vertices.a.b.cost", "expected a non-negative number")


@pytest.mark.parametrize("slo", [-5.0, 0, "fast"])
def test_builder_checks_slo_ms(slo: object) -> None:
    app = App("t", slo_ms=slo)  # type: ignore[arg-type]
    app.vertex("A")
    err = builder_error(app)
    assert err.field == "slo_ms" and "positive number of milliseconds" in err.message


@pytest.mark.parametrize(
    ("text", "policy"),
    [
        ("policy: lifetime", "lifetime"),
        ("policy: mypkg.policies:Mine", "mypkg.policies:Mine"),
        ("policy: {name: delay}", {"name": "delay", "params": {}}),
        ("policy: {code: a.b:C, params: {k: 2}}", {"code": "a.b:C", "params": {"k": 2}}),
    ],
)
def test_policy_is_named_in_the_app(text: str, policy: object) -> None:
    app = loads_app(f"name: t\n{text}\nvertices:\n  A:\n", file=FILE)
    assert app.policy == policy


def test_an_edge_size_is_bounded_by_the_largest_frame() -> None:
    """``size: 1e29`` (as an integer) used to be accepted: an edge's bytes per event are at most
    what one frame can carry, and exactly that is still fine."""
    from mso.model.app import MAX_EDGE_SIZE
    from mso.protocol.framing import MAX_FRAME

    assert MAX_EDGE_SIZE == MAX_FRAME
    doc = "name: x\nvertices:\n  A: {}\n  B: {}\nedges:\n  - {from: A, to: B, size: %d}\n"
    assert loads_app(doc % MAX_EDGE_SIZE, file="a.yaml").edges[0].size == MAX_EDGE_SIZE
    for size in (MAX_EDGE_SIZE + 1, 10**29):
        with pytest.raises(AppError, match=r"a.yaml:6: edges\[0\].size: expected a non-negative"):
            loads_app(doc % size, file="a.yaml")
