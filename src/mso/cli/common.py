"""What the ``mso`` commands share: the one-line user errors, the console, and the options that
several commands take (the same words and help everywhere). Imports only click at load: every
command module is loaded for ``mso status`` too."""

from __future__ import annotations

import contextlib
import sys
from collections.abc import Callable
from functools import wraps
from pathlib import Path
from typing import TYPE_CHECKING, Any, TypeVar

import click

from mso.errors import MsoError

if TYPE_CHECKING:
    from rich.console import Console

F = TypeVar("F", bound=Callable[..., Any])

EXAMPLES = Path(__file__).resolve().parent.parent / "examples"
DASHBOARD_LISTEN = "127.0.0.1:8765"  # mso.dashboard.server.DEFAULT_LISTEN, not imported early


def user_errors(fn: F) -> F:
    """Turn an MsoError into a one-line message and exit code 2."""

    @wraps(fn)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        try:
            return fn(*args, **kwargs)
        except MsoError as exc:
            click.echo(f"error: {exc}", err=True)
            sys.exit(exc.exit_code)

    return wrapper  # type: ignore[return-value]


def console() -> Console:
    from rich.console import Console

    return Console(highlight=False)


def progress(what: str) -> contextlib.AbstractContextManager[Any]:
    """A spinner on stderr while long work runs (a terminal only: pipes and --json stay clean)."""
    if not sys.stderr.isatty():
        return contextlib.nullcontext()
    from rich.console import Console

    return Console(stderr=True).status(what)


no_import = click.option(
    "--no-import",
    is_flag=True,
    help="Do not import vertex code and formats (plan on a machine without the app's modules).",
)
sign_option = click.option(
    "--sign",
    envvar="MSO_SIGN",
    metavar="KEYFILE",
    help="Sign the command with this operator key (made by `mso keygen`; default: $MSO_SIGN); "
    "needed by nodes started with --operator-key.",
)
operator_key_option = click.option(
    "--operator-key",
    "operator_keys",
    multiple=True,
    metavar="PUB",
    help="An operator's public key (text or .pub file, repeat): commands that change an overlay "
    "must be signed with one. Without any, the overlay key is all there is.",
)
allow_code_option = click.option(
    "--allow-code",
    "allow_code",
    multiple=True,
    metavar="MODULE",
    help="A module (and its submodules) whose vertex, format and policy code this node may "
    "import (repeat; default: $MSO_ALLOW_CODE, comma-separated; mso's bundled vertex modules "
    "always).",
)
key_option = click.option(
    "--key",
    envvar="MSO_KEY",
    help="Overlay pre-shared key (default: $MSO_KEY; else an emulated overlay's own key file, "
    "else the development key, loopback only).",
)
client_key_option = click.option(
    "--client-key",
    envvar="MSO_CLIENT_KEY",
    metavar="KEYFILE",
    help="This client's own key, certified by an operator (`mso keygen --client NAME`; default: "
    "$MSO_CLIENT_KEY): nodes that require identities serve no other client.",
)
overlay_option = click.option(
    "--overlay",
    envvar="MSO_OVERLAY",
    help="Which running emulator (`mso overlays`) when several run (default: $MSO_OVERLAY).",
)
via_option = click.option(
    "--via", help="Node to ask: a node id of the running emulator or HOST:PORT."
)
json_option = click.option("--json", "as_json", is_flag=True)
