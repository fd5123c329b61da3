"""Several stepper controllers: `stepper.controllers` held to the cell (each module driven by exactly one,
refused beside `stepper.port`), the LinkGroup splitting each tick's commands by module and stopping every
controller when one is lost or reports a fault, and the daemon latching its own e-stop when a controller
reports its hardware e-stop chain opened (FAULT ESTOP_INPUT). hwsim's firmwares on ptys, one per
controller; the live run under `clothd run --sim` is tests/test_several_controllers.py."""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from firmware_links import until

from clothd.config import StepperConfig, parse_config
from clothd.core.messages import ModuleCommands
from clothd.drivers.link_group import LinkGroup
from clothd.drivers.ports import ControllerFault
from clothd.drivers.stepper_link import StepperLink
from clothd.errors import ConfigError
from hwsim.firmware_process import FirmwareProcess

N = 8
HALVES = [list(range(4)), list(range(4, 8))]


def _controllers(*entries: tuple[str, list[Any]]) -> dict[str, Any]:
    return {"stepper": {"controllers": [{"port": p, "modules": m} for p, m in entries]}}


def test_controllers_split_the_cell_each_in_its_own_numbering() -> None:
    cfg = parse_config(_controllers(("/dev/a", ["24-47"]), ("/dev/b", ["0-23"])))
    links = cfg.stepper.links(48)
    assert [(c.cfg.port, c.modules) for c in links] == [
        ("/dev/a", tuple(range(24, 48))),
        ("/dev/b", tuple(range(24))),
    ]
    assert links[0].cfg.controllers is None and links[0].cfg.baud == cfg.stepper.baud
    one = parse_config({"stepper": {"port": "/dev/x"}}).stepper.links(48)
    assert [(c.cfg.port, c.modules) for c in one] == [("/dev/x", tuple(range(48)))]


@pytest.mark.parametrize(
    ("data", "words"),
    [
        (
            {"stepper": {"port": "/dev/x", "controllers": [{"port": "/dev/a", "modules": ["0-47"]}]}},
            "stepper.port and stepper.controllers are both given",
        ),
        (
            _controllers(("/dev/a", ["0-24"]), ("/dev/b", ["24-47"])),
            "module 24 is driven by controllers 0 and 1",
        ),
        (_controllers(("/dev/a", ["0-22"]), ("/dev/b", ["24-47"])), "module(s) 23 driven by no controller"),
        (
            _controllers(("/dev/a", ["0-47", 48])),
            "stepper.controllers[0].modules: module 48 is not on the cell",
        ),
        (_controllers(("/dev/a", ["0-23"]), ("/dev/a", ["24-47"])), "stepper.controllers[1].port"),
        (_controllers(("/dev/a", [0, 0, "1-47"])), "module 0 is driven twice"),
    ],
)
def test_controllers_that_do_not_drive_each_module_once_are_refused(data: dict[str, Any], words: str) -> None:
    with pytest.raises(ConfigError) as err:
        parse_config(data)
    assert words in str(err.value)


@contextlib.asynccontextmanager
async def _group(tmp: Path) -> AsyncIterator[tuple[LinkGroup, list[FirmwareProcess]]]:
    firmwares = [
        FirmwareProcess(len(m), tmp / f"tty{k}", tmp / f"bus{k}.bin", np.array(m))
        for k, m in enumerate(HALVES)
    ]
    cfg = dict(reconnect_initial_s=0.05, reconnect_max_s=0.2)
    links = [
        (StepperLink(StepperConfig(port=str(f.link_path), **cfg), len(f.modules)), m)
        for f, m in zip(firmwares, HALVES, strict=True)
    ]
    group = LinkGroup(links, N)
    task = asyncio.create_task(group.run())
    try:
        await until(lambda: group.connected, 10)
        yield group, firmwares
    finally:
        await group.stop()
        task.cancel()
        for f in firmwares:
            f.stop()


def _speeds(firmwares: list[FirmwareProcess]) -> np.ndarray:
    out = np.zeros(N)
    for f in firmwares:
        table = f.bus._snapshot()  # the targets the firmware set, by its own index
        out[f.modules] = table[3 : 3 + len(f.modules)]
    return out


def test_each_controller_gets_its_modules_and_one_lost_stops_the_other(tmp_path: Path) -> None:
    async def body() -> None:
        async with _group(tmp_path) as (group, firmwares):
            speeds = np.linspace(0.01, 0.08, N)
            assert group.send_commands(ModuleCommands(speeds, np.zeros(N))).sent
            await until(lambda: np.allclose(_speeds(firmwares), speeds, atol=1e-4), 5)
            assert all(c.link.connected for c in group.controllers)
            firmwares[1].unplug(2.0)
            await until(lambda: not group.connected, 5)
            assert group.state == "disconnected"
            # Controller 0 was told all-stop as controller 1's link was lost, and is told so each tick after.
            await until(lambda: not np.any(_speeds(firmwares)[:4]), 5)
            assert group.send_commands(ModuleCommands(speeds, np.zeros(N))).stopped
            assert not np.any(_speeds(firmwares)[:4])
            await until(lambda: group.connected, 10)

    asyncio.run(asyncio.wait_for(body(), 30))


def test_a_controllers_fault_names_the_cells_module_and_the_estop_reaches_all(tmp_path: Path) -> None:
    async def body() -> None:
        async with _group(tmp_path) as (group, firmwares):
            seen: list[ControllerFault] = []
            group.on_fault = seen.append
            firmwares[1].report_fault(2, 1, "stalled")  # its module 1: the cell's module 5
            await until(lambda: bool(seen), 5)
            assert (seen[0].code, seen[0].module) == (2, 5) and "stalled" in seen[0].text
            assert list(group.faults) == seen and group.counters.faults == 1
            group.estop()
            assert group.estopped
            await until(lambda: all(f.counters()["estopped"] for f in firmwares), 5)
            await until(lambda: all(c.link.controller_estopped for c in group.controllers), 5)
            group.estop_clear()
            await until(lambda: not any(f.counters()["estopped"] for f in firmwares), 5)

    asyncio.run(asyncio.wait_for(body(), 30))
