"""`POST /api/v1/record/start` is atomic: of two requests at once, one records and the other is refused
(the daemon built, not running: no tick has answered the first start yet)."""

from __future__ import annotations

from pathlib import Path

from fastapi.testclient import TestClient
from local_api import local_app

from clothd.config import Config, RecordingConfig
from clothd.run import build

BASE = "http://127.0.0.1:8080"


def test_a_second_start_before_the_first_is_answered_is_refused_and_makes_nothing(tmp_path: Path) -> None:
    parts = build(Config(recording=RecordingConfig(dir=tmp_path)))
    c = TestClient(local_app(parts), base_url=BASE)
    first = c.post("/api/v1/record/start", json={"dir": "first"})
    assert first.status_code == 200
    second = c.post("/api/v1/record/start", json={"dir": "second"})
    assert second.status_code == 409 and "is starting in" in second.json()["detail"]
    assert (tmp_path / "first").is_dir() and not (tmp_path / "second").exists()
