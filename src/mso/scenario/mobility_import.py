"""Movement from the tools users already have, as a scenario's mobility (a
:class:`~mso.model.mobility.Trace`).

- **ns-2 movement scripts** (``setdest``'s output, and what ns-3's ``Ns2MobilityHelper``, CORE and
  BonnMotion's ``NSFile`` export): ``$node_(i) set X_ x`` / ``Y_`` / ``Z_`` lines give the start,
  ``$ns_ at t "$node_(i) setdest x y speed"`` starts a straight move toward ``(x, y)`` at
  ``speed`` m/s (a newer ``setdest`` interrupts it where the node is), ``$ns_ at t "$node_(i)
  set X_ x"`` puts the node there. ``$god_`` lines and ``#`` comments are skipped.
- **BonnMotion's native movement file** (``*.movements``, gzipped or not): line *i* is node
  *i*, a flat list of ``t x y`` waypoints (``t x y z`` for 3-D scenarios); the node moves in a
  straight line from one waypoint to the next.

Node *i* of the file becomes the *i*-th id of ``ids``. The files are parsed, never executed
(an ns-2 script is Tcl: anything beyond the lines above is rejected with its line number).
"""

from __future__ import annotations

import gzip
import math
import re
from pathlib import Path

from mso.errors import ScenarioError
from mso.model.mobility import Trace, Waypoint

_NUM = r"([-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?)"
_NODE = r"\$node_\(\s*(\d+)\s*\)"
_SET = re.compile(rf"^{_NODE}\s+set\s+([XYZ])_\s+{_NUM}\s*;?$")
_AT = re.compile(rf'^\$ns_\s+at\s+{_NUM}\s+"(.*)"\s*;?$')
_SETDEST = re.compile(rf"^{_NODE}\s+setdest\s+{_NUM}\s+{_NUM}\s+{_NUM}\s*$")
_GOD = re.compile(r"^\$god_\b")

FORMATS = ("ns2", "bonnmotion")


def _err(message: str, file: str | None, line: int | None) -> ScenarioError:
    return ScenarioError(message, file=file, line=line)


def _ids_for(count: int, ids: list[str], file: str | None) -> list[str]:
    if count > len(ids):
        raise _err(
            f"the movement file has {count} nodes but only {len(ids)} node ids are given "
            f"({', '.join(ids)}); list one id per node of the file in 'mobility.nodes'",
            file,
            None,
        )
    return ids[:count]


class _Mover:
    """One node's waypoints as a script's commands arrive in time order."""

    def __init__(self) -> None:
        self.start: list[float] = [0.0, 0.0]
        self.ws: list[Waypoint] = []

    def _begin(self) -> None:
        if not self.ws:
            self.ws.append((0.0, self.start[0], self.start[1]))

    def here(self, t: float) -> tuple[float, float]:
        """Where the node is at ``t``, cutting short a move still under way then."""
        self._begin()
        while len(self.ws) >= 2 and self.ws[-2][0] > t:  # a move that had not begun
            self.ws.pop()
        last = self.ws[-1]
        if last[0] <= t:
            pos = (last[1], last[2])
        else:
            t0, x0, y0 = self.ws[-2]
            f = (t - t0) / (last[0] - t0)
            pos = (x0 + f * (last[1] - x0), y0 + f * (last[2] - y0))
            self.ws.pop()
        if self.ws[-1] != (t, *pos):
            self.ws.append((t, *pos))
        return pos

    def setdest(self, t: float, x: float, y: float, speed: float) -> None:
        here = self.here(t)
        dist = math.dist(here, (x, y))
        if speed > 0 and dist > 0:
            self.ws.append((t + dist / speed, x, y))

    def place(self, t: float, axis: str, v: float) -> None:
        x, y = self.here(t)
        self.ws.append((t, v, y) if axis == "X" else (t, x, v))


def parse_ns2(text: str, ids: list[str], *, file: str | None = None) -> Trace:
    """An ns-2 movement script as a :class:`Trace` for ``ids`` (file node i -> ``ids[i]``)."""
    movers: dict[int, _Mover] = {}
    timed: list[tuple[float, int, int, str, tuple[float, ...]]] = []  # (t, seq, node, op, args)
    for lineno, raw in enumerate(text.splitlines(), 1):
        line = raw.strip()
        if not line or line.startswith("#") or _GOD.match(line):
            continue
        if m := _SET.match(line):
            node, axis, v = int(m[1]), m[2], _finite(m[3], file, lineno)
            mover = movers.setdefault(node, _Mover())
            if mover.ws:
                raise _err(f"node {node}: 'set {axis}_' after its movement began", file, lineno)
            if axis != "Z":
                mover.start["XY".index(axis)] = v
            continue
        if m := _AT.match(line):
            t = _finite(m[1], file, lineno)
            if t < 0:
                raise _err(f"expected a time >= 0, got {m[1]}", file, lineno)
            inner = m[2].strip()
            if _GOD.match(inner):
                continue
            if d := _SETDEST.match(inner):
                x, y, speed = (_finite(d[k], file, lineno) for k in (2, 3, 4))
                if speed < 0:
                    raise _err(f"expected a speed >= 0, got {d[4]}", file, lineno)
                timed.append((t, lineno, int(d[1]), "setdest", (x, y, speed)))
                continue
            if s := _SET.match(inner):
                if s[2] != "Z":
                    v = _finite(s[3], file, lineno)
                    timed.append((t, lineno, int(s[1]), s[2], (v,)))
                continue
        raise _err(
            "expected '$node_(i) set X_|Y_|Z_ v', '$ns_ at t \"$node_(i) setdest x y speed\"', "
            f"a '$god_' line or a '#' comment, got {line[:60]!r}",
            file,
            lineno,
        )
    for t, _, node, op, args in sorted(timed):
        mover = movers.setdefault(node, _Mover())
        if op == "setdest":
            mover.setdest(t, *args)
        else:
            mover.place(t, op, args[0])
    if not movers:
        raise _err("no node found in the ns-2 movement script", file, None)
    count = max(movers) + 1
    names = _ids_for(count, ids, file)
    out: dict[str, tuple[Waypoint, ...]] = {}
    for i, mover in sorted(movers.items()):
        mover._begin()
        out[names[i]] = tuple(mover.ws)
    return Trace(out, source=file or "")


def parse_bonnmotion(text: str, ids: list[str], *, file: str | None = None, dim: int = 2) -> Trace:
    """A BonnMotion ``.movements`` file as a :class:`Trace` (line i -> ``ids[i]``)."""
    if dim not in (2, 3):
        raise _err(f"expected dim 2 or 3, got {dim!r}", file, None)
    width = dim + 1
    lines = text.splitlines()
    while lines and not lines[-1].strip():
        lines.pop()
    if not lines:
        raise _err("no node found in the BonnMotion movement file", file, None)
    names = _ids_for(len(lines), ids, file)
    out: dict[str, tuple[Waypoint, ...]] = {}
    for i, raw in enumerate(lines):
        lineno = i + 1
        tokens = raw.split()
        if not tokens or len(tokens) % width:
            raise _err(
                f"node {i}: expected groups of {width} numbers (t x y{' z' if dim == 3 else ''})"
                f", got {len(tokens)} numbers",
                file,
                lineno,
            )
        vals = [_finite(tok, file, lineno) for tok in tokens]
        ws: list[Waypoint] = []
        for k in range(0, len(vals), width):
            t, x, y = vals[k], vals[k + 1], vals[k + 2]
            if t < 0 or (ws and t < ws[-1][0]):
                raise _err(
                    f"node {i}: waypoint {k // width}: time {t:g} goes back "
                    f"(expected >= {ws[-1][0] if ws else 0:g})",
                    file,
                    lineno,
                )
            ws.append((t, x, y))
        out[names[i]] = tuple(ws)
    return Trace(out, source=file or "")


def _finite(tok: str, file: str | None, line: int) -> float:
    try:
        v = float(tok)
    except ValueError:
        raise _err(f"expected a number, got {tok!r}", file, line) from None
    if not math.isfinite(v):
        raise _err(f"expected a finite number, got {tok!r}", file, line)
    return v


def load_trace(path: str | Path, fmt: str, ids: list[str], *, dim: int = 2) -> Trace:
    """Read a movement file of format ``fmt`` (one of :data:`FORMATS`); ``.gz`` is unpacked."""
    p = Path(path)
    if fmt not in FORMATS:
        raise _err(f"expected a movement format in {FORMATS}, got {fmt!r}", str(p), None)
    try:
        data = gzip.decompress(p.read_bytes()) if p.suffix == ".gz" else p.read_bytes()
        text = data.decode("utf-8")
    except (OSError, EOFError, gzip.BadGzipFile, UnicodeDecodeError) as e:
        raise _err(f"cannot read the movement file: {e}", str(p), None) from None
    if fmt == "ns2":
        return parse_ns2(text, ids, file=str(p))
    return parse_bonnmotion(text, ids, file=str(p), dim=dim)
