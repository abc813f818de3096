"""Values no genuine node sends, refused before they reach a node's core.

A node's incarnation is the wall-clock millisecond it started (plus one per rejoin), and a
failure is recorded against the incarnation that failed. A member announcing an incarnation at
the end of its range (a ``NodeDown`` of N3 at 2⁶², say) would make every genuine incarnation of
N3 look older for ever: N3 could never rejoin. So incarnations more than a day ahead of this
node's clock, or negative, are not believed.
"""

from __future__ import annotations

from mso.protocol import messages as m

MAX_AHEAD_MS = 86_400_000  # clocks of robots in one overlay are not a day apart


def implausible(msg: m.Message, wall_ms: int) -> str:
    """Why ``msg`` cannot come from a genuine node ('' when it can)."""
    if isinstance(msg, m.NodeDown | m.NodeUp):
        incarnations = [msg.incarnation]
    elif isinstance(msg, m.Heartbeat):
        incarnations = [msg.incarnation, *msg.failed.values(), *(n.incarnation for n in msg.news)]
    else:
        return ""
    limit = wall_ms + MAX_AHEAD_MS
    for inc in incarnations:
        if not 0 <= inc <= limit:
            return f"incarnation {inc} is not a time this overlay has reached"
    return ""
