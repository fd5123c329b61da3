"""The configuration tree (config.yaml): pydantic models, unknown keys refused, every number bounded.

Each component receives only its own sub-model. `load_config` turns any problem into a ConfigError that
names the key and the bound it broke.
"""

from __future__ import annotations

from enum import StrEnum
from pathlib import Path
from typing import Any

import yaml
from pydantic import Field, ValidationError, model_validator

from clothd.config.api import (
    OPCUA_SIGN_AND_ENCRYPT,
    ApiConfig,
    OpcUaConfig,
    is_loopback,
    opcua_host_port,
)
from clothd.config.camera import (
    MAX_CAMERAS,
    CameraConfig,
    CameraSourceConfig,
    NamedCamera,
    cameras_of,
    check_cameras,
)
from clothd.config.flow import FlowConfig, PlacementConfig
from clothd.config.stepper import ControllerConfig, ControllerLink, StepperConfig, check_controllers
from clothd.config.strict import Strict
from clothd.config.tracker import (
    EkfConfig,
    FeatureConfig,
    IdealCameraConfig,
    MeshConfig,
    ModuleLimitsConfig,
    PhysicsConfig,
    StereoConfig,
    TaichiConfig,
    TrackerConfig,
)
from clothd.errors import ConfigError

# The tracker's sections live in clothd/config/tracker.py, the stepper's in stepper.py; importers may
# name them from here.
__all__ = [
    "OPCUA_SIGN_AND_ENCRYPT",
    "ApiConfig",
    "CameraConfig",
    "CameraSourceConfig",
    "ControllerConfig",
    "ControllerLink",
    "EkfConfig",
    "FeatureConfig",
    "FlowConfig",
    "IdealCameraConfig",
    "MeshConfig",
    "ModuleLimitsConfig",
    "NamedCamera",
    "OpcUaConfig",
    "PhysicsConfig",
    "PlacementConfig",
    "StepperConfig",
    "StereoConfig",
    "TaichiConfig",
    "TrackerConfig",
    "is_loopback",
    "opcua_host_port",
]


class LoopConfig(Strict):
    tick_hz: float = Field(30.0, ge=15, le=30, description="the fixed control tick")
    # 10 ticks (333 ms at 30 Hz): past a busy machine's hiccups (a loaded 2-core CI box overruns a few
    # ticks in a row now and then), well inside the camera's 1 s; at 80 mm/s the cloth moves <= 27 mm
    # on commands that old.
    max_stale_ticks: int = Field(
        10, ge=1, le=30, description="ticks in a row without the compute's answer before the modules stop"
    )
    # The controller's watchdog: a host silent longer has had its modules stopped by the controller, so
    # the commands the model drives the cloth with are no longer what the modules did.
    starved_ms: float = Field(
        250.0, ge=50, le=2000, description="the daemon silent this long: the tracker starts afresh"
    )
    # The tick's phase follows the camera's frames (clothd/loop/frame_phase.py, docs/architecture.md).
    frame_lock: bool = Field(True, description="start ticks just before the camera's frames are due")
    frame_lead_ms: float = Field(1.0, ge=0, le=10, description="how long before a frame is due a tick starts")
    # A frame later than the wait waits a whole tick for the next: with two views hwsim's frames arrived
    # up to 20 ms past their grid (p99), and at 12 ms the loop's latency p99 was 1.5-4.8 ms worse.
    frame_wait_ms: float = Field(
        15.0, ge=0, le=30, description="how long past the lead a tick's compute waits for a due frame"
    )
    phase_step_ms: float = Field(1.0, gt=0, le=5, description="the most a tick's phase moves per tick")
    track_ahead: bool = Field(
        True, description="the compute tracks a frame as it arrives, not when the tick asks for commands"
    )
    # OpenCV's threads in the compute process: LK's passes split their points among them (2000 features
    # at 24 x 24 nodes tick in 13 ms with 2, 18 ms with 1). Even on a 2-core machine shared with hwsim, 2
    # cut the frame-to-command latency p99 from 16 to 12-13 ms and missed no tick (docs/benchmarks.md).
    compute_threads: int = Field(2, ge=1, le=16, description="OpenCV threads in the compute process")
    # A loaded PC: the loop and the compute before other programs, the API after the loop
    # (clothd/drivers/priority.py, docs/deploy.md "A loaded cell PC").
    nice: int = Field(-10, ge=-20, le=0, description="the loop's thread and the compute, where permitted")
    realtime_priority: int = Field(
        20, ge=0, le=98, description="SCHED_FIFO priority of the loop's thread; 0: normal class"
    )

    @model_validator(mode="after")
    def _frame_wait_leaves_time_to_compute(self) -> LoopConfig:
        if self.frame_lead_ms + self.frame_wait_ms > 0.5e3 * self.period_s:
            raise ValueError(
                f"frame_lead_ms + frame_wait_ms ({self.frame_lead_ms + self.frame_wait_ms:g}) must be at "
                f"most half the tick period ({0.5e3 * self.period_s:.1f} ms at tick_hz {self.tick_hz:g}), "
                "to leave the other half for the compute"
            )
        return self

    @property
    def period_s(self) -> float:
        return 1.0 / self.tick_hz


class AreaConfig(Strict):
    """An axis-aligned rectangle of the table, world frame, metres."""

    x_min_m: float = Field(ge=-10, le=10)
    x_max_m: float = Field(ge=-10, le=10)
    y_min_m: float = Field(ge=-10, le=10)
    y_max_m: float = Field(ge=-10, le=10)

    @model_validator(mode="after")
    def _not_empty(self) -> AreaConfig:
        if self.x_min_m >= self.x_max_m or self.y_min_m >= self.y_max_m:
            raise ValueError("x_min_m must be below x_max_m, and y_min_m below y_max_m")
        return self


class CellConfig(Strict):
    """The conveyor table: module id = row * modules_x + col, centred on the world origin."""

    modules_x: int = Field(8, ge=1, le=64)
    modules_y: int = Field(6, ge=1, le=64)
    pitch_m: float = Field(0.075, gt=0.01, le=0.5)
    module_size_m: float = Field(0.065, gt=0.005, le=0.5)
    max_speed_m_s: float = Field(0.2, gt=0, le=2)
    workspace: AreaConfig | None = Field(
        None, description="where the cloth may be while it is moved; default: the belts less the margin"
    )
    workspace_margin_m: float = Field(
        0.02, ge=0, le=0.5, description="the default workspace keeps this far inside the outer belts' edges"
    )
    module_calibration: Path | None = Field(
        None,
        description="what clothd check-modules wrote: each module's direction, heading offset, speed scale",
    )


class FlatnessConfig(Strict):
    """When the estimate counts as flat (core/flatness.py): it turns flat below both bars and unflat only
    past twice either."""

    compressed_strain: float = Field(
        0.05, gt=0, lt=1, description="a mesh quad this much shorter on the table than at rest holds slack"
    )
    release_strain: float = Field(
        0.025, gt=0, lt=1, description="... and keeps holding it, once it did, until less short than this"
    )
    flat_height_m: float = Field(0.001, gt=0, le=0.1, description="estimated height of the highest point")
    flat_compressed_pct: float = Field(1.0, ge=0, le=100, description="share of the quads holding slack")

    @model_validator(mode="after")
    def _release_below_start(self) -> FlatnessConfig:
        if self.release_strain >= self.compressed_strain:
            raise ValueError(f"release_strain ({self.release_strain}) must be below compressed_strain")
        return self


class FlattenConfig(Strict):
    """The flattening regulator (core/flattening.py, docs/flattening.md)."""

    time_constant_s: float = Field(0.5, gt=0.01, le=60, description="a ridge's slack decays like exp(-t/τ)")
    max_speed_m_s: float = Field(0.04, gt=0, le=1, description="the most a module pulls a ridge's side")
    min_speed_m_s: float = Field(
        0.01, ge=0, le=1, description="the least a module pulls a ridge's side while the ridge is seen"
    )
    reach_m: float = Field(0.12, gt=0, le=2, description="modules this far from a ridge, or nearer, pull")
    ridge_margin_m: float = Field(
        0.01, ge=0, le=0.5, description="a module pulls once its centre is this far off a ridge's line"
    )
    finish_s: float = Field(
        0.6, ge=0, le=10, description="a ridge the estimate stops seeing is pulled on this long, at max speed"
    )

    @model_validator(mode="after")
    def _min_below_max(self) -> FlattenConfig:
        if self.min_speed_m_s > self.max_speed_m_s:
            raise ValueError(f"min_speed_m_s ({self.min_speed_m_s}) must not exceed max_speed_m_s")
        return self


class ControlConfig(Strict):
    """Moves to a setpoint: the cloth's planned velocity is limited in speed and acceleration, and
    approaches the target as gain x error near it."""

    max_speed_m_s: float = Field(0.08, gt=0, le=1)
    max_accel_m_s2: float = Field(0.4, gt=0, le=10)
    max_rate_rad_s: float = Field(0.6, gt=0, le=10)
    max_ang_accel_rad_s2: float = Field(3.0, gt=0, le=100)
    gain_1_s: float = Field(3.0, gt=0, le=50, description="proportional gain on the remaining error")
    under_cloth_margin_m: float = Field(
        0.0, ge=-0.1, le=0.2, description="a module is under the cloth when its centre is this far inside"
    )
    flatness: FlatnessConfig = FlatnessConfig()
    flatten: bool = Field(True, description="hold and move flatten the cloth as they go")
    flattening: FlattenConfig = FlattenConfig()


class RecordingFormat(StrEnum):
    """How a recording is written; named once for the config, the daemon, the compute and the status."""

    DIRECTORY = "directory"  # frames and CSVs that clothd replay reads
    MCAP = "mcap"  # one .mcap file for Foxglove

    @property
    def suffix(self) -> str:
        """What a recording's name ends with."""
        return ".mcap" if self is RecordingFormat.MCAP else ""

    @property
    def noun(self) -> str:
        return "file" if self is RecordingFormat.MCAP else "directory"

    @property
    def finished_by(self) -> str:
        """What stopping a recording writes last."""
        return "the .mcap file's summary" if self is RecordingFormat.MCAP else "estimates.npz"


class RecordingConfig(Strict):
    dir: Path = Field(Path("recordings"), description="where POST /record/start puts sessions by default")
    max_bytes: int = Field(2_000_000_000, ge=100_000, le=10**13, description="a recording stops at this size")
    format: RecordingFormat = Field(
        RecordingFormat.DIRECTORY,
        description="directory: frames and CSVs that clothd replay reads; mcap: one .mcap file for Foxglove",
    )


class FoxgloveConfig(Strict):
    """The Foxglove WebSocket server (docs/foxglove.md). The protocol has no authentication: whoever reaches
    the port sees the camera and the cloth, so it serves loopback unless allow_remote says otherwise."""

    enabled: bool = Field(False, description="serve the Foxglove WebSocket protocol")
    host: str = Field("127.0.0.1", min_length=1, max_length=255)
    port: int = Field(8765, ge=1, le=65535)
    allow_remote: bool = Field(False, description="serve on an address other machines can reach")

    @model_validator(mode="after")
    def _loopback_unless_allowed(self) -> FoxgloveConfig:
        if not is_loopback(self.host) and not self.allow_remote:
            raise ValueError(
                f"foxglove.host: {self.host} is reachable from other machines and the Foxglove protocol has "
                "no authentication; bind to 127.0.0.1, or set foxglove.allow_remote: true to serve it anyway"
            )
        return self


class Config(Strict):
    taichi: TaichiConfig = TaichiConfig()
    tracker: TrackerConfig = TrackerConfig()
    loop: LoopConfig = LoopConfig()
    camera: CameraSourceConfig = CameraSourceConfig()
    # Several cameras (clothd/config/camera.py); null: camera's one.
    cameras: list[CameraConfig] | None = Field(None, min_length=1, max_length=MAX_CAMERAS)
    stepper: StepperConfig = StepperConfig()
    cell: CellConfig = CellConfig()
    control: ControlConfig = ControlConfig()
    flow: FlowConfig = FlowConfig()
    api: ApiConfig = ApiConfig()
    opcua: OpcUaConfig = OpcUaConfig()
    recording: RecordingConfig = RecordingConfig()
    foxglove: FoxgloveConfig = FoxgloveConfig()

    @model_validator(mode="after")
    def _cameras_agree(self) -> Config:
        check_cameras(self.camera, self.cameras)
        return self

    @model_validator(mode="after")
    def _controllers_cover_cell(self) -> Config:
        check_controllers(self.stepper, self.cell.modules_x * self.cell.modules_y)
        return self

    @property
    def all_cameras(self) -> tuple[NamedCamera, ...]:
        """Every camera, the first (which tracking depends on) first."""
        return cameras_of(self.camera, self.cameras)

    @model_validator(mode="after")
    def _opcua_token_off_loopback(self) -> Config:
        """Off loopback, OPC UA clients log in as `clothd` with api.token as the password: no token, no
        start (as for the HTTP API)."""
        host, _ = opcua_host_port(self.opcua.endpoint)
        if self.opcua.enabled and not is_loopback(host) and self.api.token is None:
            raise ValueError(
                f"opcua.endpoint: {self.opcua.endpoint} is reachable from other machines; set api.token "
                "(16+ characters): OPC UA clients then log in as user clothd with it as the password"
            )
        return self


def _describe(err: ValidationError, source: str) -> str:
    first = err.errors()[0]
    key = ".".join(str(p) for p in first["loc"]) or "(top level)"
    more = f" (and {err.error_count() - 1} more)" if err.error_count() > 1 else ""
    return f"{source}: {key}: {first['msg']}{more}"


def parse_config(data: object, source: str = "<config>") -> Config:
    if data is None:
        data = {}
    if not isinstance(data, dict):
        raise ConfigError(f"{source}: the configuration is a mapping of keys, got {type(data).__name__}")
    try:
        return Config.model_validate(data)
    except ValidationError as err:
        raise ConfigError(_describe(err, source)) from None


def _merged(base: dict[str, Any], overrides: dict[str, Any]) -> dict[str, Any]:
    out = dict(base)
    for key, value in overrides.items():
        out[key] = (
            _merged(out[key], value) if isinstance(value, dict) and isinstance(out.get(key), dict) else value
        )
    return out


def yaml_problem(err: yaml.YAMLError) -> str:
    """pyyaml's error in one line: what and where (its own text spans several, with a caret)."""
    mark = getattr(err, "problem_mark", None)
    problem = getattr(err, "problem", None)
    if problem is None or mark is None:
        return " ".join(str(err).split())
    return f"{problem} (line {mark.line + 1}, column {mark.column + 1})"


def load_config(path: Path | None, overrides: dict[str, Any] | None = None) -> Config:
    """The configuration in `path` (every default when None) with `overrides` (a nested mapping, e.g.
    from command-line flags) laid over it, validated once, as a whole."""
    data: object = {}
    if path is not None:
        try:
            data = yaml.safe_load(path.read_text())
        except OSError as err:
            raise ConfigError(f"{path}: cannot read: {err.strerror}") from None
        except UnicodeDecodeError as err:
            raise ConfigError(f"{path}: not UTF-8 text (byte {err.start})") from None
        except yaml.YAMLError as err:
            raise ConfigError(f"{path}: not valid YAML: {yaml_problem(err)}") from None
    source = str(path) if path is not None else "<defaults>"
    if overrides and isinstance(data, dict | None):
        data = _merged(data or {}, overrides)
    return parse_config(data, source)


def with_overrides(cfg: Config, overrides: dict[str, Any]) -> Config:
    """cfg with `overrides` laid over it, validated again as a whole. Only what was set travels: a key
    left to its default stays unset (camera.source beside cameras is an error only when set)."""
    return parse_config(_merged(cfg.model_dump(exclude_unset=True), overrides), "<overrides>")


def with_cameras(cfg: Config, cameras: list[dict[str, Any]]) -> Config:
    """cfg with its cameras replaced by `cameras` (entries of cameras:), camera's shared settings kept."""
    data = cfg.model_dump(exclude_unset=True)
    data["camera"] = {k: v for k, v in data.get("camera", {}).items() if k not in ("source", "calibration")}
    data["cameras"] = cameras
    return parse_config(data, "<cameras>")


def first_cameras(cfg: Config, n: int, whose: str = "the configuration") -> Config:
    """cfg with only its first n cameras (n = 1: mono); more than it has is an error, saying `whose`
    cameras they are."""
    have = cfg.all_cameras
    if n > len(have):
        raise ConfigError(f"--cameras {n}: {whose} has {len(have)} camera(s)")
    entries = [{"name": c.name, "source": c.source.source, "calibration": c.source.calibration} for c in have]
    return with_cameras(cfg, entries[:n])
