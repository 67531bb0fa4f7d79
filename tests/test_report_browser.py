"""The HTML report in a real browser: headless Chromium through selenium and chromedriver.

A page fails when the browser console has any SEVERE entry (a JavaScript error, a
resource that failed to load, a Content-Security-Policy violation), when an image is
not loaded or has no width, or when it has no table; and when the summary it opens with (the ranked
table, the figure, the one-sentence conclusion) is not there.  The pages: two study reports,
a design report (the indoor robot's infeasible paper design) and a feasibility
report (a 2-D map of the small linear model).  Negative controls run the same
checking functions on pages with a broken image, a JavaScript error, no table, and no summary or a
summary without its figure or its conclusion.

Without Chromium or chromedriver the tests are skipped, unless the environment sets
``CFDESIGN_REQUIRE_BROWSER=1`` (CI does, after installing them), which makes them fail.
"""
from __future__ import annotations

import base64
import os
import shutil
import tempfile
from pathlib import Path

import pytest

from studies import api

REQUIRE = os.environ.get("CFDESIGN_REQUIRE_BROWSER") == "1"
PNG_1x1 = base64.b64decode(
    "iVBORw0KGgoAAAANSUhEUgAAAAEAAAABCAYAAAAfFcSJAAAADUlEQVR42mP8z8BQDwAEhQGAhKmMIQAAAABJRU5ErkJggg==")
FLAGS = ("--headless=new", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
         "--disable-background-networking", "--disable-component-update", "--disable-sync",
         "--window-size=1280,1024")


def _first(*candidates) -> str | None:
    for c in candidates:
        if c and Path(c).is_file() and os.access(c, os.X_OK):
            return c
    return None


def _unavailable(reason: str):
    if REQUIRE:
        pytest.fail(f"CFDESIGN_REQUIRE_BROWSER=1 but {reason}")
    pytest.skip(reason)


@pytest.fixture(scope="module")
def browser():
    try:
        from selenium import webdriver
        from selenium.webdriver.chrome.service import Service
    except ImportError:
        _unavailable("selenium is not installed")
    chromium = _first("/usr/bin/chromium", shutil.which("chromium"), shutil.which("chromium-browser"),
                      shutil.which("google-chrome"))
    driver_path = _first("/usr/bin/chromedriver", shutil.which("chromedriver"))
    if chromium is None or driver_path is None:
        _unavailable(f"chromium ({chromium}) or chromedriver ({driver_path}) not found")
    profile = tempfile.mkdtemp(prefix="cfdesign-chromium-")
    options = webdriver.ChromeOptions()
    options.binary_location = chromium
    for flag in FLAGS:
        options.add_argument(flag)
    options.add_argument(f"--user-data-dir={profile}")
    options.set_capability("goog:loggingPrefs", {"browser": "ALL"})
    try:
        driver = webdriver.Chrome(service=Service(driver_path), options=options)
    except Exception as exc:  # a broken install: same policy as a missing one
        shutil.rmtree(profile, ignore_errors=True)
        _unavailable(f"chromium did not start: {type(exc).__name__}: {exc}".splitlines()[0])
    driver.set_page_load_timeout(60)
    try:
        yield driver
    finally:
        driver.quit()
        shutil.rmtree(profile, ignore_errors=True)


def page_problems(driver, path: Path) -> list[str]:
    """Everything wrong with the page at ``path`` once loaded; an empty list means it renders cleanly."""
    from selenium.webdriver.support.ui import WebDriverWait

    driver.get_log("browser")  # drop entries of earlier pages
    driver.get(path.resolve().as_uri())
    WebDriverWait(driver, 30).until(lambda d: d.execute_script("return document.readyState") == "complete")
    # let late console entries (image errors, uncaught exceptions) arrive
    driver.execute_async_script("const done = arguments[arguments.length - 1]; setTimeout(done, 200);")
    problems = []
    images = driver.execute_script(
        "return Array.from(document.images, i => [i.getAttribute('data-file') || i.getAttribute('src'), "
        "i.complete, i.naturalWidth]);")
    for name, complete, width in images:
        if not complete or not width:
            problems.append(f"image {str(name)[:60]} not rendered (complete={complete}, naturalWidth={width})")
    if driver.execute_script("return document.getElementsByTagName('table').length;") == 0:
        problems.append("no <table>")
    for entry in driver.get_log("browser"):
        if entry.get("level") == "SEVERE":
            problems.append(f"console: {entry.get('message')}")
    return problems


LINEAR = str(Path(__file__).resolve().parents[1] / "examples" / "linear_network_model.py")


@pytest.fixture(scope="module")
def reports(tmp_path_factory):
    enc = tmp_path_factory.mktemp("enc")
    api.study("encrypted-switching", out=enc, runs=2, particles=20)
    con = tmp_path_factory.mktemp("con")
    api.study("consensus-robot", out=con, runs=2)
    return [enc / "report.html", con / "report.html"]


@pytest.fixture(scope="module")
def design_and_map(tmp_path_factory):
    design = tmp_path_factory.mktemp("design")
    api.design("indoor-robot", mode="paper", seed=1, out=design)  # infeasible, the report says why
    fmap = tmp_path_factory.mktemp("map")
    api.feasibility(LINEAR, ["sigma=0:12:4", "beta=0:12:4"], mode="paper", u_scale=0, v_scale=0, out=fmap)
    return [design / "report.html", fmap / "report.html"]


def _renders_cleanly(driver, path: Path, min_images: int, min_tables: int) -> None:
    assert page_problems(driver, path) == [], path
    n = driver.execute_script("return document.images.length;")
    assert n == len(list(path.parent.glob("*.png"))) and n >= min_images, path
    assert driver.execute_script("return document.getElementsByTagName('table').length;") >= min_tables, path
    assert driver.execute_script("return document.querySelectorAll('script').length;") == 0
    # every in-page link of the contents leads to a heading of the page
    missing = driver.execute_script(
        "return Array.from(document.querySelectorAll('a[href^=\"#\"]'), a => decodeURIComponent("
        "a.getAttribute('href').slice(1))).filter(id => !document.getElementById(id));")
    assert missing == [], path


# What the summary of each kind of report holds: its figure and the first words of its one-sentence conclusion.
SUMMARY = {"study": ("fig_tradeoff.png", "Which to pick"), "design": ("fig_trace_bound.png", "Use this schedule?"),
           "feasibility": ("feasibility.png", "Where the design is")}


def summary_problems(driver, path: Path, kind: str) -> list[str]:
    """What the page's summary lacks: the section right after the title, before the contents, with the ranked
    table, the figure (rendered) and the one-sentence conclusion."""
    driver.get(path.resolve().as_uri())
    found = driver.execute_script(
        "const h = document.getElementById('summary'); if (!h) return null;"
        "const els = []; for (let e = h.nextElementSibling; e && e.tagName !== 'H2'; e = e.nextElementSibling)"
        " els.push(e);"
        "const next = els.length ? els[els.length - 1].nextElementSibling : h.nextElementSibling;"
        "const h2 = Array.from(document.querySelectorAll('h2'));"
        "return {first: h2.length > 0 && h2[0] === h, next: next ? next.id : null,"
        " heads: els.flatMap(e => Array.from(e.querySelectorAll('th'), t => t.innerText.trim())),"
        " rows: els.reduce((n, e) => n + e.querySelectorAll('tbody tr').length, 0),"
        " images: els.flatMap(e => Array.from(e.querySelectorAll('img'),"
        "   i => [i.getAttribute('data-file'), i.complete && i.naturalWidth > 0])),"
        " picks: els.filter(e => e.tagName === 'P' && e.firstElementChild && e.firstElementChild.tagName === 'STRONG')"
        "   .map(e => e.innerText)};")
    if found is None:
        return ["no summary section"]
    figure, lead = SUMMARY[kind]
    problems = []
    if not found["first"] or found["next"] != "contents":
        problems.append(f"the summary is not the first section before the contents ({found['next']})")
    if "rank" not in found["heads"] or not found["rows"]:
        problems.append(f"no ranked table in the summary ({found['heads'][:4]})")
    if [figure, True] not in found["images"]:
        problems.append(f"no rendered {figure} in the summary ({found['images']})")
    picks = [p for p in found["picks"] if p.startswith(lead)]
    if not picks or any("\n" in p.strip() or not p.strip().endswith(".") for p in picks):
        problems.append(f"no one-sentence conclusion starting {lead!r} ({found['picks']})")
    return problems


def test_reports_render_cleanly(browser, reports):
    for path in reports:
        _renders_cleanly(browser, path, 4, 3)
        assert summary_problems(browser, path, "study") == [], path


def test_design_and_feasibility_reports_render_cleanly(browser, design_and_map):
    design, fmap = design_and_map
    _renders_cleanly(browser, design, 2, 3)  # the bound, the margins; binding, per node, parameters
    assert "Infeasible." in browser.execute_script("return document.body.innerText;")
    assert summary_problems(browser, design, "design") == []
    _renders_cleanly(browser, fmap, 1, 1)  # the heat map; the grid
    assert "grid points are certified." in browser.execute_script("return document.body.innerText;")
    assert summary_problems(browser, fmap, "feasibility") == []


def test_the_summary_check_sees_what_is_missing(browser, reports, tmp_path):
    """Negative controls: the same report without its summary, its figure or its pick sentence."""
    import re

    page = reports[0].read_text()
    head, rest = page.split('<h2 id="summary">', 1)
    summary, tail = rest.split('<h2 id="contents">', 1)
    cases = {"none": head + '<h2 id="contents">' + tail,
             "figure": page.replace(re.search(r"<figure>.*?</figure>", summary, flags=re.S).group(0), ""),
             "pick": page.replace("<strong>Which to pick", "<strong>Perhaps")}
    for what, html_text in cases.items():
        path = tmp_path / f"{what}.html"
        path.write_text(html_text)
        problems = summary_problems(browser, path, "study")
        assert problems and (what != "none" or problems == ["no summary section"]), (what, problems)
        assert what == "none" or any(("fig_tradeoff" if what == "figure" else "conclusion") in p
                                     for p in problems), (what, problems)


def _page(tmp_path: Path, name: str, body: str) -> Path:
    path = tmp_path / name
    path.write_text(f"<!DOCTYPE html><html><head><meta charset='utf-8'><title>{name}</title></head>"
                    f"<body>{body}</body></html>")
    return path


def test_checker_accepts_a_clean_page(browser, tmp_path):
    src = "data:image/png;base64," + base64.b64encode(PNG_1x1).decode()
    path = _page(tmp_path, "clean.html", f"<table><tr><td>1</td></tr></table><img src='{src}' alt='dot'>")
    assert page_problems(browser, path) == []


def test_checker_detects_a_broken_image(browser, tmp_path):
    path = _page(tmp_path, "broken.html", "<table><tr><td>1</td></tr></table><img src='missing.png' alt='x'>")
    problems = page_problems(browser, path)
    assert any(p.startswith("image missing.png not rendered") for p in problems), problems
    assert any(p.startswith("console:") and "missing.png" in p for p in problems), problems


def test_checker_detects_a_javascript_error(browser, tmp_path):
    path = _page(tmp_path, "jserror.html",
                 "<table><tr><td>1</td></tr></table><script>throw new Error('deliberate failure');</script>")
    problems = page_problems(browser, path)
    assert any(p.startswith("console:") and "deliberate failure" in p for p in problems), problems


def test_checker_detects_a_page_without_table(browser, tmp_path):
    assert page_problems(browser, _page(tmp_path, "notable.html", "<p>no table here</p>")) == ["no <table>"]


def test_checker_detects_a_blocked_external_resource(browser, tmp_path):
    # the report's Content-Security-Policy: anything not inline is refused and logged
    csp = "<meta http-equiv='Content-Security-Policy' content=\"default-src 'none'; img-src data:\">"
    path = tmp_path / "csp.html"
    path.write_text(f"<!DOCTYPE html><html><head>{csp}</head><body><table><tr><td>1</td></tr></table>"
                    "<img src='https://example.invalid/x.png' alt='x'></body></html>")
    problems = page_problems(browser, path)
    assert any(p.startswith("image") for p in problems), problems
    assert any(p.startswith("console:") for p in problems), problems
