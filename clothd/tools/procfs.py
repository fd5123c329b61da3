"""What a process holds, read from /proc (Linux): the benchmarks' memory and descriptor figures; and
stopping a process group the benches and tests started."""

from __future__ import annotations

import os
import signal
import subprocess
from pathlib import Path

STOP_WAIT_S = 20.0  # clothd run stops the modules, then its compute process and hwsim, in this time


def stop_group(proc: subprocess.Popen[bytes] | subprocess.Popen[str]) -> None:
    """SIGTERM to the process group `proc` leads (started with start_new_session), SIGKILL if it is not
    gone within STOP_WAIT_S."""
    if proc.poll() is not None:
        return
    os.killpg(proc.pid, signal.SIGTERM)
    try:
        proc.wait(timeout=STOP_WAIT_S)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait()


def spawned_children(pid: int) -> dict[int, str]:
    """The children of process `pid` that multiprocessing's spawn started, by pid: their names (comm)."""
    children: dict[int, str] = {}
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            parent = int((entry / "stat").read_text().rsplit(")", 1)[1].split()[1])
            spawned = b"spawn_main" in (entry / "cmdline").read_bytes()
            name = (entry / "comm").read_text().strip()
        except OSError:  # gone meanwhile
            continue
        if parent == pid and spawned:
            children[int(entry.name)] = name
    return children


def rss_mb(pid: int | str = "self") -> float:
    """Resident memory of the process, MB."""
    pages = int(Path(f"/proc/{pid}/statm").read_text().split()[1])
    return pages * os.sysconf("SC_PAGE_SIZE") / 1e6


def open_fds(pid: int | str = "self") -> int:
    """How many file descriptors the process has open."""
    return len(os.listdir(f"/proc/{pid}/fd"))
