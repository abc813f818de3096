"""``mso bench``: the benchmarks of docs/benchmarks.md, run as commands."""

from __future__ import annotations

import sys
from pathlib import Path

import click


@click.group()
def bench() -> None:
    """Benchmarks (see docs/benchmarks.md)."""


@bench.command(name="lifetime", context_settings={"ignore_unknown_options": True})
@click.argument("args", nargs=-1, type=click.UNPROCESSED)
def bench_lifetime(args: tuple[str, ...]) -> None:
    """The energy study: the convoy under four placements, battery-limited robots."""
    from mso.benchmarks.lifetime import main as lifetime

    sys.exit(lifetime(list(args)))


@bench.command(name="table1")
@click.option("--json", "json_file", type=click.Path(dir_okay=False, path_type=Path))
@click.option("--runs", type=click.IntRange(1, 100_000), default=30, show_default=True)
@click.option("--quick", is_flag=True, help="A few runs, to check it works.")
@click.option("--quiet", is_flag=True, help="No progress lines on stderr.")
def bench_table1(json_file: Path | None, runs: int, quick: bool, quiet: bool) -> None:
    """Table 1 of the paper: mapping, relocations, chain and global remaps, on 4 node processes."""
    from mso.benchmarks.table1 import main as table1

    args = ["--runs", str(runs)] + (["--json", str(json_file)] if json_file else [])
    args += ["--quick"] if quick else []
    sys.exit(table1(args + (["--quiet"] if quiet else [])))
