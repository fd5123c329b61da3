"""What the firmware tests share: clothd's stepper link run against a controller on a port, and the
conformance kit's verdict judged without a wall-clock upper bound."""

from __future__ import annotations

import asyncio
import contextlib
import time
from collections.abc import AsyncIterator, Awaitable, Callable
from pathlib import Path
from typing import Any

from clothd.config import StepperConfig
from clothd.drivers.stepper_link import StepperLink
from clothd.tools.conformance_checks import WATCHDOG_MS

TIMED_CHECKS = {"watchdog.fault"}  # its upper bound is wall-clock: the kit's table reports it


async def until(check: Callable[[], bool], timeout_s: float = 3.0, poll_s: float = 0.01) -> float:
    """Wait for check(); returns the seconds it took."""
    start = time.monotonic()
    while not check():
        assert time.monotonic() - start < timeout_s, "condition not reached in time"
        await asyncio.sleep(poll_s)
    return time.monotonic() - start


@contextlib.asynccontextmanager
async def running(
    port: Path | str, n_modules: int, ack_timeout_s: float = 0.05
) -> AsyncIterator[StepperLink]:
    """clothd's stepper link on `port`, connected; stopped on leaving."""
    cfg = StepperConfig(
        port=str(port), reconnect_initial_s=0.05, reconnect_max_s=0.2, ack_timeout_s=ack_timeout_s
    )
    link = StepperLink(cfg, n_modules)
    task = asyncio.create_task(link.run())
    try:
        await until(lambda: link.connected)
        yield link
    finally:
        await link.stop()
        task.cancel()


def run(body: Awaitable[None], timeout_s: float = 10.0) -> None:
    asyncio.run(asyncio.wait_for(body, timeout_s))


def check_conformance(code: int, rows: list[dict[str, Any]]) -> None:
    """Every rule the kit checked holds. The watchdog's FAULT may come late on a loaded machine (a figure
    for the kit's table), never early: the test holds it to no sooner than the watchdog."""
    failed = {r["name"] for r in rows if r["passed"] is False}
    watchdog = next(r for r in rows if r["name"] == "watchdog.fault")
    assert float(str(watchdog["figure"]).removesuffix(" ms")) >= WATCHDOG_MS, watchdog
    assert failed <= TIMED_CHECKS, failed
    assert code == (1 if failed else 0)
