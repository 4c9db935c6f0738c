"""report.html in a real browser: headless Chromium opens from disk (file://) the page of a small detector
evaluation, a VLM evaluation and a closed-loop run, each built from constructed records as test_page.py builds
them. Each page: no console error, every image loads, nothing is fetched from anywhere but the disk, a click on a
numeric header sorts its column, a screenshot; the detector page's main table holds main.json's numbers.

Needs chromium, chromedriver (Debian: `apt-get install chromium chromium-driver`) and selenium (the dev extra).
Without them the tests are skipped, unless the environment variable CI is set: there a missing browser fails."""

from __future__ import annotations

import json
import math
import os
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

from lanevil_train.report import page as page_module
from lanevil_train.report.robustness import write_report
from tests.report.test_page import TRACE, _answer, _keyed, _run, _with_images, closed_loop_runs
from tests.report.test_robustness import RECORDS

BROWSERS = ("chromium", "chromium-browser", "google-chrome")
LOCAL = ("file://", "data:", "about:")
WINDOW = (1400, 2000)
TIMEOUT_S = 120  # page loads and waits: generous, the first launch on a loaded machine is slow


def _in_ci() -> bool:
    return os.environ.get("CI", "").strip().lower() not in ("", "0", "false", "no")


def _missing() -> list[str]:
    missing = []
    try:
        import selenium  # noqa: F401
    except ImportError:
        missing.append("selenium (pip install -e '.[dev]')")
    if not any(shutil.which(name) for name in BROWSERS):
        missing.append("chromium")
    if not shutil.which("chromedriver"):
        missing.append("chromedriver")
    return missing


@pytest.fixture(scope="module")
def driver():
    """One headless Chromium for the module, logging console messages and DevTools network events."""
    missing = _missing()
    if missing:
        reason = f"the browser tests need {', '.join(missing)} (apt-get install chromium chromium-driver)"
        if _in_ci():
            pytest.fail(f"CI is set: {reason}")
        pytest.skip(reason)
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    options = webdriver.ChromeOptions()
    for arg in ("--headless=new", "--no-sandbox", "--disable-gpu", "--disable-dev-shm-usage",
                f"--window-size={WINDOW[0]},{WINDOW[1]}"):
        options.add_argument(arg)
    options.binary_location = next(shutil.which(name) for name in BROWSERS if shutil.which(name))
    options.set_capability("goog:loggingPrefs", {"browser": "ALL", "performance": "ALL"})
    browser = webdriver.Chrome(service=Service(shutil.which("chromedriver")), options=options)
    browser.set_page_load_timeout(TIMEOUT_S)
    browser.set_script_timeout(TIMEOUT_S)
    yield browser
    browser.quit()


# ------------------------------------------------------------------------------------------------- the pages
def _detector_page(folder: Path) -> Path:
    """test_page.py's 2-model lane run: main table rows A/B x shadow, reflection, average; Accuracy Perturbed
    40, 50, 45, 50, 90, 70 (test_robustness.py's hand values): unsorted."""
    return _run(folder, _with_images(folder, _keyed(RECORDS)))


def _vlm_page(folder: Path) -> Path:
    """A VLM run over three illusion categories, each hurting the answers by its own amount, with clip frames."""
    answers = [_answer("c1", "q1", 0, 90.0, "Yes."), _answer("c1", "q2", 0, 80.0, "Yes."),
               _answer("c2", "q1", 0, 70.0, "Yes.")]
    hurt = {("fence_shadow", "shadow"): (20.0, 60.0, 70.0),
            ("sunlight_reflection", "reflection"): (85.0, 80.0, 70.0),
            ("tire_marks", "road_damage"): (10.0, 30.0, 40.0)}
    for (illusion, category), scores in hurt.items():
        for (case, qa), score in zip((("c1", "q1"), ("c1", "q2"), ("c2", "q1")), scores):
            answers.append({**_answer(case, qa, 3, score, "No." if score < 50 else "Yes.", illusion),
                            "category": category, "clip_id": f"{case}-{illusion}-s3",
                            "key": f"{case}-{illusion}-s3/{qa}"})
    frames = {}
    for clip in sorted({r["clip_id"] for r in answers}):
        frames[clip] = []
        for i in range(5):
            path = folder / "clips" / f"{clip}-{i}.png"
            path.parent.mkdir(parents=True, exist_ok=True)
            cv2.imwrite(str(path), np.full((36, 64, 3), 30 * i + 20, np.uint8))
            frames[clip].append(str(path))
    out = folder / "run"
    out.mkdir()
    results = out / "per_answer.jsonl"
    results.write_text("".join(json.dumps(r) + "\n" for r in answers))
    (out / "per_answer.suite.json").write_text(json.dumps({"suite": "clip_frames", "frames": frames}))
    write_report(answers, out)
    return page_module.write_vlm_page(out, [results])


def _closed_loop_page(folder: Path) -> Path:
    """A closed loop over 4 cases and 3 categories: ASR traffic_obstruction 100, shadow 25, reflection 50, all 7/12
    (the rows in the taxonomy's order: unsorted)."""
    from lanevil_train.report.closed_loop import write_closed_loop_report

    hits = {"vehicle": {"c1", "c2", "c3", "c4"}, "fence_shadow": {"c1"}, "sunlight_reflection": {"c1", "c2"}}
    categories = {"vehicle": "traffic_obstruction", "fence_shadow": "shadow", "sunlight_reflection": "reflection"}
    write_closed_loop_report(closed_loop_runs(("c1", "c2", "c3", "c4"), categories, hits), lambda record: TRACE,
                             folder, {"cases": 4})
    return page_module.write_closed_loop_page(folder, {"cases": 4})


BUILDERS = {"detector": _detector_page, "vlm": _vlm_page, "closed_loop": _closed_loop_page}
# per page: a table, the data-key of its numeric column to sort by (a suffix when it starts with "/"), and that
# column's values as built
SORTED = {"detector": ("table-main", "/Accuracy/Perturbed", [40.0, 50.0, 45.0, 50.0, 90.0, 70.0]),
          "vlm": ("table-main", "/MiniLM_score/Perturbed", None),  # None: main.json's order, checked unsorted
          "closed_loop": ("table-asr_by_category", "ASR (%)", [100.0, 25.0, 50.0, 100.0 * 7 / 12])}


@pytest.fixture(scope="module")
def pages(tmp_path_factory):
    return {name: build(tmp_path_factory.mktemp(name)) for name, build in BUILDERS.items()}


# ----------------------------------------------------------------------------------------------- the browser
def _open(driver, path: Path) -> dict:
    """Open the page from disk, scroll every image into view (they load lazily) and wait for all to finish;
    the console messages, the requested URLs and the failed requests of this visit."""
    from selenium.webdriver.support.ui import WebDriverWait

    driver.get_log("browser"), driver.get_log("performance")  # what earlier visits left
    driver.get(path.resolve().as_uri())
    for image in driver.find_elements("tag name", "img"):
        driver.execute_script("arguments[0].scrollIntoView({block: 'center'});", image)
    WebDriverWait(driver, TIMEOUT_S).until(
        lambda d: d.execute_script("return Array.prototype.every.call(document.images, i => i.complete);"))
    driver.execute_script("window.scrollTo(0, 0);")
    requests, failed = [], []
    for entry in driver.get_log("performance"):
        message = json.loads(entry["message"])["message"]
        if message["method"] == "Network.requestWillBeSent":
            requests.append(message["params"]["request"]["url"])
        elif message["method"] == "Network.loadingFailed":
            failed.append(message["params"])
    images = driver.execute_script(
        "return Array.prototype.map.call(document.images, i => [i.src, i.naturalWidth, i.naturalHeight]);")
    return {"console": driver.get_log("browser"), "requests": requests, "failed": failed, "images": images}


def _column(driver, table_id: str, suffix: str) -> tuple[int, list[float]]:
    """The index of the table's column whose first-row cell's data-key is `suffix` (or ends with it, for a
    suffix from "/"), and its data-values top to bottom as the page shows them now."""
    return driver.execute_script("""
        var table = document.getElementById(arguments[0]);
        var first = table.tBodies[0].rows[0].cells, col = -1;
        for (var i = 0; i < first.length; i++) {
          var key = first[i].getAttribute('data-key');
          var s = arguments[1];
          if (key !== null && (key === s || (s[0] === '/' && key.endsWith(s)))) { col = i; break; }
        }
        return [col, Array.prototype.map.call(table.tBodies[0].rows,
                                              r => Number(r.cells[col].getAttribute('data-value')))];
    """, table_id, suffix)


@pytest.mark.parametrize("name", list(BUILDERS))
def test_page_loads_cleanly_from_disk(driver, pages, name):
    """No console message of level SEVERE (a script error, an image that failed), no failed request, every
    image decoded, and every URL requested local: the page itself, its images, nothing from a host."""
    visit = _open(driver, pages[name])
    assert [e for e in visit["console"] if e["level"] == "SEVERE"] == []
    assert visit["failed"] == []
    assert visit["images"], "the page shows images"
    broken = [src for src, width, height in visit["images"] if not (width > 0 and height > 0)]
    assert broken == []
    assert [url for url in visit["requests"] if not url.startswith(LOCAL)] == []
    # the network log saw this visit: the page and each of its images were requested
    assert pages[name].resolve().as_uri() in visit["requests"]
    assert {src for src, _, _ in visit["images"]} <= set(visit["requests"])


def test_detector_main_table_equals_main_json(driver, pages):
    """Every keyed cell of table-main as the browser parsed it: main.json's number for that model and column."""
    path = pages["detector"]
    _open(driver, path)
    main = {row["model"]: row for row in json.loads((path.parent / "main.json").read_text())}
    cells = driver.execute_script("""
        return Array.prototype.flatMap.call(document.querySelectorAll('#table-main tbody tr'), function(row) {
          var model = row.cells[0].textContent.trim();
          return Array.prototype.filter.call(row.cells, c => c.hasAttribute('data-key')).map(
            c => [model, c.getAttribute('data-key'), c.getAttribute('data-value')]);
        });""")
    assert len(cells) == 2 * 3 * 2 * 3  # models x (2 categories + average) x (Accuracy, F1) x Perturbed/Original/Gap
    for model, key, value in cells:
        want, got = main[model][key], float(value)
        assert (math.isnan(want) and math.isnan(got)) or got == want, (model, key, value)


@pytest.mark.parametrize("name", list(BUILDERS))
def test_header_click_sorts_column(driver, pages, name):
    """A click on a numeric column's header orders the rows by it ascending, a second click descending."""
    table_id, suffix, built = SORTED[name]
    path = pages[name]
    _open(driver, path)
    col, before = _column(driver, table_id, suffix)
    assert col >= 0
    if built is None:  # main.json's rows, in the order the page was built from
        built = [row[key] for row in json.loads((path.parent / "main.json").read_text())
                 for key in row if key.endswith(suffix)]
    assert before == built
    assert before != sorted(before) and before != sorted(before, reverse=True)  # the click has something to do
    header = driver.find_element("css selector", f'#{table_id} thead th[data-col="{col}"]')
    header.click()
    ascending = _column(driver, table_id, suffix)[1]
    assert ascending == sorted(before) and ascending != before
    assert header.get_attribute("aria-sort") == "ascending"
    header.click()
    descending = _column(driver, table_id, suffix)[1]
    assert descending == sorted(before, reverse=True)
    assert header.get_attribute("aria-sort") == "descending"


@pytest.mark.parametrize("name", list(BUILDERS))
def test_screenshot(driver, pages, tmp_path, name):
    _open(driver, pages[name])
    shot = tmp_path / f"{name}.png"
    assert driver.save_screenshot(str(shot))
    assert shot.stat().st_size > 20_000
    image = cv2.imread(str(shot))
    viewport = driver.execute_script("return [innerHeight * devicePixelRatio, innerWidth * devicePixelRatio];")
    assert image is not None and list(image.shape[:2]) == viewport
    assert image.std() > 5  # not a blank page
