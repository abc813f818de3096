"""Draw the PNG figures of docs/benchmarks.md from the kept results in bench/results/.

Usage: .venv/bin/python bench/plots.py [--results bench/results] [--out docs/img]
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from mso import plots

HERE = Path(__file__).resolve().parent


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--results", type=Path, default=HERE / "results")
    ap.add_argument("--out", type=Path, default=HERE.parent / "docs" / "img")
    a = ap.parse_args(argv)
    for name, draw in plots.BENCHMARKS.items():
        src = a.results / f"{name}.json"
        if not src.exists():
            print(f"skipped {name}: no {src}")
            continue
        print(f"written: {draw(json.loads(src.read_text()), a.out / f'bench-{name}.png')}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
