"""The browser half of tools/view_screenshot.py, run with the Python that has Playwright (a separate virtual
environment: the project does not depend on it): open Lichtblick at ``--url`` in headless Chromium (software
WebGL), wait for live data and screenshot the 3D panel of the first source's tab. Imports nothing of gcdtrav.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from playwright.sync_api import ConsoleMessage, sync_playwright

CHROMIUM_FLAGS = ["--no-sandbox", "--use-angle=swiftshader", "--enable-unsafe-swiftshader", "--ignore-gpu-blocklist"]
VIEWPORT = {"width": 2400, "height": 1500}  # the 3D panel is about half of it in the generated layout
ZOOM_STEP = -400  # one mouse-wheel step towards the robot
THREE_D = '[data-testid~="panel-mouseenter-container"][data-testid*="3D!gcdtrav-"]'


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--url", required=True)
    parser.add_argument("--chromium", default="/usr/bin/chromium")
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--page-out", type=Path, help="also a screenshot of the whole page")
    parser.add_argument("--wait", type=float, default=25.0)
    parser.add_argument("--zoom-steps", type=int, default=12, help="wheel steps from Lichtblick's 20 m view")
    args = parser.parse_args()

    seen: set[str] = set()

    def console(message: ConsoleMessage) -> None:  # each distinct warning once
        text = f"browser {message.type}: {message.text[:300]}"
        if message.type in ("error", "warning") and text not in seen:
            seen.add(text)
            print(text, file=sys.stderr)

    with sync_playwright() as playwright:
        browser = playwright.chromium.launch(executable_path=args.chromium, args=CHROMIUM_FLAGS)
        page = browser.new_page(viewport=VIEWPORT)
        page.on("console", console)
        page.goto(args.url)
        panel = page.locator(THREE_D).first
        panel.wait_for(timeout=120_000)
        time.sleep(args.wait)
        box = panel.bounding_box()
        if box is None:
            raise RuntimeError("the 3D panel is not shown")
        page.mouse.move(box["x"] + box["width"] / 2, box["y"] + box["height"] / 2)
        for _ in range(args.zoom_steps):
            page.mouse.wheel(0, ZOOM_STEP)
        page.mouse.move(0, 0)  # no hover highlight in the picture
        time.sleep(3)
        # A clip of the page, not an element screenshot: the 3D panel redraws all the time, so Playwright never
        # finds it "stable".
        page.screenshot(path=str(args.out), clip=box, timeout=180_000)
        if args.page_out:
            page.screenshot(path=str(args.page_out), timeout=180_000)
        browser.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
