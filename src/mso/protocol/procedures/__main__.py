"""Print every procedure's transition table as Markdown (docs/architecture.md is drawn from
this, so the documentation cannot drift from the code): ``python -m mso.protocol.procedures``."""

from __future__ import annotations

from mso.protocol.procedures.base import Procedure, table_rows
from mso.protocol.procedures.deploy import Deploy
from mso.protocol.procedures.relocate import Relocation
from mso.protocol.procedures.remap import Remap
from mso.protocol.procedures.status import StatusFanout

PROCEDURES: list[type[Procedure]] = [Deploy, Relocation, Remap, StatusFanout]


def markdown() -> str:
    out = []
    for cls in PROCEDURES:
        out.append(f"**{cls.NAME}** (deadline {cls.DEADLINE_S:g} s unless set per run)\n")
        out.append("| state | event | next state |\n|---|---|---|")
        out += [f"| {a} | {e} | {b} |" for a, e, b in table_rows(cls)]
        out.append("")
    return "\n".join(out)


if __name__ == "__main__":
    print(markdown())
