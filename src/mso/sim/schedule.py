"""One fault run's world, shared by the generator (``mso.sim.faults``) and the checker
(``mso.sim.invariants``), so neither imports the other."""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass

from mso.model.network import Network
from mso.protocol import messages as m
from mso.scenario.format import Change


@dataclass(frozen=True)
class Settings:
    """How long each phase lasts (virtual seconds) and how busy the app is."""

    start_s: float = 1.5  # deployment settles before the first fault
    faults_s: float = 6.0  # faults are drawn in [start_s, start_s + faults_s)
    quiet_s: float = 6.0  # after everything heals: recovery, rejoins, catch-up
    rate: float = 20.0  # events per second per source
    max_faults: int = 6
    # daemon restarts too (the kind ``restart``, a new process with its spill store kept): on
    # since the ninth stop's 10,000 seeds with them held (docs/benchmarks.md); the seeds of the
    # runs before are recorded with ``restarts=False``
    restarts: bool = True
    # how the app's chains are split (``planner:``): the paper's split, as the committed runs
    # were; the default bytes split is run too (``bench/faults.py --planner bytes``)
    planner: str = "paper"
    # a study, not part of the committed runs: each control frame (not events, acks, beats or
    # status) lost on the way with this probability once the app is deployed, as a frame that
    # waited out its route wait is (``bench/faults.py --control-loss``)
    control_loss: float = 0.0


@dataclass
class Schedule:
    """One seed's world: topology, app document, timeline changes, client requests."""

    seed: int
    topology: str
    network: Network
    app: str
    changes: list[Change]
    requests: list[tuple[float, str, m.Message]]
    faults: Counter[str]
    settings: Settings
    pinned: dict[str, str]

    @property
    def end(self) -> float:
        return self.settings.start_s + self.settings.faults_s + self.settings.quiet_s
