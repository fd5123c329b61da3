"""A rendered frame as the sensor delivers it: Gaussian noise in grey levels, then 8 bits."""

from __future__ import annotations

import numpy as np


def to_sensor_bgr8(image: np.ndarray, noise_sigma: float, rng: np.random.Generator) -> np.ndarray:
    """Quantise a [0, 1] float image to 8 bits after adding Gaussian sensor noise (grey levels)."""
    noise = rng.standard_normal(image.shape, dtype=np.float32) * noise_sigma if noise_sigma > 0 else None
    return quantise_bgr8(image, noise)


def quantise_bgr8(image: np.ndarray, noise_levels: np.ndarray | None) -> np.ndarray:
    """A [0, 1] float32 image as 8 bits, after adding `noise_levels` (grey levels; None: none), rounded.
    Worked in one array, in place: each fresh frame-sized array costs its page faults, and the three an
    expression like clip(image * 255 + noise + 0.5) makes took ten times as long as the arithmetic."""
    level = image * np.float32(255.0)
    if noise_levels is not None:
        level += noise_levels
    level += np.float32(0.5)
    np.clip(level, 0, 255, out=level)
    return level.astype(np.uint8)
