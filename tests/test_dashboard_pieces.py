"""The dashboard's pieces (mode flow) in a real headless Chromium (as tests/test_dashboard_browser.py), over
the API served in process by uvicorn on a daemon built but not started: statuses with pieces are published
into its hub as the loop would, and reach the page over the WebSocket."""

from __future__ import annotations

import re
import shutil
import threading
from collections.abc import Iterator
from pathlib import Path

import pytest
import uvicorn
from flow_statuses import FLAP, piece, publish
from live_cell import wait
from local_api import local_app
from playwright.sync_api import Page, sync_playwright

from clothd.api.app import STATIC_DIR
from clothd.api.stream import StreamHub
from clothd.config import ApiConfig, Config
from clothd.core.modes import Mode, PieceState
from clothd.run import build
from clothd.tools.bench_loop import free_port

CHROMIUM = shutil.which("chromium") or "/usr/bin/chromium"
ARTIFACTS = Path(__file__).resolve().parent.parent / "out" / "test-artifacts"
WAIT_MS = 20000  # a bound on waiting for what must come, never a measured time
# The pixels of the pieces' overlay that something was drawn on.
DRAWN = """() => { const c = document.getElementById('pieces-view');
    if (!c.width) return 0; const d = c.getContext('2d').getImageData(0, 0, c.width, c.height).data;
    let n = 0; for (let i = 3; i < d.length; i += 4) if (d[i] > 0) n++; return n; }"""


@pytest.fixture(scope="module")
def served() -> Iterator[tuple[str, StreamHub]]:
    port = free_port()
    parts = build(Config())
    app = local_app(parts, ApiConfig(port=port))
    server = uvicorn.Server(
        uvicorn.Config(app, host="127.0.0.1", port=port, log_level="warning", timeout_graceful_shutdown=1)
    )
    thread = threading.Thread(target=server.run, daemon=True)
    thread.start()
    try:
        wait(lambda: server.started, 30, "uvicorn serving")
        yield f"http://127.0.0.1:{port}", parts.hub
    finally:
        server.should_exit = True
        thread.join(10)


@pytest.fixture(scope="module")
def page(served: tuple[str, StreamHub]) -> Iterator[Page]:
    with sync_playwright() as p:
        browser = p.chromium.launch(executable_path=CHROMIUM, args=["--no-sandbox"])
        pg = browser.new_page(viewport={"width": 1280, "height": 900})
        pg.goto(served[0] + "/", wait_until="domcontentloaded")  # no camera: the view never loads
        pg.wait_for_function("tableToPixel !== null", timeout=WAIT_MS)
        yield pg
        pg.close()
        browser.close()


@pytest.mark.slow
def test_the_page_lists_every_piece_with_a_rejects_reason_and_draws_their_poses(
    page: Page, served: tuple[str, StreamHub]
) -> None:
    hub = served[1]
    assert page.is_hidden("#pieces-panel")  # not in mode flow
    table = [
        piece(3, PieceState.PLACING, 0.05),
        piece(4, PieceState.FLATTENING, -0.15),
        piece(5, PieceState.ENTERING),  # not tracked: no pose to draw
    ]
    gone = [piece(1, PieceState.LEFT, 0.5, gone=True), piece(2, PieceState.REJECTED, 0.5, True, FLAP)]
    publish(hub, table + gone)
    page.wait_for_selector("#pieces-panel:visible", timeout=WAIT_MS)
    page.wait_for_function(
        "document.querySelectorAll('#pieces-rows tr[data-id]').length === 5", timeout=WAIT_MS
    )
    rows = page.eval_on_selector_all(
        "#pieces-rows tr", "rs => rs.map(r => r.innerText.replace(/\\s+/g, ' '))"
    )
    assert rows[0].startswith("#3 placing 0.050, 0.020 5.7° flat · 0.4 mm")
    assert rows[1].startswith("#4 flattening -0.150, 0.020 5.7° wrinkled · 2.5 mm")
    assert rows[2].startswith("#5 entering –, – – –")
    # The gone, newest first: the reject with its reason on a line of its own, then the one that left.
    assert rows[3].startswith("#2 rejected (gone)") and rows[4] == f"#2: {FLAP}"
    assert rows[5].startswith("#1 left (gone)") and len(rows) == 6
    summary = page.text_content("#pieces-summary") or ""
    assert summary == "3 on the table · last 2 gone, 1 rejected"
    wait(lambda: page.evaluate(DRAWN) > 0, 10, "the pieces drawn over the view")
    ARTIFACTS.mkdir(parents=True, exist_ok=True)
    page.screenshot(path=str(ARTIFACTS / "dashboard-pieces.png"))
    # Each posed piece on the table is drawn where its pose projects: a pixel of its own colour there.
    for p, colour in ((table[0], (0xBA, 0x68, 0xC8)), (table[1], (0xFF, 0xB7, 0x4D))):
        assert p.pose is not None
        near = page.evaluate(
            """([x, y]) => { const [u, v] = toPixel(x, y).map(Math.round);
            return Array.from(document.getElementById('pieces-view').getContext('2d')
                .getImageData(u - 8, v - 8, 17, 17).data); }""",
            [p.pose.x_m, p.pose.y_m],
        )
        pixels = {tuple(near[i : i + 3]) for i in range(0, len(near), 4) if near[i + 3] == 255}
        assert colour in pixels, f"piece {p.id} not drawn at its pose"

    publish(hub, None, Mode.IDLE)  # out of mode flow: the panel goes, and the drawing with it
    page.wait_for_selector("#pieces-panel", state="hidden", timeout=WAIT_MS)
    assert page.evaluate(DRAWN) == 0


def test_the_page_names_only_the_piece_states_the_api_has() -> None:
    js = (STATIC_DIR / "app.js").read_text()
    colours = re.search(r"PIECE_COLOURS = \{(.*?)\}", js, re.S)
    assert colours is not None
    named = set(re.findall(r"(\w+): \"#", colours.group(1))) | set(re.findall(r'p\.state [!=]== "(\w+)"', js))
    assert named and named <= set(PieceState)
    assert set(PieceState) - {PieceState.LEFT} <= named  # every state a piece on the table can be in
