"""Argument types of the ``mso`` command: numbers are finite and in range, or refused in one line.

Click's own error is several lines (usage, hint, error); :class:`OneLineGroup` prints
``error: <option>: <what was expected>`` and exits with code 2, like every other user error.
"""

from __future__ import annotations

import math
import sys
from typing import Any

import click


class Number(click.ParamType):  # type: ignore[type-arg]
    """A finite float with a lower bound (``>`` when ``strict``, else ``>=``)."""

    name = "number"

    def __init__(self, low: float = 0.0, *, strict: bool = True, high: float = 1e12) -> None:
        self.low, self.strict, self.high = low, strict, high

    def convert(self, value: Any, param: click.Parameter | None, ctx: click.Context | None) -> Any:
        if isinstance(value, float):
            x = value
        else:
            try:
                x = float(value)
            except (TypeError, ValueError):
                self.fail(f"expected a number, got {value!r}", param, ctx)
        rel = ">" if self.strict else ">="
        if not math.isfinite(x) or x < self.low or (self.strict and x == self.low) or x > self.high:
            self.fail(f"expected a finite number {rel} {self.low:g}, got {value!r}", param, ctx)
        return x


POSITIVE = Number(0.0, strict=True)
NON_NEGATIVE = Number(0.0, strict=False)


def power_model(text: str) -> tuple[float, float, float, float]:
    """``IDLE_W,CPU_W,TX_UJ,RX_UJ``: four finite numbers >= 0."""
    parts = text.split(",")
    try:
        values = [float(x) for x in parts]
    except ValueError:
        values = []
    if len(values) != 4 or not all(math.isfinite(v) and v >= 0 for v in values):
        raise click.BadParameter(
            f"expected IDLE_W,CPU_W,TX_UJ,RX_UJ as four numbers >= 0, got {text!r}",
            param_hint="'--power'",
        )
    return values[0], values[1], values[2], values[3]


class OneLineGroup(click.Group):
    """Usage errors in one line on stderr, exit code 2 (no usage dump)."""

    def main(self, *args: Any, **kwargs: Any) -> Any:
        standalone = kwargs.pop("standalone_mode", True)
        try:
            return super().main(*args, standalone_mode=False, **kwargs)  # type: ignore[call-overload]
        except click.exceptions.Abort:
            if not standalone:
                raise
            click.echo("aborted", err=True)
            sys.exit(1)
        except click.ClickException as exc:
            if not standalone:
                raise
            # "Invalid value for '--cpu': ..." names the option already
            click.echo(f"error: {exc.format_message().replace(chr(10), ' ')}", err=True)
            sys.exit(exc.exit_code)
