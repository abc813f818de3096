"""Errors a user can act on: each names where (file, line, field) and what was expected."""

from __future__ import annotations


class MsoError(Exception):
    """Base class for every error mso reports to a user (CLI exit code 2, never a traceback)."""

    exit_code = 2


class SpecError(MsoError):
    """A problem in an app or scenario definition, located as precisely as we can.

    Rendered as ``file:line: field: message`` with the parts that are known.
    """

    def __init__(
        self,
        message: str,
        *,
        file: str | None = None,
        line: int | None = None,
        field: str | None = None,
        path: tuple[str | int, ...] | None = None,
    ) -> None:
        self.message = message
        self.file = file
        self.line = line
        self.field = field
        self.path = path  # where in the document, when known (for the line)
        super().__init__(self.render())

    def render(self) -> str:
        where = ""
        if self.file:
            where = self.file + (f":{self.line}" if self.line else "") + ": "
        elif self.line:
            where = f"line {self.line}: "
        field = f"{self.field}: " if self.field else ""
        return f"{where}{field}{self.message}"


class AppError(SpecError):
    """The application graph is invalid."""


class ScenarioError(SpecError):
    """The scenario (network description) is invalid."""


class PlanningError(MsoError):
    """No placement satisfies the request (e.g. a pinned node is unreachable)."""


def with_code_hint(message: str) -> str:
    """An import failure of app code, with how code reaches a node: the first thing a user
    whose own package is "not found" needs to know, as the error is often seen on a node."""
    if "does not resolve: no module named" not in message:
        return message
    module = message.rpartition("no module named ")[2].strip("'\"")
    top = module.split(".")[0]
    return (
        f"{message} (app code must be importable on every node: install its package there, "
        f"e.g. pip install -e ., or put it on PYTHONPATH; nodes run only allowed code: "
        f"--allow-code {top} or $MSO_ALLOW_CODE)"
    )
