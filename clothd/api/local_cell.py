"""The cell served by a daemon in this process (api/cell.py's port): the API tests' app over a daemon
that is built and, in most of them, never started."""

from __future__ import annotations

from contextlib import AbstractContextManager
from pathlib import Path

import numpy as np

from clothd.api.bridge import DaemonBridge
from clothd.api.cell import CellSettings
from clothd.core.drive_script import DriveScript
from clothd.core.modes import Mode
from clothd.loop.daemon import Daemon


class LocalCell:
    """The cell served by a daemon in this process: each command runs on the daemon's loop (bridge.py)."""

    def __init__(self, daemon: Daemon, bridge: DaemonBridge | None = None) -> None:
        self.daemon = daemon
        self.bridge = bridge or DaemonBridge()
        self._settings = CellSettings.of(daemon.settings)

    @property
    def settings(self) -> CellSettings:
        return self._settings

    async def set_setpoint(self, mode: Mode, pose: np.ndarray | None, script: DriveScript | None) -> None:
        await self.bridge.call(self.daemon.set_setpoint, mode, pose, script)

    async def estop(self) -> None:
        await self.bridge.call(self.daemon.estop)

    async def estop_clear(self) -> None:
        await self.bridge.call(self.daemon.estop_clear)

    async def reset(self) -> None:
        await self.bridge.call(self.daemon.reset)

    async def start_recording(self, out: Path) -> Path:
        return await self.bridge.call(self.daemon.start_recording, out)

    async def stop_recording(self) -> None:
        await self.bridge.call(self.daemon.stop_recording)

    def watching(self) -> AbstractContextManager[None]:
        return self.daemon.view.watching()

    def latest_view(self) -> tuple[bytes | None, int]:
        return self.daemon.view.latest()
