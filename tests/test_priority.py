"""Nice values and scheduling classes are per thread (Linux): the Foxglove writer's thread lowers itself
without touching the loop's, a thread started by the real-time loop can leave its class, and a priority
that is not permitted is reported, not fatal. The session's nice value is the daemon's where it leads one."""

from __future__ import annotations

import logging
import os
import subprocess
import sys
import threading

import pytest

from clothd.drivers.priority import AUTOGROUP, claim_realtime, leave_realtime, set_thread_nice


def test_a_thread_lowers_only_its_own_priority() -> None:
    before = os.getpriority(os.PRIO_PROCESS, threading.get_native_id())
    seen: list[int] = []

    def lower() -> None:
        assert set_thread_nice(before + 5, "a test thread")
        seen.append(os.getpriority(os.PRIO_PROCESS, threading.get_native_id()))

    t = threading.Thread(target=lower)
    t.start()
    t.join()
    assert seen == [before + 5]
    assert os.getpriority(os.PRIO_PROCESS, threading.get_native_id()) == before


def test_a_priority_not_permitted_is_reported_and_the_thread_runs_on(
    monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    def refuse(which: int, who: int, prio: int) -> None:
        raise PermissionError(1, "Operation not permitted")

    monkeypatch.setattr(os, "setpriority", refuse)
    with caplog.at_level(logging.WARNING):
        assert not set_thread_nice(-10, "the loop")
    assert "the loop stays at nice" in caplog.text and "CAP_SYS_NICE" in caplog.text


def test_the_loop_claims_the_realtime_class_and_a_thread_it_starts_leaves_it_at_its_nice() -> None:
    seen: dict[str, object] = {}

    def served() -> None:  # as the Foxglove writer's thread does
        seen["inherited"] = os.sched_getscheduler(0)
        leave_realtime()
        seen["left"] = os.sched_getscheduler(0)
        seen["nice"] = os.getpriority(os.PRIO_PROCESS, threading.get_native_id())

    def loop() -> None:  # a thread of its own: the test's thread stays as it is
        assert set_thread_nice(-5, "the loop") and claim_realtime(3, "the loop")
        seen["loop"] = (os.sched_getscheduler(0), os.sched_getparam(0).sched_priority)
        t = threading.Thread(target=served)
        t.start()
        t.join()
        leave_realtime()

    t = threading.Thread(target=loop)
    t.start()
    t.join()
    assert seen == {
        "loop": (os.SCHED_FIFO, 3),
        "inherited": os.SCHED_FIFO,
        "left": os.SCHED_OTHER,
        "nice": -5,
    }
    assert os.sched_getscheduler(0) == os.SCHED_OTHER


def test_the_realtime_class_not_permitted_is_reported_and_priority_0_turns_it_off(
    monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    def refuse(pid: int, policy: int, param: os.sched_param) -> None:
        raise PermissionError(1, "Operation not permitted")

    monkeypatch.setattr(os, "sched_setscheduler", refuse)
    assert not claim_realtime(0, "the loop") and not caplog.text  # off: not even tried
    with caplog.at_level(logging.WARNING):
        assert not claim_realtime(20, "the loop")
    assert "the loop stays in the normal class" in caplog.text and "CPUSchedulingPolicy" in caplog.text


SESSION_NICE = """
import os, sys
from clothd.drivers.priority import AUTOGROUP, set_session_nice
print(set_session_nice(int(sys.argv[1])), (AUTOGROUP.read_text().split() or ["none"])[-1])
"""


def _session_nice(nice: int, own_session: bool) -> list[str]:
    """What set_session_nice(nice) answers in a fresh process, and its autogroup's nice after."""
    cmd = [sys.executable, "-c", SESSION_NICE, str(nice)]
    done = subprocess.run(cmd, capture_output=True, text=True, check=True, start_new_session=own_session)
    return done.stdout.split()


def test_the_daemon_weighs_its_own_session_against_other_programs_but_not_a_terminals() -> None:
    """Autogroups: the scheduler shares the CPU between sessions first, so a busy program in another
    session weighed as much as the whole daemon whatever its threads' nice values."""
    assert _session_nice(-7, own_session=True) == ["True", "-7"]
    # A process still in the session the machine booted with is in no autogroup: the file is empty.
    ours = (AUTOGROUP.read_text().split() or ["none"])[-1]
    assert _session_nice(-7, own_session=False) == ["False", ours]  # the test's session stays as it was
