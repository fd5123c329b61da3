"""Request and response bodies of the API (pydantic): validation at the edge and the OpenAPI schema. The
status's models are clothd/loop/status.py's."""

from __future__ import annotations

import math
from typing import Annotated, Literal

from pydantic import BaseModel, ConfigDict, Field

from clothd.core.drive_script import DriveScript
from clothd.core.modes import Mode


class _Strict(BaseModel):
    # Strict: `true` is not a number and "1" is not a float, whatever Python would make of them.
    model_config = ConfigDict(extra="forbid", strict=True)


class IdleSetpoint(_Strict):
    """Stop every module."""

    mode: Literal[Mode.IDLE]


class HoldSetpoint(_Strict):
    """Keep the pose the cloth has now."""

    mode: Literal[Mode.HOLD]


class MoveSetpoint(_Strict):
    """Move the cloth to this pose (world frame, the table plane) within the speed limits."""

    mode: Literal[Mode.MOVE]
    x_m: float = Field(ge=-5, le=5, allow_inf_nan=False)
    y_m: float = Field(ge=-5, le=5, allow_inf_nan=False)
    theta_rad: float = Field(ge=-math.pi, le=math.pi, allow_inf_nan=False)


class FlattenSetpoint(_Strict):
    """Flatten the cloth where it lies, holding its pose (needs the mesh tracker)."""

    mode: Literal[Mode.FLATTEN]


class DriveSetpoint(_Strict):
    """Play a drive script: chosen modules driven over time (docs/api.md, "Drive scripts")."""

    mode: Literal[Mode.DRIVE]
    script: DriveScript


class FlowSetpoint(_Strict):
    """Take pieces in, flatten and place each at flow.placement, and drive it out (docs/flow.md)."""

    mode: Literal[Mode.FLOW]


SetpointRequest = Annotated[
    IdleSetpoint | HoldSetpoint | MoveSetpoint | FlattenSetpoint | DriveSetpoint | FlowSetpoint,
    Field(discriminator="mode"),
]


# A name, or a relative path of names, each starting with a letter or digit: nothing absolute, no "."
# or ".." step. The daemon still resolves it and keeps it inside recording.dir (symlinks).
RECORDING_NAME = r"^[A-Za-z0-9][A-Za-z0-9._-]{0,63}(/[A-Za-z0-9][A-Za-z0-9._-]{0,63}){0,7}$"


class RecordStart(_Strict):
    dir: str | None = Field(
        None,
        pattern=RECORDING_NAME,
        description="a new directory inside recording.dir, by name or relative path; default: dated",
    )


class CameraInfo(BaseModel):
    width: int
    height: int
    table_to_pixel: list[list[float]] = Field(description="3 x 3 homography: table [x_m, y_m, 1] to pixels")


class AccessInfo(BaseModel):
    token_required: bool = Field(description="every change (the e-stop too) needs Authorization: Bearer")


class OutfeedPiece(BaseModel):
    """One piece hwsim's outfeed judged from its truth as it crossed the +x edge (hwsim/outfeed.py); hwsim
    may add keys."""

    model_config = ConfigDict(extra="allow")

    id: int = Field(description="hwsim's own numbering, in the order laid (not the daemon's piece id)")
    flap: bool = Field(description="laid with a corner folded over: it should leave as a reject")
    t_s: float = Field(description="time in the cell, from laid at the infeed to reaching the outfeed")
    max_height_mm: float = Field(description="its true highest node")
    pose_error_mm: float = Field(
        description="its centre's distance across the outfeed from the placement's y"
    )
    pose_error_deg: float = Field(description="its heading's distance from the placement's")


class ErrorResponse(BaseModel):
    detail: str = Field(description="what was wrong, in words")


class Ok(BaseModel):
    ok: bool = True
    detail: str = ""
