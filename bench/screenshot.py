"""The dashboard screenshots in docs/img: `mso demo`'s run (the convoy on ``convoy-demo.yaml``,
its scripted route change and the robot whose battery empties), the rules on, shot at 1280×800
and 1920×1080 once the recovery has happened (``--at`` seconds into the run), as a viewer sees
the page without scrolling; then the page after the run ended. Drawn by Debian's headless
chromium (``apt-get install chromium``) through Playwright.

Usage: .venv/bin/python bench/screenshot.py [--at 46] [--out docs/img]
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
SIZES = ((1280, 800), (1920, 1080))


async def shoot(at: float, out: Path) -> None:
    emu = Emulator(load_scenario(EXAMPLES / "convoy-demo.yaml"))
    await emu.start()
    player = asyncio.create_task(emu.play())  # the route change; N3's battery empties by itself
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
            pages = []
            for w, h in SIZES:
                page = await browser.new_page(viewport={"width": w, "height": h})
                await page.goto(url)
                await expect(page.locator("#conn")).to_have_text("live")
                pages.append(page)
            await asyncio.sleep(max(0.0, emu.t0 + at - asyncio.get_running_loop().time()))
            await board.wait_update(5.0)
            await board.wait_update(5.0)
            for (w, h), page in zip(SIZES, pages, strict=True):
                path = out / f"dashboard-{w}x{h}.png"
                await page.screenshot(path=str(path))
                print(f"written: {path}")
            await board.stop()
            board = None
            page = pages[0]
            await expect(page.locator("#conn")).to_have_text("ended")
            path = out / "dashboard-ended.png"
            await page.screenshot(path=str(path))
            print(f"written: {path}")
            await browser.close()
    finally:
        player.cancel()
        if board is not None:
            await board.stop()
        await emu.stop()


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--at", type=float, default=46.0, help="seconds into the run")
    ap.add_argument("--out", type=Path, default=HERE.parent / "docs" / "img")
    a = ap.parse_args(argv)
    asyncio.run(shoot(a.at, a.out))
    return 0


if __name__ == "__main__":
    sys.exit(main())
