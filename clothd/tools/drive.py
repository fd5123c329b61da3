"""`clothd drive SCRIPT.yaml`: play a drive script on a running daemon's cell, optionally recorded.

The script is checked here first (its schema, docs/api.md "Drive scripts"), then by the daemon, which
refuses it with the reason (422) when the cell cannot play it or it could carry the cloth out of the
workspace. A fault stops it as it stops a move; the recording is stopped either way.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path

import yaml
from pydantic import ValidationError

from clothd.config import yaml_problem
from clothd.core.drive_script import DriveScript
from clothd.errors import InputError
from clothd.tools.cell_client import CellClient


def load_script(path: Path) -> DriveScript:
    try:
        data = yaml.safe_load(path.read_text())
    except OSError as err:
        raise InputError(f"{path}: cannot read a drive script ({err.strerror})") from None
    except yaml.YAMLError as err:
        raise InputError(f"{path}: not valid YAML: {yaml_problem(err)}") from None
    try:
        return DriveScript.model_validate(data)
    except ValidationError as err:
        where = "; ".join(f"{'.'.join(map(str, e['loc']))}: {e['msg']}" for e in err.errors())
        raise InputError(f"{path}: {where}") from None


# The recording goes on this long after the drive has ended: the status reads idle as the stop is sent,
# while the frames taken up to then are still on their way (the camera's latency, a tick or two), and the
# commands.csv row of the stop is written with the next tick. Stopped at once, it lost the last 0.1 s.
RECORD_TAIL_S = 0.5


def drive(
    client: CellClient, script: DriveScript, record: str | None, sleep: Callable[[float], None] = time.sleep
) -> Path | None:
    """Play `script`, recording into `record` (a name inside the daemon's recording.dir) when given, up to
    RECORD_TAIL_S after its end; returns where it recorded."""
    where = client.record_start(record) if record is not None else None
    try:
        client.play(script)
        if where is not None:
            sleep(RECORD_TAIL_S)
    finally:
        if where is not None:
            client.record_stop()
    return where
