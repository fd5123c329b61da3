"""`clothd bench loop --hog N`: the closed loop on a loaded PC, measured from outside.

`clothd run --sim` runs MOVES moves between two poses, one after another, while N busy processes at
normal priority (nice 0) keep the cores busy, and a headless browser (Debian's chromium, loading the
dashboard) is started BROWSER_STARTS times during the moves: many processes, memory and disk at once,
what cancelled moves on a 2-core cell PC. Counted: the stepper link's losses, the moves cancelled (a
halt before the move arrived), the moves that arrived, and the missed ticks.

Three times, each from a tracker started afresh, because on a real cell the stepper controller is a
microcontroller and the cloth and camera are not programs, while hwsim runs all three on the PC. First
with hwsim's firmware in the real-time class above the daemon's loop (the microcontroller that nothing
on the PC starves), as `clothd run --sim` starts it, and its world (the cloth and the camera, which no
load on the PC slows either) weighed by the bench as the daemon is: its session at the daemon's
session's nice value. The bars are judged on this: the physical parts keep their time, and the daemon
has what the world leaves it, less than a cell PC's whole CPU. Not the world in the real-time class:
its renders held a core for 30-50 ms at a time, and the kernel worker that carries a serial port's bytes
(in the normal class) waited behind them, on a cell PC that has no such program (docs/benchmarks.md).
What of the result is the simulator's: then with hwsim as `clothd run --sim` starts it (its threads at
the loop's nice value in a session of its own at 0, which weighs as much as a hog's), and last with every
thread of hwsim in the normal class at nice 0, beside the hogs.
"""

from __future__ import annotations

import contextlib
import math
import os
import shutil
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any, Literal

import httpx
from tqdm import tqdm

from clothd.tools.bench_loop import ANGLE_TOL_RAD, POS_TOL_M, DaemonProcess, free_port, pose_error

MOVES = 10
BROWSER_STARTS = 3
TARGETS = ((0.05, 0.03, 0.2), (-0.05, -0.03, -0.2))
MOVE_TIMEOUT_S = 20.0
# How a phase runs hwsim: as clothd run --sim starts it, with its world's session weighed as the daemon's,
# or every thread at nice 0.
HwsimAs = Literal["started", "world_weighted", "normal"]
SESSION_START_NICE = 0  # a session's nice value as setsid makes it (hwsim serve leads its own)
HOG_LIMIT_S = 600.0  # a hog ends by itself even if the bench is killed
BROWSER_FLAGS = (
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-quic",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
)


@contextlib.contextmanager
def hogs(n: int) -> Iterator[list[subprocess.Popen[bytes]]]:
    """n processes that keep a core busy each, at normal priority, for as long as the block runs."""
    code = f"import time\nend = time.monotonic() + {HOG_LIMIT_S}\nwhile time.monotonic() < end:\n    pass\n"
    procs = [subprocess.Popen([sys.executable, "-c", code]) for _ in range(n)]
    try:
        yield procs
    finally:
        for p in procs:
            p.kill()
            p.wait()


def start_browser(url: str, profile: Path) -> subprocess.Popen[bytes] | None:
    """Debian's chromium loading `url` headless (None when it is not installed)."""
    exe = shutil.which("chromium")
    if exe is None:
        return None
    cmd = [exe, *BROWSER_FLAGS, f"--user-data-dir={profile}", "--dump-dom", url]
    return subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)


def children(pid: int) -> list[int]:
    return [
        int(child)
        for tid in os.listdir(f"/proc/{pid}/task")
        for child in Path(f"/proc/{pid}/task/{tid}/children").read_text().split()
    ]


def hwsim_processes(daemon_pid: int) -> tuple[int, int, list[int]]:
    """The `hwsim serve` child of `clothd run --sim`, its firmware's process, and its cameras'."""
    for child in children(daemon_pid):
        if "hwsim.cli" in Path(f"/proc/{child}/cmdline").read_text():
            theirs = children(child)
            firmware = [
                c for c in theirs if "hwsim.firmware_process" in Path(f"/proc/{c}/cmdline").read_text()
            ]
            return child, firmware[0], [c for c in theirs if c not in firmware]
    raise RuntimeError("clothd run --sim has no hwsim serve child")


def to_normal_class(pid: int) -> None:
    """Every thread of the process (Linux's scheduling is per thread) in the normal class at nice 0."""
    for tid in os.listdir(f"/proc/{pid}/task"):
        with contextlib.suppress(ProcessLookupError):
            os.sched_setscheduler(int(tid), os.SCHED_OTHER, os.sched_param(0))
            os.setpriority(os.PRIO_PROCESS, int(tid), 0)


def session_nice(pid: int) -> int:
    """The nice value of the session (autogroup) the process belongs to."""
    return int(Path(f"/proc/{pid}/autogroup").read_text().split()[-1])


def weigh_session_as(pid: int, nice: int) -> None:
    """The process's session (its autogroup: hwsim serve leads its own) at `nice`."""
    Path(f"/proc/{pid}/autogroup").write_text(str(nice))


def scheduling_of(pid: int) -> str:
    """'SCHED_FIFO 40' or 'nice -10, session -10', for the process's main thread."""
    if os.sched_getscheduler(pid) == os.SCHED_FIFO:
        return f"SCHED_FIFO {os.sched_getparam(pid).sched_priority}"
    return f"nice {os.getpriority(os.PRIO_PROCESS, pid)}, session {session_nice(pid)}"


def _status(d: DaemonProcess) -> dict[str, Any]:
    return dict(httpx.get(f"{d.base}/api/v1/status", timeout=10).json())


def wait_ready(d: DaemonProcess, timeout_s: float) -> None:
    """Until the cloth is tracked with the link up (a move is refused otherwise), or the timeout."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        s = _status(d)
        if s["state"] == "tracking" and s["link"]["state"] == "connected":
            return
        time.sleep(0.2)


def run_move(d: DaemonProcess, target: tuple[float, float, float]) -> str:
    """'arrived', 'cancelled: <why>' (a refusal included) or 'timed out: <where truth and estimate stood>'."""
    wait_ready(d, MOVE_TIMEOUT_S)
    body = {"mode": "move", "x_m": target[0], "y_m": target[1], "theta_rad": target[2]}
    answer = httpx.put(f"{d.base}/api/v1/setpoint", json=body, timeout=10)
    if answer.status_code != 200:
        return f"cancelled: refused ({answer.status_code}): {answer.json().get('detail')}"
    deadline = time.monotonic() + MOVE_TIMEOUT_S
    while True:
        s = _status(d)
        if s["mode"] != "move":
            return f"cancelled: {s['halt_reason']}"
        dist, ang = pose_error(httpx.get(d.truth_url, timeout=10).json()["pose"], target)
        if dist < POS_TOL_M and ang < ANGLE_TOL_RAD:
            return "arrived"
        if time.monotonic() >= deadline:
            estimate = _estimate_off_by(s, target)
            return f"timed out: {_off_by(dist, ang)} by the truth, {estimate} by the estimate"
        time.sleep(0.1)


def _off_by(dist_m: float, angle_rad: float) -> str:
    return f"{dist_m * 1e3:.1f} mm, {math.degrees(angle_rad):.2f} deg off"


def _estimate_off_by(status: dict[str, Any], target: tuple[float, float, float]) -> str:
    pose = status.get("pose") or {}
    if pose.get("x_m") is None:
        return "none"
    return _off_by(*pose_error([pose["x_m"], pose["y_m"], pose["theta_rad"]], target))


def measure_phase(d: DaemonProcess, n_hogs: int, hwsim_as: HwsimAs = "started") -> dict[str, Any]:
    """hwsim_as: 'started' (as clothd run --sim starts it), 'world_weighted' or 'normal' (all at nice 0)."""
    # Each phase from a tracker started afresh on the still cloth, as the first: a lagging angle left by
    # one phase's browser starts is not the next phase's.
    httpx.post(f"{d.base}/api/v1/reset", timeout=10).raise_for_status()
    wait_ready(d, MOVE_TIMEOUT_S)
    world, firmware, cameras = hwsim_processes(d.proc.pid)
    # Each phase sets the session's weight afresh: the one before may have changed it.
    weigh_session_as(world, session_nice(d.proc.pid) if hwsim_as == "world_weighted" else SESSION_START_NICE)
    if hwsim_as == "normal":
        for pid in (world, firmware, *cameras):
            to_normal_class(pid)
    hwsim = f"world {scheduling_of(world)}, firmware {scheduling_of(firmware)}"
    before = _status(d)
    outcomes: list[str] = []
    browsers: list[subprocess.Popen[bytes]] = []
    start_at = {round(MOVES * (k + 0.5) / BROWSER_STARTS) for k in range(BROWSER_STARTS)}
    profiles_dir = tempfile.TemporaryDirectory(prefix="clothd-hog-browser-", ignore_cleanup_errors=True)
    with profiles_dir as profiles, hogs(n_hogs):
        for i in tqdm(range(MOVES), desc=f"moves, hwsim {hwsim}", disable=None, leave=False):
            if i in start_at:
                browser = start_browser(f"{d.base}/", Path(profiles) / str(i))
                if browser is not None:
                    browsers.append(browser)
            outcomes.append(run_move(d, TARGETS[i % 2]))
        for b in browsers:
            with contextlib.suppress(subprocess.TimeoutExpired):
                b.wait(timeout=30)
            if b.poll() is None:
                os.killpg(b.pid, 9)
                b.wait()
    after = _status(d)
    ticks = after["timing"]["ticks"] - before["timing"]["ticks"]
    missed = after["timing"]["missed_ticks"] - before["timing"]["missed_ticks"]
    return {
        "hwsim": hwsim,
        "hogs": n_hogs,
        "browser_starts": len(browsers),
        "moves": len(outcomes),
        "moves_arrived": outcomes.count("arrived"),
        "moves_cancelled": sum(o.startswith("cancelled") for o in outcomes),
        "moves_timed_out": sum(o.startswith("timed out") for o in outcomes),
        "halt_reasons": sorted({o.split(": ", 1)[1] for o in outcomes if o.startswith("cancelled")}),
        "timeouts": [o.split(": ", 1)[1] for o in outcomes if o.startswith("timed out")],
        "links_lost": after["link"]["counters"]["losses"] - before["link"]["counters"]["losses"],
        "missed_tick_pct": 100.0 * missed / max(ticks + missed, 1),
    }


def run_bench(n_hogs: int, config: Path | None = None) -> dict[str, Any]:
    """The bars' phase (hwsim's world weighed as the daemon) at the top level, the others under
    `hwsim_as_started` and `hwsim_at_normal_priority`."""
    d = DaemonProcess(config, free_port())
    try:
        d.wait_ready()
        wait_ready(d, 120)
        time.sleep(2.0)
        result = measure_phase(d, n_hogs, "world_weighted")
        result["hwsim_as_started"] = measure_phase(d, n_hogs)
        result["hwsim_at_normal_priority"] = measure_phase(d, n_hogs, "normal")
        result["daemon"] = scheduling_of(d.proc.pid)
        return result
    finally:
        d.stop()


def format_result(r: dict[str, Any]) -> str:
    def phase(p: dict[str, Any], what: str) -> list[str]:
        reasons = "; ".join(p["halt_reasons"]) or "none"
        return [
            f"  {what}: {p['moves_arrived']} of {p['moves']} moves arrived, "
            f"{p['moves_cancelled']} cancelled, {p['moves_timed_out']} timed out; "
            f"links lost {p['links_lost']}; missed ticks {p['missed_tick_pct']:.3f} %",
            f"    {p['hogs']} hogs at nice 0, the browser started {p['browser_starts']} times",
            f"    halts: {reasons}",
            *(f"    timed out: {t}" for t in p["timeouts"]),
        ]

    bars = "bars: 0 links lost, 0 moves cancelled, missed ticks <= 0.5 %"
    return "\n".join(
        [
            f"clothd bench loop --hog {r['hogs']} (the daemon's loop at {r['daemon']}; {bars})",
            *phase(r, f"hwsim as the cell's physical parts ({r['hwsim']})"),
            *phase(r["hwsim_as_started"], "hwsim as clothd run --sim starts it (the simulator's share)"),
            *phase(r["hwsim_at_normal_priority"], "hwsim at nice 0, beside the hogs (the simulator's share)"),
        ]
    )
