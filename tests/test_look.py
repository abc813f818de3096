"""The pieces of mso echo / hz / record / logs that need no overlay: reading logfmt, shortening
an event for a terminal, naming a bag and its topics, decoding a tap's copies."""

from __future__ import annotations

from pathlib import Path

import msgspec
import pytest

from mso.api import decode_event
from mso.cli.logs import parse_logfmt
from mso.cli.look import _bag_path, _topic, brief
from mso.daemon.logs import logfmt
from mso.errors import MsoError


def test_logfmt_lines_parse_back_to_what_the_daemon_wrote() -> None:
    fields = {"t": "3.204", "level": "info", "node": "N1", "event": "relocation",
              "move": "N1 -> N2", "asked": 'the rule said "go"\nnow', "took_ms": "1.3"}  # fmt: skip
    assert parse_logfmt(logfmt(fields)) == fields
    assert parse_logfmt("plain words, no pairs") == {"msg": "plain words, no pairs"}
    assert parse_logfmt('a=1 flag b="x') == {"a": "1", "flag": "", "b": "x"}  # cut: no crash


def test_events_are_shortened_for_a_terminal_not_for_full() -> None:
    event = {"data": b"\x00" * 921600, "ranges": list(range(100)), "n": {"x": b"ab"}}
    short = brief(event)
    assert short["data"] == "<921600 bytes>" and short["n"] == {"x": "<2 bytes>"}
    assert short["ranges"][:16] == list(range(16)) and short["ranges"][16] == "... (100 items)"
    assert len(brief(event, full=True)["ranges"]) == 100


class Point(msgspec.Struct, array_like=True):
    x: float
    y: float


def test_a_positional_format_is_read_with_its_field_names() -> None:
    payload = msgspec.msgpack.encode(Point(1.0, 2.5))
    assert decode_event(payload, ["x", "y"]) == {"x": 1.0, "y": 2.5}
    assert decode_event(payload) == [1.0, 2.5]
    assert decode_event(msgspec.msgpack.encode({"data": "hi"}), ["x", "y"]) == {"data": "hi"}


def test_bag_names_and_topics() -> None:
    assert _bag_path(Path("run.mcap"), None) == (Path("run"), "mcap")
    assert _bag_path(Path("run.db3"), None) == (Path("run"), "sqlite3")
    assert _bag_path(Path("run"), "sqlite3") == (Path("run"), "sqlite3")
    with pytest.raises(MsoError, match="the name says mcap"):
        _bag_path(Path("run.mcap"), "sqlite3")
    assert _topic("chat", "shout->rec") == "/chat/shout/rec"
    assert _topic("my-app", "2d->x.y") == "/my_app/x2d/x_y"
