"""A running daemon's HTTP API as the commissioning commands use it (`clothd drive`, `clothd check-modules`):
status, setpoints, recordings, and playing a drive script to its end."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import httpx

from clothd.core.drive_script import DriveScript
from clothd.errors import ClothdError

POLL_S = 0.1
END_SLACK_S = 5.0  # a played script is idle within a tick or two; this much later something is wrong


class CellError(ClothdError):
    """The daemon refused, or could not be reached; the message says why."""


class CellClient:
    def __init__(self, url: str, token: str | None = None) -> None:
        headers = {"authorization": f"Bearer {token}"} if token else {}
        self.http = httpx.Client(base_url=url.rstrip("/") + "/api/v1", headers=headers, timeout=10.0)
        self.url = url

    def close(self) -> None:
        self.http.close()

    def _call(self, method: str, path: str, body: object | None = None) -> Any:
        try:
            r = self.http.request(method, path, json=body)
        except httpx.HTTPError as err:
            raise CellError(f"no answer from the daemon at {self.url}: {err}") from None
        if r.status_code >= 400:
            try:
                detail = r.json().get("detail", r.text)
            except ValueError:
                detail = r.text
            raise CellError(f"{method} {path}: {r.status_code} {detail}")
        return r.json()

    def status(self) -> dict[str, Any]:
        return dict(self._call("GET", "/status"))

    def set_mode(self, mode: str) -> None:
        """A setpoint that is a mode alone (idle, hold, flatten, flow)."""
        self._call("PUT", "/setpoint", {"mode": mode})

    def sim_truth(self) -> dict[str, Any]:
        """hwsim's truth without the cloth's nodes (against the simulated cell only)."""
        return dict(self._call("GET", "/sim/truth?nodes=false"))

    def outfeed(self) -> list[dict[str, Any]]:
        """hwsim's judgement of each piece that left, oldest first (against the simulated cell only)."""
        return list(self._call("GET", "/sim/outfeed"))

    def record_start(self, name: str | None) -> Path:
        """Start recording into `name` inside the daemon's recording.dir; where it records."""
        self._call("POST", "/record/start", {"dir": name} if name else None)
        deadline = time.monotonic() + END_SLACK_S
        while time.monotonic() < deadline:
            rec = self.status().get("recording") or {}
            if rec.get("active") and rec.get("dir"):
                return Path(rec["dir"])
            time.sleep(POLL_S)
        raise CellError("the recording did not start")

    def record_stop(self) -> None:
        self._call("POST", "/record/stop")

    def play(self, script: DriveScript) -> None:
        """Play a drive script and wait for its end; CellError with the halt reason if a fault stopped it."""
        self._call("PUT", "/setpoint", {"mode": "drive", "script": script.model_dump(mode="json")})
        deadline = time.monotonic() + script.duration_s + END_SLACK_S
        while time.monotonic() < deadline:
            s = self.status()
            if s["mode"] == "idle":
                if s.get("halt_reason"):
                    raise CellError(f"the drive stopped: {s['halt_reason']}")
                return
            time.sleep(POLL_S)
        self._call("PUT", "/setpoint", {"mode": "idle"})
        raise CellError(f"the drive did not end within {script.duration_s + END_SLACK_S:.0f} s; set idle")
