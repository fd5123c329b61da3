"""Short scenarios on the live cell's coarse cloth, cheap to run: two cameras of a quarter the live
cell's pixels (f_px / 4 keeps the view, at 1/16 of the pixels)."""

from __future__ import annotations

from typing import Any

SMALL_TOP = {"width": 160, "height": 120, "f_px": 225.0}
SMALL_OBLIQUE = {**SMALL_TOP, "name": "side", "position_m": [0.0, -0.423, 0.906], "tilt_rad": 0.436}


def two_cameras(**extra: Any) -> dict[str, Any]:
    """A short two-camera scenario's data, `extra` keys replacing its own."""
    return {
        "name": "two-cameras",
        "duration_s": 0.1,
        "settle_s": 0.0,
        "supersample": 1,
        "cloth": {"spacing_m": 0.0075, "substep_s": 0.0005, "stretch_iterations": 1},
        "cameras": [SMALL_TOP, SMALL_OBLIQUE],
        **extra,
    }
