"""`hwsim record`: run a scenario and write a recording (format: docs/recording-format.md).

DIR/frames/NNNNNN.png   lossless frames, BGR, the first camera's
DIR/camera.json         K, dist, width, height, T_cam_world
DIR/cameras/NAME/       each further camera's frames/ and camera.json, in the same layout
DIR/table.json          the module layout (ids, centres), for replaying commands
DIR/commands.csv        t_s, module, speed_m_s, heading_rad: the commands in force while each frame was taken
DIR/truth.npz           ground truth, for grading only
DIR/scenario.yaml       the scenario as run
"""

from __future__ import annotations

import csv
import json
import time
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import yaml
from tqdm import tqdm

from hwsim.camera import Camera
from hwsim.paths import camera_dir, frame_path
from hwsim.quantise import to_sensor_bgr8
from hwsim.renderer import Renderer
from hwsim.renderer_spares import make_renderer
from hwsim.scenario import Scenario, ScenarioError
from hwsim.scene import SceneState
from hwsim.world import World

# PNG level 1: about 3x faster than the default with files ~15 % larger; still lossless.
_PNG_PARAMS = [cv2.IMWRITE_PNG_COMPRESSION, 1]


@dataclass(frozen=True)
class RecordStats:
    frames: int
    wall_s: float
    physics_ms: float  # mean per frame
    render_ms: float  # mean per frame, including sensor noise


class FrameSink:
    """Writes frames on a background thread (PNG encoding releases the GIL) while the world steps."""

    def __init__(self, out_dir: Path) -> None:
        (out_dir / "frames").mkdir(parents=True, exist_ok=True)
        self.out_dir = out_dir
        self._pool = ThreadPoolExecutor(max_workers=1)
        self._pending: list[Future[bool]] = []

    def write(self, index: int, image: np.ndarray) -> None:
        self._pending.append(
            self._pool.submit(cv2.imwrite, str(frame_path(self.out_dir, index)), image, _PNG_PARAMS)
        )
        if len(self._pending) > 8:
            self._check(self._pending.pop(0))

    def close(self) -> None:
        for fut in self._pending:
            self._check(fut)
        self._pool.shutdown()

    @staticmethod
    def _check(fut: Future[bool]) -> None:
        if not fut.result():
            raise OSError("could not write a frame (disk full or not writable?)")


def render_frame(world: World, renderer: Renderer, skew_s: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """The frame at the world's current instant plus `skew_s` (a camera's capture_skew_s): image in [0, 1]
    and node visibility, with motion blur spread over the exposure when the scenario asks for it."""
    return renderer.render(frame_states(world, skew_s))


def frame_states(world: World, skew_s: float = 0.0) -> list[SceneState]:
    """What a camera exposing at the world's current instant plus `skew_s` sees: one state per motion-blur
    sample across the exposure, the last at the frame's instant."""
    noise = world.scenario.noise
    n = noise.motion_blur_samples
    backs = [noise.exposure_s * (n - 1 - k) / max(n - 1, 1) - skew_s for k in range(n)]
    return [world.scene_state(before_s=b) for b in backs]


def noise_rng(scenario: Scenario, index: int) -> np.random.Generator:
    """Camera `index`'s own sensor noise; the first camera's draws are those of a one-camera scenario."""
    seed = scenario.noise.seed
    return np.random.default_rng(seed if index == 0 else (seed, index))


def record(scenario: Scenario, out_dir: Path, arch: str = "cpu") -> RecordStats:
    if scenario.infeed is not None:  # truth.npz holds one cloth; a flow's pieces come and go
        raise ScenarioError(f"{scenario.name}: a flow (infeed) cannot be recorded; run it with hwsim serve")
    out_dir.mkdir(parents=True, exist_ok=True)
    world = World(scenario, arch)
    specs = scenario.camera_specs
    cameras = [Camera.from_spec(spec) for spec in specs]
    renderers = [make_renderer(scenario, cam, world.cloth.grid, world) for cam in cameras]
    rngs = [noise_rng(scenario, i) for i in range(len(specs))]
    sinks = [FrameSink(camera_dir(out_dir, i, str(spec.name))) for i, spec in enumerate(specs)]
    n = scenario.frame_count
    nodes = np.empty((n, world.cloth.grid.ny, world.cloth.grid.nx, 3), np.float32)
    visible = np.empty((n, world.cloth.grid.ny, world.cloth.grid.nx), bool)
    speeds = np.empty((n, world.table.n_modules), np.float32)
    headings = np.empty((n, world.table.n_modules), np.float32)
    physics_s = render_s = 0.0
    start = time.perf_counter()
    try:
        # A progress bar on a terminal only (tqdm disables itself elsewhere: logs and CI stay quiet).
        for k in tqdm(range(n), desc=f"recording {scenario.name}", unit="frame", disable=None, leave=False):
            t0 = time.perf_counter()
            for i, spec in enumerate(specs):
                image, seen = render_frame(world, renderers[i], spec.capture_skew_s)
                sinks[i].write(k, to_sensor_bgr8(image, scenario.noise.sigma, rngs[i]))
                if i == 0:
                    visible[k] = seen  # truth's visibility is the first camera's
            nodes[k] = world.cloth.positions_m()
            speeds[k], headings[k] = world.table.speed_m_s, world.table.heading_rad
            t1 = time.perf_counter()
            if k < n - 1:
                world.step()
            physics_s += time.perf_counter() - t1
            render_s += t1 - t0
    finally:
        for sink in sinks:
            sink.close()
    for i, (spec, cam) in enumerate(zip(specs, cameras, strict=True)):
        cam.save(camera_dir(out_dir, i, str(spec.name)) / "camera.json")
    write_table(world, out_dir / "table.json")
    _write_commands(world, out_dir / "commands.csv")
    (out_dir / "scenario.yaml").write_text(yaml.safe_dump(scenario.model_dump(mode="json"), sort_keys=False))
    np.savez_compressed(
        out_dir / "truth.npz",
        t_s=np.arange(n) / scenario.fps,
        nodes_m=nodes,
        st_m=world.cloth.grid.st_m,
        visible=visible,
        module_speed_m_s=speeds,
        module_heading_rad=headings,
    )
    return RecordStats(n, time.perf_counter() - start, physics_s / n * 1e3, render_s / n * 1e3)


def write_table(world: World, path: Path) -> None:
    spec = world.table.spec
    path.write_text(
        json.dumps(
            {
                "modules_x": spec.modules_x,
                "modules_y": spec.modules_y,
                "pitch_m": spec.pitch_m,
                "module_size_m": spec.module_size_m,
                "centres_m": world.table.centres_m.tolist(),
            },
            indent=2,
        )
        + "\n"
    )


def _write_commands(world: World, path: Path) -> None:
    """Each command stamped with the first frame it moved: the world renders frame k at t_k, then tells
    the controller what is due at t_k and advances, so a command told at t_k acts while frame k + 1 is
    taken. That is what a clothd recording's commands.csv holds too (the commands in force while each
    frame was captured); stamped with t_k, a replay's model ran every command a frame early."""
    with path.open("w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["t_s", "module", "speed_m_s", "heading_rad"])
        for row in world.command_log:
            acts_s = row.t_s + world.dt_s
            w.writerow([f"{acts_s:.6f}", row.module, f"{row.speed_m_s:.6f}", f"{row.heading_rad:.6f}"])
