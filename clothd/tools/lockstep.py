"""The closed loop in lockstep: hwsim's cell and clothd's tracker and cell controller in one process,
tick by tick, as fast as the CPU allows.

No clock, no threads, no sleeps: time is the world's, and it advances one tick of `loop.tick_hz` at a
time. Each tick the controller's last commands reach the drives (hwsim's firmware semantics), the world
steps, the camera delivers a frame when one is due (rendered, sensor noise and JPEG, as `hwsim serve`
streams it), the tracker tracks it with the commands that were in force, and the cell controller
answers. The same seed gives the same run under any load (on one kind of processor: floating point
differs across instruction sets). What it leaves out is the real-time path (the stepper link, the video
stream, the compute process, the tick's timing), which the integration tests and `clothd bench loop`
cover. The files between them are the real ones: hwsim writes camera.json and clothd reads it.

The daemon's own rules for a setpoint are kept to what the benches use: hold and flatten hold the pose
the cloth has when they are set, a move needs the cloth tracked, and a fault (a halt reason) drops the
setpoint to idle until the next one.
"""

from __future__ import annotations

import math
import tempfile
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from clothd.config import Config
from clothd.core.camera_model import CameraModel
from clothd.core.cell_controller import CellController
from clothd.core.control import Setpoint
from clothd.core.conveyor import ConveyorLayout
from clothd.core.flatness import Flatness
from clothd.core.messages import Estimate, ModuleCommands, PairedView
from clothd.core.modes import FlatnessBasis, LoopState, Mode
from clothd.core.tracker import Tracker
from clothd.core.workspace import Workspace
from clothd.formats import read_camera
from clothd.loop.status import FlatnessState
from clothd.taichi_runtime import start_taichi
from hwsim import scenario as scenarios
from hwsim.camera import Camera
from hwsim.firmware import drive_targets
from hwsim.scenario import Pose, Push
from hwsim.sensor import Sensor
from hwsim.world import World

CAMERA_FPS = 15.0  # as `hwsim serve` streams it


def scenario_cameras(
    sc: scenarios.Scenario, world: World, cameras: int | None, skew_s: float | None = None
) -> tuple[list[Sensor], list[CameraModel]]:
    """hwsim's sensors of the scenario's first `cameras` cameras (None: all), and clothd's models of them
    read from the camera.json hwsim writes: the interface between them, as live. skew_s: every further
    camera's capture this long after the first's (None: as the scenario sets it)."""
    sensors, models = [], []
    with tempfile.TemporaryDirectory(prefix="clothd-lockstep-") as tmp:
        for index, spec in enumerate(sc.camera_specs[:cameras]):
            camera = Camera.from_spec(spec)
            camera.save(Path(tmp) / f"camera{index}.json")
            models.append(read_camera(Path(tmp) / f"camera{index}.json"))
            skew = spec.capture_skew_s if skew_s is None or index == 0 else skew_s
            sensors.append(Sensor(sc, camera, world.cloth.grid, index, skew))
    return sensors, models


def frame_of(world: World, sensor: Sensor, k: int) -> np.ndarray:
    """Frame k as `hwsim serve` streams it (rendered, sensor noise and JPEG), decoded."""
    image = cv2.imdecode(np.frombuffer(sensor.jpeg(world, k), np.uint8), cv2.IMREAD_COLOR)
    assert image is not None  # hwsim's own JPEG
    return image


def command_table(world: World, commands: ModuleCommands) -> None:
    """The commands reach the drives, as hwsim's firmware turns them into drive targets."""
    world.table.command(
        np.arange(world.table.n_modules), *drive_targets(commands.speed_m_s, commands.heading_rad)
    )


def frames_of(world: World, sensors: list[Sensor], k: int) -> tuple[np.ndarray, list[PairedView | None]]:
    """Frame k of the first sensor, and the further sensors' as views paired with it."""
    images = [frame_of(world, sensor, k) for sensor in sensors]
    views: list[PairedView | None] = [
        PairedView(image, world.t_s + s.skew_s) for image, s in zip(images[1:], sensors[1:], strict=True)
    ]
    return images[0], views


class LockstepCell:
    """hwsim's scenario and clothd's loop, advanced together by `sleep`."""

    def __init__(
        self, cfg: Config, scenario: str = "cell", cameras: int | None = None, skew_s: float | None = None
    ) -> None:
        """cameras: the scenario's first this many (None: all of them); skew_s: as scenario_cameras'."""
        start_taichi(cfg.taichi.arch)
        sc = self.scenario = scenarios.load(scenario)
        self.world = World(sc, log_commands=False)
        self._earlier_worlds_s = 0.0
        self.period_s = cfg.loop.period_s
        if not math.isclose(self.world.dt_s, self.period_s):
            raise ValueError(f"lockstep needs the world's step ({self.world.dt_s:g} s) to be the tick")
        self.sensors, models = scenario_cameras(sc, self.world, cameras, skew_s)
        self.camera_every = max(1, round(sc.fps / CAMERA_FPS))
        layout = ConveyorLayout.of_cell(cfg.cell)
        self.tracker = Tracker(cfg.tracker, models[0], layout, other_cameras=models[1:])
        self.cell = CellController(
            cfg.control,
            cfg.cell,
            layout,
            Workspace.of_cell(cfg.cell),
            self.period_s,
            cfg.tracker.physics.strain_limit,
            cfg.tracker.estimates_shape,
        )
        self.n_modules = layout.n_modules
        self._loop_idle()
        self.ticks = 0

    def _loop_idle(self) -> None:
        """The loop as it starts: modules told to stop, idle, nothing tracked yet."""
        self.commands = ModuleCommands.all_stop(self.n_modules)
        self.setpoint = Setpoint(Mode.IDLE, None)
        self.state = LoopState.STARTING
        self.halt_reason: str | None = None
        self.estimate: Estimate | None = None
        self.flatness: Flatness | None = None

    # -- time ----------------------------------------------------------------------------------------

    def now(self) -> float:
        return self.world.t_s

    @property
    def simulated_s(self) -> float:
        """The simulated time this cell has run, over all its worlds."""
        return self._earlier_worlds_s + self.world.t_s

    def restart(self) -> None:
        """The cell as it was built: a new world (time 0, the belts stopped and straight, the scenario's
        cloth, whose solver is reused bit for bit: hwsim/cloth_spares.py) and the loop idle and not
        tracking. What runs after this depends on nothing that ran before it."""
        self._earlier_worlds_s += self.world.t_s
        del self.world  # its cloth becomes the spare the new world takes
        self.world = World(self.scenario, log_commands=False)
        self._loop_idle()
        self.tracker.restart()
        self.cell.reset()

    def sleep(self, seconds: float) -> None:
        for _ in range(max(1, round(seconds / self.period_s))):
            self._tick()

    def wait(self, check: Any, timeout_s: float, what: str) -> None:
        deadline = self.now() + timeout_s
        while not check():
            if self.now() > deadline:
                raise RuntimeError(f"{what}: not within {timeout_s} s")
            self._tick()

    # -- what the benches ask of a cell ----------------------------------------------------------------

    def status(self) -> dict[str, Any]:
        est = self.estimate
        pose = None
        if est is not None and est.tracking:
            pose = {"x_m": est.pose[0], "y_m": est.pose[1], "theta_rad": est.pose[2]}
        flatness = None if self.flatness is None else FlatnessState.of(self.flatness).model_dump()
        return {
            "state": self.state.value,
            "mode": self.setpoint.mode.value,
            "link": {"state": "connected"},
            "pose": pose,
            "flatness": flatness,
            "halt_reason": self.halt_reason,
        }

    def truth(self) -> dict[str, Any]:
        return {
            "t_s": self.world.t_s,
            "pose": self.world.cloth_pose().tolist(),
            "module_speed_m_s": self.world.table.speed_m_s.tolist(),
            "module_cmd_speed_m_s": self.world.table.cmd_speed_m_s.tolist(),
            **self.world.sheet_measures(),
        }

    def setpoint_request(self, body: dict[str, Any]) -> None:
        mode = Mode(body["mode"])
        est = self.estimate
        if mode != Mode.IDLE and (self.state != LoopState.TRACKING or est is None or not est.tracking):
            raise RuntimeError(f"setpoint {body}: the cloth is not tracked (state {self.state})")
        if mode == Mode.MOVE:
            target: np.ndarray | None = np.array([body["x_m"], body["y_m"], body["theta_rad"]])
        elif mode in (Mode.HOLD, Mode.FLATTEN):
            assert est is not None
            target = est.pose.copy()
        elif mode == Mode.IDLE:
            target = None
        else:
            raise ValueError(f"lockstep does not play {mode} setpoints")
        self.setpoint = Setpoint(mode, target, started_mono_s=self.now())
        self.halt_reason = None

    def lay(
        self,
        pose: list[float],
        ridges: list[dict[str, Any]] | None = None,
        flaps: list[dict[str, Any]] | None = None,
    ) -> None:
        """hwsim's POST /cloth (flaps and ridges as a scenario's pose gives them), then a reset of tracking
        onto it, as the benches do it live."""
        self.setpoint_request({"mode": "idle"})
        self.wait(lambda: not self.world.table.speed_m_s.any(), 5, "belts stopped")
        laid = {
            "x_m": pose[0],
            "y_m": pose[1],
            "theta_rad": pose[2],
            "flaps": flaps or [],
            "ridges": ridges or [],
        }
        self.world.lay(Pose.model_validate(laid))
        self.reset()
        self.wait(lambda: self.state == LoopState.TRACKING, 30, "tracking again")

    def push(self, push: dict[str, Any], then_s: float) -> None:
        self.world.push(Push.model_validate(push))
        self.sleep(then_s)

    def reset(self) -> None:
        self.tracker.reset()
        self.cell.reset()
        self.estimate = self.flatness = None

    # -- one tick ------------------------------------------------------------------------------------

    def _tick(self) -> None:
        command_table(self.world, self.commands)
        in_force = self.commands
        self.world.step()
        self.ticks += 1
        if self.world.frame_index % self.camera_every == 0:
            k = self.world.frame_index // self.camera_every
            # The further cameras matter when tracking begins, and after only where it began measured
            # (clothd/core/second_view.py): rendering them otherwise would only slow the lockstep.
            measured = self.tracker.initialising or self.tracker.flatness_basis == FlatnessBasis.MEASURED
            sensors = self.sensors if measured else self.sensors[:1]
            image, views = frames_of(self.world, sensors, k)
            self.estimate = self.tracker.track(image, self.world.t_s, in_force, views)
            self.flatness = self.cell.read_flatness(self.estimate)
        have_frame = self.world.frame_index >= self.camera_every
        step = self.cell.step(have_frame, self.estimate, self.setpoint, self.flatness, self.now())
        self.state = step.state
        self.commands = step.commands
        if step.halt_reason is not None and self.setpoint.mode != Mode.IDLE:
            self.setpoint = Setpoint(Mode.IDLE, None)
            self.halt_reason = step.halt_reason
