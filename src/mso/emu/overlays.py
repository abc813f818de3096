"""Running overlays on this machine: each emulator claims a name and keeps a state file (its
pid, its nodes' addresses, where its dashboard is, node positions; never the key) under
``/tmp/mso-UID/overlays/`` — whatever ``$TMPDIR`` says, so a shell with another one finds it
(``$MSO_RUN_DIR`` moves it: tests keep theirs apart) — and its command socket beside
(``NAME.sock``), so commands in another terminal find it by name. An emulator that made up its
overlay key (none given) leaves it beside, in ``NAME.key`` (mode 0600, in a directory only its
user may enter), so that user's ``mso status``/``mso deploy`` reach it and no other local user
can. Run under sudo, an emulator keeps these in the invoking user's directory, as that user's:
their commands find it; root's commands find every user's overlays (permissions allow it).
Light on imports on purpose: ``mso status`` reads these before anything else."""

from __future__ import annotations

import contextlib
import json
import os
import re
from pathlib import Path
from typing import Any

from mso.errors import MsoError

OVERLAY_NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9_.-]{0,63}")


RUN_DIR_ENV = "MSO_RUN_DIR"


def owner() -> int:
    """Whose overlays this process keeps: under sudo the user who ran it, else its own."""
    sudo = os.environ.get("SUDO_UID", "")
    return int(sudo) if os.geteuid() == 0 and sudo.isdigit() else os.getuid()


def _base() -> Path:
    return Path(os.environ.get(RUN_DIR_ENV) or "/tmp").absolute()


def overlays_dir(uid: int | None = None) -> Path:
    """Where running emulators of user ``uid`` (default: :func:`owner`) leave their state
    files: one per overlay, private to the user. Not under ``$TMPDIR``: a shell with another
    one must find them; ``$MSO_RUN_DIR`` moves the base (tests use their own)."""
    return _base() / f"mso-{owner() if uid is None else uid}" / "overlays"


def _other_users_dirs() -> list[Path]:
    """Other users' overlay directories that this process may read (root: all of them)."""
    mine = overlays_dir()
    found = []
    with contextlib.suppress(OSError):
        for d in sorted(_base().glob("mso-*/overlays")):
            if d != mine and os.access(d, os.R_OK | os.X_OK):
                found.append(d)
    return found


def state_file(name: str) -> Path:
    return overlays_dir() / f"{name}.json"


def key_file(name: str) -> Path:
    return overlays_dir() / f"{name}.key"


def control_file(name: str) -> Path:
    """The command socket of overlay ``name``'s emulator (``mso emulator``)."""
    return overlays_dir() / f"{name}.sock"


def give(path: Path) -> None:
    """Under sudo, hand what this emulator made to the user who ran it."""
    uid = owner()
    if uid != os.getuid():
        with contextlib.suppress(OSError):
            os.chown(path, uid, -1, follow_symlinks=False)


def _private(path: Path) -> bool:
    """Is ``path`` its folder's user's and closed to everyone else (not planted by another
    local user)? Root trusts any user's private file in that user's folder."""
    try:
        st, folder = path.lstat(), path.parent.lstat()
    except OSError:
        return False
    mine = st.st_uid == owner() or (os.geteuid() == 0 and st.st_uid == folder.st_uid)
    return mine and not st.st_mode & 0o077


def _safe_folder(folder: Path) -> bool:
    """Is ``folder`` (made private now if it is ours) a place only this user can reach into:
    owned by us, not a link, in a parent that is ours and that no one else may write?"""
    try:
        st, up = folder.lstat(), folder.parent.lstat()
    except OSError:
        return False
    uid = owner()
    if st.st_uid != uid or up.st_uid != uid or up.st_mode & 0o022 or folder.is_symlink():
        return False
    if st.st_mode & 0o077:  # made by an older mso: ours, so close it
        folder.chmod(0o700)
    return True


def write_key(name: str, key: str) -> None:
    """Leave overlay ``name``'s key for its user's later commands (mode 0600, never followed
    through a link); refused if the directory is not private to this user."""
    write_private(key_file(name), key, "the overlay key")


def write_private(path: Path, text: str, what: str) -> None:
    """Write ``text`` to ``path`` in the overlays directory, mode 0600, never through a link;
    refused if the directory is not private to this user."""
    folder = overlays_dir()
    if not _safe_folder(folder):
        raise MsoError(
            f"{folder} is not private to this user (owned by uid {os.getuid()}, mode 0700): "
            f"not writing {what} there; give --key or set $MSO_KEY"
        )
    with contextlib.suppress(FileNotFoundError):
        path.unlink()
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW, 0o600)
    with os.fdopen(fd, "w") as f:
        f.write(text + "\n")
    give(path)


def identity_files(name: str) -> tuple[Path, Path]:
    """Where an emulator run with identities leaves its operator key and a command client's
    key for its user (each with its .pub or .cert beside it)."""
    return overlays_dir() / f"{name}.operator.key", overlays_dir() / f"{name}.client.key"


def remove_key(name: str) -> None:
    operator, client = identity_files(name)
    for path in (key_file(name), operator, client):
        for each in (path, path.with_name(path.name + ".pub"), path.with_name(path.name + ".cert")):
            with contextlib.suppress(OSError):
                each.unlink()


def key_for(address: str) -> str | None:
    """The key an emulator of this user made up for the overlay that has a node at
    ``address`` (None: no such overlay, or its key was given, not made up)."""
    path = _own_file(address, "key")
    try:
        return path.read_text().strip() or None if path is not None else None
    except OSError:
        return None


def client_key_for(address: str) -> str | None:
    """The client key an emulator of this user made for the overlay, run with identities,
    that has a node at ``address`` (None: no such overlay, or it has no identities)."""
    path = _own_file(address, "client.key")
    return str(path) if path is not None else None


def _own_file(address: str, suffix: str) -> Path | None:
    """``NAME.SUFFIX`` of the overlay of this user's that has a node at ``address``, if it
    is there and private (never a file another local user planted)."""
    for name, state in running_overlays(everyone=True).items():
        if address in state["nodes"].values():
            path = folder_of(name) / f"{name}.{suffix}"
            return path if _private(path) else None
    return None


def _alive(pid: int, uid: int | None = None) -> bool:
    """Does emulator ``pid`` (run by ``uid``, e.g. root under sudo) still run?"""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # another user's: the emulator's, or someone else's has the pid now
        try:
            return uid is not None and Path(f"/proc/{pid}").stat().st_uid == uid
        except OSError:
            return False
    return True


def running_overlays(*, everyone: bool = False) -> dict[str, dict[str, Any]]:
    """Name -> state of every overlay whose emulator still runs (``everyone``: other users'
    too, where this process may read them; this user's come first and win a name); a state
    file left by an emulator that died (SIGKILL, power cut) is removed, with its key."""
    found: dict[str, dict[str, Any]] = {}
    folders = [overlays_dir(), *(_other_users_dirs() if everyone else [])]
    for folder in folders:
        if not folder.is_dir():
            continue
        for path in sorted(folder.glob("*.json"), key=lambda p: p.stem):
            try:
                state = json.loads(path.read_text())
                pid = int(state["pid"])
                uid = int(state["uid"]) if "uid" in state else None
            except (OSError, ValueError, KeyError, TypeError):
                continue  # being written, or not ours
            if not _alive(pid, uid):
                if folder == folders[0]:
                    with contextlib.suppress(OSError):
                        path.unlink()
                    remove_key(path.stem)
                    with contextlib.suppress(OSError):
                        control_file(path.stem).unlink()
                continue
            if isinstance(state.get("nodes"), dict) and path.stem not in found:
                found[path.stem] = state
    return found


def folder_of(name: str) -> Path:
    """The folder holding overlay ``name``'s files: this user's, else another user's that this
    process may read (root's commands reach every user's emulators)."""
    for folder in (overlays_dir(), *_other_users_dirs()):
        if (folder / f"{name}.json").exists():
            return folder
    return overlays_dir()


def find_overlay(name: str | None) -> tuple[str, dict[str, Any]]:
    """The running overlay called ``name``, or the only one running; a clear error otherwise."""
    running = {n: s for n, s in running_overlays(everyone=True).items() if s["nodes"]}
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
    if not folder.is_dir():
        folder.mkdir(parents=True, exist_ok=True, mode=0o700)
        give(folder.parent)
        give(folder)
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
            json.dump({"name": name, "pid": os.getpid(), "uid": os.geteuid(), "nodes": {}}, f)
        give(state_file(name))
        return name
    raise MsoError(f"no free overlay name like {base!r}")


def emulator_address(node: str, overlay: str | None = None) -> str | None:
    """The address of an emulated node: in overlay ``overlay``, or in the one running overlay
    that has a node of that name (an error if several have)."""
    if overlay is not None:
        _, state = find_overlay(overlay)
        addr = state["nodes"].get(node)
        return str(addr) if addr else None
    running = running_overlays(everyone=True)
    having = {n: s["nodes"][node] for n, s in running.items() if node in s["nodes"]}
    if len(having) > 1:
        raise MsoError(
            f"node {node!r} is in {len(having)} running overlays ({', '.join(having)}): "
            "give --overlay NAME"
        )
    return str(next(iter(having.values()))) if having else None


LOGS_PREFIXES = ("mso-emu-", "mso-netns-")  # an emulator's node logs under the temp dir
OWNER_FILE = "emulator.pid"  # in such a folder: the pid of the emulator writing it
KEPT_FILE = "KEPT"  # in such a folder: why its emulator kept it (a node crashed)
KEPT_FOR_S = 86400.0  # logs kept for a look are removed a day later


def make_log_dir(prefix: str) -> Path:
    """A fresh folder for an emulator's node logs (under the temp dir), marked as this
    process's; the folders of emulators that died without removing theirs go first."""
    import tempfile

    base = Path(tempfile.gettempdir())
    clean_stale_logs(base)
    folder = Path(tempfile.mkdtemp(prefix=prefix, dir=base))
    (folder / OWNER_FILE).write_text(f"{os.getpid()}\n")
    return folder


def keep_logs(folder: Path, why: str) -> None:
    """Mark ``folder`` as kept for a look (``why``); :func:`clean_stale_logs` removes it a
    day later."""
    with contextlib.suppress(OSError):
        (folder / KEPT_FILE).write_text(why + "\n")


def clean_stale_logs(base: Path, now: float | None = None) -> list[Path]:
    """Remove this user's emulator log folders under ``base`` whose emulator is gone (killed,
    crashed) and that were not kept for a look, or were kept more than a day ago; returns
    them. Folders of running emulators, and of other users, are left alone."""
    import shutil
    import time

    now = time.time() if now is None else now
    removed = []
    for folder in sorted(p for prefix in LOGS_PREFIXES for p in base.glob(prefix + "*")):
        try:
            st = folder.lstat()
            if not folder.is_dir() or folder.is_symlink() or st.st_uid != os.getuid():
                continue
            pid = int((folder / OWNER_FILE).read_text().strip() or 0)
        except (OSError, ValueError):
            continue  # not one of ours (no owner file: being made, or an older mso's)
        if pid and _alive(pid):
            continue
        kept = folder / KEPT_FILE
        if kept.exists() and now - kept.stat().st_mtime < KEPT_FOR_S:
            continue
        shutil.rmtree(folder, ignore_errors=True)
        removed.append(folder)
    return removed
