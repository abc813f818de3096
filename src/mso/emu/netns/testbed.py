"""The namespace testbed: one network namespace per node on one Linux bridge.

Layout (measured in the project's testbed notes): the bridge lives in a namespace of its own
(``mso-u<uid>-<pid>-m``; STP and multicast snooping off); node *i* lives in
``mso-u<uid>-<pid>-n<i>`` with one interface ``eth0`` (MAC ``02:00:00:00:hh:ll``, address
``10.77.hh.ll/16``) whose veth peer is the bridge port ``p<i>``. Who hears whom is one nftables
bridge table in the medium namespace: a set of allowed (sender port . receiver port) pairs,
everything else dropped, broadcast and multicast too — so a link is one set element per
direction, changed in-process. Every node has permanent neighbour entries for every other (after
an outage the first packet is not lost to ARP), ``ip_forward=1``, no redirects, no reverse-path
filter; its egress is shaped with ``tbf``. Loss is nft ``numgen`` (the kernel here has no
``netem``, so there is no delay either).

Only addresses inside these namespaces are ever used. Every namespace name carries the user who
asked (``mso-u<uid>-…``; under sudo, the user sudo was run by) and the pid of the process that
built it: :func:`cleanup` removes only that user's whose builder is gone (after a crash, or
``mso emulate --cleanup``), killing by PID the processes still inside them; another user's
namespaces never match.
"""

from __future__ import annotations

import contextlib
import os
import re
import shutil
import signal
import subprocess
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from pathlib import Path

from mso.emu.netns.nft import Nft
from mso.errors import MsoError

PREFIX = "mso-"
TABLE = "mso"
MAX_NODES = 4000
BABELD_CONF = """\
# written by mso's netns testbed: the settings that converge on a shared, filtered medium
interface eth0 type wired split-horizon false hello-interval 0.5
smoothing-half-life 0
"""


def _ip(*args: str, netns: str | None = None, check: bool = True) -> str:
    cmd = ["ip", *(["-n", netns] if netns else []), *args]
    proc = subprocess.run(cmd, capture_output=True)
    if check and proc.returncode != 0:
        raise MsoError(f"{' '.join(cmd)}: {proc.stderr.decode().strip()}")
    return proc.stdout.decode()


def _batch(netns: str | None, lines: Iterable[str]) -> None:
    """Many ``ip`` commands in one process (``ip -batch``)."""
    text = "\n".join(lines) + "\n"
    cmd = ["ip", *(["-n", netns] if netns else []), "-batch", "-"]
    proc = subprocess.run(cmd, input=text.encode(), capture_output=True)
    if proc.returncode != 0:
        raise MsoError(f"ip -batch in {netns}: {proc.stderr.decode().strip()}")


def user() -> int:
    """Whose namespaces these are: the user sudo was run by, else this process's user."""
    sudo = os.environ.get("SUDO_UID", "")
    return int(sudo) if os.geteuid() == 0 and sudo.isdigit() else os.getuid()


def prefix(owner: int) -> str:
    """The start of every namespace name the process ``owner`` builds for this user."""
    return f"{PREFIX}u{user()}-{owner}-"


def _ours() -> re.Pattern[str]:
    return re.compile(rf"^{PREFIX}u{user()}-(\d+)-(m|n\d+)$")


def unavailable() -> str | None:
    """Why namespaces cannot be made here (None: they can)."""
    if shutil.which("ip") is None:
        return "iproute2's 'ip' command is not installed"
    if os.geteuid() != 0:
        return "creating network namespaces needs root (or a user namespace: unshare -Urnm)"
    name = f"{prefix(os.getpid())}probe"
    proc = subprocess.run(["ip", "netns", "add", name], capture_output=True)
    if proc.returncode != 0:
        return f"network namespaces unavailable: {proc.stderr.decode().strip()}"
    subprocess.run(["ip", "netns", "del", name], capture_output=True)
    return None


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def namespaces() -> list[str]:
    out = _ip("netns", "list", check=False)
    return [line.split()[0] for line in out.splitlines() if line.strip()]


def cleanup(*, owner: int | None = None) -> list[str]:
    """Remove the testbed namespaces of ``owner`` (None: of every builder no longer alive),
    killing by PID what still runs inside them; returns the namespaces removed."""
    removed = []
    ours = _ours()
    for ns in namespaces():
        m = ours.match(ns)
        if m is None:
            continue
        pid = int(m[1])
        if (owner is not None and pid != owner) or (owner is None and _alive(pid)):
            continue
        for line in _ip("netns", "pids", ns, check=False).split():
            if line.isdigit() and int(line) != os.getpid():
                with contextlib.suppress(ProcessLookupError):
                    os.kill(int(line), signal.SIGKILL)
        _ip("netns", "del", ns, check=False)
        removed.append(ns)
    return removed


@dataclass
class Testbed:
    """Build, change and tear down the namespaces of ``nodes`` (in this order: node i+1)."""

    nodes: list[str]
    owner: int = field(default_factory=os.getpid)
    links: set[tuple[str, str]] = field(default_factory=set)
    loss: dict[tuple[str, str], float] = field(default_factory=dict)
    rates: dict[str, float | None] = field(default_factory=dict)
    nft: Nft | None = None
    built: bool = False

    def __post_init__(self) -> None:
        if not 0 < len(self.nodes) <= MAX_NODES:
            raise MsoError(f"the netns testbed takes 1 to {MAX_NODES} nodes")
        self.index = {n: i + 1 for i, n in enumerate(self.nodes)}

    # -- names and addresses --------------------------------------------------------------
    @property
    def medium(self) -> str:
        return f"{prefix(self.owner)}m"

    def netns(self, node: str) -> str:
        return f"{prefix(self.owner)}n{self.index[node]}"

    def address(self, node: str) -> str:
        i = self.index[node]
        return f"10.77.{i >> 8}.{i & 0xFF}"

    def mac(self, node: str) -> str:
        i = self.index[node]
        return f"02:00:00:00:{i >> 8:02x}:{i & 0xFF:02x}"

    def port(self, node: str) -> str:
        return f"p{self.index[node]}"

    # -- life -----------------------------------------------------------------------------
    def build(self) -> None:
        """Create the bridge, the nodes and the (empty: nobody hears anybody) filter."""
        cleanup()  # what a crashed run left
        try:
            self._build()
        except BaseException:
            self.teardown()
            raise

    def _build(self) -> None:
        med = self.medium
        _ip("netns", "add", med)
        self.built = True
        for n in self.nodes:
            _ip("netns", "add", self.netns(n))
        _batch(
            med,
            [
                "link set lo up",
                "link add br0 type bridge stp_state 0 mcast_snooping 0",
                "link set br0 up",
            ],
        )
        for n in self.nodes:
            ns = self.netns(n)
            _ip("link", "add", "eth0", "netns", ns, "type", "veth", "peer", "name",
                self.port(n), "netns", med)  # fmt: skip
        _batch(med, [f"link set {self.port(n)} master br0 up" for n in self.nodes])
        for n in self.nodes:
            ns = self.netns(n)
            sysctls = [
                "net.ipv4.ip_forward=1",
                "net.ipv4.conf.all.send_redirects=0",
                "net.ipv4.conf.eth0.send_redirects=0",
                "net.ipv4.conf.all.accept_redirects=0",
                "net.ipv4.conf.all.rp_filter=0",
                "net.ipv4.conf.eth0.rp_filter=0",
                "net.ipv6.conf.all.accept_redirects=0",
                "net.ipv6.conf.eth0.accept_dad=0",  # link-local usable at once: babeld speaks it
            ]
            proc = subprocess.run(
                ["ip", "netns", "exec", ns, "sysctl", "-qw", *sysctls], capture_output=True
            )
            if proc.returncode != 0:
                raise MsoError(f"sysctl in {ns}: {proc.stderr.decode().strip()}")
            lines = [
                "link set lo up",
                f"link set eth0 address {self.mac(n)}",
                f"addr add {self.address(n)}/16 brd + dev eth0",  # batmand needs one
                "link set eth0 up",
            ]
            lines += [
                f"neigh replace {self.address(o)} lladdr {self.mac(o)} dev eth0 nud permanent"
                for o in self.nodes
                if o != n
            ]
            _batch(ns, lines)
        self.nft = Nft(med)
        self.nft.run(
            f"add table bridge {TABLE}\n"
            f"add set bridge {TABLE} links {{ type ifname . ifname; }}\n"
            f"add chain bridge {TABLE} loss\n"
            f"add chain bridge {TABLE} forward {{ type filter hook forward priority 0; "
            f"policy drop; }}\n"
            f"add rule bridge {TABLE} forward iifname . oifname @links jump loss\n"
            f"add rule bridge {TABLE} forward iifname . oifname @links accept\n"
        )

    def teardown(self) -> None:
        """Kill (by PID) what runs inside, delete every namespace; idempotent."""
        if self.nft is not None:
            self.nft.close()
            self.nft = None
        cleanup(owner=self.owner)
        self.built = False

    # -- links ----------------------------------------------------------------------------
    def _pair(self, a: str, b: str) -> str:
        return f'"{self.port(a)}" . "{self.port(b)}"'

    def set_links(
        self,
        links: Iterable[tuple[str, str]],
        loss: Mapping[tuple[str, str], float] | None = None,
    ) -> int:
        """Make exactly ``links`` (undirected) hear each other, with ``loss`` per link; one
        nft transaction. Returns how many links changed."""
        assert self.nft is not None, "build() first"
        want = {(a, b) if a <= b else (b, a) for a, b in links}
        add, drop = want - self.links, self.links - want
        cmds = []
        if add:
            elems = ", ".join(f"{self._pair(a, b)}, {self._pair(b, a)}" for a, b in sorted(add))
            cmds.append(f"add element bridge {TABLE} links {{ {elems} }}")
        if drop:
            elems = ", ".join(f"{self._pair(a, b)}, {self._pair(b, a)}" for a, b in sorted(drop))
            cmds.append(f"delete element bridge {TABLE} links {{ {elems} }}")
        lossy = {k: p for k, p in (loss or {}).items() if p > 0 and k in want}
        if lossy != self.loss:
            cmds.append(f"flush chain bridge {TABLE} loss")
            for (a, b), p in sorted(lossy.items()):
                per_mille = round(p * 1000)
                for x, y in ((a, b), (b, a)):
                    cmds.append(
                        f'add rule bridge {TABLE} loss iifname "{self.port(x)}" oifname '
                        f'"{self.port(y)}" numgen random mod 1000 < {per_mille} drop'
                    )
        if cmds:
            self.nft.run("\n".join(cmds) + "\n")
        self.links, self.loss = want, lossy
        return len(add) + len(drop)

    def shape(self, node: str, mbps: float | None) -> None:
        """Rate-limit ``node``'s radio (egress of its eth0) with tbf; None removes it."""
        if self.rates.get(node) == mbps:
            return
        ns = self.netns(node)
        if mbps is None:
            subprocess.run(["tc", "-n", ns, "qdisc", "del", "dev", "eth0", "root"],
                           capture_output=True)  # fmt: skip
        else:
            burst = max(3200, int(mbps * 1e6 / 8 * 0.002))  # 2 ms of traffic, >= 2 frames
            proc = subprocess.run(
                ["tc", "-n", ns, "qdisc", "replace", "dev", "eth0", "root", "tbf", "rate",
                 f"{mbps:g}mbit", "burst", str(burst), "latency", "50ms"],
                capture_output=True,
            )  # fmt: skip
            if proc.returncode != 0:
                raise MsoError(f"tc in {ns}: {proc.stderr.decode().strip()}")
        self.rates[node] = mbps

    # -- processes inside -----------------------------------------------------------------
    def popen(
        self, node: str, cmd: list[str], log: Path, env: Mapping[str, str] | None = None
    ) -> subprocess.Popen[bytes]:
        """Start ``cmd`` inside ``node``'s namespace, output to ``log``."""
        with log.open("ab") as out:
            return subprocess.Popen(
                ["ip", "netns", "exec", self.netns(node), *cmd],
                stdout=out,
                stderr=subprocess.STDOUT,
                env=dict(env) if env is not None else None,
                start_new_session=True,
            )

    def babeld(self, node: str, workdir: Path) -> subprocess.Popen[bytes]:
        """Start babeld in ``node``'s namespace (foreground: a child we can kill by PID)."""
        exe = shutil.which("babeld")
        if exe is None:
            raise MsoError(
                "babeld is not installed (Debian: apt-get install babeld; `make netns-deps`)"
            )
        conf = workdir / "babeld.conf"
        if not conf.exists():
            conf.write_text(BABELD_CONF)
        i = self.index[node]
        # a restart after a SIGKILL: the dead daemon's routes would linger until the new one
        # learns better (its stale pid file: mso.emu.netns.daemons.babeld)
        _ip("route", "flush", "proto", "babel", netns=self.netns(node), check=False)
        cmd = [exe, "-c", str(conf), "-C", f"router-id {self.mac(node)}",
               "-I", str(workdir / f"babeld-{i}.pid"),
               "-S", str(workdir / f"babeld-{i}.state"), "eth0"]  # fmt: skip
        return self.popen(node, cmd, workdir / f"babeld-{node}.log")

    def counters(self, node: str) -> dict[str, int]:
        """``node``'s eth0 byte and packet counters, as the kernel counts them."""
        out = {}
        ns = self.netns(node)
        for key in ("rx_bytes", "tx_bytes", "rx_packets", "tx_packets"):
            proc = subprocess.run(
                ["ip", "netns", "exec", ns, "cat", f"/sys/class/net/eth0/statistics/{key}"],
                capture_output=True,
            )
            out[key] = int(proc.stdout or 0)
        return out
