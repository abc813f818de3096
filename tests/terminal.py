"""A child process started as if from a terminal, whatever started the test run.

A shell starts a background job (``make test &``, ``nohup``, a CI runner's script) with SIGINT
ignored, and a child inherits that: Python then installs no KeyboardInterrupt handler, and a
test's Ctrl-C (SIGINT) to ``mso emulate`` would do nothing. A user's Ctrl-C comes to a
foreground process whose SIGINT is the default: ``Popen(..., preexec_fn=ctrl_c_as_in_a_terminal)``
gives the child that."""

from __future__ import annotations

import signal


def ctrl_c_as_in_a_terminal() -> None:
    """Run in the child before exec: SIGINT back to its default action."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)
