"""The dashboard in a real headless Chromium (Debian's `chromium`, driven by Playwright's Python package;
no browser download) against the daemon in sim mode (`clothd run --sim`, hwsim serve as its child)."""

from __future__ import annotations

import contextlib
import math
import shutil
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import pytest
from live_cell import wait
from playwright.sync_api import Browser, Page, sync_playwright

from clothd.tools.bench_loop import DaemonProcess, free_port
from clothd.tools.procfs import stop_group
from hwsim.firmware import Firmware, TableDrives
from hwsim.scenario import TableSpec
from hwsim.table import Table

pytestmark = pytest.mark.slow
CHROMIUM = shutil.which("chromium") or "/usr/bin/chromium"
ARTIFACTS = Path(__file__).resolve().parent.parent / "out" / "test-artifacts"
READY = ("tracking", "connected")  # moves need the cloth tracked and the link up (docs/state-machine.md)


class Sim:
    """`clothd run --sim`: the daemon's status and hwsim's truth."""

    def __init__(self, d: DaemonProcess) -> None:
        self.base, self.truth_url = d.base, d.truth_url

    def status(self) -> dict[str, Any]:
        return dict(httpx.get(f"{self.base}/api/v1/status", timeout=5).json())

    def truth(self) -> dict[str, Any]:
        return dict(httpx.get(self.truth_url, timeout=5).json())


@pytest.fixture(scope="module")
def sim() -> Iterator[Sim]:
    d = DaemonProcess(None, free_port())
    try:
        d.wait_ready()
        s = Sim(d)
        wait(lambda: (s.status()["state"], s.status()["link"]["state"]) == READY, 60, "tracking, link up")
        yield s
    finally:
        d.stop()


@pytest.fixture(scope="module")
def browser() -> Iterator[Browser]:
    with sync_playwright() as p:
        b = p.chromium.launch(executable_path=CHROMIUM, args=["--no-sandbox"])
        yield b
        b.close()


@pytest.fixture(scope="module")
def page(browser: Browser, sim: Sim) -> Iterator[Page]:
    pg = browser.new_page(viewport={"width": 1280, "height": 720})
    pg.goto(sim.base + "/")
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
    # The link comes up on its own schedule (the firmware's pty), not with the tracking: wait for it too.
    page.wait_for_function("document.getElementById('link').classList.contains('ok')", timeout=20000)
    # The cloth lies flat on the live cell, and the page says so from the status's flatness block.
    page.wait_for_function(
        "document.getElementById('flatness').textContent.startsWith('flat ·')", timeout=10000
    )
    assert "0 ridges" in (page.text_content("#flatness") or "")
    # Beside it, what the flatness rests on (the status's flatness.basis), in words.
    page.wait_for_function(
        "document.getElementById('basis').textContent.startsWith('· basis: ')", timeout=10000
    )
    assert (page.text_content("#basis") or "").removeprefix("· basis: ") in ("measured", "since start")
    # Both cameras of the default cell with the rate their frames arrive at, the second with its skew to
    # the first measured.
    page.wait_for_function(
        "/^cam0 streaming \\d+\\.\\d fps \\| cam1 streaming \\d+\\.\\d fps · skew [+-]\\d+\\.\\d ms/"
        ".test(document.getElementById('cameras').textContent)",
        timeout=20000,
    )
    # The tick's figures: the loop's missed deadlines and the ticks the compute answered late.
    assert (page.text_content("#missed") or "").isdigit() and (page.text_content("#late") or "").isdigit()
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


def _move_through_the_form(page: Page, sim: Sim, x_m: float, y_m: float, theta_deg: float) -> None:
    """Set a move in the page's form until the daemon runs it. A move is refused, or halted at once, while
    the cloth is not tracked or the link not up (docs/state-machine.md); on a loaded machine a stalled
    tick can do that, and an operator would press Apply again. Three tries, each reason kept."""
    reasons: list[str] = []
    for _ in range(3):
        wait(lambda: (sim.status()["state"], sim.status()["link"]["state"]) == READY, 30, "tracking, link up")
        page.select_option("#mode-select", "move")
        page.fill("#in-x", str(x_m))
        page.fill("#in-y", str(y_m))
        page.fill("#in-t", str(theta_deg))
        page.click("#apply")
        try:
            wait(lambda: sim.status()["mode"] == "move", 5, "mode move")
            return
        except AssertionError:
            status = sim.status()
            reasons.append(f"{page.text_content('#message')!r}, halt_reason {status['halt_reason']!r}")
    raise AssertionError(f"the page's move never ran: {reasons}")


def test_a_setpoint_set_in_the_page_reaches_the_daemon(page: Page, sim: Sim) -> None:
    _move_through_the_form(page, sim, 0.03, -0.02, 10)
    assert page.text_content("#in-t-rad") == "θ = 0.1745 rad"  # the angle as the API takes it
    sp = sim.status()["setpoint"]
    assert math.isclose(sp["x_m"], 0.03) and math.isclose(sp["y_m"], -0.02)
    assert math.isclose(sp["theta_rad"], math.radians(10), rel_tol=1e-6)


def test_the_estop_button_stops_the_modules(page: Page, sim: Sim) -> None:
    _move_through_the_form(page, sim, -0.05, 0.03, -15)
    wait(lambda: max(map(abs, sim.truth()["module_speed_m_s"])) > 0.01, 10, "modules running")
    page.click("#estop")
    try:
        wait(lambda: sim.truth()["estopped"], 5, "the controller's e-stop")
        assert not any(sim.truth()["module_speed_m_s"])
        page.wait_for_function("document.getElementById('estop').classList.contains('latched')", timeout=5000)
        page.wait_for_selector("#banner-estop:visible", timeout=5000)
        assert "Emergency stop latched" in (page.text_content("#banner-estop") or "")
        # The link holds every command back: its pill says so, and is not green.
        assert (page.text_content("#link") or "").endswith(" · e-stop")
        assert page.get_attribute("#link", "class") == "pill bad"
        assert page.is_hidden("#banner-halt")  # an e-stop is no halt
        ARTIFACTS.mkdir(parents=True, exist_ok=True)
        page.screenshot(path=str(ARTIFACTS / "dashboard_estop.png"))
        assert (ARTIFACTS / "dashboard_estop.png").stat().st_size > 10_000
    finally:  # the tests after this one need the e-stop clear
        page.click("#estop-clear")
        wait(lambda: not sim.truth()["estopped"], 5, "e-stop cleared")
    page.wait_for_selector("#banner-estop", state="hidden", timeout=5000)
    page.wait_for_function("!document.getElementById('link').textContent.includes('e-stop')", timeout=5000)
    time.sleep(0.1)


def test_a_move_halted_by_a_fault_says_why_and_when(page: Page, sim: Sim) -> None:
    hwsim = sim.truth_url.removesuffix("/truth")
    _move_through_the_form(page, sim, 0.04, 0.02, 5)
    httpx.post(f"{hwsim}/unplug?seconds=1", timeout=5).raise_for_status()
    wait(lambda: sim.status()["halt_reason"] is not None, 10, "the move halted")
    status = sim.status()
    page.wait_for_selector("#banner-halt:visible", timeout=5000)
    at = time.strftime("%H:%M:%S", time.localtime(status["halt_t_unix_s"]))
    said = f"Stopped by itself at {at}: {status['halt_reason']}. The modules are idle until a new setpoint."
    assert page.text_content("#banner-halt") == said
    assert page.text_content("#mode") == "mode idle" and page.text_content("#sp-x") == "–"
    # A fault the controller reports is listed, newest first, with its module and code.
    wait(lambda: sim.status()["link"]["state"] == "connected", 10, "the link back")
    httpx.post(f"{hwsim}/fault?code=2&module=7&text=stalled", timeout=5).raise_for_status()
    newest = "document.querySelector('#faults li').textContent"
    page.wait_for_function(f"{newest}.endsWith('module 7 · STALL: stalled')", timeout=10000)
    httpx.post(f"{hwsim}/fault?code=3&module=4", timeout=5).raise_for_status()  # a fault without text
    page.wait_for_function(f"{newest}.endsWith('module 4 · OVERTEMP')", timeout=10000)
    ARTIFACTS.mkdir(parents=True, exist_ok=True)
    page.screenshot(path=str(ARTIFACTS / "dashboard_halt.png"))
    # A new setpoint clears the halt, and its banner.
    _move_through_the_form(page, sim, 0.0, 0.0, 0)
    page.wait_for_selector("#banner-halt", state="hidden", timeout=5000)
    httpx.put(f"{sim.base}/api/v1/setpoint", json={"mode": "idle"}, timeout=5).raise_for_status()


def test_the_truth_overlay_draws_hwsims_cloth(page: Page) -> None:
    page.wait_for_selector("#truth-toggle:not([hidden])", timeout=10000)
    page.check("#show-truth")
    yellow = (
        "() => { const c = document.getElementById('truth'); if (!c.width) return 0;"
        " const d = c.getContext('2d').getImageData(0, 0, c.width, c.height).data; let n = 0;"
        " for (let i = 0; i < d.length; i += 4)"
        " if (d[i] > 200 && d[i + 1] > 200 && d[i + 2] < 100) n++; return n; }"
    )
    wait(lambda: page.evaluate(yellow) > 500, 5, "truth nodes drawn")
    page.uncheck("#show-truth")
    wait(lambda: page.evaluate(yellow) == 0, 5, "overlay cleared")


def test_the_page_follows_a_dropped_camera_and_its_return(page: Page, sim: Sim) -> None:
    hwsim = sim.truth_url.removesuffix("/truth")
    httpx.post(f"{hwsim}/camera/drop?seconds=1.5", timeout=5).raise_for_status()
    page.wait_for_function("document.getElementById('state').textContent === 'camera_lost'", timeout=10000)
    page.wait_for_function("document.getElementById('state').textContent === 'tracking'", timeout=30000)
    first = _video_signature(page)
    wait(lambda: _video_signature(page) != first, 10, "the video moving again")
    page.wait_for_function("document.getElementById('stream').textContent === 'stream live'", timeout=5000)


# Every change to the link's pill, with the faults list and whether the starting banner shows, from the
# page's first status on (an observer's records come after the status has been drawn whole).
WATCH_THE_LINK = """document.addEventListener("DOMContentLoaded", () => {
  window.linkSeen = [];
  const link = document.getElementById("link"), faults = document.getElementById("faults");
  const banner = document.getElementById("banner-starting");
  const note = () => window.linkSeen.push(
    [link.textContent, link.className, faults.textContent, !banner.hidden]);
  new MutationObserver(note).observe(link, { childList: true, attributes: true });
});"""


@contextlib.contextmanager
def _daemon_before_its_controller(tmp_path: Path) -> Iterator[tuple[str, Path]]:
    """`clothd run` on a cell whose controller is not plugged in yet (its port is absent; no camera):
    the daemon's URL and the port where the test plugs hwsim's firmware in."""
    port, api_port = tmp_path / "ttyCELL", free_port()
    cfg = tmp_path / "clothd.yaml"
    cfg.write_text(
        f"camera:\n  source: http://127.0.0.1:{free_port()}/absent.mjpg\n"
        f"stepper:\n  port: {port}\nopcua:\n  enabled: false\n"
    )
    cmd = [sys.executable, "-m", "clothd.cli", "run", "--config", str(cfg), "--port", str(api_port)]
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
    base = f"http://127.0.0.1:{api_port}"
    try:
        wait(lambda: _answers(f"{base}/api/v1/status"), 60, "clothd run serving")
        yield base, port
    finally:
        stop_group(proc)


def _answers(url: str) -> bool:
    try:
        return httpx.get(url, timeout=1).status_code == 200
    except httpx.TransportError:
        return False


def test_start_up_shows_as_starting_not_as_a_fault(browser: Browser, tmp_path: Path) -> None:
    with _daemon_before_its_controller(tmp_path) as (base, port):
        pg = browser.new_page(viewport={"width": 1280, "height": 720})
        try:
            pg.add_init_script(WATCH_THE_LINK)
            pg.goto(base + "/", wait_until="domcontentloaded")  # no camera: the view never loads
            pg.wait_for_selector("#banner-starting:visible", timeout=10000)
            said = pg.text_content("#banner-starting") or ""
            assert said.startswith("Starting: waiting for the stepper controller")
            pg.select_option("#mode-select", "hold")
            pg.click("#apply")
            pg.wait_for_function(
                "document.getElementById('message').textContent === 'starting'", timeout=5000
            )
            fw = Firmware(TableDrives(Table(TableSpec())), port)  # the controller is plugged in
            fw.start()
            try:
                pg.wait_for_function("document.getElementById('link').className === 'pill ok'", timeout=20000)
            finally:
                fw.stop()
            seen = pg.evaluate("window.linkSeen")
        finally:
            pg.close()
    before_up = seen[: [cls for _, cls, _, _ in seen].index("pill ok")]
    # Until the link first comes up it is starting (amber, with its banner), never red, and no fault is
    # listed; once up, the banner is gone.
    starting = ["link starting", "pill warn", "none", True]
    assert before_up and all(s == starting for s in before_up), seen
    assert seen[len(before_up)][3] is False


def test_a_daemon_with_a_token_gets_one_from_the_page(
    browser: Browser, tmp_path_factory: pytest.TempPathFactory
) -> None:
    token = "browser-test-token-0123"
    cfg = tmp_path_factory.mktemp("token") / "clothd.yaml"
    cfg.write_text(f"api:\n  token: {token}\n")
    d = DaemonProcess(cfg, free_port())
    try:
        d.wait_ready()
        s = Sim(d)
        wait(lambda: (s.status()["state"], s.status()["link"]["state"]) == READY, 60, "tracking, link up")
        pg = browser.new_page(viewport={"width": 1280, "height": 720})
        pg.goto(s.base + "/")
        # Asked for as the page opens, before any button is pressed: the E-STOP needs it too.
        pg.wait_for_selector("#token-box:not([hidden])", timeout=5000)
        assert "E-STOP too" in (pg.text_content("#message") or "")
        pg.fill("#token", token)
        pg.click("#token-save")
        pg.click("#estop")
        wait(lambda: s.truth()["estopped"], 5, "the e-stop with the token")
        pg.close()
    finally:
        d.stop()
