"""The systemd unit says what the service needs: notify, watchdog, restart, and its devices."""

from __future__ import annotations

from pathlib import Path

import pytest

from clothd.config import LoopConfig

pytestmark = pytest.mark.clock_free

UNIT = Path(__file__).resolve().parent.parent / "deploy" / "clothd.service"


def _settings() -> dict[str, list[str]]:
    out: dict[str, list[str]] = {}
    for line in UNIT.read_text().splitlines():
        line = line.strip()
        if line and not line.startswith(("#", "[")):
            key, _, value = line.partition("=")
            out.setdefault(key, []).append(value)
    return out


def test_unit_is_a_notifying_watched_service_that_restarts() -> None:
    s = _settings()
    assert s["Type"] == ["notify"]
    assert s["Restart"] == ["on-failure"]
    assert s["WatchdogSec"] and s["WatchdogSec"][0].rstrip("s").isdigit()
    assert "clothd run --config" in s["ExecStart"][0]


def test_unit_is_hardened_but_reaches_serial_and_video() -> None:
    s = _settings()
    assert "PrivateDevices" not in s
    assert set(s["SupplementaryGroups"][0].split()) == {"dialout", "video"}
    allowed = {v.split()[0] for v in s["DeviceAllow"]}
    assert {"char-ttyACM", "char-ttyUSB", "char-video4linux"} <= allowed
    assert s["DevicePolicy"] == ["closed"] and s["NoNewPrivileges"] == ["yes"]
    assert s["ProtectSystem"] == ["strict"]


def test_unit_permits_the_priorities_the_daemon_takes() -> None:
    """The loop's thread, its session and the capture threads get what loop.* asks without root."""
    s, loop = _settings(), LoopConfig()
    assert int(s["Nice"][0]) == loop.nice
    assert 20 - int(s["LimitNICE"][0]) <= loop.nice  # a raw RLIMIT_NICE of n permits nice 20 - n
    assert int(s["LimitRTPRIO"][0]) >= loop.realtime_priority
