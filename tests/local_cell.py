"""The cell served by a daemon in the test's own process (clothd/api/cell.py's port): the API tests' app
and OPC UA server over a daemon that is built and, in most of them, never started. Each command runs at
once, on the test's loop; `clothd run` serves the port from its API process instead
(clothd/api/remote_cell.py)."""

from __future__ import annotations

from contextlib import AbstractContextManager
from pathlib import Path

import numpy as np

from clothd.api.cell import CellSettings
from clothd.core.drive_script import DriveScript
from clothd.core.modes import Mode
from clothd.loop.daemon import Daemon
from clothd.outputs.recorder import make_recording_place, remove_recording_place


class LocalCell:
    def __init__(self, daemon: Daemon) -> None:
        self.daemon = daemon
        self._settings = CellSettings.of(daemon.settings)

    @property
    def settings(self) -> CellSettings:
        return self._settings

    async def set_setpoint(self, mode: Mode, pose: np.ndarray | None, script: DriveScript | None) -> None:
        self.daemon.set_setpoint(mode, pose, script)

    async def estop(self) -> None:
        self.daemon.estop()

    async def estop_clear(self) -> bool:
        return self.daemon.estop_clear()

    async def reset(self) -> None:
        self.daemon.reset()

    async def start_recording(self, out: Path) -> Path:
        out = make_recording_place(out, self.settings.recording_format)
        try:
            self.daemon.start_recording(out)
        except Exception:
            remove_recording_place(out)
            raise
        return out

    async def stop_recording(self) -> None:
        self.daemon.stop_recording()

    def watching(self) -> AbstractContextManager[None]:
        return self.daemon.view.watching()

    def latest_view(self) -> tuple[bytes | None, int]:
        return self.daemon.view.latest()
