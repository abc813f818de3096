"""mso.api judges every reply in one place: what a refusal says, what a name of a chain means,
and that a front end's error keeps the node's reason."""

from __future__ import annotations

from pathlib import Path

import pytest

from mso.api import CommandFailed, chain_indices, expect, judge, resolve_address, running
from mso.errors import MsoError
from mso.protocol import messages as m

NODES = {"N1": {"apps": {"pipe": {"chains": [["src", "mid"], ["mid", "sink"]]}, "other": {}}}}


def test_a_refused_command_says_what_failed_and_keeps_the_nodes_reason() -> None:
    refused = m.RelocateReply("pipe", "mid", ok=False, error="no_route")
    with pytest.raises(CommandFailed) as exc:
        judge(refused, m.RelocateReply, "relocation refused")
    assert str(exc.value) == "relocation refused: no_route"
    assert exc.value.reason == "no_route" and exc.value.exit_code == 2
    ok = m.RelocateReply("pipe", "mid", ok=True, node="N2")
    assert judge(ok, m.RelocateReply, "relocation refused") is ok
    assert expect(refused, m.RelocateReply) is refused  # unjudged: the emulator's callers look


def test_a_reply_of_another_kind_is_an_error() -> None:
    with pytest.raises(MsoError, match="unexpected reply"):
        expect(m.RelocateReply("pipe", "mid", ok=True), m.StatusReply)
    with pytest.raises(CommandFailed, match="remap refused: RelocateReply"):
        judge(m.RelocateReply("pipe", "mid", ok=True), m.RemapReply, "remap refused")


def test_chains_are_named_by_index_or_head_to_tail() -> None:
    assert running(NODES) == ["other", "pipe"]
    assert chain_indices(NODES, "pipe", [1, "0", "mid-sink"]) == [1, 0, 1]
    with pytest.raises(MsoError, match=r"unknown chain 'x' \(chains: src-mid, mid-sink\)"):
        chain_indices(NODES, "pipe", ["x"])
    with pytest.raises(MsoError, match="no running app named 'nope'"):
        chain_indices(NODES, "nope", ["0"])


def test_an_address_is_taken_as_given_and_an_unknown_node_id_is_an_error(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv("MSO_RUN_DIR", str(tmp_path))  # no emulator runs there
    assert resolve_address("127.0.0.1:7000") == "127.0.0.1:7000"
    with pytest.raises(MsoError, match="unknown node or overlay 'N9'"):
        resolve_address("N9")
    with pytest.raises(MsoError, match="no --via given and no emulator running"):
        resolve_address(None)


def test_a_relocation_is_awaited_as_long_as_its_coordinator_may_take() -> None:
    """A busy vertex hands over after its call and the events before the markers: the client
    must not give up (and report the node unreachable) before the coordinator's deadline."""
    import inspect

    from mso.api import RELOCATE_S, AsyncOverlay
    from mso.protocol.procedures.relocation import SWITCH_DEADLINE_S, Relocation

    assert RELOCATE_S > Relocation.DEADLINE_S + SWITCH_DEADLINE_S
    default = inspect.signature(AsyncOverlay.relocate).parameters["timeout"].default
    assert default == RELOCATE_S
