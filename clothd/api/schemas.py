"""Request and response bodies of the API (pydantic): validation at the edge and the OpenAPI schema."""

from __future__ import annotations

import math
from typing import Annotated, Literal

from pydantic import BaseModel, ConfigDict, Field


class _Strict(BaseModel):
    # Strict: `true` is not a number and "1" is not a float, whatever Python would make of them.
    model_config = ConfigDict(extra="forbid", strict=True)


class IdleSetpoint(_Strict):
    """Stop every module."""

    mode: Literal["idle"]


class HoldSetpoint(_Strict):
    """Keep the pose the cloth has now."""

    mode: Literal["hold"]


class MoveSetpoint(_Strict):
    """Move the cloth to this pose (world frame, the table plane) within the speed limits."""

    mode: Literal["move"]
    x_m: float = Field(ge=-5, le=5)
    y_m: float = Field(ge=-5, le=5)
    theta_rad: float = Field(ge=-math.pi, le=math.pi)


SetpointRequest = Annotated[IdleSetpoint | HoldSetpoint | MoveSetpoint, Field(discriminator="mode")]


class Pose(BaseModel):
    x_m: float | None
    y_m: float | None
    theta_rad: float | None


class PoseWithCovariance(Pose):
    cov: list[list[float | None]] = Field(description="3 x 3 over (x_m, y_m, theta_rad)")


class Mesh(BaseModel):
    nx: int
    ny: int
    nodes_m: list[list[float]] = Field(description="ny*nx rows of [x, y, z], row by row, world frame")


class Residual(BaseModel):
    mean_px: float | None
    worst_px: float | None


class Window(BaseModel):
    mean_ms: float | None
    p50_ms: float | None
    p99_ms: float | None
    max_ms: float | None


class Timing(BaseModel):
    ticks: int
    missed_ticks: int
    missed_pct: float
    compute_overruns: int = Field(description="ticks sent with the previous commands: compute not done")
    stages: dict[str, Window]
    jitter: Window
    frame_to_command: Window


class CameraState(BaseModel):
    state: str
    healthy: bool
    source: str
    last_error: str | None
    reconnects: int


class LinkCounters(BaseModel):
    sent: int
    retransmitted: int
    acked: int
    invalid: int
    nacked: int
    faults: int
    reconnects: int
    rtt_p50_ms: float | None
    rtt_p99_ms: float | None


class LinkState(BaseModel):
    state: str
    port: str
    firmware: str | None
    last_error: str | None
    controller_estop: bool
    counters: LinkCounters


class FaultReport(BaseModel):
    t_unix_s: float
    code: int
    module: int
    text: str


class Recording(BaseModel):
    active: bool
    dir: str | None
    frames: int
    bytes: int
    max_bytes: int
    stopped_reason: str | None = Field(description="why it stopped: a request, the size limit, a full disk")


class RecordStart(_Strict):
    dir: str | None = Field(
        None, min_length=1, max_length=1024, description="a new directory; default: dated"
    )


class StatusResponse(BaseModel):
    t_unix_s: float
    state: str = Field(description="starting | tracking | tracking_lost | camera_lost | fault")
    mode: Literal["idle", "hold", "move"]
    setpoint: Pose | None
    estop: bool
    pose: PoseWithCovariance | None
    mesh: Mesh | None
    features: int = Field(description="features measured and accepted in the last frame")
    rejected_features: int = Field(description="rejected by the filter's gate in the last frame")
    residual: Residual
    timing: Timing
    camera: CameraState
    link: LinkState
    faults: list[FaultReport]
    recording: Recording | None


class CameraInfo(BaseModel):
    width: int
    height: int
    table_to_pixel: list[list[float]] = Field(description="3 x 3 homography: table [x_m, y_m, 1] to pixels")


class ErrorResponse(BaseModel):
    detail: str = Field(description="what was wrong, in words")


class Ok(BaseModel):
    ok: bool = True
    detail: str = ""
