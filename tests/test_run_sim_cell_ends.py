"""`clothd run --sim` whose simulated cell ends (its world failed, or it was killed) stops and says so,
instead of retrying a camera and a stepper link that will never come back."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
from pathlib import Path

from live_cell import wait

from clothd.tools.bench_loop import free_port


def _hwsim_children(pid: int) -> list[int]:
    found = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().split(") ", 1)[1].split()
            cmdline = (stat.parent / "cmdline").read_bytes()
        except (FileNotFoundError, ProcessLookupError, IndexError):
            continue
        if int(fields[1]) == pid and b"hwsim.cli" in cmdline:
            found.append(int(stat.parent.name))
    return found


def test_the_daemon_stops_with_an_error_when_its_simulated_cell_ends(tmp_path: Path) -> None:
    opcua = f"opc.tcp://127.0.0.1:{free_port()}/clothd/"
    cmd = [
        sys.executable,
        "-m",
        "clothd.cli",
        "run",
        "--sim",
        "--port",
        str(free_port()),
        "--opcua-endpoint",
        opcua,
    ]
    proc = subprocess.Popen(
        cmd,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,
        env={**os.environ, "TMPDIR": str(tmp_path)},
    )
    try:
        assert proc.stdout is not None
        while "clothd: dashboard" not in (line := proc.stdout.readline()):
            assert line, "clothd run --sim ended before it was ready"
        (hwsim,) = _hwsim_children(proc.pid)
        os.kill(hwsim, signal.SIGKILL)
        wait(lambda: proc.poll() is not None, 60, "clothd run --sim to stop")
        _, stderr = proc.communicate(timeout=10)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
    assert proc.returncode != 0
    assert "the simulated cell (hwsim serve) ended with code -9" in stderr
