"""What the APIs need of the cell: its commands, the few settings the routes read, and the annotated view.
The HTTP app (app.py), the commands (commands.py) and through them the OPC UA server depend on this port,
not on the daemon. The API process serves it over its channel to the daemon (remote_cell.py);
the API tests serve it over a daemon in their own process (tests/local_cell.py).

Every command runs on the daemon's loop and returns once it has; a refusal is raised as the daemon
raised it (a ClothdError), which each API maps to its own codes.
"""

from __future__ import annotations

from contextlib import AbstractContextManager
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Protocol

import numpy as np

from clothd.config import RecordingFormat
from clothd.core.drive_script import DriveScript
from clothd.core.modes import Mode

if TYPE_CHECKING:  # not imported in the API process, which has no daemon (nor its compute's Taichi)
    from clothd.loop.daemon_settings import DaemonSettings


@dataclass(frozen=True)
class CellSettings:
    """The daemon's settings that the routes read."""

    recording_format: RecordingFormat
    recording_dir: Path  # where POST /record/start puts recordings
    view_period_s: float  # the annotated view's frame interval

    @classmethod
    def of(cls, settings: DaemonSettings) -> CellSettings:
        return cls(settings.recording_format, settings.recording_dir, settings.view_period_s)


class Cell(Protocol):
    @property
    def settings(self) -> CellSettings: ...

    async def set_setpoint(self, mode: Mode, pose: np.ndarray | None, script: DriveScript | None) -> None:
        """Daemon.set_setpoint."""

    async def estop(self) -> None: ...

    async def estop_clear(self) -> bool:
        """Daemon.estop_clear: whether an e-stop was latched."""

    async def reset(self) -> None: ...

    async def start_recording(self, out: Path) -> Path:
        """The recording's place made (`make_recording_place`), then Daemon.start_recording: where it
        records."""

    async def stop_recording(self) -> None: ...

    def watching(self) -> AbstractContextManager[None]:
        """Someone watches the annotated view while this is entered: the daemon draws it only then."""

    def latest_view(self) -> tuple[bytes | None, int]:
        """The newest annotated view (JPEG) and its number (0 before the first)."""
