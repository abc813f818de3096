"""Running overlays on this machine: each emulator claims a name and keeps a state file (its
pid, its nodes' addresses, where its dashboard is, node positions; never the key) under
``$TMPDIR/mso-UID/overlays/``, so commands in another terminal find it by name. An emulator
that made up its overlay key (none given) leaves it beside, in ``NAME.key`` (mode 0600, in a
directory only its user may enter), so that user's ``mso status``/``mso deploy`` reach it and
no other local user can. Light on imports on purpose: ``mso status`` reads these before
anything else."""

from __future__ import annotations

import contextlib
import json
import os
import re
from pathlib import Path
from typing import Any

from mso.errors import MsoError

OVERLAY_NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9_.-]{0,63}")


def overlays_dir() -> Path:
    """Where running emulators leave their state files: one per overlay, private to the user
    (under ``$TMPDIR``, so tests with their own temporary directory see only their overlays).

    The directory is ``tempfile.gettempdir()``'s first choice, the first of ``$TMPDIR``,
    ``$TEMP``, ``$TMP`` that is set, else ``/tmp``, without importing tempfile (10 ms of the
    150 ms ``mso status`` may take)."""
    env = os.environ
    base = env.get("TMPDIR") or env.get("TEMP") or env.get("TMP") or "/tmp"
    return Path(base).absolute() / f"mso-{os.getuid()}" / "overlays"


def state_file(name: str) -> Path:
    return overlays_dir() / f"{name}.json"


def key_file(name: str) -> Path:
    return overlays_dir() / f"{name}.key"


def _private(path: Path) -> bool:
    """Is ``path`` ours and closed to everyone else (not planted by another local user)?"""
    try:
        st = path.lstat()
    except OSError:
        return False
    return st.st_uid == os.getuid() and not st.st_mode & 0o077


def _safe_folder(folder: Path) -> bool:
    """Is ``folder`` (made private now if it is ours) a place only this user can reach into:
    owned by us, not a link, in a parent that is ours and that no one else may write?"""
    try:
        st, up = folder.lstat(), folder.parent.lstat()
    except OSError:
        return False
    uid = os.getuid()
    if st.st_uid != uid or up.st_uid != uid or up.st_mode & 0o022 or folder.is_symlink():
        return False
    if st.st_mode & 0o077:  # made by an older mso: ours, so close it
        folder.chmod(0o700)
    return True


def write_key(name: str, key: str) -> None:
    """Leave overlay ``name``'s key for its user's later commands (mode 0600, never followed
    through a link); refused if the directory is not private to this user."""
    folder = overlays_dir()
    if not _safe_folder(folder):
        raise MsoError(
            f"{folder} is not private to this user (owned by uid {os.getuid()}, mode 0700): "
            "not writing the overlay key there; give --key or set $MSO_KEY"
        )
    path = key_file(name)
    with contextlib.suppress(FileNotFoundError):
        path.unlink()
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW, 0o600)
    with os.fdopen(fd, "w") as f:
        f.write(key + "\n")


def remove_key(name: str) -> None:
    with contextlib.suppress(OSError):
        key_file(name).unlink()


def key_for(address: str) -> str | None:
    """The key an emulator of this user made up for the overlay that has a node at
    ``address`` (None: no such overlay, or its key was given, not made up)."""
    for name, state in running_overlays().items():
        if address in state["nodes"].values():
            path = key_file(name)
            if not _private(path):  # absent, or not ours: never use a planted key
                return None
            try:
                return path.read_text().strip() or None
            except OSError:
                return None
    return None


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # someone else's process has that pid now
        return False
    return True


def running_overlays() -> dict[str, dict[str, Any]]:
    """Name -> state of every overlay whose emulator still runs; a state file left by an
    emulator that died (SIGKILL, power cut) is removed."""
    found: dict[str, dict[str, Any]] = {}
    folder = overlays_dir()
    if not folder.is_dir():
        return found
    for path in sorted(folder.glob("*.json"), key=lambda p: p.stem):
        try:
            state = json.loads(path.read_text())
            pid = int(state["pid"])
        except (OSError, ValueError, KeyError, TypeError):
            continue  # being written, or not ours
        if not _alive(pid):
            with contextlib.suppress(OSError):
                path.unlink()
            remove_key(path.stem)
            continue
        if isinstance(state.get("nodes"), dict):
            found[path.stem] = state
    return found


def find_overlay(name: str | None) -> tuple[str, dict[str, Any]]:
    """The running overlay called ``name``, or the only one running; a clear error otherwise."""
    running = {n: s for n, s in running_overlays().items() if s["nodes"]}
    if name is not None:
        if name not in running:
            others = ", ".join(running) or "none"
            raise MsoError(f"no running overlay named {name!r} (running: {others})")
        return name, running[name]
    if not running:
        raise MsoError("no --via given and no emulator running; pass --via HOST:PORT or a node id")
    if len(running) > 1:
        raise MsoError(
            f"{len(running)} overlays are running ({', '.join(running)}): "
            "give --overlay NAME (or $MSO_OVERLAY), or --via HOST:PORT"
        )
    return next(iter(running.items()))


def _claim(wanted: str | None, default: str) -> str:
    """Reserve an overlay name for this process: ``wanted`` exactly (an error if a live
    emulator holds it), else ``default``, ``default-2``, ... whichever is free."""
    folder = overlays_dir()
    folder.mkdir(parents=True, exist_ok=True, mode=0o700)
    base = wanted or (re.sub(r"[^A-Za-z0-9_.-]", "-", default).strip("-.") or "overlay")
    if not OVERLAY_NAME.fullmatch(base):
        raise MsoError(
            f"--name: expected letters, digits, '_', '.' or '-' (at most 64), got {base!r}"
        )
    running_overlays()  # removes state files of emulators that died
    for i in range(1, 1000):
        name = base if i == 1 else f"{base}-{i}"
        try:
            fd = os.open(state_file(name), os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o600)
        except FileExistsError:
            if wanted:
                raise MsoError(
                    f"an overlay named {name!r} is already running; choose another --name"
                ) from None
            continue
        with os.fdopen(fd, "w") as f:
            json.dump({"name": name, "pid": os.getpid(), "nodes": {}}, f)
        return name
    raise MsoError(f"no free overlay name like {base!r}")


def emulator_address(node: str, overlay: str | None = None) -> str | None:
    """The address of an emulated node: in overlay ``overlay``, or in the one running overlay
    that has a node of that name (an error if several have)."""
    if overlay is not None:
        _, state = find_overlay(overlay)
        addr = state["nodes"].get(node)
        return str(addr) if addr else None
    having = {n: s["nodes"][node] for n, s in running_overlays().items() if node in s["nodes"]}
    if len(having) > 1:
        raise MsoError(
            f"node {node!r} is in {len(having)} running overlays ({', '.join(having)}): "
            "give --overlay NAME"
        )
    return str(next(iter(having.values()))) if having else None
