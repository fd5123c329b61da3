"""The camera's sensor as `hwsim serve` delivers it: the rendered frame, sensor noise and JPEG."""

from __future__ import annotations

import cv2
import numpy as np

from hwsim.camera import Camera
from hwsim.cloth_grid import ClothGrid
from hwsim.quantise import quantise_bgr8
from hwsim.recording import frame_states, noise_rng
from hwsim.renderer_spares import make_renderer
from hwsim.scenario import Scenario
from hwsim.scene import SceneState
from hwsim.world import World

NOISE_BANK = 8  # sensor-noise frames drawn once and cycled: per-frame draws cost more than rendering
JPEG_QUALITY = 90


class Sensor:
    """Camera `index` of the scenario (its own noise bank), frames `skew_s` after the world's instant."""

    def __init__(
        self, scenario: Scenario, camera: Camera, grid: ClothGrid, index: int = 0, skew_s: float = 0.0
    ) -> None:
        self.renderer = make_renderer(scenario, camera, grid, self)
        self.skew_s = skew_s
        rng = noise_rng(scenario, index)
        shape = (camera.height, camera.width, 3)
        self._noise = rng.standard_normal((NOISE_BANK, *shape), dtype=np.float32) * scenario.noise.sigma

    def jpeg(self, world: World, k: int) -> bytes:
        """Frame k of the stream, at the world's current instant."""
        return self.encode(frame_states(world, self.skew_s), k)

    def encode(self, states: list[SceneState], k: int) -> bytes:
        """Frame k of the stream, of the scene `states` (hwsim.recording.frame_states)."""
        image, _ = self.renderer.render(states)
        bgr = quantise_bgr8(image, self._noise[k % NOISE_BANK])
        ok, jpeg = cv2.imencode(".jpg", bgr, [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY])
        if not ok:
            raise RuntimeError("JPEG encoding failed")
        return bytes(jpeg.tobytes())
