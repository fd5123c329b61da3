"""`clothd bench loop --hog`'s weighing of hwsim's session: the judged phase gives the simulated world's
session (its autogroup) the daemon's nice value, and every other phase puts it back as setsid made it."""

from __future__ import annotations

import subprocess
import sys

import pytest

from clothd.tools.bench_hog import SESSION_START_NICE, session_nice, weigh_session_as

pytestmark = pytest.mark.clock_free


def test_a_session_of_its_own_is_weighed_and_put_back() -> None:
    child = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"], start_new_session=True)
    try:
        assert session_nice(child.pid) == SESSION_START_NICE
        weigh_session_as(child.pid, 7)  # raising a nice value needs no privilege
        assert session_nice(child.pid) == 7
        weigh_session_as(child.pid, SESSION_START_NICE)
        assert session_nice(child.pid) == SESSION_START_NICE
    finally:
        child.kill()
        child.wait()
