"""`hwsim serve --exit-with-parent` (as `clothd run --sim` starts it) ends when its parent is killed with
-9, instead of running the cell on its own."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import textwrap
from pathlib import Path

from live_cell import wait

PARENT = textwrap.dedent(
    """
    import subprocess, sys, time
    child = subprocess.Popen(
        [sys.executable, "-m", "hwsim.cli", "serve", "--exit-with-parent", "--state-dir", sys.argv[1]]
    )
    print(json.dumps({"hwsim_pid": child.pid}), flush=True)
    time.sleep(600)
    """
).replace("import subprocess", "import json, subprocess")


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    try:  # a zombie (not yet reaped by init) is gone too
        state = Path(f"/proc/{pid}/stat").read_text().split(") ", 1)[1][0]
    except FileNotFoundError:
        return False
    return state != "Z"


def test_hwsim_serve_stops_when_its_parent_is_killed(tmp_path: Path) -> None:
    parent = subprocess.Popen(
        [sys.executable, "-c", PARENT, str(tmp_path)], stdout=subprocess.PIPE, stderr=subprocess.DEVNULL
    )
    assert parent.stdout is not None
    hwsim_pid = 0
    try:
        for line in parent.stdout:  # the parent's line, then hwsim's ready line (its stdout is inherited)
            if line.startswith(b"{"):
                info = json.loads(line)
                hwsim_pid = info.get("hwsim_pid", hwsim_pid)
                if "serial" in info:
                    break
        assert hwsim_pid and _alive(hwsim_pid)
        os.kill(parent.pid, signal.SIGKILL)
        parent.wait()
        took = wait(lambda: not _alive(hwsim_pid), 20, "hwsim ended after its parent was killed")
        print(f"hwsim ended {took:.2f} s after its parent was killed with -9")
    finally:
        if parent.poll() is None:
            parent.kill()
        if hwsim_pid and _alive(hwsim_pid):
            os.kill(hwsim_pid, signal.SIGKILL)
