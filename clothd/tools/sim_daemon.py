"""`clothd run --sim SCENARIO` as a child process for a commissioning command's `--sim`: its own API and
OPC UA ports, recordings in a directory of its own, and ready once it tracks the cloth with the link up."""

from __future__ import annotations

import contextlib
import socket
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import httpx
import yaml

from clothd.errors import HardwareError
from clothd.tools.procfs import stop_group

READY_TIMEOUT_S = 180.0


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@contextlib.contextmanager
def sim_daemon(scenario: str, workdir: Path, cameras: int | None = None) -> Iterator[str]:
    """The daemon's URL while it runs (on the cell's first `cameras` cameras; None: all); stopped (its
    process group) on leaving."""
    port = _free_port()
    config = workdir / "clothd-sim.yaml"
    config.write_text(
        yaml.safe_dump(
            {
                "api": {"port": port},
                "opcua": {"endpoint": f"opc.tcp://127.0.0.1:{_free_port()}/clothd/"},
                "recording": {"dir": str(workdir / "recordings")},
            }
        )
    )
    cmd = [sys.executable, "-m", "clothd.cli", "run", "--sim", scenario, "--config", str(config)]
    if cameras is not None:
        cmd += ["--cameras", str(cameras)]
    log = workdir / "clothd-sim.log"  # what it says when it cannot start
    with log.open("wb") as stderr:
        proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=stderr, start_new_session=True)
    url = f"http://127.0.0.1:{port}"
    try:
        _wait_ready(url, proc, log)
        yield url
    finally:
        stop_group(proc)


def _wait_ready(url: str, proc: subprocess.Popen[bytes], log: Path) -> None:
    deadline = time.monotonic() + READY_TIMEOUT_S
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            # Its own error lines, and hwsim's (the child's stderr is its): one line each, no traceback.
            lines = log.read_text(errors="replace").splitlines()
            why = "; ".join(line for line in lines if line.startswith(("clothd: ", "hwsim: ")))
            said = f": {why}" if why else ""
            raise HardwareError(f"clothd run --sim exited with {proc.returncode}{said}")
        with contextlib.suppress(httpx.HTTPError, ValueError):
            s = httpx.get(f"{url}/api/v1/status", timeout=2).json()
            if s["state"] == "tracking" and s["link"]["state"] == "connected":
                return
        time.sleep(0.3)
    raise HardwareError(f"clothd run --sim was not tracking the cloth within {READY_TIMEOUT_S:.0f} s")
