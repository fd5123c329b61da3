"""The daemon's status: what GET /api/v1/status returns and the WebSocket pushes, as typed models.

These models are the status's one definition: the daemon builds a `Status` once per tick and serialises
it once (non-finite numbers become null), and the API documents the same models in its OpenAPI schema.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import asdict
from typing import Any, Literal

import numpy as np
from pydantic import BaseModel, Field

from clothd.config import RecordingFormat
from clothd.config.camera import default_camera_name
from clothd.core.control import Setpoint
from clothd.core.flatness import Flatness
from clothd.core.messages import Estimate, ModuleCommands
from clothd.core.modes import FlatnessBasis, LoopState, Mode, PieceState
from clothd.core.pieces import PieceReport
from clothd.drivers.link_group import LinkGroup
from clothd.drivers.ports import RATE_WINDOW_S, FrameSourceHealth, ModuleLink
from clothd.loop.pairing import CameraReport, PairingStats
from clothd.outputs.recorder import RecordingStatus

NODE_DECIMALS = 5  # 10 µm: the status carries the mesh, not the filter's noise


class Pose(BaseModel):
    x_m: float | None
    y_m: float | None
    theta_rad: float | None

    @classmethod
    def of(cls, pose: np.ndarray) -> Pose:
        return cls(x_m=pose[0], y_m=pose[1], theta_rad=pose[2])


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


class LatencyTail(BaseModel):
    """Why the slowest frames were slow: each part's mean over the frames at or above the 95th percentile
    of frame-to-command (clothd/loop/loop_stats.py FrameToCommand). wait + compute + delivery is the whole."""

    frames: int
    wait_ms: float | None = Field(description="from the frame's arrival until the compute began on it")
    compute_ms: float | None
    delivery_ms: float | None = Field(description="from the compute's reply to the commands sent")
    tick_ms: float | None = Field(
        description="how long the frame waited for its tick to ask (overlaps compute when tracked ahead)"
    )


class Timing(BaseModel):
    ticks: int
    missed_ticks: int
    missed_pct: float
    compute_overruns: int = Field(description="ticks sent with the previous commands: compute not done")
    starved_restarts: int = Field(
        0, description="times the tracker started afresh after the daemon was silent past loop.starved_ms"
    )
    frame_locked: bool = Field(
        False,
        description="the tick's phase follows the camera's frames (loop.frame_lock, docs/architecture.md)",
    )
    stages: dict[str, Window]
    jitter: Window
    frame_to_command: Window
    frame_to_command_tail: LatencyTail = LatencyTail(
        frames=0, wait_ms=None, compute_ms=None, delivery_ms=None, tick_ms=None
    )
    gc_pause: Window = Field(
        Window(mean_ms=None, p50_ms=None, p99_ms=None, max_ms=None),
        description="full garbage collections in the daemon's process: the tick waits them out",
    )


FPS_DOC = f"frames that arrived per second over the last {RATE_WINDOW_S:g} s; null before two"
GAP_DOC = "the longest wait between two of those frames: a camera dropping frames shows here first"


class CameraState(BaseModel):
    state: str
    healthy: bool
    source: str
    last_error: str | None
    reconnects: int
    fps: float | None = Field(None, description=FPS_DOC)
    longest_gap_ms: float | None = Field(None, description=GAP_DOC)


class CameraEntry(BaseModel):
    """One camera of `cameras:` (the first is also `camera`)."""

    name: str
    source: str = Field(description="as configured, a URL's credentials shown as ***")
    state: str = Field(description="connecting | streaming | lost")
    healthy: bool = Field(description="a frame fresher than camera.stale_after_s is there")
    last_error: str | None
    reconnects: int
    fps: float | None = Field(None, description=FPS_DOC)
    longest_gap_ms: float | None = Field(None, description=GAP_DOC)
    skew_ms: float | None = Field(
        description="median over recent pairs of this camera's frame time minus the first camera's "
        "(arrival, host monotonic); null for the first camera and before any pair"
    )
    skew_p95_ms: float | None = Field(description="95th percentile of the skew's magnitude; null likewise")
    paired_pct: float | None = Field(
        description="share of the first camera's recent frames this one had a frame within "
        "tracker.stereo.max_skew_ms of; null for the first camera"
    )


class LinkCounters(BaseModel):
    sent: int
    retransmitted: int
    acked: int
    invalid: int
    nacked: int
    faults: int
    reconnects: int
    losses: int
    rtt_p50_ms: float | None
    rtt_p99_ms: float | None


class LinkState(BaseModel):
    state: str
    port: str
    firmware: str | None
    last_error: str | None
    controller_estop: bool
    counters: LinkCounters


class ControllerLinkState(LinkState):
    modules: list[int] = Field(description="the cell's module ids it drives, by its own index 0..k-1")


def link_states(link: ModuleLink, link_port: str) -> tuple[LinkState, list[ControllerLinkState]]:
    """The link taken together (every controller's: its state connected only when every one is, its
    counters summed; the first controller's port) and each controller's own."""

    def state(one: ModuleLink, port: str) -> dict[str, Any]:
        counters = LinkCounters.model_validate(one.counters.snapshot())
        return dict(
            state=one.state,
            port=port,
            firmware=one.firmware,
            last_error=one.last_error,
            controller_estop=one.controller_estopped,
            counters=counters,
        )

    controllers = link.controllers if isinstance(link, LinkGroup) else []
    each = [ControllerLinkState(**state(c.link, c.port), modules=c.modules.tolist()) for c in controllers]
    first_port = controllers[0].port if controllers else link_port
    return LinkState(**state(link, first_port)), each


class Modules(BaseModel):
    speed_m_s: list[float] = Field(description="each module's belt speed in force, by module id")
    heading_rad: list[float] = Field(description="each module's heading in force, by module id")


class FaultReport(BaseModel):
    t_unix_s: float
    code: int
    module: int
    text: str


class Recording(BaseModel):
    active: bool
    dir: str | None = Field(description="the recording's directory, or its .mcap file (format mcap)")
    frames: int
    bytes: int
    max_bytes: int
    stopped_reason: str | None = Field(description="why it stopped: a request, the size limit, a full disk")
    format: RecordingFormat = Field(description="recording.format")
    dropped_frames: int = Field(
        description="new frames left out because the MCAP writer was behind (always 0 for directory)"
    )


class RidgeState(BaseModel):
    x_m: float = Field(
        description="world position of its highest point (measured: its highest quad's centre)"
    )
    y_m: float
    direction_rad: float = Field(description="the direction its line runs in, world, [0, π)")
    height_mm: float
    area_m2: float = Field(description="rest area of the compressed quads it covers")


class FlapState(BaseModel):
    kind: Literal["flap"] = "flap"
    x_m: float = Field(description="world position of the middle of the cloth missing where it folded over")
    y_m: float
    area_m2: float = Field(description="rest area of the mesh quads not seen")


class FlatnessState(BaseModel):
    max_height_mm: float = Field(
        description="the highest point of the estimate: a node, or the cloth over a folded edge between two"
    )
    compressed_area_pct: float = Field(description="share of the mesh quads that hold slack")
    flat: bool = Field(
        description="with hysteresis: on below control.flatness's bars, off past twice them; off with a flap"
    )
    ridges: list[RidgeState] = Field(description="highest first")
    flaps: list[FlapState] = Field(description="folded-over corners or edges, largest first; not pulled")
    basis: FlatnessBasis = Field(
        description="measured: a second view measured the heights when tracking began, so wrinkles a piece "
        "arrived with count; since_start: one view, only slack gained since tracking began is seen"
    )

    @classmethod
    def of(cls, f: Flatness) -> FlatnessState:
        return cls(
            basis=f.basis,
            max_height_mm=f.max_height_m * 1e3,
            compressed_area_pct=f.compressed_area_pct,
            flat=f.flat,
            ridges=[
                RidgeState(
                    x_m=r.position_m[0],
                    y_m=r.position_m[1],
                    direction_rad=r.direction_rad,
                    height_mm=r.height_m * 1e3,
                    area_m2=r.area_m2,
                )
                for r in f.ridges
            ],
            flaps=[FlapState(x_m=p.position_m[0], y_m=p.position_m[1], area_m2=p.area_m2) for p in f.flaps],
        )


class PieceStatus(BaseModel):
    """One piece of the production flow (docs/flow.md)."""

    id: int
    state: PieceState
    pose: Pose | None = Field(description="while tracked")
    flat: bool | None = Field(description="null until its flatness is read")
    max_height_mm: float | None
    reason: str | None = Field(description="why it was rejected")
    found_t_mono_s: float = Field(description="first seen, on the host's monotonic clock")
    left_t_mono_s: float | None = Field(description="let go over the outfeed edge")

    @classmethod
    def of(cls, r: PieceReport) -> PieceStatus:
        return cls(
            id=r.id,
            state=r.state,
            pose=None if r.pose is None else Pose.of(np.array(r.pose)),
            flat=r.flat,
            max_height_mm=r.max_height_mm,
            reason=r.reason,
            found_t_mono_s=r.found_s,
            left_t_mono_s=r.left_s,
        )


class Status(BaseModel):
    t_unix_s: float
    state: LoopState
    mode: Mode
    setpoint: Pose | None
    halt_reason: str | None = Field(
        description="why the last hold or move stopped by itself (a fault); null after a new setpoint"
    )
    halt_t_unix_s: float | None = Field(description="when it stopped (wall clock); null with halt_reason")
    estop: bool
    pose: PoseWithCovariance | None
    mesh: Mesh | None
    flatness: FlatnessState | None = Field(description="of the mesh estimate; null without one")
    features: int = Field(description="features measured and accepted in the last frame")
    rejected_features: int = Field(description="rejected by the filter's gate in the last frame")
    residual: Residual
    timing: Timing
    camera: CameraState = Field(description="the first camera, which tracking depends on")
    cameras: list[CameraEntry] = Field(
        description="every camera, first first; a further camera's loss leaves tracking on one view"
    )
    link: LinkState = Field(
        description="every stepper controller taken together: connected when each is, counters summed, "
        "the first controller's port"
    )
    links: list[ControllerLinkState] = Field(
        description="each stepper controller, in stepper.controllers' order"
    )
    modules: Modules = Field(description="what the modules were last told (stopped while the link is down)")
    faults: list[FaultReport]
    recording: Recording | None
    pieces: list[PieceStatus] | None = Field(
        None, description="mode flow: every piece on the table, then the last that left; null otherwise"
    )


def camera_entries(
    first: FrameSourceHealth,
    first_source: str,
    cameras: Sequence[tuple[str, str]],
    further: Sequence[CameraReport],
) -> list[CameraEntry]:
    """Every camera's entry: `cameras` names them (the first alone when empty); a further camera with no
    report yet is connecting."""
    named = list(cameras) or [(default_camera_name(0), first_source)]
    waiting = CameraReport(FrameSourceHealth("connecting", False, None, 0), PairingStats(None, None, None))
    reports = [CameraReport(first, PairingStats(None, None, None)), *further]
    reports += [waiting] * (len(named) - len(reports))
    return [
        CameraEntry(name=name, source=source, **asdict(r.health), **asdict(r.pairing))
        for (name, source), r in zip(named, reports, strict=False)
    ]


def build_status(
    *,
    state: str,
    setpoint: Setpoint,
    halt_reason: str | None,
    halt_t_unix_s: float | None,
    estimate: Estimate | None,
    flatness: Flatness | None,
    timing: dict[str, object],
    camera: FrameSourceHealth,
    camera_source: str,
    cameras: Sequence[tuple[str, str]] = (),
    further: Sequence[CameraReport] = (),
    link: ModuleLink,
    link_port: str,
    commands: ModuleCommands,
    recording: RecordingStatus | None,
    pieces: Sequence[PieceReport] | None = None,
) -> Status:
    """The status from the parts the daemon holds; the estimate counts only while it is tracking."""
    est = estimate if estimate is not None and estimate.tracking else None
    pose = mesh = None
    features = rejected = 0
    residual = Residual(mean_px=None, worst_px=None)
    if est is not None:
        pose = PoseWithCovariance(
            x_m=est.pose[0], y_m=est.pose[1], theta_rad=est.pose[2], cov=est.pose_cov.tolist()
        )
        if est.nodes_m is not None:
            ny, nx = est.nodes_m.shape[:2]
            mesh = Mesh(nx=nx, ny=ny, nodes_m=np.round(est.nodes_m.reshape(-1, 3), NODE_DECIMALS).tolist())
        features = int((~np.isnan(est.meas_px[:, 0])).sum()) if len(est.meas_px) else 0
        rejected = est.stats.rejected
        r = est.residual_px
        if len(r):
            residual = Residual(mean_px=float(r.mean()), worst_px=float(r.max()))
    link_state, links = link_states(link, link_port)
    return Status(
        t_unix_s=time.time(),
        state=state,
        mode=setpoint.mode,
        setpoint=None if setpoint.pose is None else Pose.of(setpoint.pose),
        halt_reason=halt_reason,
        halt_t_unix_s=halt_t_unix_s,
        estop=link.estopped,
        pose=pose,
        mesh=mesh,
        flatness=None if est is None or flatness is None else FlatnessState.of(flatness),
        features=features,
        rejected_features=rejected,
        residual=residual,
        timing=Timing.model_validate(timing),
        camera=CameraState(source=camera_source, **asdict(camera)),
        cameras=camera_entries(camera, camera_source, cameras, further),
        link=link_state,
        links=links,
        modules=Modules(speed_m_s=commands.speed_m_s.tolist(), heading_rad=commands.heading_rad.tolist()),
        faults=[FaultReport(**asdict(f)) for f in link.faults],
        recording=None if recording is None else Recording(**asdict(recording)),
        pieces=None if pieces is None else [PieceStatus.of(r) for r in pieces],
    )
