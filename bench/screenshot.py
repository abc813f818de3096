"""The dashboard screenshot in docs/: the convoy on the line with a battery-bound leader
(``convoy-energy.yaml``), the management rules on, after ``--wait`` seconds of running, so the
timeline shows the rules moving work off the leader; then one relocation asked from the page.
Drawn by Debian's headless chromium (``apt-get install chromium``) through Playwright.

Usage: .venv/bin/python bench/screenshot.py [--wait 30] [--out docs/img/dashboard.png]
"""

from __future__ import annotations

import argparse
import asyncio
import sys
from pathlib import Path

from playwright.async_api import async_playwright, expect

import mso.examples
from mso.dashboard.server import Dashboard
from mso.emu.controller import Emulator
from mso.scenario import load_scenario

HERE = Path(__file__).resolve().parent
EXAMPLES = Path(mso.examples.__file__).parent


async def shoot(wait: float, out: Path) -> None:
    emu = Emulator(load_scenario(EXAMPLES / "convoy-energy.yaml"))
    await emu.start()
    board = None
    try:
        await emu.deploy((EXAMPLES / "convoy.yaml").read_text(), "convoy.yaml", "N1", check=True)
        board = Dashboard([emu.address(n) for n in emu.nodes], name=str(emu.name),
                          positions=emu.node_positions, expected=list(emu.nodes))  # fmt: skip
        url = await board.start()
        async with async_playwright() as pw:
            browser = await pw.chromium.launch(
                executable_path="/usr/bin/chromium", headless=True, args=["--no-sandbox"]
            )
            page = await browser.new_page(viewport={"width": 1400, "height": 1000})
            await page.goto(url)
            await expect(page.locator("#conn")).to_have_text("live")
            await asyncio.sleep(wait)
            await page.select_option("#relocate-vertex", "path_planning")
            await page.select_option("#relocate-target", "upstream")
            await page.click("#relocate-go")
            await expect(page.locator("#control-result")).to_contain_text("now runs on")
            await board.wait_update(5.0)
            await board.wait_update(5.0)
            await page.screenshot(path=str(out), full_page=True)
            await browser.close()
        print(f"written: {out}")
    finally:
        if board is not None:
            await board.stop()
        await emu.stop()


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--wait", type=float, default=30.0)
    ap.add_argument("--out", type=Path, default=HERE.parent / "docs" / "img" / "dashboard.png")
    a = ap.parse_args(argv)
    asyncio.run(shoot(a.wait, a.out))
    return 0


if __name__ == "__main__":
    sys.exit(main())
