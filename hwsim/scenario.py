"""Scenario files: the pydantic schema of a simulated-cell run, and loading with clear errors.

A scenario fixes everything a recording depends on: duration and frame rate, the table of conveyor
modules, the cloth and its texture, the camera, sensor noise, the cloth's initial pose, a timeline of
module commands, and occluders. The schema is documented in docs/scenarios.md; every number is bounded
and unknown keys are refused, so a typo is an error that names the key, not a silent default.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Annotated, Literal

import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from hwsim.scenario_flow import Flow, Infeed

SCENARIO_DIR = Path(__file__).parent / "scenarios"
MAX_CAMERAS = 4


class ScenarioError(ValueError):
    """A scenario file that cannot be used; the message names the file and the offending key."""


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class Miscalibration(_Strict):
    """A module that does not do what it is told, as a cell before commissioning may have: its drive wired
    the wrong way round, its steering's zero off, its belt's speed off scale (a wrong pulley or microstep
    setting). The module applies these to every command it receives (`clothd check-modules` finds them)."""

    module: int = Field(ge=0, description="module id")
    reversed: bool = Field(False, description="the belt runs the other way from the one commanded")
    heading_offset_deg: float = Field(0.0, ge=-180, le=180, description="added to every commanded heading")
    speed_scale: float = Field(1.0, ge=0.5, le=1.5, description="the belt's speed over the commanded speed")


class TableSpec(_Strict):
    """The array of steerable conveyor modules, centred on the world origin."""

    modules_x: int = Field(8, ge=1, le=64)
    modules_y: int = Field(6, ge=1, le=64)
    pitch_m: float = Field(0.075, gt=0.01, le=0.5)
    module_size_m: float = Field(0.065, gt=0.005, le=0.5, description="side of a module's square belt")
    max_speed_m_s: float = Field(0.2, gt=0, le=2.0)
    accel_limit_m_s2: float = Field(2.0, gt=0, le=20.0)
    steer_rate_limit_rad_s: float = Field(3.0, gt=0, le=50.0)
    miscalibrated: list[Miscalibration] = Field([], max_length=64)

    @model_validator(mode="after")
    def _module_fits_pitch(self) -> TableSpec:
        if self.module_size_m > self.pitch_m:
            raise ValueError(f"module_size_m ({self.module_size_m}) must not exceed pitch_m ({self.pitch_m})")
        return self

    @model_validator(mode="after")
    def _miscalibrated_modules_exist(self) -> TableSpec:
        ids = [m.module for m in self.miscalibrated]
        n_modules = self.modules_x * self.modules_y
        bad = [i for i in ids if i >= n_modules]
        if bad:
            raise ValueError(f"miscalibrated: modules {bad} out of range (table has {n_modules})")
        if len(set(ids)) != len(ids):
            raise ValueError("miscalibrated: a module is listed twice")
        return self


class FrictionSpec(_Strict):
    """Coulomb friction of the cloth on a belt: a node at rest on its belt sticks while the pull on it
    stays within mu_static x its normal force, and slides against mu x the normal force once it slips."""

    mu: float = Field(1.1, gt=0, le=3.0, description="kinetic coefficient, denim on rubber belt")
    mu_static: float = Field(1.2, gt=0, le=3.0, description="static coefficient, at least mu")

    @model_validator(mode="after")
    def _static_at_least_kinetic(self) -> FrictionSpec:
        if self.mu_static < self.mu:
            raise ValueError(f"mu_static ({self.mu_static}) must be at least mu ({self.mu})")
        return self


class ClothSpec(_Strict):
    """Ground-truth cloth: a fine XPBD sheet. Defaults are a mid-weight (400 g/m²) denim."""

    size_m: tuple[Annotated[float, Field(gt=0.02, le=2.0)], Annotated[float, Field(gt=0.02, le=2.0)]] = (
        0.25,
        0.20,
    )
    spacing_m: float = Field(0.005, ge=0.002, le=0.05, description="node spacing of the truth mesh")
    areal_density_kg_m2: float = Field(0.40, gt=0.01, le=5.0)
    stretch_stiffness_n_m: float = Field(2.0e4, gt=0, le=1e7)
    shear_stiffness_n_m: float = Field(2.0e3, gt=0, le=1e7)
    bending_stiffness_n_m: float = Field(1.0e-5, gt=0, le=1.0, description="flexural rigidity B, N·m")
    # The yarns' friction holds a laid or pushed ridge on still belts, and is weak enough for belts to pull
    # one below 1 mm: HB/B 25 m^-1, inside denims' measured 23-54 (docs/hwsim.md, "The yarns' friction in
    # bending").
    bending_hysteresis_n: float = Field(
        2.5e-4,
        ge=0,
        le=1.0,
        description="HB, the yarns' frictional couple in bending, N·m/m (half KES's 2HB; 0: purely elastic)",
    )
    damping_1_s: float = Field(0.5, ge=0, le=100.0, description="velocity damping rate")
    friction: FrictionSpec = FrictionSpec()
    substep_s: float = Field(1.0 / 1000, ge=1e-5, le=0.01, description="XPBD substep")
    stretch_iterations: int = Field(5, ge=1, le=50, description="stretch sweeps per substep")
    vibration_m_s: float = Field(
        0.003, ge=0, le=0.1, description="std of vertical kicks from running belts (seeds buckling)"
    )


class TextureSpec(_Strict):
    kind: Literal["denim", "plain_twill", "gingham", "image"] = "denim"
    seed: int = Field(7, ge=0)
    path: str | None = Field(None, description="image file, for kind: image")
    texels_per_m: float = Field(4000.0, ge=500.0, le=20000.0)
    relief_m: float = Field(
        0.0, ge=0.0, le=0.002, description="peak-to-peak depth of the wales (0: a flat print, lit evenly)"
    )

    @model_validator(mode="after")
    def _path_for_image(self) -> TextureSpec:
        if (self.kind == "image") != (self.path is not None):
            raise ValueError("path is required for kind 'image' and only allowed there")
        if self.kind == "image" and self.relief_m > 0:
            raise ValueError("relief_m is for the woven kinds (denim, plain_twill, gingham), not an image")
        return self


class CameraSpec(_Strict):
    """Pinhole camera looking at the table. The default hangs 1 m above the origin, straight down."""

    width: int = Field(640, ge=64, le=4096)
    height: int = Field(480, ge=64, le=4096)
    f_px: float = Field(900.0, gt=50, le=20000)
    principal_px: tuple[float, float] | None = Field(None, description="(cx, cy); default image centre")
    dist: tuple[float, float, float, float, float] = Field(
        (0.0, 0.0, 0.0, 0.0, 0.0), description="OpenCV order k1, k2, p1, p2, k3"
    )
    position_m: tuple[float, float, Annotated[float, Field(gt=0.1, le=10.0)]] = (0.0, 0.0, 1.0)
    tilt_rad: float = Field(0.0, ge=-0.5, le=0.5, description="rotation about the world x axis")
    yaw_rad: float = Field(0.0, ge=-math.pi, le=math.pi, description="rotation about the view axis")
    name: str | None = Field(
        None, pattern=r"^[a-z0-9_-]{1,32}$", description="URL and directory name; default cam0, cam1, ..."
    )
    # Unsynchronised cameras: each frame shows the world this long after the first camera's frame of the
    # same index (negative: before). Rendered by extrapolating the scene, as motion blur is.
    capture_skew_s: float = Field(0.0, ge=-0.1, le=0.1, description="capture lag behind the first camera")


class NoiseSpec(_Strict):
    sigma: float = Field(1.5, ge=0, le=50, description="Gaussian sensor noise, grey levels of 255")
    motion_blur_samples: int = Field(1, ge=1, le=16, description="sub-frame renders averaged per frame")
    exposure_s: float = Field(0.008, ge=0, le=0.1, description="shutter time spanned by those samples")
    seed: int = Field(11, ge=0)


class LightSpec(_Strict):
    direction: tuple[float, float, float] = Field((0.35, -0.25, 1.0), description="towards the light")
    ambient: float = Field(0.35, ge=0, le=1)


class Ridge(_Strict):
    """A ridge of slack laid into the cloth along a straight line, as a hand-laid cloth has: a Gaussian
    profile across the line. The sheet keeps its material length, so the cloth on either side is drawn
    towards the ridge. Where two ridges cross, their heights add."""

    height_m: float = Field(gt=0, le=0.05, description="height of the profile as laid, before it settles")
    sigma_m: float = Field(0.012, gt=0.002, le=0.2, description="Gaussian width of the profile")
    at_m: tuple[float, float] = Field(
        (0.0, 0.0), description="a point of the ridge line: cloth frame (s, t), metres from its centre"
    )
    direction_rad: float = Field(
        math.pi / 2, ge=-2 * math.pi, le=2 * math.pi, description="line direction, from the s axis"
    )

    @model_validator(mode="after")
    def _not_overhanging(self) -> Ridge:
        # The profile's steepest slope is 0.61 height/sigma; a sheet cannot rise steeper than vertical.
        if self.sigma_m < 0.65 * self.height_m:
            raise ValueError(f"sigma_m ({self.sigma_m}) must be at least 0.65 x height_m: it would overhang")
        return self


class Flap(_Strict):
    """A corner folded over onto the cloth along a line at 45° to its edges: the triangle within size_m of
    the corner (along either edge) lies face down on the cloth, one cloth thickness up."""

    corner: Literal["-s-t", "+s-t", "+s+t", "-s+t"] = Field(description="which corner, in the cloth frame")
    size_m: float = Field(gt=0.005, le=0.2, description="how far along each edge from the corner the fold is")


class Pose(_Strict):
    x_m: float = Field(0.0, ge=-5, le=5)
    y_m: float = Field(0.0, ge=-5, le=5)
    theta_rad: float = Field(0.0, ge=-2 * math.pi, le=2 * math.pi)
    ridges: list[Ridge] = Field([], max_length=8)
    flaps: list[Flap] = Field([], max_length=4)


class Push(_Strict):
    """Two hands push a ridge into the cloth: they press it down on either side of a line (world frame),
    between a quarter of reach_m and reach_m from it, and move towards the line until slack_m has gone into
    the strip between them, while fingers draw the line up (hwsim.world.World.push)."""

    at_m: tuple[float, float] = Field(description="a point of the line, world x, y")
    direction_rad: float = Field(ge=-2 * math.pi, le=2 * math.pi, description="the line's direction, world")
    slack_m: float = Field(gt=0, le=0.05, description="how much closer the two hands end up")
    duration_s: float = Field(1.0, gt=0.05, le=10)
    reach_m: float = Field(0.06, gt=0.01, le=0.5)


class ModuleSelector(_Strict):
    """Which modules a command applies to. Exactly one way of choosing."""

    all: bool = False
    ids: list[Annotated[int, Field(ge=0)]] | None = None
    region_m: tuple[float, float, float, float] | None = Field(
        None, description="x_min, y_min, x_max, y_max of module centres, world metres"
    )

    @model_validator(mode="after")
    def _exactly_one(self) -> ModuleSelector:
        chosen = [self.all, self.ids is not None, self.region_m is not None]
        if sum(chosen) != 1:
            raise ValueError("choose modules with exactly one of: all, ids, region_m")
        return self


class SetCommand(_Strict):
    """From t_s on, the selected modules are told this speed and heading (held until changed)."""

    t_s: float = Field(ge=0)
    modules: ModuleSelector
    speed_m_s: float = Field(ge=0, le=2.0)
    heading_rad: float = Field(ge=-2 * math.pi, le=2 * math.pi)


class RandomDrive(_Strict):
    """From t_s to t_end_s, every module follows a random rigid velocity field (translation plus
    rotation about the cloth's centre) that wanders smoothly (Ornstein-Uhlenbeck) and is pulled back
    towards the table centre, so the cloth stays on the table."""

    t_s: float = Field(ge=0)
    t_end_s: float = Field(gt=0)
    seed: int = Field(3, ge=0)
    speed_m_s: float = Field(0.04, gt=0, le=0.5, description="typical translation speed")
    yaw_rate_rad_s: float = Field(0.3, ge=0, le=5.0, description="typical rotation rate")
    correlation_s: float = Field(1.5, gt=0.05, le=60.0)
    keep_within_m: float = Field(0.08, gt=0, le=2.0, description="centre pull starts past this radius")


class Occluder(_Strict):
    """An arm reaching over the table: a capsule at height_m from the shoulder to the hand. The hand
    reaches in from the shoulder in reach_s, sweeps from from_m to to_m, and withdraws in reach_s."""

    t_start_s: float = Field(ge=0)
    t_end_s: float = Field(gt=0)
    reach_s: float = Field(0.15, gt=0, le=10)
    shoulder_m: tuple[float, float] = Field(description="where the arm enters, world x, y (off the table)")
    from_m: tuple[float, float]
    to_m: tuple[float, float]
    width_m: float = Field(0.07, gt=0.005, le=0.5)
    height_m: float = Field(0.25, gt=0.0, le=0.9)

    @model_validator(mode="after")
    def _ordered(self) -> Occluder:
        if self.t_end_s - self.t_start_s <= 2 * self.reach_s:
            raise ValueError("t_end_s - t_start_s must leave time to reach in and withdraw (2 x reach_s)")
        return self


class Scenario(_Strict):
    name: str = Field(min_length=1, max_length=64)
    seed: int = Field(1, ge=0, description="the world's own randomness (belt vibration)")
    duration_s: float = Field(gt=0, le=3600)
    fps: float = Field(30.0, ge=1, le=240)
    settle_s: float = Field(0.3, ge=0, le=10, description="simulated before frame 0, modules stopped")
    table: TableSpec = TableSpec()
    cloth: ClothSpec = ClothSpec()
    texture: TextureSpec = TextureSpec()
    camera: CameraSpec = CameraSpec()
    cameras: list[CameraSpec] = Field(
        [], max_length=MAX_CAMERAS, description="every camera, first first; `camera` is a one-camera list"
    )
    noise: NoiseSpec = NoiseSpec()
    light: LightSpec = LightSpec()
    initial_pose: Pose = Pose()
    supersample: int = Field(2, ge=1, le=4, description="render scale before area downsampling")
    timeline: list[SetCommand] = []
    random_drives: list[RandomDrive] = []
    occluders: list[Occluder] = []
    infeed: Infeed | None = Field(None, description="pieces laid at the -x edge at a rate (a flow)")
    flow: Flow | None = Field(None, description="the placement a flow's outfeed judges against")

    @property
    def frame_count(self) -> int:
        return math.floor(self.duration_s * self.fps + 1e-9) + 1

    @property
    def camera_specs(self) -> list[CameraSpec]:
        """Every camera, the first being `camera`, each with its name filled in (cam0, cam1, ...)."""
        specs = [self.camera, *self.cameras[1:]]
        return [s if s.name else s.model_copy(update={"name": f"cam{i}"}) for i, s in enumerate(specs)]

    @model_validator(mode="after")
    def _cameras_agree(self) -> Scenario:
        if self.cameras:
            # A dumped scenario holds both, equal; anything else is two answers to "the first camera".
            if "camera" in self.model_fields_set and self.camera != self.cameras[0]:
                raise ValueError("camera: give camera (one camera) or cameras (several), not both")
            object.__setattr__(self, "camera", self.cameras[0])  # frozen model: set once, here
        if self.camera.capture_skew_s != 0.0:
            key = "cameras.0" if self.cameras else "camera"
            raise ValueError(f"{key}.capture_skew_s must be 0: skews are measured from the first camera")
        names = [s.name for s in self.camera_specs]
        for i, name in enumerate(names):
            if name in names[:i]:
                raise ValueError(f"cameras.{i}.name: {name!r} is taken by an earlier camera")
        return self

    @model_validator(mode="after")
    def _flaps_fit(self) -> Scenario:
        for i, flap in enumerate(self.initial_pose.flaps):
            check_flap(flap, self.cloth, f"initial_pose.flaps.{i}")
        return self

    @model_validator(mode="after")
    def _flow_fits(self) -> Scenario:
        _check_flow(self)
        return self

    @model_validator(mode="after")
    def _module_ids_exist(self) -> Scenario:
        n_modules = self.table.modules_x * self.table.modules_y
        for i, cmd in enumerate(self.timeline):
            bad = [m for m in cmd.modules.ids or [] if m >= n_modules]
            if bad:
                raise ValueError(f"timeline[{i}].modules.ids: {bad} out of range (table has {n_modules})")
        return self


def _check_flow(sc: Scenario) -> None:
    """A flow's pieces and placement lie on its table; `flow` judges what an infeed lays."""
    half_x, half_y = sc.table.modules_x * sc.table.pitch_m / 2, sc.table.modules_y * sc.table.pitch_m / 2
    if sc.flow is not None and sc.infeed is None:
        raise ValueError("flow: needs an infeed, whose pieces it judges")
    if sc.infeed is not None:
        if max(abs(y) for y in sc.infeed.y_m) > half_y:
            raise ValueError(f"infeed.y_m: must lie within the table's ±{half_y:g} m")
        if sc.infeed.lead_m > 2 * half_x:
            raise ValueError(f"infeed.lead_m: must be at most the table's length, {2 * half_x:g} m")
    if sc.flow is not None:
        p = sc.flow.placement
        if abs(p.x_m) > half_x or abs(p.y_m) > half_y:
            raise ValueError(f"flow.placement: ({p.x_m}, {p.y_m}) is off the table ±{half_x:g}, ±{half_y:g}")


def check_flap(flap: Flap, cloth: ClothSpec, key: str) -> None:
    """A flap folds over at most half of the cloth's shorter side, so it lies on the cloth."""
    most_m = min(cloth.size_m) / 2.0
    if flap.size_m > most_m:
        raise ValueError(
            f"{key}.size_m ({flap.size_m}) must be at most {most_m}, half the cloth's shorter side"
        )


def _format_errors(source: str, err: ValidationError) -> str:
    lines = [f"{source}: invalid scenario"]
    for e in err.errors():
        key = ".".join(str(p) for p in e["loc"]) or "(top level)"
        lines.append(f"  {key}: {e['msg']}")
    return "\n".join(lines)


def resolve_path(name_or_path: str | Path) -> Path:
    """A path as given, or the name of a shipped scenario ('compress' -> hwsim/scenarios/compress.yaml)."""
    path = Path(name_or_path)
    if path.exists():
        return path
    shipped = SCENARIO_DIR / f"{name_or_path}.yaml"
    if shipped.exists():
        return shipped
    names = ", ".join(sorted(p.stem for p in SCENARIO_DIR.glob("*.yaml")))
    raise ScenarioError(f"{name_or_path}: no such file, and not a shipped scenario ({names})")


def shipped_names() -> list[str]:
    return sorted(p.stem for p in SCENARIO_DIR.glob("*.yaml"))


def parse(data: object, source: str = "<scenario>") -> Scenario:
    if not isinstance(data, dict):
        raise ScenarioError(f"{source}: a scenario is a mapping of keys, got {type(data).__name__}")
    try:
        return Scenario.model_validate(data)
    except ValidationError as err:
        raise ScenarioError(_format_errors(source, err)) from None


def load(name_or_path: str | Path, **overrides: object) -> Scenario:
    """Read and validate a scenario; `overrides` replace top-level keys (e.g. duration_s for a short run)."""
    path = resolve_path(name_or_path)
    try:
        data = yaml.safe_load(path.read_text())
    except yaml.YAMLError as err:
        raise ScenarioError(f"{path}: not valid YAML: {err}") from None
    if isinstance(data, dict):
        data.update({k: v for k, v in overrides.items() if v is not None})
    return parse(data, str(path))
