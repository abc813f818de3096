"""Print every procedure's transition table as Markdown (docs/architecture.md is drawn from
this, so the documentation cannot drift from the code): ``python -m mso.protocol.procedures``."""

from __future__ import annotations

from mso.protocol.procedures.base import Procedure, StateMachine, table_rows
from mso.protocol.procedures.deploy import Deploy
from mso.protocol.procedures.instance import AWAIT_NOTE, InstanceLife
from mso.protocol.procedures.lookup import Lookup
from mso.protocol.procedures.membership.detector import PeerLife, Suspicion, Vouch
from mso.protocol.procedures.relocation import Relocation
from mso.protocol.procedures.remap import Remap
from mso.protocol.procedures.replication import ACK_ATTEMPTS, ACK_TIMEOUT_S, Replication
from mso.protocol.procedures.status import StatusFanout

PROCEDURES: list[type[Procedure]] = [
    Deploy,
    Relocation,
    Remap,
    Lookup,
    StatusFanout,
    Suspicion,
    Vouch,
]
# the other ends: a vertex instance at its host, and each other node as one node holds it
PARTICIPANTS: list[tuple[type[StateMachine], str]] = [
    (InstanceLife, AWAIT_NOTE),
    (PeerLife, "silence judged against the liveness window; out of reach, asked about"),
    (
        Replication,
        f"a replicated vertex at its host; a replica silent {ACK_TIMEOUT_S:g} s is sent the "
        f"snapshot again, replaced after {ACK_ATTEMPTS} sends",
    ),
]


def _table(cls: type[StateMachine], heading: str) -> list[str]:
    out = [f"**{cls.NAME}** ({heading})\n", "| state | event | next state |\n|---|---|---|"]
    out += [f"| {a} | {e} | {b} |" for a, e, b in table_rows(cls)]
    out.append("")
    return out


def markdown() -> str:
    out = []
    for cls in PROCEDURES:
        out += _table(cls, f"deadline {cls.DEADLINE_S:g} s unless set per run")
    for part, note in PARTICIPANTS:
        out += _table(part, note)
    return "\n".join(out)


if __name__ == "__main__":
    print(markdown())
