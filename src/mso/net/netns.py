"""Work in another network namespace from a process that stays where it is.

The netns testbed's controller and tests talk to nodes inside namespaces they built; ``setns``
moves only the calling thread, so a socket is made on a thread that has entered the namespace
and keeps that namespace for its whole life, wherever it is used afterwards.
"""

from __future__ import annotations

import ctypes
import os
import socket
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from typing import TypeVar

CLONE_NEWNET = 0x40000000
NETNS_DIR = "/run/netns"

T = TypeVar("T")


def enter(netns: str) -> None:
    """Move the calling thread into the named network namespace."""
    libc = ctypes.CDLL(None, use_errno=True)
    fd = os.open(f"{NETNS_DIR}/{netns}", os.O_RDONLY)
    try:
        if libc.setns(fd, CLONE_NEWNET) != 0:
            err = ctypes.get_errno()
            raise OSError(err, f"cannot enter network namespace {netns}: {os.strerror(err)}")
    finally:
        os.close(fd)


def worker(netns: str) -> ThreadPoolExecutor:
    """One thread that lives in ``netns``: what it runs sees that namespace."""
    return ThreadPoolExecutor(1, thread_name_prefix=f"netns-{netns}", initializer=enter,
                              initargs=(netns,))  # fmt: skip


def run_in(netns: str, fn: Callable[[], T]) -> T:
    """``fn()`` on a short-lived thread inside ``netns``."""
    with worker(netns) as w:
        return w.submit(fn).result()


def socket_in_netns(netns: str | None, family: int, kind: int) -> socket.socket:
    """A socket of the network namespace ``netns`` (None: this one)."""
    if netns is None:
        return socket.socket(family, kind)
    return run_in(netns, lambda: socket.socket(family, kind))
