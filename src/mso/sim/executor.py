"""The simulator's executor: vertex effects carried out inline, their results due in virtual
time.

The same :class:`~mso.runtime.worker.VertexWorker` as the daemon's threads runs the user's code;
only time differs. Each instance is busy one effect at a time; with ``model_time`` an effect takes
the vertex's modelled cost (``cost`` ms per event at ``cpu: 1.0``, divided by the node's cpu), so
a slow vertex holds its own input back, and through the windows its producers, exactly as on a
device. Without it results are due at once (after the other events of the same instant).
"""

from __future__ import annotations

from collections.abc import Callable

from mso.protocol import effects as fx
from mso.runtime.worker import VertexWorker

LOOP_STEP_S = 1e-3  # virtual time a free-running source's batch takes at least


class SimExecutor:
    def __init__(
        self,
        cpu: float,
        push: Callable[[float, fx.VertexResult], None],
        clock: Callable[[], float],
        model_time: bool = False,
    ) -> None:
        self.cpu = cpu
        self.push = push
        self.clock = clock
        self.model_time = model_time
        self.workers: dict[int, VertexWorker] = {}
        self._busy_until: dict[int, float] = {}
        self._credit: dict[int, int] = {}

    def _due(self, instance: int, now: float, events: int, floor: float = 0.0) -> float:
        worker = self.workers[instance]
        cost_s = worker.start.vertex.cost * events / max(self.cpu, 1e-9) / 1e3
        took = max(cost_s, floor) if self.model_time else floor
        at = max(now, self._busy_until.get(instance, now)) + took
        self._busy_until[instance] = at
        return at

    def submit(self, eff: fx.VertexEffect, now: float) -> None:
        if isinstance(eff, fx.StartVertex):
            worker = self.workers[eff.instance] = VertexWorker(
                eff, cpu_clock=lambda: 0.0, clock=self.clock
            )
            self.push(self._due(eff.instance, now, 0), worker.open())
            return
        worker_or_none = self.workers.get(eff.instance)
        if worker_or_none is None:
            return
        worker = worker_or_none
        if isinstance(eff, fx.FeedVertex):
            self.push(self._due(eff.instance, now, len(eff.events)), worker.feed(eff))
        elif isinstance(eff, fx.RunSource):
            res = worker.run_source(eff.first, eff.count, eff.now)
            self.push(self._due(eff.instance, now, eff.count), res)
        elif isinstance(eff, fx.Credit):
            credit = self._credit.get(eff.instance, 0) + eff.count
            self._credit[eff.instance] = 0
            if credit > 0 and not worker.ended:
                pulled = worker.pull(credit, float("inf"))
                self._credit[eff.instance] = credit - pulled.calls
                self.push(self._due(eff.instance, now, pulled.calls, LOOP_STEP_S), pulled)
        elif isinstance(eff, fx.RestoreVertex):
            worker.restore(eff.state)
        elif isinstance(eff, fx.SnapshotVertex):
            self.push(self._due(eff.instance, now, 0), worker.snapshot(eff.token))
        elif isinstance(eff, fx.StopVertex):
            worker.close()
            del self.workers[eff.instance]
            self._busy_until.pop(eff.instance, None)
            self._credit.pop(eff.instance, None)

    def instance_of(self, instance: int) -> object | None:
        """The user's object of a live instance (tests read a vertex's own state)."""
        worker = self.workers.get(instance)
        return worker.instance.fn if worker is not None and worker.instance is not None else None
