"""The loop's share of a loaded cell PC's CPU.

On a 2-core PC a starting browser (many processes, page faults, disk) delayed the daemon enough for the
stepper link to time out and a move to be cancelled. What Linux offers, and what clothd takes:
- nice values (Linux's setpriority, per thread): the daemon's loop thread (tick and stepper link), the
  threads it starts and the compute process run at `loop.nice` (-10), so that the scheduler gives them
  ten times the CPU share of a program at 0 whenever both want it. The API's thread among them: it
  shares the GIL with the tick, and a thread preempted while it holds the GIL holds the tick too. At
  nice 0 beside two busy programs and a starting browser, it did (`clothd bench loop --hog 2`: 6 links
  lost, 2 of 10 moves arrived; at -10: 2 and 8). Raising a priority needs root, CAP_SYS_NICE or the
  systemd unit's `Nice=`; lowering one never does.
Not `mlockall`: it locks every mapped page, and Taichi maps a 1 GB arena, so the daemon's locked
memory went from 0 to 1.1 GB (VmLck) and its resident memory from 0.3 to 0.9 GB for pages that a cell PC
with room to spare never swaps out anyway.
Real-time scheduling (SCHED_FIFO) is not used: the compute runs for most of each tick, and a FIFO
thread that keeps a core busy starves everything else on it, the camera's driver threads included.
Each step that is not permitted is reported once, in words, and the daemon runs on.
"""

from __future__ import annotations

import logging
import os
import threading

log = logging.getLogger(__name__)


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
