"""Nice values are per thread (Linux): the API's thread lowers itself without touching the loop's, and a
priority that is not permitted is reported, not fatal."""

from __future__ import annotations

import logging
import os
import threading

import pytest

from clothd.priority import set_thread_nice


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
