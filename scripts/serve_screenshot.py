"""Screenshot of `usdrelight serve` for the README: docs/manual/images/serve_screenshot.png.

Opens the app on the motorcycle stage (after `make demo`) in headless Chromium (Debian's /usr/bin/chromium via
Playwright), with a night set-up made through the app's own methods: the fitted lighting dimmed to 15%, a warm
spot light from the left, a faint blue dome, the split view at 30% (original photo left of the line). Nothing is
saved to the stage.

    python scripts/serve_screenshot.py [--stage out/motorcycle/scene.usda] [-o docs/manual/images/serve_screenshot.png]
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from playwright.sync_api import sync_playwright  # noqa: E402

from usdrelight.serve.app import ServeApp  # noqa: E402
from usdrelight.serve.state import quat_pointing_along  # noqa: E402


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--stage", type=Path, default=ROOT / "out" / "motorcycle" / "scene.usda")
    ap.add_argument("-o", "--output", type=Path, default=ROOT / "docs" / "manual" / "images" / "serve_screenshot.png")
    args = ap.parse_args(argv)
    with ServeApp(args.stage, port=0, max_side=512) as app:
        dome = app.add_light("dome")
        app.set_light(dome, color=(0.5, 0.6, 1.0), intensity=0.03)
        spot = app.add_light("spot")
        app.set_light(spot, position=(-1.2, 0.5, -1.0), rotation=quat_pointing_along([0.8, -0.2, -0.6]),
                      color=(1.0, 0.6, 0.3), intensity=8.0, cone_angle=40.0, softness=0.4)
        app.set_fitted(dimmer=0.1)
        app.set_display(split=0.3)
        app.wait_shown(app.update(), timeout=120)
        with sync_playwright() as pw:
            browser = pw.chromium.launch(executable_path="/usr/bin/chromium", args=["--no-sandbox"])
            page = browser.new_page(viewport={"width": 1600, "height": 900})
            page.goto(app.url)
            page.get_by_role("button", name="Add light").wait_for(timeout=60000)
            page.locator("img[src^='blob:']").first.wait_for(timeout=60000)
            page.add_style_tag(content=".mantine-Notifications-root { display: none !important; }")
            time.sleep(8)  # the photo mesh arrives and software WebGL draws it
            args.output.parent.mkdir(parents=True, exist_ok=True)
            page.screenshot(path=str(args.output))
            browser.close()
    print(f"wrote {args.output}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
