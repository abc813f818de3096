"""The routing daemons the netns testbed can run in a node's namespace, each set up as it needs.

A daemon here is what turns the testbed's links into kernel routes; the nodes' kernel view
(:mod:`mso.net.routes_kernel`) reads what it installs, whatever table it uses. Each runs in the
foreground as a child of the controller, so it is killed by PID with its node.

- **babeld** (1.12): ``interface eth0 type wired split-horizon false hello-interval 0.5``,
  ``smoothing-half-life 0`` (split horizon never converged on the shared medium; with smoothing
  babeld ignored a new, shorter link for over 8 s). Routes in the main table. A stale pid file
  from a killed babeld stops the next one: it is removed before each start.
- **batmand** (0.3.2, B.A.T.M.A.N. III in user space): needs ``eth0`` to have a broadcast
  address (the testbed gives one) and a ``/run`` of its own (its unix socket is
  ``/var/run/batmand.socket``; two daemons sharing one refuse to start), so it runs under
  ``unshare -m`` with a private directory bound on ``/run``. Routes in table 66 behind policy
  rules (6600 and 6700: to the subnet), with table 67's ``unreachable default`` after them.
  Originator interval 500 ms (``-o 500``; the default is 1 s). It keeps a dead originator's
  routes for about 200 s (its purge timeout).

To add another (FRR's babeld or ospfd, BIRD): write its configuration for one interface
``eth0`` on the testbed's shared /16 (it is a broadcast medium: no split horizon, point-to-
multipoint for OSPF), run it in the foreground (no daemonising: the controller kills it by
PID), give it its own state and pid files (one per node, under the run's log directory) and
its own ``/run`` if it keeps a socket there, and add it to :data:`DAEMONS`. The view needs only
that the daemon installs host (or subnet) routes for the other nodes' addresses in some table
that a policy rule selects for them (any table; ``proto`` other than ``kernel``), with the
next hop as the gateway, and that it withdraws a route it no longer has.
"""

from __future__ import annotations

import shutil
import subprocess
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING

from mso.errors import MsoError

if TYPE_CHECKING:
    from mso.emu.netns.testbed import Testbed

BATMAND_ORIGINATOR_MS = 500


def _exe(name: str) -> str:
    exe = shutil.which(name)
    if exe is None:
        raise MsoError(
            f"{name} is not installed (Debian: apt-get install {name}; `make netns-deps`)"
        )
    return exe


def batmand(tb: Testbed, node: str, workdir: Path) -> subprocess.Popen[bytes]:
    """Start batmand in ``node``'s namespace with its own ``/run`` (foreground)."""
    exe = _exe("batmand")
    unshare = _exe("unshare")
    run = workdir / f"batmand-run-{tb.index[node]}"
    run.mkdir(parents=True, exist_ok=True)
    for stale in run.iterdir():  # a killed daemon's socket would stop the next one
        if stale.is_file() or stale.is_socket():
            stale.unlink()
    script = f'mount --bind "$1" /run && exec "$2" --no-detach -o {BATMAND_ORIGINATOR_MS} eth0'
    cmd = [unshare, "-m", "sh", "-c", script, "batmand", str(run), exe]
    return tb.popen(node, cmd, workdir / f"batmand-{node}.log")


def babeld(tb: Testbed, node: str, workdir: Path) -> subprocess.Popen[bytes]:
    """Start babeld in ``node``'s namespace (foreground), without a stale pid file."""
    (workdir / f"babeld-{tb.index[node]}.pid").unlink(missing_ok=True)
    return tb.babeld(node, workdir)


DAEMONS: dict[str, Callable[[Testbed, str, Path], subprocess.Popen[bytes]]] = {
    "babeld": babeld,
    "batmand": batmand,
}
"""Routing daemon name -> how to start it in a node's namespace."""


def missing(name: str) -> str | None:
    """Why daemon ``name`` cannot run here (None: it can)."""
    if name not in DAEMONS:
        return f"unknown routing daemon {name!r} (known: {', '.join(DAEMONS)})"
    if shutil.which(name) is None:
        return f"{name} is not installed (Debian: apt-get install {name}, or `make netns-deps`)"
    return None
