"""A live simulated cell for tests: `hwsim serve` and `clothd run` as separate processes, configured as
on a real cell (the daemon uses the pty and the video URL hwsim reports)."""

from __future__ import annotations

import contextlib
import json
import os
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import httpx
import pytest
import yaml


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def wait(check: Callable[[], bool], timeout_s: float, what: str, every_s: float = 0.05) -> float:
    """Poll until check() holds; returns the seconds it took."""
    t0 = time.monotonic()
    while not check():
        if time.monotonic() - t0 > timeout_s:
            raise AssertionError(f"{what}: not within {timeout_s} s")
        time.sleep(every_s)
    return time.monotonic() - t0


@dataclass
class Cell:
    http: str
    ready: dict[str, Any]

    def truth(self) -> dict[str, Any]:
        return dict(httpx.get(f"{self.http}/truth", timeout=5).json())

    def post(self, path: str) -> None:
        httpx.post(f"{self.http}{path}", timeout=5).raise_for_status()


@dataclass
class Daemon:
    base: str
    proc: subprocess.Popen[bytes]
    recording_dir: Path

    def status(self) -> dict[str, Any]:
        return dict(httpx.get(f"{self.base}/api/v1/status", timeout=5).json())

    def put_setpoint(self, body: dict[str, Any]) -> None:
        r = httpx.put(f"{self.base}/api/v1/setpoint", json=body, timeout=5)
        if r.is_error:  # the daemon's reason, which a bare status code hides from a failed test's report
            raise httpx.HTTPStatusError(f"{r.status_code}: {r.text}", request=r.request, response=r)

    def tracking_near(self, xy_m: tuple[float, float], tol_m: float = 0.01) -> bool:
        """Tracking a cloth within tol_m of xy_m: after POST /reset, the status says `tracking` until the
        reset takes effect, so the state alone cannot tell the new track from the old."""
        s = self.status()
        pose = s["pose"]
        return bool(
            s["state"] == "tracking"
            and pose is not None
            and abs(pose["x_m"] - xy_m[0]) < tol_m
            and abs(pose["y_m"] - xy_m[1]) < tol_m
        )

    def post(self, path: str) -> None:
        httpx.post(f"{self.base}/api/v1{path}", timeout=5).raise_for_status()

    def post_json(self, path: str, body: dict[str, Any]) -> None:
        httpx.post(f"{self.base}/api/v1{path}", json=body, timeout=5).raise_for_status()

    def stop(self) -> None:
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(timeout=20)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()


def serve_cell(tmp_path_factory: pytest.TempPathFactory, scenario: str = "cell") -> Iterator[Cell]:
    """`hwsim serve` for a test module (use as a module-scoped fixture)."""
    state = tmp_path_factory.mktemp("cell")
    # At the daemon's loop.nice, as `clothd run --sim` starts it: the simulated controller stands for a
    # microcontroller, which nothing on the PC starves (nice only warns where it is not permitted).
    hwsim = [sys.executable, "-m", "hwsim.cli", "serve", "--scenario", scenario, "--state-dir", str(state)]
    proc = subprocess.Popen(
        ["nice", "-n", "-10", *hwsim],
        stdout=subprocess.PIPE,
        stderr=subprocess.DEVNULL,
    )
    try:
        assert proc.stdout is not None
        line = b""
        while not line.startswith(b"{"):  # Taichi announces itself on stdout first
            line = proc.stdout.readline()
            assert line, "hwsim serve exited before it was ready"
        ready = json.loads(line)
        yield Cell(str(ready["http"]), ready)
    finally:
        proc.terminate()
        proc.wait(timeout=20)


def start_daemon(
    cell: Cell,
    tmp_path: Path,
    env: dict[str, str] | None = None,
    config: dict[str, Any] | None = None,
    cameras: int | None = None,
) -> Daemon:
    """`clothd run` against the cell; `config` adds sections to its configuration. It reads every camera
    of the cell, as `clothd run --sim` does, or the first `cameras`."""
    port = _free_port()
    cfg: dict[str, Any] = {
        "cameras": [
            {"name": c["name"], "source": c["video_url"], "calibration": c["camera_json"]}
            for c in cell.ready["cameras"][:cameras]
        ],
        "stepper": {"port": cell.ready["serial"]},
        "api": {"port": port},
        "opcua": {"endpoint": f"opc.tcp://127.0.0.1:{_free_port()}/clothd/"},  # never the shared 4840
        # A few frames: recordings in these tests get cut short.
        "recording": {"max_bytes": 3_000_000, "dir": str(tmp_path / "recordings")},
    }
    for section, values in (config or {}).items():
        cfg[section] = {**cfg.get(section, {}), **values}
    path = tmp_path / f"clothd-{port}.yaml"
    path.write_text(yaml.safe_dump(cfg))
    proc = subprocess.Popen(
        [sys.executable, "-m", "clothd.cli", "run", "--config", str(path)],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
        env={**os.environ, **(env or {})},
    )
    d = Daemon(f"http://127.0.0.1:{port}", proc, tmp_path / "recordings")

    def tracking() -> bool:
        with contextlib.suppress(httpx.HTTPError):
            s = d.status()
            return s["state"] == "tracking" and s["link"]["state"] == "connected"
        return False

    wait(tracking, 120, "daemon tracking the cloth with the link up", every_s=0.3)
    return d
