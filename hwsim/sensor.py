"""The camera's sensor as `hwsim serve` delivers it: the rendered frame, sensor noise and JPEG."""

from __future__ import annotations

import cv2
import numpy as np

from hwsim.camera import Camera
from hwsim.cloth import ClothGrid
from hwsim.recording import render_frame
from hwsim.renderer import Renderer
from hwsim.scenario import Scenario
from hwsim.world import World

NOISE_BANK = 8  # sensor-noise frames drawn once and cycled: per-frame draws cost more than rendering
JPEG_QUALITY = 90


class Sensor:
    def __init__(self, scenario: Scenario, camera: Camera, grid: ClothGrid) -> None:
        self.renderer = Renderer(scenario, camera, grid)
        rng = np.random.default_rng(scenario.noise.seed)
        shape = (camera.height, camera.width, 3)
        self._noise = rng.standard_normal((NOISE_BANK, *shape), dtype=np.float32) * scenario.noise.sigma

    def jpeg(self, world: World, k: int) -> bytes:
        """Frame k of the stream, at the world's current instant."""
        image, _ = render_frame(world, self.renderer)
        level = image * 255.0 + self._noise[k % NOISE_BANK]
        bgr = np.clip(level + 0.5, 0, 255).astype(np.uint8)
        ok, jpeg = cv2.imencode(".jpg", bgr, [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY])
        if not ok:
            raise RuntimeError("JPEG encoding failed")
        return bytes(jpeg.tobytes())
