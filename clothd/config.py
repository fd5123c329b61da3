"""The configuration tree (config.yaml): pydantic models, unknown keys refused, every number bounded.

Each component receives only its own sub-model. `load_config` turns any problem into a ConfigError that
names the key and the bound it broke.
"""

from __future__ import annotations

import ipaddress
from pathlib import Path
from typing import Any, Literal
from urllib.parse import urlsplit

import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from clothd.errors import ConfigError


def is_loopback(host: str) -> bool:
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class IdealCameraConfig(_Strict):
    """Used when footage comes without camera.json: principal point at the image centre, table parallel
    to the image plane at `distance_m`."""

    f_px: float = Field(900.0, gt=10, le=20000)
    distance_m: float = Field(1.0, gt=0.05, le=20)
    width_px: int = Field(640, ge=64, le=8192, description="the live camera's image size")
    height_px: int = Field(480, ge=64, le=8192)


class FeatureConfig(_Strict):
    max_features: int = Field(600, ge=10, le=5000, description="about what the default cloth offers")
    quality_level: float = Field(0.01, gt=0, le=1, description="Shi-Tomasi, relative to the best corner")
    min_distance_px: float = Field(5.0, ge=1, le=100)
    block_size_px: int = Field(5, ge=3, le=31)
    lk_window_px: int = Field(11, ge=5, le=63)
    lk_levels: int = Field(1, ge=0, le=6, description="pyramid levels above the base")
    lk_max_iterations: int = Field(20, ge=1, le=200)
    lk_epsilon_px: float = Field(0.01, gt=0, le=1)
    fb_max_error_px: float = Field(0.5, gt=0, le=20, description="forward-backward check threshold")
    # A patch that is still itself one frame later correlates >= 0.75 in hwsim footage, across the compress
    # fold's shading and the random scenario's motion blur (median ~0.96); a patch replaced by noise
    # correlates <= 0.5. The default lies between.
    lk_min_ncc: float = Field(0.6, ge=-1, le=1, description="the LK window must still correlate this well")
    ncc_window_px: int = Field(9, ge=3, le=63, description="the centre of the LK window that NCC compares")
    # LK's covariance is sigma² G⁻¹: along a wale (an edge in the patch) a measurement says little. Above 1,
    # the estimator takes each feature's R from its structure tensor, its weak side at most this many times
    # the variance of its strong side, and the forward-backward check looks across the edge only
    # (clothd/core/features.py). 1 (off) on a cloth with corners, where it changes nothing for the better.
    aperture_max_ratio: float = Field(
        1.0, ge=1, le=1e6, description="largest variance ratio of a measurement's weak to strong axis"
    )
    # A periodic weave (a plain twill: stripes, no corners) tells itself at the start: the median λ1/λ2 of
    # the structure tensors of the first features is ~70-90 on hwsim's twill and ~4 on its denim. On such
    # a cloth LK takes periodic_lk_window_px, each measurement counts across the stripes only (its
    # aperture ratio capped at periodic_aperture_max_ratio), the mesh holds its shape (EkfConfig.
    # periodic_shape_sigma_m), and the outline becomes a measurement (clothd/core/outline_edges.py): the
    # edge searched for across the mesh's border at outline_per_side points a side (0: never), within
    # outline_search_px of the estimate. docs/architecture.md, "Periodic weaves".
    periodic_ratio: float = Field(20.0, ge=1, le=1e9, description="median λ1/λ2 that marks a periodic weave")
    periodic_lk_window_px: int = Field(15, ge=5, le=63, description="LK window on a periodic weave")
    periodic_aperture_max_ratio: float = Field(
        1000.0, ge=1, le=1e6, description="aperture_max_ratio on a periodic weave"
    )
    outline_per_side: int = Field(160, ge=0, le=200, description="edge points on each side of the mesh")
    outline_search_px: float = Field(4.0, gt=0, le=50, description="how far across the outline to search")
    # A repeating pattern with corners (a check) tells itself at the start too: the median best match of
    # the first features' windows with the same windows moved 3-8 px (features.self_similarity) reaches
    # repetitive_ncc (hwsim's gingham 0.94-0.96, denim ~0.62). There LK takes repetitive_lk_levels (a
    # coarser level halves a 5.4 px check to the Nyquist limit, where LK lands on look-alikes even from
    # a start 0.8 px off), the mesh holds its shape as on a periodic weave, every feature is also tracked
    # from where it was, and where that and the prediction's start land on different look-alikes the
    # cloth the other features place decides (clothd/core/tracker.py). Above 1: never.
    repetitive_ncc: float = Field(
        0.85, gt=0, le=2, description="self-similarity that marks a repeating pattern"
    )
    repetitive_lk_levels: int = Field(0, ge=0, le=6, description="LK pyramid levels on a repeating pattern")
    resample_below_fraction: float = Field(0.7, gt=0, le=1, description="of max_features")
    resample_cell_px: int = Field(48, ge=8, le=640, description="a cell of the cloth with no feature")
    edge_margin_px: float = Field(6.0, ge=0, le=100, description="keep new features this far inside")
    # Drift correction (clothd/core/anchors.py): every frame-to-frame result refined from its anchor frame.
    anchor: bool = Field(True, description="hold each feature to its appearance in an anchor frame")
    anchor_max_px: float = Field(
        0.5, gt=0, le=10, description="the anchored and frame-to-frame positions must agree this well"
    )
    anchor_still_px: float = Field(
        1.0, gt=0, le=100, description="a feature this far off its anchor has moved: it is anchored anew"
    )
    anchor_adopt_frames: int = Field(15, ge=1, le=10000, description="anchor loose features this often")
    anchor_max_frames: int = Field(4, ge=1, le=64, description="anchor frames kept; past this, all re-anchor")


class MeshConfig(_Strict):
    nodes_x: int = Field(12, ge=2, le=64)
    nodes_y: int = Field(12, ge=2, le=64)
    fold_tolerance_strain: float = Field(
        0.10, ge=0, lt=1, description="an edge this much shorter on the table than at rest has folded up"
    )


class PhysicsConfig(_Strict):
    """The tracker's own cloth model: a Provot mass-spring on the tracking mesh."""

    areal_density_kg_m2: float = Field(0.40, gt=0.01, le=5)
    stretch_k_n_m: float = Field(50.0, gt=0, le=1e5, description="structural spring; Provot: soft + limited")
    shear_k_n_m: float = Field(10.0, gt=0, le=1e5)
    flexion_k_n_m: float = Field(2.0, ge=0, le=1e5)
    damping_1_s: float = Field(8.0, ge=0, le=1000, description="velocity damping relative to the belt")
    friction_mu: float = Field(1.0, gt=0, le=3)
    stick_speed_m_s: float = Field(0.002, gt=0, le=0.1)
    strain_limit: float = Field(0.05, gt=0, le=1, description="Provot: springs never stretch past this")
    slack_strain: float = Field(
        0.04, ge=0, lt=1, description="springs pull only past this strain (a woven fabric's crimp)"
    )
    compression_k_ratio: float = Field(
        0.05, ge=0, le=1, description="a compressed spring's share of its stiffness: cloth buckles instead"
    )
    substeps: int = Field(20, ge=1, le=500)

    @model_validator(mode="after")
    def _slack_below_limit(self) -> PhysicsConfig:
        if self.slack_strain >= self.strain_limit:
            raise ValueError(
                f"slack_strain ({self.slack_strain}) must be below strain_limit ({self.strain_limit})"
            )
        return self


class EkfConfig(_Strict):
    meas_sigma_px: float = Field(0.7, gt=0, le=50)
    # A frame exposed for exposure_s up to its time stamp shows a moving cloth smeared over that time, and
    # LK finds the smear's middle: the measurement model of the mesh EKF places it where the nodes were
    # exposure_s / 2 earlier (p - v exposure_s / 2). 0: the frame is an instant (estimators/mesh.py).
    exposure_s: float = Field(0.0, ge=0, le=0.1, description="the camera's exposure, ending at the frame")
    process_pos_sigma_m: float = Field(0.0005, gt=0, le=1, description="per tick")
    process_vel_sigma_m_s: float = Field(0.01, gt=0, le=10, description="per tick")
    initial_pos_sigma_m: float = Field(0.002, gt=0, le=1)
    initial_vel_sigma_m_s: float = Field(0.01, gt=0, le=10)
    gate_chi2: float = Field(13.8, gt=0, le=1000, description="Mahalanobis gate, 2 dof (13.8 = 99.9 %)")
    smoothness_sigma_m: float = Field(
        0.005, gt=0, le=1, description="how far the corrections of neighbouring mesh nodes may differ"
    )
    # On a periodic weave the features measure across the stripes only, and nothing inside the cloth says
    # where along them it lies: every mesh edge (sides and diagonals) is held to its rest length within
    # this while stretched, 3x more loosely while compressed (cloth buckles into folds). A repeating
    # pattern (FeatureConfig.repetitive_ncc) is held the same way. 0: never.
    periodic_shape_sigma_m: float = Field(
        0.0002, ge=0, le=0.1, description="how closely a periodic weave's mesh edges keep their rest length"
    )
    divergence_nis: float = Field(50.0, gt=0, le=1e6, description="mean NIS per measurement that means lost")


class ModuleLimitsConfig(_Strict):
    """The steppers' limits, so the model's input is what the modules do, not only what they were told."""

    accel_limit_m_s2: float = Field(2.0, gt=0, le=50)
    steer_rate_limit_rad_s: float = Field(3.0, gt=0, le=100)


class TaichiConfig(_Strict):
    arch: Literal["cpu", "cuda", "vulkan"] = "cpu"


class TrackerConfig(_Strict):
    model: Literal["none", "predict", "rigid", "mesh"] = "mesh"
    use_input: bool = True
    camera: IdealCameraConfig = IdealCameraConfig()
    modules: ModuleLimitsConfig = ModuleLimitsConfig()
    features: FeatureConfig = FeatureConfig()
    mesh: MeshConfig = MeshConfig()
    physics: PhysicsConfig = PhysicsConfig()
    ekf: EkfConfig = EkfConfig()

    @property
    def estimates_shape(self) -> bool:
        """The model tracks the cloth's shape (a mesh of its own), so flatness can be read off it."""
        return self.model in ("mesh", "predict")


class LoopConfig(_Strict):
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
    # The tick's phase follows the camera's frames (clothd/frame_phase.py, docs/architecture.md).
    frame_lock: bool = Field(True, description="start ticks just before the camera's frames are due")
    frame_lead_ms: float = Field(1.0, ge=0, le=10, description="how long before a frame is due a tick starts")
    frame_wait_ms: float = Field(
        12.0, ge=0, le=30, description="how long past the lead a tick's compute waits for a due frame"
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
    # (clothd/priority.py, docs/deploy.md "A loaded cell PC").
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


class CameraSourceConfig(_Strict):
    """Where frames come from: a device index ("0"), a device path, a video file, a stream URL or a
    directory of images."""

    source: str = Field("0", min_length=1, max_length=1024)
    calibration: Path | None = Field(None, description="camera.json (K, dist, T_cam_world); else ideal")
    reconnect_initial_s: float = Field(0.5, gt=0, le=60)
    reconnect_max_s: float = Field(5.0, gt=0, le=600)
    stale_after_s: float = Field(1.0, gt=0, le=60, description="no new frame for this long: camera lost")


class StepperConfig(_Strict):
    port: str = Field("/dev/ttyACM0", min_length=1, max_length=1024)
    baud: int = Field(921600, ge=1200, le=12_000_000)
    ack_timeout_s: float = Field(0.05, gt=0.001, le=1, description="retransmit an unacknowledged command")
    # Unanswered for ack_timeout_s x (max_retransmits + 1), 150 ms by default, the link is lost: well inside
    # the controller's 250 ms watchdog, so the host knows first.
    max_retransmits: int = Field(2, ge=0, le=20, description="then the link is lost and reopened")
    handshake_timeout_s: float = Field(0.5, gt=0.01, le=10)
    reconnect_initial_s: float = Field(0.2, gt=0, le=60)
    reconnect_max_s: float = Field(5.0, gt=0, le=600)


class AreaConfig(_Strict):
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


class CellConfig(_Strict):
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


class FlatnessConfig(_Strict):
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


class FlattenConfig(_Strict):
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
        0.3, ge=0, le=10, description="a ridge the estimate stops seeing is pulled on this long, at max speed"
    )

    @model_validator(mode="after")
    def _min_below_max(self) -> FlattenConfig:
        if self.min_speed_m_s > self.max_speed_m_s:
            raise ValueError(f"min_speed_m_s ({self.min_speed_m_s}) must not exceed max_speed_m_s")
        return self


class ControlConfig(_Strict):
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


class ApiConfig(_Strict):
    host: str = Field("127.0.0.1", min_length=1, max_length=255)
    port: int = Field(8080, ge=1, le=65535)
    token: str | None = Field(None, min_length=16, max_length=256, description="required off loopback")
    view_fps: float = Field(10.0, gt=0, le=30, description="the annotated MJPEG view's rate")
    allowed_hosts: tuple[str, ...] = Field(
        (), max_length=32, description="host names the API answers to besides 127.0.0.1, localhost and [::1]"
    )
    allowed_origins: tuple[str, ...] = Field(
        (),
        max_length=32,
        description="web origins (scheme://host[:port]) that may change things, besides its own",
    )
    max_body_bytes: int = Field(
        4096, ge=256, le=1_000_000, description="a larger request body is refused (413)"
    )
    max_connections: int = Field(
        128, ge=8, le=2048, description="open HTTP connections; one more evicts the oldest idle one"
    )
    request_timeout_s: float = Field(
        5.0, gt=0, le=120, description="a request must arrive whole this soon after its connection opens"
    )
    max_streams: int = Field(
        32, ge=1, le=512, description="WebSockets and MJPEG views open at once, apart from max_connections"
    )
    stall_timeout_s: float = Field(
        5.0, gt=0, le=120, description="a client that reads nothing this long while data waits is dropped"
    )

    @model_validator(mode="after")
    def _token_off_loopback(self) -> ApiConfig:
        """Off loopback, the API needs a token: refuse to start without one."""
        if not is_loopback(self.host) and self.token is None:
            raise ValueError(
                f"api.host: {self.host} is reachable from other machines; set api.token (16+ characters) "
                "so that changes need Authorization: Bearer <token>, or bind to 127.0.0.1"
            )
        return self


OPCUA_SIGN_AND_ENCRYPT = "Basic256Sha256_SignAndEncrypt"


def opcua_host_port(endpoint: str) -> tuple[str, int]:
    """The host and port an opc.tcp:// endpoint binds to (4840, OPC UA's registered port, when none)."""
    url = urlsplit(endpoint)
    return url.hostname or "", url.port or 4840


class OpcUaConfig(_Strict):
    """The OPC UA server (docs/opcua.md). Loopback: anonymous reads, no security policy needed. Anywhere
    else: Basic256Sha256 SignAndEncrypt only, with a certificate made on first start in `cert_dir`."""

    enabled: bool = True
    endpoint: str = Field("opc.tcp://127.0.0.1:4840/clothd/", min_length=1, max_length=255)
    security_policies: tuple[Literal["None", "Basic256Sha256_SignAndEncrypt"], ...] = Field(
        ("None",), min_length=1, max_length=2, description="offered to clients; None only on loopback"
    )
    cert_dir: Path = Field(
        Path("opcua"), description="server key and certificate; relative: to the state directory (systemd)"
    )
    publish_hz: float = Field(10.0, gt=0, le=10, description="how often the variables follow the status")
    max_message_bytes: int = Field(
        262_144,
        ge=8192,
        le=16_777_216,
        description="a larger request, or a chunk over 64 KiB, closes its peer",
    )
    max_anonymous_sessions: int = Field(32, ge=0, le=1000, description="activated anonymous sessions at once")
    max_user_sessions: int = Field(8, ge=1, le=100, description="activated sessions of user clothd, apart")
    max_pending_connections: int = Field(
        32, ge=1, le=1000, description="connections with no session yet; one more closes the oldest"
    )
    activation_timeout_s: float = Field(
        5.0, gt=0, le=60, description="a connection with no activated session after this is closed"
    )

    @field_validator("endpoint")
    @classmethod
    def _opc_tcp_url(cls, endpoint: str) -> str:
        try:
            host, _ = opcua_host_port(endpoint)  # a port that is no number, or out of range, raises
        except ValueError as err:
            raise ValueError(f"{endpoint!r} is not a URL: {err}") from None
        if urlsplit(endpoint).scheme != "opc.tcp" or not host:
            raise ValueError(f"{endpoint!r}: an endpoint is opc.tcp://HOST:PORT/PATH")
        return endpoint

    @model_validator(mode="after")
    def _secure_off_loopback(self) -> OpcUaConfig:
        """Off loopback, the None policy (plain text, no server identity) is refused at start."""
        host, _ = opcua_host_port(self.endpoint)
        if not is_loopback(host) and self.security_policies != (OPCUA_SIGN_AND_ENCRYPT,):
            raise ValueError(
                f"opcua.endpoint: {self.endpoint} is reachable from other machines; set "
                f"opcua.security_policies to [{OPCUA_SIGN_AND_ENCRYPT}] (no None policy off loopback), "
                "or bind to 127.0.0.1"
            )
        return self


class RecordingConfig(_Strict):
    dir: Path = Field(Path("recordings"), description="where POST /record/start puts sessions by default")
    max_bytes: int = Field(2_000_000_000, ge=100_000, le=10**13, description="a recording stops at this size")
    format: Literal["directory", "mcap"] = Field(
        "directory",
        description="directory: frames and CSVs that clothd replay reads; mcap: one .mcap file for Foxglove",
    )


class FoxgloveConfig(_Strict):
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


class Config(_Strict):
    taichi: TaichiConfig = TaichiConfig()
    tracker: TrackerConfig = TrackerConfig()
    loop: LoopConfig = LoopConfig()
    camera: CameraSourceConfig = CameraSourceConfig()
    stepper: StepperConfig = StepperConfig()
    cell: CellConfig = CellConfig()
    control: ControlConfig = ControlConfig()
    api: ApiConfig = ApiConfig()
    opcua: OpcUaConfig = OpcUaConfig()
    recording: RecordingConfig = RecordingConfig()
    foxglove: FoxgloveConfig = FoxgloveConfig()

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


def load_config(path: Path | None, overrides: dict[str, Any] | None = None) -> Config:
    """The configuration in `path` (every default when None) with `overrides` (a nested mapping, e.g.
    from command-line flags) laid over it, validated once, as a whole."""
    data: object = {}
    if path is not None:
        try:
            data = yaml.safe_load(path.read_text())
        except OSError as err:
            raise ConfigError(f"{path}: cannot read: {err.strerror}") from None
        except yaml.YAMLError as err:
            raise ConfigError(f"{path}: not valid YAML: {err}") from None
    source = str(path) if path is not None else "<defaults>"
    if overrides and isinstance(data, dict | None):
        data = _merged(data or {}, overrides)
    return parse_config(data, source)


def with_overrides(cfg: Config, overrides: dict[str, Any]) -> Config:
    """cfg with `overrides` laid over it, validated again as a whole."""
    return parse_config(_merged(cfg.model_dump(), overrides), "<overrides>")
