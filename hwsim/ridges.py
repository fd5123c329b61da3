"""Ridges laid into a flat sheet without stretching it.

A ridge is a Gaussian profile z(u) = h·exp(-u²/2σ²) across a straight line, u the material distance from
the line. Laid with u as arc length, a material point at u lies at horizontal distance
∫₀ᵘ √(1 - z'(s)²) ds from the line: the sheet keeps its length, and the cloth on either side is drawn
towards the ridge by the draw ∫₀ᵘ (1 - √(1 - z'²)) ds. Each ridge adds its height and its draw.
"""

from __future__ import annotations

import math

import numpy as np

from hwsim.scenario import Ridge

_SAMPLE_M = 1e-4  # the draw integral's step


def _draw_m(u_m: np.ndarray, ridge: Ridge) -> np.ndarray:
    """Signed draw towards the ridge line of the points at material distances u_m from it."""
    reach = float(np.abs(u_m).max(initial=0.0)) + _SAMPLE_M
    s = np.arange(-reach, reach + _SAMPLE_M, _SAMPLE_M)
    slope = -ridge.height_m * s / ridge.sigma_m**2 * np.exp(-0.5 * (s / ridge.sigma_m) ** 2)
    shortfall = 1.0 - np.sqrt(np.clip(1.0 - slope**2, 0.0, None))
    cumulative = np.concatenate([[0.0], np.cumsum((shortfall[1:] + shortfall[:-1]) / 2.0 * _SAMPLE_M)])
    cumulative -= np.interp(0.0, s, cumulative)
    return np.asarray(np.interp(u_m, s, cumulative))


def lay_ridges(st_m: np.ndarray, ridges: list[Ridge]) -> tuple[np.ndarray, np.ndarray]:
    """Positions in the cloth frame of material points st_m (..., 2), measured from the cloth's centre:
    (xy (..., 2), z (...)) with the ridges laid in."""
    xy = np.array(st_m, dtype=float)
    z = np.zeros(xy.shape[:-1])
    for ridge in ridges:
        along = np.array([math.cos(ridge.direction_rad), math.sin(ridge.direction_rad)])
        normal = np.array([-along[1], along[0]])
        u = (st_m - np.asarray(ridge.at_m)) @ normal
        z += ridge.height_m * np.exp(-0.5 * (u / ridge.sigma_m) ** 2)
        xy -= _draw_m(u, ridge)[..., None] * normal
    return xy, z
