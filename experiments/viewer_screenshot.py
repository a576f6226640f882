"""A screenshot of ``ne-jax view`` for the docs: the viewer started on a trained run, the page opened
in headless Chromium (selenium), a full-resolution frame awaited, points selected with the page's
button, and the window saved.

    python -m experiments.viewer_screenshot --run RUN [--out docs/images/viewer.png]

Needs the ``view`` and ``test`` extras (viser, selenium) and Debian's ``chromium`` + ``chromium-driver``.
"""

from __future__ import annotations

import argparse
import shutil
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def _wait(cond, what: str, timeout: float = 300.0) -> None:
    t0 = time.time()
    while time.time() - t0 < timeout:
        if cond():
            return
        time.sleep(0.2)
    raise TimeoutError(f"viewer_screenshot: timed out after {timeout:.0f} s waiting for {what}")


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--run", required=True, help="a trained run directory")
    parser.add_argument("--out", default=str(REPO / "docs" / "images" / "viewer.png"))
    parser.add_argument("--size", default="1200,760", help="browser window WIDTH,HEIGHT")
    parser.add_argument("--max-side", type=int, default=256, help="the viewer's full-resolution frame size")
    args = parser.parse_args(argv)
    chromium, driver_bin = shutil.which("chromium") or shutil.which("chromium-browser"), shutil.which("chromedriver")
    if chromium is None or driver_bin is None:
        print("viewer_screenshot: expected chromium and chromedriver on PATH (Debian: apt-get install chromium "
              "chromium-driver), found none", file=sys.stderr)
        return 2
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service
    from selenium.webdriver.common.by import By

    from ne_jax.atomic import atomic_write_bytes
    from ne_jax.view.viewer import Viewer

    opts = webdriver.ChromeOptions()
    opts.binary_location = chromium
    for a in ("--headless=new", "--no-sandbox", "--disable-dev-shm-usage", f"--window-size={args.size}",
              "--use-angle=swiftshader", "--enable-unsafe-swiftshader", "--ignore-gpu-blocklist"):
        opts.add_argument(a)
    viewer = Viewer(args.run, port=0, max_side=args.max_side)
    driver = webdriver.Chrome(service=Service(driver_bin), options=opts)
    try:
        driver.get(viewer.url)
        _wait(lambda: viewer.frames >= 1 and "full" in viewer._gui_time.content, "a full-resolution frame")
        driver.find_element(By.XPATH, "//button[normalize-space()='Select in region']").click()
        _wait(lambda: viewer.selection.size > 0, "a selection")
        time.sleep(3.0)  # let the page draw the selection and the last frame
        png = driver.get_screenshot_as_png()
    finally:
        driver.quit()
        viewer.stop()
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    atomic_write_bytes(Path(args.out), png)
    print(f"wrote {args.out} ({len(png)} bytes)")
    return 0


if __name__ == "__main__":
    import ne_jax

    ne_jax.setup(huge_pages=True)  # as `ne-jax` does: a host device per core, huge pages (restarts)
    sys.exit(main())
