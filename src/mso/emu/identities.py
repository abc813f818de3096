"""The emulator's identity mode (``mso emulate --identities``): the secure configuration,
rehearsed on one machine.

The run's emulator key acts as its operator key: every node is given it as
``--operator-key`` (so apps come and go only by its signature), its own node key certified
by it (``--identity``: links are proven, what a node originates is signed end to end), and it
serves only certified clients. The emulator's own connections are such a client (an operator
key certifies itself, :func:`mso.protocol.clients.operator_client`); for its user's later
commands it leaves the operator key and a command client's key in the overlays directory
(mode 0600, removed when it stops): ``mso status --overlay NAME`` finds the client key as it
finds the overlay key, and ``--sign NAME.operator.key`` deploys.
"""

from __future__ import annotations

import time
from collections.abc import Iterable
from pathlib import Path

from mso.emu.overlays import identity_files, write_private
from mso.protocol import clients
from mso.protocol.authority import Signer
from mso.protocol.identity import certify


def node_identities(operator: Signer, nodes: Iterable[str], folder: Path) -> dict[str, Path]:
    """Each node's key file (its certificate beside it), made in ``folder`` (mode 0700)."""
    folder.mkdir(mode=0o700, exist_ok=True)
    now_ms = time.time_ns() // 1_000_000
    paths = {}
    for node in nodes:
        key = Signer()
        path = paths[node] = folder / f"{node}.key"
        _write(path, key.private_text())
        _write(
            path.with_name(path.name + ".cert"), certify(operator, node, key.public, now_ms).text()
        )
    return paths


def leave_for_user(operator: Signer, name: str) -> tuple[Path, Path]:
    """The operator key and a command client's key of overlay ``name``, left in the overlays
    directory for its user's commands."""
    op_path, client_path = identity_files(name)
    write_private(op_path, operator.private_text(), "the run's operator key")
    write_private(op_path.with_name(op_path.name + ".pub"), operator.public_text(), "its half")
    key = Signer()
    cert = clients.certify(operator, f"{name}-user", key.public, time.time_ns() // 1_000_000)
    write_private(client_path, key.private_text(), "a client key")
    write_private(client_path.with_name(client_path.name + ".cert"), cert.text(), "its cert")
    return op_path, client_path


def _write(path: Path, text: str) -> None:
    import os

    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC | os.O_NOFOLLOW, 0o600)
    with os.fdopen(fd, "w") as f:
        f.write(text + "\n")
