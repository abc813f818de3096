"""The ``mso`` command line. Thin: it parses, calls the library, and renders.

Every user error (bad app or scenario file, impossible request) prints one line on stderr and
exits with code 2; a traceback means a bug in mso. The commands live in modules by what they
work on: :mod:`.app` (an app file), :mod:`.overlay` (a running overlay, through :mod:`mso.api`),
:mod:`.node` (the daemon's options; :mod:`mso.daemon` runs it), :mod:`.emulate` (and
:mod:`.control`, commands to a running one), :mod:`.simulate`, :mod:`.dashboard`, :mod:`.demo`,
:mod:`.bench`; what they print in common is in :mod:`.render`. Each imports its heavy modules
where used: ``mso status`` needs neither numpy, the planner, rich nor asyncio."""

from __future__ import annotations

import click

from mso.cli import (
    app,
    bench,
    control,
    dashboard,
    demo,
    emulate,
    logs,
    look,
    node,
    overlay,
    scenario,
    simulate,
    sweep,
)  # fmt: skip
from mso.cliargs import OneLineGroup


@click.group(cls=OneLineGroup, context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(package_name="mso")
def main() -> None:
    """mso: run a dataflow app across a mobile ad hoc network and keep re-placing it.

    \b
    An app is a graph of vertices (sources, operators, sinks) joined by edges; mso cuts it into
    chains (mso chains) and places each chain along the route to its sink (mso plan). Every
    device runs the same daemon (mso node); together they form an overlay, reached through any
    of its nodes (--via). A running app is moved without losing an event: one vertex
    (mso relocate), a chain or the whole app (mso remap), by hand or by the nodes' management
    rules as batteries drain, links change and nodes fail.

    \b
    Try it on one machine:  mso demo --dashboard
      mso emulate SCENARIO --app APP --dashboard   # one process per node, live web view
      mso status --watch                           # from another terminal
    Shell completion:  eval "$(mso completion bash)"   (or zsh, fish)
    """


@main.command()
@click.argument("shell", type=click.Choice(["bash", "zsh", "fish"]))
def completion(shell: str) -> None:
    """Print the shell completion script: eval "$(mso completion bash)" in ~/.bashrc
    (zsh: ~/.zshrc; fish: mso completion fish > ~/.config/fish/completions/mso.fish)."""
    from click.shell_completion import get_completion_class

    cls = get_completion_class(shell)
    assert cls is not None
    click.echo(cls(main, {}, "mso", "_MSO_COMPLETE").source())


for _command in (
    app.validate, app.profile, app.chains, app.plan_cmd, app.compare,
    overlay.keygen, overlay.deploy, overlay.relocate, overlay.remap, overlay.undeploy,
    overlay.revoke_node, overlay.status, overlay.overlays,
    look.echo, look.hz, look.record, logs.logs,
    node.node, emulate.emulate, control.emulator, simulate.simulate, dashboard.dashboard,
    demo.demo, bench.bench, scenario.scenario, sweep.sweep,
):  # fmt: skip
    main.add_command(_command)
