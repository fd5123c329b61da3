"""The loop's share of a loaded cell PC's CPU.

On a 2-core PC two busy programs and a starting browser delayed the daemon enough for the stepper link
to time out, a move to be cancelled and the tracked angle to lag the cloth's. What Linux offers, and
what clothd takes (docs/deploy.md, "A loaded cell PC", has the figures):
- The real-time class (SCHED_FIFO at `loop.realtime_priority`) for the loop's thread: the tick, the
  stepper link's reads, writes and retransmits, and the thread that takes the compute's replies. No
  program in the normal class can delay them, however busy; they wait most of each tick, and the
  kernel's real-time throttle (95 % of each second) still bounds a fault that spins.
- Not for the compute process (but for its cameras' capture threads, below), nor what serves people
  (the API process, HTTP and OPC UA; the Foxglove writer): they leave the class as they start. The compute
  keeps a core busy for much of each tick, and the serial port's bytes pass through a kernel worker in
  the normal class (a pty's and a USB port's alike): a compute above that worker starved it, and the
  link timed out with no other program busy. A flood of requests must not take a core from the loop
  either. They all keep the loop's nice value.
- nice values (Linux's setpriority, per thread): `loop.nice` (-10), ten times the CPU share of a
  program at 0, for the loop's threads, the compute and the API process: an operator's e-stop request
  finds a core on a busy PC.
- The session's nice value (Linux's autogroup, /proc/self/autogroup): where no cgroup CPU controller
  places the daemon (a PC whose systemd does not enable it, a container, a terminal), the scheduler first
  shares the CPU between sessions, each weighted by that value, and only within a session by the threads'
  nice values. At 0 a busy program started from a terminal weighed as much as the whole daemon, whatever
  its threads' nice. The daemon sets it to `loop.nice` when it leads its session (a systemd service does;
  `clothd run` from a terminal shares the terminal's, which is its user's to set). Under a cgroup CPU
  controller the unit's `CPUWeight=` does this instead.
- The cameras' capture threads in the real-time class, just below the loop's thread: a frame is stamped
  as it arrives, and a capture thread held up by a busy PC stamped a backlog of frames 1 ms apart that
  the camera took 67 ms apart. Their work is bounded by the frame rate (a read and a decode a frame).
Raising a priority or entering the real-time class needs root, CAP_SYS_NICE or the systemd unit's
`Nice=`/`CPUSchedulingPolicy=`; lowering one never does.
Not `mlockall`: it locks every mapped page, and Taichi maps a 1 GB arena, so the daemon's locked
memory went from 0 to 1.1 GB (VmLck) and its resident memory from 0.3 to 0.9 GB for pages that a cell PC
with room to spare never swaps out anyway.
Each step that is not permitted is reported once, in words, and the daemon runs on.
"""

from __future__ import annotations

import logging
import os
import sys
import threading
from pathlib import Path

log = logging.getLogger(__name__)

AUTOGROUP = Path("/proc/self/autogroup")
GIL_SWITCH_S = 0.001  # Python's default is 5 ms


def bound_gil_wait() -> None:
    """A thread that wants the GIL waits at most GIL_SWITCH_S while another of the process's threads runs
    Python: the daemon's tick beside its link and reply threads, the compute's tracking beside the second
    view's heights (clothd/core/second_view.py)."""
    sys.setswitchinterval(GIL_SWITCH_S)


def set_thread_nice(nice: int, what: str) -> bool:
    """Give the calling thread (only it) this nice value; False, and a log line, when not permitted."""
    tid = threading.get_native_id()
    try:
        os.setpriority(os.PRIO_PROCESS, tid, nice)
    except PermissionError:
        now = os.getpriority(os.PRIO_PROCESS, tid)
        log.warning(
            "%s stays at nice %d: nice %d needs root, CAP_SYS_NICE or the unit's Nice= (docs/deploy.md)",
            what,
            now,
            nice,
        )
        return False
    return True


def set_session_nice(nice: int) -> bool:
    """Give the daemon's session (its autogroup) this nice value when the daemon leads it; False, and a
    log line where that is not done."""
    if not AUTOGROUP.exists():  # a kernel without autogroups: cgroups or the threads' nice values decide
        return False
    if os.getsid(0) != os.getpid():
        log.info(
            "the daemon shares its session's CPU share with the programs started beside it (a shell, make): "
            "as a service, or started by setsid itself, it gets its own (docs/deploy.md)"
        )
        return False
    try:
        AUTOGROUP.write_text(str(nice))
    except PermissionError:
        log.warning("the daemon's session stays at its nice value: nice %d needs root or CAP_SYS_NICE", nice)
        return False
    return True


def claim_realtime(priority: int, what: str) -> bool:
    """Put the calling thread (only it) in the real-time class at `priority`; the threads and processes it
    starts afterwards inherit it. False, and a log line, when not permitted; False at priority 0."""
    if priority == 0:
        return False
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
    except PermissionError:
        log.warning(
            "%s stays in the normal class: SCHED_FIFO needs root, CAP_SYS_NICE or the unit's "
            "CPUSchedulingPolicy= (docs/deploy.md)",
            what,
        )
        return False
    return True


def leave_realtime() -> None:
    """Put the calling thread in the normal class, at the nice value it already has (a thread inherits
    its starter's): for a thread that serves people and was started by the loop's."""
    if os.sched_getscheduler(0) != os.SCHED_OTHER:
        os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
