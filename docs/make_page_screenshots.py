"""Screenshot a run's report.html in headless Chromium: docs/report_page.png, docs/report_closed_loop.png.

Usage: python docs/make_page_screenshots.py --run RUN/robustness --out docs/report_page.png
       python docs/make_page_screenshots.py --run CLOSED_LOOP_RUN --out docs/report_closed_loop.png
       (--run and --out may be given several times, paired in order; --run is a folder holding report.html, or the
       page itself) [--width 1400] [--height 2000] [--scale 0.5]
RUN is an `experiment=quickstart` training run (its suite's page is in robustness/), CLOSED_LOOP_RUN a
`task=closed_loop` run. The page is opened from disk as a reader would, every image scrolled into view (they
load lazily) and waited for, then the top of the page (--width x --height CSS pixels, less if the page is shorter)
is captured and downscaled by --scale into a PNG. Needs chromium and chromedriver (Debian: `apt-get install chromium
chromium-driver`) and selenium (the dev extra). The page itself is not changed; a console error (a script error, an
image that did not load) is printed.
"""

from __future__ import annotations

import argparse
import base64
import shutil
from pathlib import Path

import cv2
import numpy as np

BROWSERS = ("chromium", "chromium-browser", "google-chrome")
TIMEOUT_S = 120


def start_browser(width: int, height: int):
    """Headless Chromium through the system's chromedriver, logging the console."""
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    browser = next((shutil.which(name) for name in BROWSERS if shutil.which(name)), None)
    driver_path = shutil.which("chromedriver")
    if browser is None or driver_path is None:
        raise SystemExit("needs chromium and chromedriver on PATH (Debian: apt-get install chromium chromium-driver)")
    options = webdriver.ChromeOptions()
    for arg in ("--headless=new", "--no-sandbox", "--disable-gpu", "--disable-dev-shm-usage", "--hide-scrollbars",
                f"--window-size={width},{height}"):
        options.add_argument(arg)
    options.binary_location = browser
    options.set_capability("goog:loggingPrefs", {"browser": "ALL"})
    driver = webdriver.Chrome(service=Service(driver_path), options=options)
    driver.set_page_load_timeout(TIMEOUT_S)
    return driver


def page_of(run: Path) -> Path:
    page = run if run.is_file() else run / "report.html"
    if not page.is_file():
        raise SystemExit(f"{run}: no report.html (runs write it unless task.html=false; `python -m lanevil_train "
                         f"task=report task.runs=[{run}]` writes one for a detector or VLM evaluation)")
    return page


def screenshot(driver, page: Path, out: Path, width: int, height: int, scale: float) -> tuple[int, int]:
    """The top width x height CSS pixels of the page (all images loaded), downscaled by `scale`, as a PNG at
    `out`; returns its size (width, height)."""
    from selenium.webdriver.support.ui import WebDriverWait

    driver.get_log("browser")
    driver.get(page.resolve().as_uri())
    for image in driver.find_elements("tag name", "img"):
        driver.execute_script("arguments[0].scrollIntoView({block: 'center'});", image)
    WebDriverWait(driver, TIMEOUT_S).until(
        lambda d: d.execute_script("return Array.prototype.every.call(document.images, i => i.complete);"))
    driver.execute_script("window.scrollTo(0, 0);")
    for entry in driver.get_log("browser"):
        if entry["level"] == "SEVERE":
            print(f"{page}: console: {entry['message']}")
    full = driver.execute_script("return document.documentElement.scrollHeight;")
    shot = driver.execute_cdp_cmd("Page.captureScreenshot", {
        "format": "png", "captureBeyondViewport": True,
        "clip": {"x": 0, "y": 0, "width": width, "height": min(height, full), "scale": 1}})
    image = cv2.imdecode(np.frombuffer(base64.b64decode(shot["data"]), np.uint8), cv2.IMREAD_COLOR)
    if scale != 1:
        image = cv2.resize(image, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA)
    out.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(out), image, [cv2.IMWRITE_PNG_COMPRESSION, 9])
    return image.shape[1], image.shape[0]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--run", type=Path, action="append", required=True,
                        help="a run folder holding report.html (or the page); repeat for several")
    parser.add_argument("--out", type=Path, action="append", required=True, help="the PNG of each --run, in order")
    parser.add_argument("--width", type=int, default=1400, help="page width (CSS pixels)")
    parser.add_argument("--height", type=int, default=2000, help="the most of the page's height captured")
    parser.add_argument("--scale", type=float, default=0.5, help="downscale of the capture")
    args = parser.parse_args()
    if len(args.run) != len(args.out):
        parser.error(f"{len(args.run)} --run but {len(args.out)} --out: one PNG per run")
    pages = [page_of(run) for run in args.run]
    driver = start_browser(args.width, args.height)
    try:
        for page, out in zip(pages, args.out):
            w, h = screenshot(driver, page, out, args.width, args.height, args.scale)
            print(f"{out}: {w}x{h}, {out.stat().st_size / 1024:.0f} KB (from {page})")
    finally:
        driver.quit()


if __name__ == "__main__":
    main()
