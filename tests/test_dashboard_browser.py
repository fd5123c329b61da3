"""The dashboard in a real headless Chromium (Debian's `chromium`, driven by Playwright's Python package;
no browser download) against the daemon and `hwsim serve` as separate processes."""

from __future__ import annotations

import math
import shutil
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
from live_cell import Cell, Daemon, serve_cell, start_daemon, wait
from playwright.sync_api import Browser, Page, sync_playwright

pytestmark = pytest.mark.slow
CHROMIUM = shutil.which("chromium") or "/usr/bin/chromium"
ARTIFACTS = Path(__file__).resolve().parent.parent / "out" / "test-artifacts"

cell = pytest.fixture(scope="module", name="cell")(serve_cell)


@pytest.fixture(scope="module")
def daemon(cell: Cell, tmp_path_factory: pytest.TempPathFactory) -> Iterator[Daemon]:
    d = start_daemon(cell, tmp_path_factory.mktemp("daemon"))
    yield d
    d.stop()


@pytest.fixture(scope="module")
def browser() -> Iterator[Browser]:
    with sync_playwright() as p:
        b = p.chromium.launch(executable_path=CHROMIUM, args=["--no-sandbox"])
        yield b
        b.close()


@pytest.fixture(scope="module")
def page(browser: Browser, daemon: Daemon) -> Iterator[Page]:
    pg = browser.new_page(viewport={"width": 1280, "height": 720})
    pg.goto(daemon.base + "/")
    yield pg
    pg.close()


def _video_signature(page: Page) -> float:
    """Sum of a downscaled copy of the current video frame, read back through a canvas."""
    return float(
        page.evaluate(
            """() => { const img = document.getElementById('video');
            const c = document.createElement('canvas'); c.width = 64; c.height = 48;
            const g = c.getContext('2d'); g.drawImage(img, 0, 0, 64, 48);
            return g.getImageData(0, 0, 64, 48).data.reduce((a, b) => a + b, 0); }"""
        )
    )


def test_page_loads_and_shows_the_live_state(page: Page) -> None:
    assert page.title() == "clothd"
    page.wait_for_function("document.getElementById('state').textContent === 'tracking'", timeout=20000)
    assert "ok" in (page.get_attribute("#link", "class") or "")
    assert page.is_visible("#estop")  # always visible at 1280 x 720
    box = page.locator("#estop").bounding_box()
    assert box is not None and box["y"] + box["height"] <= 720 and box["x"] + box["width"] <= 1280


def test_video_and_plots_update(page: Page) -> None:
    page.wait_for_function("document.getElementById('video').naturalWidth > 0", timeout=20000)
    first = _video_signature(page)
    samples = page.evaluate("samples.features.length")
    wait(lambda: _video_signature(page) != first, 10, "a new video frame")
    wait(lambda: page.evaluate("samples.features.length") > samples, 10, "new plot samples")
    drawn = page.evaluate(
        "document.getElementById('plot-features').getContext('2d').getImageData(0, 0, 400, 90)"
        ".data.some((v, i) => i % 4 === 3 && v > 0)"
    )
    assert drawn


def test_a_setpoint_set_in_the_page_reaches_the_daemon(page: Page, daemon: Daemon) -> None:
    page.select_option("#mode-select", "move")
    page.fill("#in-x", "0.03")
    page.fill("#in-y", "-0.02")
    page.fill("#in-t", "10")
    page.click("#apply")
    wait(lambda: daemon.status()["mode"] == "move", 5, "mode move")
    sp = daemon.status()["setpoint"]
    assert math.isclose(sp["x_m"], 0.03) and math.isclose(sp["y_m"], -0.02)
    assert math.isclose(sp["theta_rad"], math.radians(10), rel_tol=1e-6)


def test_the_estop_button_stops_the_modules(page: Page, daemon: Daemon, cell: Cell) -> None:
    page.select_option("#mode-select", "move")
    page.fill("#in-x", "-0.05")
    page.fill("#in-y", "0.03")
    page.fill("#in-t", "-15")
    page.click("#apply")
    wait(lambda: max(map(abs, cell.truth()["module_speed_m_s"])) > 0.01, 10, "modules running")
    page.click("#estop")
    wait(lambda: cell.truth()["estopped"], 5, "the controller's e-stop")
    assert not any(cell.truth()["module_speed_m_s"])
    page.wait_for_function("document.getElementById('estop').classList.contains('latched')", timeout=5000)
    ARTIFACTS.mkdir(parents=True, exist_ok=True)
    page.screenshot(path=str(ARTIFACTS / "dashboard.png"))
    assert (ARTIFACTS / "dashboard.png").stat().st_size > 10_000
    page.click("#estop-clear")
    wait(lambda: not cell.truth()["estopped"], 5, "e-stop cleared")
    time.sleep(0.1)
