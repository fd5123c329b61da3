"""The API in-process: schemathesis fuzzes every documented route against its schema, and the rules the
schema cannot state (auth, exposure, 409 on impossible requests) are checked one by one. The daemon is
real but not started: no camera, no serial port."""

from __future__ import annotations

import re
import socket
import subprocess
import sys
import tempfile
from pathlib import Path

import hypothesis
import numpy as np
import pytest
import schemathesis
from fastapi import FastAPI
from fastapi.testclient import TestClient
from local_api import local_app
from starlette.websockets import WebSocketDisconnect

from clothd.api.stream import Subscriber
from clothd.config import ApiConfig, CameraSourceConfig, Config, RecordingConfig, TrackerConfig, parse_config
from clothd.core.camera_model import CameraModel
from clothd.core.modes import LoopState, Mode
from clothd.drivers.camera import redact_source
from clothd.drivers.ports import FrameSourceHealth
from clothd.errors import ConfigError
from clothd.formats import write_camera
from clothd.loop.pairing import CameraReport, PairingStats
from clothd.run import build

TOKEN = "s3cret-token-for-tests"


BASE = "http://127.0.0.1:8080"  # the daemon's own name and port: the guard refuses any other Host
WS_OWN = {"Host": "127.0.0.1:8080"}  # the test client's WebSocket ignores base_url


def _app(
    token: str | None = None, allowed_hosts: tuple[str, ...] = (), max_body_bytes: int = 4096
) -> FastAPI:
    """The app over a daemon built as `clothd run` builds it (ideal camera), never started; recordings go
    to a directory of their own."""
    parts = build(Config(recording=RecordingConfig(dir=Path(tempfile.mkdtemp(prefix="clothd-api-")))))
    api = ApiConfig(token=token, allowed_hosts=allowed_hosts, max_body_bytes=max_body_bytes)
    return local_app(parts, api)


# schemathesis's ASGI client calls itself "testserver": a name this daemon is told it has. Its invalid
# bodies are judged by the schema's 422, not the body limit's 413 (tested on its own): the limit is raised.
schema = schemathesis.openapi.from_asgi(
    "/openapi.json", _app(allowed_hosts=("testserver",), max_body_bytes=1_000_000)
)


# The MJPEG view never ends, and /healthz answers 503 by design while nothing runs (tested below).
@schema.exclude(path_regex="view.mjpg|healthz").parametrize()
@hypothesis.settings(max_examples=40, deadline=None, derandomize=True)
def test_api_conforms_to_its_schema(case: schemathesis.Case) -> None:
    # Every response has a documented status and body; nothing returns 5xx.
    case.call_and_validate()


@pytest.fixture
def client() -> TestClient:
    return TestClient(_app(), base_url=BASE)


def test_status_reports_every_section(client: TestClient) -> None:
    s = client.get("/api/v1/status").json()
    assert s["mode"] == "idle" and s["estop"] is False
    assert {"pose", "mesh", "features", "residual", "timing", "camera", "link"} <= set(s)
    assert s["link"]["state"] == "starting"  # never up since the start
    assert s["halt_reason"] is None and s["halt_t_unix_s"] is None


def test_setpoint_validation_gives_reasons(client: TestClient) -> None:
    r = client.put("/api/v1/setpoint", json={"mode": "move", "x_m": 0.1})
    assert r.status_code == 422
    assert "y_m" in r.text and "theta_rad" in r.text and "missing" in r.text
    r = client.put("/api/v1/setpoint", json={"mode": "spin"})
    assert r.status_code == 422
    assert "mode 'spin' is none of: idle, hold, move, flatten, drive" in r.json()["detail"]
    markup = "<script>alert(1)</script>" + "A" * 3000
    r = client.put("/api/v1/setpoint", json={"mode": markup})
    assert r.status_code == 422 and "script" not in r.text and len(r.text) < 300
    assert "the mode given is none of: idle" in r.json()["detail"]
    r = client.put("/api/v1/setpoint", json={"mode": "move", "x_m": 0.1, "y_m": 0, "theta_rad": 9})
    assert r.status_code == 422 and "theta_rad" in r.text


def test_flatten_with_a_rigid_tracker_is_a_conflict_that_says_why() -> None:
    parts = build(Config(tracker=TrackerConfig(model="rigid")))
    c = TestClient(local_app(parts), base_url=BASE)
    r = c.put("/api/v1/setpoint", json={"mode": "flatten"})
    assert r.status_code == 409 and "mesh tracker" in r.json()["detail"]
    assert c.get("/api/v1/status").json()["mode"] == "idle"


def test_a_setpoint_before_the_link_first_comes_up_is_refused_as_starting(client: TestClient) -> None:
    """Never started: the link has not been up yet, which is the start, not a fault (each refusal by
    itself: tests/test_loop_safety.py)."""
    for body in ({"mode": "hold"}, {"mode": "move", "x_m": 0.1, "y_m": 0.0, "theta_rad": 0.5}):
        r = client.put("/api/v1/setpoint", json=body)
        assert (r.status_code, r.json()) == (409, {"detail": "starting"})
    assert client.put("/api/v1/setpoint", json={"mode": "idle"}).status_code == 200
    assert client.get("/api/v1/status").json()["mode"] == "idle"


def test_estop_latches_and_refuses_moves_until_cleared(client: TestClient) -> None:
    assert client.post("/api/v1/estop").status_code == 200
    assert client.get("/api/v1/status").json()["estop"] is True
    move = {"mode": "move", "x_m": 0.1, "y_m": 0.0, "theta_rad": 0.0}
    r = client.put("/api/v1/setpoint", json=move)
    assert r.status_code == 409 and "emergency stop" in r.json()["detail"]
    r = client.post("/api/v1/estop/clear")
    assert r.status_code == 200 and r.json()["detail"] == "emergency stop cleared; mode is idle"
    assert client.get("/api/v1/status").json()["estop"] is False
    assert client.post("/api/v1/estop/clear").json()["detail"] == "no emergency stop was latched"
    # Cleared, but this daemon never started: no link, no cloth, so still nothing may move.
    r = client.put("/api/v1/setpoint", json=move)
    assert (r.status_code, r.json()["detail"]) == (409, "starting")
    assert client.get("/api/v1/status").json()["mode"] == "idle"


def test_token_guards_changes_but_not_reads() -> None:
    c = TestClient(_app(token=TOKEN), base_url=BASE)
    assert c.get("/api/v1/status").status_code == 200
    missing = c.post("/api/v1/estop")
    assert missing.status_code == 401 and "needs Authorization" in missing.json()["detail"]
    wrong = c.post("/api/v1/estop", headers={"Authorization": "Bearer wrong-token-xxxxxxx"})
    assert wrong.status_code == 401 and "not this daemon's" in wrong.json()["detail"]
    basic = c.post("/api/v1/estop", headers={"Authorization": f"Basic {TOKEN}"})
    assert basic.status_code == 401 and "must be Bearer" in basic.json()["detail"]
    assert c.post("/api/v1/estop", headers={"Authorization": f"Bearer {TOKEN}"}).status_code == 200
    # The page asks whether it needs a token as it opens (a read: no token needed to ask).
    assert c.get("/api/v1/access").json() == {"token_required": True}
    open_app = TestClient(_app(), base_url=BASE)
    assert open_app.get("/api/v1/access").json() == {"token_required": False}


def test_binding_off_loopback_needs_a_token() -> None:
    with pytest.raises(ConfigError, match=r"api: .*api\.token"):
        parse_config({"api": {"host": "0.0.0.0"}})
    assert parse_config({"api": {"host": "0.0.0.0", "token": TOKEN}}).api.token == TOKEN
    assert ApiConfig(host="::1").token is None


def test_metrics_and_health(client: TestClient) -> None:
    text = client.get("/metrics").text
    assert "clothd_missed_ticks_total" in text and "clothd_link_up 0.0" in text
    gauges = [line for line in text.splitlines() if line.startswith("clothd_state{")]
    state_gauge = {line.split('"')[1]: line.rsplit(" ", 1)[1] for line in gauges}
    assert state_gauge == {s.value: "1.0" if s == LoopState.STARTING else "0.0" for s in LoopState}
    r = client.get("/healthz")
    assert r.status_code == 503 and set(r.json()["problems"]) == {"camera", "stepper link"}


def test_stream_sends_the_status_at_once(client: TestClient) -> None:
    with client.websocket_connect("/api/v1/stream?hz=5", headers=WS_OWN) as ws:
        first = ws.receive_json()
    assert first["mode"] == "idle"
    assert first["cameras"] == client.get("/api/v1/status").json()["cameras"]  # the same status
    assert [c["name"] for c in first["cameras"]] == ["cam0"]


def test_a_stream_at_a_rate_it_cannot_have_is_closed_with_the_reason(client: TestClient) -> None:
    for hz in ("0", "-1", "abc", "31", "nan"):
        with (
            client.websocket_connect(f"/api/v1/stream?hz={hz}", headers=WS_OWN) as ws,
            pytest.raises(WebSocketDisconnect) as closed,
        ):
            ws.receive_json()
        assert closed.value.code == 1008 and closed.value.reason == "hz must be a number in (0, 30]", hz


def test_slow_subscriber_drops_instead_of_queueing() -> None:
    sub = Subscriber(0.0)
    for k in range(5):
        sub.offer(str(k).encode())
    assert sub.dropped == 4
    assert np.isclose(float(sub._slot or b"nan"), 4.0)


def test_dashboard_page_and_its_assets_are_served(client: TestClient) -> None:
    page = client.get("/")
    assert page.status_code == 200 and "text/html" in page.headers["content-type"]
    for element in ('id="estop"', 'id="video"', 'id="plot-residual"', 'id="setpoint-form"', "/static/app.js"):
        assert element in page.text
    js = client.get("/static/app.js")
    assert js.status_code == 200 and "/api/v1/stream" in js.text
    assert client.get("/static/style.css").status_code == 200


def test_camera_homography_maps_the_table_like_the_camera_model(client: TestClient) -> None:
    info = client.get("/api/v1/camera").json()
    H = np.asarray(info["table_to_pixel"])
    cam = CameraModel.ideal(640, 480, 900.0, 1.0)
    pts = np.array([[0.0, 0.0], [0.1, -0.05], [-0.2, 0.15]])
    hom = np.column_stack([pts, np.ones(3)]) @ H.T
    np.testing.assert_allclose(
        hom[:, :2] / hom[:, 2:], cam.project(np.column_stack([pts, np.zeros(3)])), atol=1e-9
    )
    assert (info["width"], info["height"]) == (640, 480)


# -- the request guard: what a web page in the cell PC's browser, or a flood, must not do -----------------

EVIL = {"Origin": "http://evil.example"}


def test_a_foreign_page_cannot_clear_the_estop_or_move(client: TestClient) -> None:
    assert client.post("/api/v1/estop").status_code == 200
    # A "simple" cross-site request: text/plain, no preflight in a browser.
    r = client.post("/api/v1/estop/clear", headers={**EVIL, "Content-Type": "text/plain"}, content="x")
    assert r.status_code == 403
    assert client.post("/api/v1/estop/clear", headers=EVIL).status_code == 403
    assert client.post("/api/v1/reset", headers={"Referer": "http://evil.example/page"}).status_code == 403
    assert client.get("/api/v1/status").json()["estop"] is True
    # The daemon's own page (same origin) may.
    assert client.post("/api/v1/estop/clear", headers={"Origin": BASE}).status_code == 200


def test_a_rebound_host_name_is_refused(client: TestClient) -> None:
    r = client.get("/api/v1/status", headers={"Host": "evil.example:8080"})
    assert r.status_code == 421
    assert client.get("/api/v1/status", headers={"Host": "localhost:8080"}).status_code == 200
    assert client.get("/api/v1/status", headers={"Host": "LocalHost:8080"}).status_code == 200
    assert client.get("/api/v1/status", headers={"Host": "127.0.0.1:9999"}).status_code == 421


def test_the_websocket_checks_host_and_origin(client: TestClient) -> None:
    for headers in ({**WS_OWN, **EVIL}, {"Host": "evil.example:8080"}):
        with (
            pytest.raises(WebSocketDisconnect),
            client.websocket_connect("/api/v1/stream", headers=headers) as ws,
        ):
            ws.receive_json()
    with client.websocket_connect("/api/v1/stream", headers={**WS_OWN, "Origin": BASE}) as ws:
        assert ws.receive_json()["mode"] == "idle"


def test_bodies_are_json_bounded_and_never_echoed(client: TestClient) -> None:
    r = client.put("/api/v1/setpoint", content="mode=idle", headers={"Content-Type": "text/plain"})
    assert r.status_code == 415
    huge = b'{"mode": "' + b"x" * 20_000_000 + b'"}'
    r = client.put("/api/v1/setpoint", content=huge, headers={"Content-Type": "application/json"})
    assert r.status_code == 413 and len(r.content) < 200
    for bad in ('{"mode": "move", "x_m": NaN, "y_m": 0, "theta_rad": 0}', '{"mode": "\\ud800"}'):
        r = client.put("/api/v1/setpoint", content=bad, headers={"Content-Type": "application/json"})
        assert r.status_code == 422, bad
        assert "NaN" not in r.text and "ud800" not in r.text


def test_a_body_that_is_not_json_is_a_422_as_docs_api_md_says(client: TestClient) -> None:
    r = client.put("/api/v1/setpoint", content='{"mode": ', headers={"Content-Type": "application/json"})
    assert r.status_code == 422 and "detail" in r.json()
    api_md = " ".join((Path(__file__).parent.parent / "docs" / "api.md").read_text().split())
    assert f"{r.status_code} for a body that is not JSON" in api_md


def test_with_a_token_nothing_is_read_before_it_is_checked() -> None:
    c = TestClient(_app(token=TOKEN), base_url=BASE)
    huge = b"{" + b" " * 10_000_000 + b"}"
    r = c.put("/api/v1/setpoint", content=huge, headers={"Content-Type": "application/json"})
    assert r.status_code == 401


def _client_recording_into(recording_dir: Path, format: str = "directory") -> TestClient:
    parts = build(Config(recording=RecordingConfig(dir=recording_dir, format=format)))
    return TestClient(local_app(parts), base_url=BASE)


def test_recordings_stay_inside_the_recording_directory(tmp_path: Path) -> None:
    root = tmp_path / "recordings"
    root.mkdir()
    (root / "escape").symlink_to(tmp_path)
    c = _client_recording_into(root)
    for bad in ("/proc/evil", "../outside", "escape/x", "a\x00b", ".", ""):
        r = c.post("/api/v1/record/start", json={"dir": bad})
        assert r.status_code == 422, (bad, r.text)
    assert not (tmp_path / "outside").exists() and not (tmp_path / "x").exists()
    r = c.post("/api/v1/record/start", json={"dir": "session-1"})
    assert r.status_code == 200 and (root / "session-1").is_dir()
    assert c.post("/api/v1/record/start", json={"dir": "session-1"}).status_code == 409  # exists


def test_an_mcap_recording_is_one_new_file_named_as_asked(tmp_path: Path) -> None:
    root = tmp_path / "recordings"
    root.mkdir()
    c = _client_recording_into(root, "mcap")
    r = c.post("/api/v1/record/start", json={"dir": "line-3/session-1"})
    assert r.status_code == 200 and r.json()["detail"].endswith("line-3/session-1.mcap")
    assert (root / "line-3" / "session-1.mcap").is_file()
    for again in ("line-3/session-1", "line-3/session-1.mcap"):  # exists, with or without the suffix
        assert c.post("/api/v1/record/start", json={"dir": again}).status_code == 409
    (root / "escape.mcap").symlink_to(tmp_path / "elsewhere.mcap")
    assert c.post("/api/v1/record/start", json={"dir": "escape"}).status_code == 422
    assert not (tmp_path / "elsewhere.mcap").exists()


def test_a_place_that_cannot_be_written_is_refused_at_once(tmp_path: Path) -> None:
    (tmp_path / "a-file").write_text("")
    c = _client_recording_into(tmp_path / "a-file")  # a directory cannot be made under a file
    r = c.post("/api/v1/record/start", json={"dir": "s"})
    assert r.status_code == 422 and "cannot create" in r.json()["detail"]


def test_camera_credentials_stay_out_of_the_status() -> None:
    assert redact_source("rtsp://admin:s3cret@10.0.0.9:554/stream") == "rtsp://***@10.0.0.9:554/stream"
    assert redact_source("/dev/video0") == "/dev/video0"
    parts = build(Config(camera=CameraSourceConfig(source="rtsp://admin:s3cret@cam/stream")))
    c = TestClient(local_app(parts), base_url=BASE)
    status = c.get("/api/v1/status")
    assert "s3cret" not in status.text and status.json()["camera"]["source"] == "rtsp://***@cam/stream"


def test_every_camera_is_in_the_status_metrics_and_health_and_only_the_first_is_needed(
    tmp_path: Path,
) -> None:
    top_json, side_json = tmp_path / "top.json", tmp_path / "side.json"
    for path in (top_json, side_json):
        write_camera(path, CameraModel.ideal(640, 480, 900.0, 1.0))
    cameras = [
        {"source": "0", "calibration": str(top_json)},
        {"name": "side", "source": "rtsp://u:s3cret@side/s", "calibration": str(side_json)},
    ]
    parts = build(parse_config({"cameras": cameras}))
    c = TestClient(local_app(parts), base_url=BASE)
    status = c.get("/api/v1/status")
    assert "s3cret" not in status.text
    first, side = status.json()["cameras"]
    assert (first["name"], first["source"], side["name"], side["source"]) == (
        "cam0",
        "0",
        "side",
        "rtsp://***@side/s",
    )
    assert side["state"] == "connecting" and side["skew_ms"] is None and first["skew_ms"] is None
    assert status.json()["camera"]["source"] == "0"  # the first camera, as before
    # A further camera streaming with its pairing measured; the first lost.
    stats = PairingStats(skew_ms=4.5, skew_p95_ms=7.0, paired_pct=98.0)
    parts.daemon.further = (CameraReport(FrameSourceHealth("streaming", True, None, 2, 12.5, 133.4), stats),)
    parts.daemon.publish()
    side = c.get("/api/v1/status").json()["cameras"][1]
    assert (side["fps"], side["longest_gap_ms"]) == (12.5, 133.4)
    assert (side["skew_ms"], side["skew_p95_ms"], side["paired_pct"], side["reconnects"]) == (
        4.5,
        7.0,
        98.0,
        2,
    )
    text = c.get("/metrics").text
    assert (
        'clothd_camera_skew_ms{camera="side"} 4.5' in text
        and 'clothd_camera_skew_ms{camera="cam0"}' not in text
    )
    assert (
        'clothd_camera_healthy{camera="side"} 1.0' in text
        and 'clothd_camera_healthy{camera="cam0"} 0.0' in text
    )
    assert 'clothd_camera_paired_ratio{camera="side"} 0.98' in text
    assert 'clothd_camera_fps{camera="side"} 12.5' in text and 'clothd_camera_fps{camera="cam0"}' not in text
    assert 'clothd_camera_longest_gap_ms{camera="side"} 133.4' in text
    health = c.get("/healthz").json()
    assert "camera" in health["problems"] and health["degraded"] == []
    # The further camera lost: degraded, not a problem (tracking goes on with the first view).
    parts.daemon.further = (CameraReport(FrameSourceHealth("lost", False, "gone", 3), stats),)
    parts.daemon.publish()
    health = c.get("/healthz").json()
    assert health["degraded"] == ["camera side"] and "camera side" not in health["problems"]


def test_a_taken_port_ends_the_start_at_once_and_clearly() -> None:
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        done = subprocess.run(
            [sys.executable, "-m", "clothd.cli", "run", "--sim", "--port", str(port)],
            capture_output=True,
            text=True,
            timeout=60,
        )
    assert done.returncode != 0
    assert f"127.0.0.1:{port}" in done.stderr and "--port" in done.stderr
    assert "hwsim" not in done.stdout  # nothing was started: no simulated cell, no compute


def test_cors_only_for_configured_origins() -> None:
    hmi = "http://hmi.plant.example"
    parts = build(Config())
    app = local_app(parts, ApiConfig(allowed_origins=(hmi,)))
    c = TestClient(app, base_url=BASE)
    preflight = {"Access-Control-Request-Method": "POST", "Access-Control-Request-Headers": "content-type"}
    r = c.options("/api/v1/estop", headers={"Origin": hmi, **preflight})
    assert r.status_code == 200 and r.headers["access-control-allow-origin"] == hmi
    assert c.post("/api/v1/estop", headers={"Origin": hmi}).status_code == 200
    r = c.options("/api/v1/estop", headers={"Origin": "http://evil.example", **preflight})
    assert "access-control-allow-origin" not in r.headers
    # Without the setting there is no CORS at all.
    r = TestClient(_app(), base_url=BASE).options("/api/v1/estop", headers={"Origin": hmi, **preflight})
    assert "access-control-allow-origin" not in r.headers


def test_the_dashboard_names_only_the_modes_and_states_the_api_has() -> None:
    """The page compares with the words; they are clothd/core/modes.py's, and it offers every mode a
    person can pick without a script."""
    static = Path(__file__).parent.parent / "clothd" / "api" / "static"
    js = (static / "app.js").read_text()
    states = set(re.findall(r's\.state === "(\w+)"', js))
    modes = set(re.findall(r'mode === "(\w+)"', js))
    offered = set(re.findall(r'<option value="(\w+)">', (static / "index.html").read_text()))
    assert states and states <= set(LoopState)
    assert modes and modes <= set(Mode)
    assert offered == set(Mode) - {Mode.DRIVE}


def test_the_api_docs_page_needs_no_internet(client: TestClient) -> None:
    """A cell PC may have none: /docs loads Swagger UI from the daemon itself, not from a CDN."""
    page = client.get("/docs")
    assert page.status_code == 200 and "cdn." not in page.text
    scripts = re.findall(r'src="([^"]+\.js)"', page.text)
    assert scripts and all(client.get(src).status_code == 200 for src in scripts)
