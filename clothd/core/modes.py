"""The cell's modes and the loop's states, named once for the daemon, the API, OPC UA and the metrics.

String enums: they compare equal to, and serialise as, the words the API and docs/api.md use.
"""

from __future__ import annotations

from enum import StrEnum


class Mode(StrEnum):
    """What the cell is asked to do (the setpoint's mode)."""

    IDLE = "idle"  # every module stopped
    HOLD = "hold"  # keep the pose the cloth had when it began
    MOVE = "move"  # bring the cloth to a pose
    FLATTEN = "flatten"  # hold, and take the slack out (the mesh tracker)
    DRIVE = "drive"  # play a drive script
    FLOW = "flow"  # take pieces in, flatten and place each, and let them go (core/flow.py)


class LoopState(StrEnum):
    """What the loop can do now."""

    STARTING = "starting"  # no frame tracked yet since the start
    TRACKING = "tracking"
    TRACKING_LOST = "tracking_lost"  # frames arrive, the cloth is not tracked in them
    CAMERA_LOST = "camera_lost"  # no frame for camera.stale_after_s
    FAULT = "fault"  # the compute failed, or the loop stopped on a fault


class FlatnessBasis(StrEnum):
    """What a flatness reading rests on."""

    MEASURED = "measured"  # a second view measured the surface's heights when tracking began
    SINCE_START = "since_start"  # one view: only slack gained since tracking began can be seen


class PieceState(StrEnum):
    """Where a piece of the production flow is (core/pieces.py, core/flow.py)."""

    ENTERING = "entering"  # coming in over the infeed edge: not all of it in the workspace yet
    TRACKED = "tracked"  # all in and stilled; its tracking is starting
    FLATTENING = "flattening"  # held where it is while its slack is taken out
    PLACING = "placing"  # brought to the placement
    LEAVING = "leaving"  # placed, and driven out over the outfeed edge
    LEFT = "left"  # gone to the next station
    REJECTED = "rejected"  # cannot be flattened or placed: driven out and reported, with the reason
