"""A link model: how many frames a radio link loses, and how much later they arrive, from the
distance between its ends.

Two ways to say it:

- **log-distance path loss**: the power received at distance *d* is
  ``tx_dbm - ref_loss_db - 10 * exponent * log10(d / ref_distance_m) - shadow``, and the loss
  is a logistic curve around the receiver's sensitivity,
  ``1 / (1 + exp((received - sensitivity_dbm) / width_db))``: half the frames are lost at the
  sensitivity, few a few dB above it, nearly all a few dB below. ``shadow`` is log-normal
  shadowing: one draw per link from ``N(0, shadowing_db)``, fixed by ``seed`` and the two ids,
  so two runs with the same seed see the same links;
- **a loss curve**: ``[[distance_m, loss], ...]``, interpolated linearly, flat beyond its ends.

A pair of nodes is linked while the distance is within the scenario's radio range (by default
where the loss reaches ``max_loss``) and the link's loss is at most ``max_loss``. A lossy link
also delays: a link layer that retries a lost frame (802.11 does) delivers after
``loss / (1 - loss)`` retransmissions on average, each ``retry_delay_ms``, so a link's delay is
its ``delay_ms`` plus that. Only the user-space backend can apply delay: the netns testbed has
no ``netem`` and applies the loss alone.
"""

from __future__ import annotations

import itertools
import math
import random
import zlib
from dataclasses import dataclass

from mso.model.network import LinkSpec

MODELS = ("log_distance", "curve")


@dataclass(frozen=True)
class Propagation:
    """The parameters of a link model (see the module doc); defaults: 2.4 GHz, 15 dBm out,
    an outdoor exponent, a receiver that loses half its frames at -82 dBm."""

    model: str = "log_distance"
    tx_dbm: float = 15.0
    ref_loss_db: float = 40.0  # free space at 1 m, 2.4 GHz
    ref_distance_m: float = 1.0
    exponent: float = 3.0
    sensitivity_dbm: float = -82.0
    width_db: float = 2.0
    shadowing_db: float = 0.0
    seed: int = 0
    max_loss: float = 0.9
    retry_delay_ms: float = 0.0
    curve: tuple[tuple[float, float], ...] = ()

    def shadow_db(self, a: str, b: str) -> float:
        """The link's fixed shadowing (0 without it): the same for (a, b) and (b, a)."""
        if self.shadowing_db <= 0:
            return 0.0
        lo, hi = sorted((a, b))
        rng = random.Random(zlib.crc32(f"{self.seed}:{lo}:{hi}".encode()))
        return rng.gauss(0.0, self.shadowing_db)

    def received_dbm(self, distance_m: float, shadow_db: float = 0.0) -> float:
        d = max(distance_m, self.ref_distance_m * 1e-3)  # two nodes in one place: still finite
        path = self.ref_loss_db + 10 * self.exponent * math.log10(d / self.ref_distance_m)
        return self.tx_dbm - path - shadow_db

    def loss(self, distance_m: float, a: str = "", b: str = "") -> float:
        """The fraction of frames a link of this length (between ``a`` and ``b``) loses."""
        if self.model == "curve":
            return _interpolate(self.curve, distance_m)
        margin = self.received_dbm(distance_m, self.shadow_db(a, b)) - self.sensitivity_dbm
        x = max(-700.0, min(700.0, margin / self.width_db))
        return 1.0 / (1.0 + math.exp(x))

    def range_m(self) -> float:
        """Where the loss (without shadowing) reaches ``max_loss``: the default radio range."""
        if self.model == "curve":
            inside = [d for d, p in self.curve if p <= self.max_loss]
            return max(inside) if inside else 0.0
        # loss = max_loss  <=>  margin = width * ln((1 - max_loss) / max_loss)
        margin = self.width_db * math.log((1 - self.max_loss) / self.max_loss)
        path = self.tx_dbm - self.sensitivity_dbm - margin - self.ref_loss_db
        return float(self.ref_distance_m * 10 ** (path / (10 * self.exponent)))

    def delay_ms(self, base_ms: float, loss: float) -> float:
        """``base_ms`` plus the expected retransmissions' time at this loss."""
        if loss >= 1.0:
            return math.inf
        return base_ms + self.retry_delay_ms * loss / (1 - loss)

    def link(
        self, a: str, b: str, distance_m: float, template: LinkSpec | None = None
    ) -> LinkSpec | None:
        """The link between ``a`` and ``b`` at this distance, shaped like ``template`` but for
        its loss and delay; None when it would lose more than ``max_loss``."""
        loss = self.loss(distance_m, a, b)
        if loss > self.max_loss:
            return None
        t = template or LinkSpec(a, b)
        loss = round(loss, 4)  # a steady position gives the same spec, so no change is news
        return LinkSpec(a, b, t.bandwidth_mbps, round(self.delay_ms(t.delay_ms, loss), 3), loss)


def _interpolate(curve: tuple[tuple[float, float], ...], d: float) -> float:
    if d <= curve[0][0]:
        return curve[0][1]
    for (d0, p0), (d1, p1) in itertools.pairwise(curve):
        if d <= d1:
            return p0 + (p1 - p0) * (d - d0) / (d1 - d0) if d1 > d0 else p1
    return curve[-1][1]
