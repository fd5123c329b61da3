"""hwsim's firmware in a process of its own: the drive bus between it and the world, and the clothd
stepper link driving a table through it."""

from __future__ import annotations

import asyncio
import math
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from clothd.config import StepperConfig
from clothd.core.messages import ModuleCommands
from clothd.drivers.stepper_link import StepperLink
from hwsim.drive_bus import DriveBus
from hwsim.firmware import COUNTERS
from hwsim.firmware_process import FirmwareProcess
from hwsim.scenario import TableSpec
from hwsim.table import Table


def _table() -> Table:
    return Table(TableSpec())


def test_targets_reach_the_table_once_and_a_cut_stops_it_at_once(tmp_path: Path) -> None:
    table = _table()
    n = table.n_modules
    firmware_side = DriveBus(tmp_path / "bus", n, create=True)
    world_side = DriveBus(tmp_path / "bus", n)
    heading = np.linspace(-1.0, 1.0, n)
    firmware_side.command(np.full(n, 9.0), heading)  # beyond the modules' top speed
    world_side.apply_to(table)
    np.testing.assert_allclose(table.cmd_speed_m_s, table.spec.max_speed_m_s)
    np.testing.assert_allclose(table.cmd_heading_rad, heading)
    # Targets are applied when they change, not over what the world itself commanded since.
    table.command(np.arange(n), 0.01, 0.0)
    world_side.apply_to(table)
    np.testing.assert_allclose(table.cmd_speed_m_s, 0.01)
    table.speed_m_s[:] = 0.05  # the modules run
    firmware_side.stop_all()  # the watchdog: a ramped stop, the belts still turning
    world_side.apply_to(table)
    assert not table.cmd_speed_m_s.any() and np.all(table.speed_m_s == 0.05)
    firmware_side.cut()  # the e-stop: drivers disabled
    world_side.apply_to(table)
    assert not table.speed_m_s.any()


def test_the_firmware_counters_cross_the_bus(tmp_path: Path) -> None:
    firmware_side = DriveBus(tmp_path / "bus", 4, create=True)
    world_side = DriveBus(tmp_path / "bus", 4)
    counters = dict.fromkeys(COUNTERS, 0) | {"estopped": True, "estop_t_mono_s": 12.5, "frames_ok": 7}
    counters["commands_at_estop"] = None
    firmware_side.publish(counters)
    assert world_side.counters() == counters


def test_clothd_drives_a_table_through_the_firmware_process(tmp_path: Path) -> None:
    """The link's commands, e-stop and its clearing reach the world's table through the process."""
    table = _table()
    n = table.n_modules
    firmware = FirmwareProcess(n, tmp_path / "ttyCELL", tmp_path / "drives.bin")

    async def until(check: Callable[[], bool], timeout_s: float = 5.0) -> None:
        deadline = time.monotonic() + timeout_s
        while not check():
            assert time.monotonic() < deadline, "condition not reached in time"
            firmware.bus.apply_to(table)  # what the world's thread does every step
            await asyncio.sleep(0.01)

    async def body() -> None:
        link = StepperLink(StepperConfig(port=str(firmware.link_path)), n)
        task = asyncio.create_task(link.run())
        try:
            await until(lambda: link.connected)
            await until(
                lambda: (
                    link.send_commands(ModuleCommands(np.full(n, 0.04), np.full(n, 0.5))).sent
                    and (abs(table.cmd_speed_m_s[0] - 0.04) < 1e-4)
                )
            )
            assert abs(table.cmd_heading_rad[-1] - 0.5) < 1e-3
            table.speed_m_s[:] = 0.04
            link.estop()
            await until(lambda: link.controller_estopped and not table.speed_m_s.any())
            counters = firmware.counters()
            assert counters["estopped"] and counters["commands_applied"] == counters["commands_at_estop"]
            assert isinstance(counters["estop_t_mono_s"], float) and math.isfinite(counters["estop_t_mono_s"])
            link.estop_clear()
            await until(lambda: not firmware.counters()["estopped"])
            await link.stop()
        finally:
            task.cancel()

    try:
        asyncio.run(asyncio.wait_for(body(), 30))
    finally:
        firmware.stop()
    assert firmware.process.returncode == 0  # it stopped when told, not killed
