"""Long commands show progress on a terminal and nothing elsewhere; the daemon's logs suit journald and
a storm of errors writes a few lines, not a storm."""

from __future__ import annotations

import logging
import os
import select
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

import pytest
from terminal import on_terminal, piped

from clothd.logs import RateLimit
from clothd.outputs.view import wall_clock_label

Recorder = Callable[[str], Path]


def _replay(rec: Path, out: Path, on_a_terminal: bool) -> str:
    cmd = [sys.executable, "-m", "clothd.cli", "replay", str(rec), "--out", str(out), "--model", "none"]
    return on_terminal(cmd) if on_a_terminal else piped(cmd)


def test_replay_shows_progress_on_a_terminal_only(short_recording: Recorder, tmp_path: Path) -> None:
    rec = short_recording("translate")
    shown = _replay(rec, tmp_path / "tty", on_a_terminal=True)
    assert f"replaying {rec.name}" in shown
    assert "frame/s" in shown or "s/frame" in shown
    logged = _replay(rec, tmp_path / "pipe", on_a_terminal=False)
    assert "frame/s" not in logged and "replaying" not in logged


def _log_lines(env: dict[str, str]) -> list[str]:
    code = (
        "import logging\n"
        "from clothd.logs import configure_logging\n"
        "configure_logging()\n"
        "logging.getLogger('clothd.loop.daemon').warning('tick overran')\n"
        "logging.getLogger('httpx').info('HTTP Request: GET /truth 200')\n"
        "logging.getLogger('uvicorn.access').info('127.0.0.1 GET /api/v1/status 200')\n"
    )
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=60)
    return done.stderr.splitlines()


def test_logs_leave_time_stamps_to_journald_and_skip_per_request_lines() -> None:
    base = {k: v for k, v in os.environ.items() if k != "JOURNAL_STREAM"}
    assert _log_lines({**base, "JOURNAL_STREAM": "8:1234"}) == ["WARNING clothd.loop.daemon: tick overran"]
    on_a_terminal = _log_lines(base)
    assert len(on_a_terminal) == 1 and on_a_terminal[0].endswith("WARNING clothd.loop.daemon: tick overran")
    assert on_a_terminal[0][:4].isdigit()  # a time stamp of our own first


def test_the_live_view_labels_frames_with_the_wall_clock() -> None:
    label = wall_clock_label(time.monotonic() - 2.0)
    expected = time.strftime("%H:%M:%S", time.localtime(time.time() - 2.0))
    assert label.startswith(expected[:5]) and len(label) == len("12:34:56.7")


def test_a_storm_of_errors_is_rate_limited_with_one_traceback_and_a_count(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    now = [100.0]
    monkeypatch.setattr("clothd.logs.time.monotonic", lambda: now[0])
    limit = RateLimit(burst=3, window_s=10.0)

    def record(msg: str) -> logging.LogRecord:
        try:
            raise ValueError("malformed")
        except ValueError:
            return logging.LogRecord("asyncua.x", logging.ERROR, __file__, 1, msg, (), sys.exc_info())

    storm = [record("Exception raised while parsing") for _ in range(20)]
    passed = [r for r in storm if limit.filter(r)]
    assert len(passed) == 3
    assert passed[0].exc_info is not None and all(r.exc_info is None for r in passed[1:])
    assert limit.filter(record("another place"))  # counted apart
    now[0] += 10.0
    later = record("Exception raised while parsing")
    assert limit.filter(later) and later.getMessage().endswith("(17 more like this dropped)")
    assert later.exc_info is not None  # a new window's first keeps its traceback


def test_logging_does_not_wait_for_a_stderr_nobody_reads() -> None:
    """A stderr that does not drain (a stalled journald, a full pipe) holds the thread that writes the
    lines, not the one that logged: 5,000 distinct warnings (far more than a pipe holds) are logged while
    nothing reads them, and every one is written once the pipe is read."""
    code = (
        "import logging, sys\n"
        "from clothd.logs import configure_logging\n"
        "configure_logging()\n"
        "for k in range(5000):\n"
        "    logging.getLogger(f'clothd.test{k}').warning('line %d of a long log', k)\n"
        "print('logged', flush=True)\n"
    )
    proc = subprocess.Popen(
        [sys.executable, "-c", code], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True
    )
    try:
        assert proc.stdout is not None
        ready, _, _ = select.select([proc.stdout], [], [], 60)  # a hang guard: blocked, it never comes
        assert ready and proc.stdout.readline() == "logged\n", "logging waited for stderr to be read"
        _, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    lines = err.splitlines()
    assert len(lines) == 5000 and lines[-1].endswith("line 4999 of a long log")
