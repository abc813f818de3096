"""``mso profile`` (issue 25 item 5): measuring an app leaves the files its vertices write as
they were, and ``--write`` adds the costs and edge sizes a file does not have yet."""

from __future__ import annotations

import sqlite3
from pathlib import Path

import pytest
from click.testing import CliRunner

from mso.cli import main
from mso.errors import MsoError
from mso.model.appfile import load_app
from mso.runtime.profile import profile, write_back


def logging_app(tmp_path: Path, db: Path) -> Path:
    app = tmp_path / "app.yaml"
    app.write_text(
        "# the user's pipeline\n"
        "name: logged\n"
        "vertices:\n"
        "  src: {code: runtime_vertices:CountingSource, rate: 10, output: runtime_vertices:Num}\n"
        "  mid:\n"
        "    code: runtime_vertices:Double   # doubles\n"
        "    output: runtime_vertices:Num\n"
        f"  log: {{code: runtime_vertices:SqliteLog, params: {{db: '{db}'}}}}\n"
        "edges:\n"
        "  - [src, mid]   # short form\n"
        "  - from: mid\n"
        "    to: log\n"
    )
    return app


def test_profile_leaves_the_sinks_file_unchanged(tmp_path: Path) -> None:
    db = tmp_path / "log.sqlite"
    conn = sqlite3.connect(db)
    conn.execute("CREATE TABLE log (seq INTEGER)")
    conn.executemany("INSERT INTO log VALUES (?)", [(i,) for i in range(5)])
    conn.commit()
    conn.close()
    before = db.read_bytes()
    prof = profile(load_app(logging_app(tmp_path, db)), seconds=3.0)
    assert prof.vertices["log"].calls == 30 and prof.vertices["log"].errors == 0
    assert db.read_bytes() == before  # the 30 rows went into a scratch copy
    assert any(s.startswith("log.db:") for s in prof.scratch)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["app.yaml", "log.sqlite"]


def test_profile_a_file_to_be_is_not_created(tmp_path: Path) -> None:
    db = tmp_path / "new.sqlite"
    prof = profile(load_app(logging_app(tmp_path, db)), seconds=1.0)
    assert prof.vertices["log"].calls == 10
    assert not db.exists()


def test_a_dry_run_hook_points_a_vertex_at_the_scratch_directory(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    real = tmp_path / "env.log"
    monkeypatch.setenv("MSO_TEST_ENVLOG", str(real))
    app = tmp_path / "app.yaml"
    app.write_text(
        "name: env\nvertices:\n"
        "  src: {code: runtime_vertices:CountingSource, rate: 5, output: runtime_vertices:Num}\n"
        "  log: {code: runtime_vertices:EnvLog}\n"
        "edges:\n  - [src, log]\n"
    )
    prof = profile(load_app(app), seconds=2.0)
    assert prof.vertices["log"].calls == 10 and prof.vertices["log"].errors == 0
    assert not real.exists()
    assert any("dry_run" in s for s in prof.scratch)


def test_write_adds_missing_costs_and_sizes_in_every_form(tmp_path: Path) -> None:
    app_file = logging_app(tmp_path, tmp_path / "log.sqlite")
    costs = {"src": 0.25, "mid": 1.5, "log": 3.0}
    sizes = {("src", "mid"): 17, ("mid", "log"): 23}
    assert write_back(app_file, costs, sizes) == []
    text = app_file.read_text()
    assert "# the user's pipeline" in text and "# short form" in text and "# doubles" in text
    assert "- {from: src, to: mid, size: 17}   # short form" in text
    again = load_app(app_file, resolve_code=False)
    assert {v: x.cost for v, x in again.vertices.items()} == costs
    assert {(e.src, e.dst): e.size for e in again.edges} == sizes
    # written again, the keys are there now and are replaced in place
    assert write_back(app_file, {"mid": 2.0}, {("src", "mid"): 9}) == []
    again = load_app(app_file, resolve_code=False)
    assert again.vertices["mid"].cost == 2.0 and again.edges[0].size == 9
    assert app_file.read_text().count("cost:") == 3


def test_write_of_a_null_vertex_and_a_flow_edge(tmp_path: Path) -> None:
    app_file = tmp_path / "a.yaml"
    app_file.write_text("name: a\nvertices:\n  s:\n  t: {}\nedges:\n  - {from: s, to: t}\n")
    assert write_back(app_file, {"s": 1.0, "t": 2.0}, {("s", "t"): 5}) == []
    again = load_app(app_file, resolve_code=False)
    assert again.vertices["s"].cost == 1.0 and again.vertices["t"].cost == 2.0
    assert again.edges[0].size == 5


def test_write_that_would_not_read_back_leaves_the_file(tmp_path: Path) -> None:
    app_file = tmp_path / "a.yaml"
    original = "name: a\nvertices:\n  s: {cost: 1}\n  t: {}\nedges:\n  - [s, t]\n"
    app_file.write_text(original)
    with pytest.raises(MsoError, match="left unchanged"):
        write_back(app_file, {"s": -3.0}, {})  # a negative cost does not validate
    assert app_file.read_text() == original


def test_cli_profile_write(tmp_path: Path) -> None:
    db = tmp_path / "log.sqlite"
    app_file = logging_app(tmp_path, db)
    result = CliRunner().invoke(main, ["profile", str(app_file), "--seconds", "2", "--write"])
    assert result.exit_code == 0, result.output
    assert "kept off the real file: log.db" in result.output
    again = load_app(app_file, resolve_code=False)
    assert all(e.size is not None for e in again.edges)
    assert not db.exists()
