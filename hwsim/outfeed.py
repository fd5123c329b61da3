"""The outfeed: a piece is judged from its truth as its leading edge reaches the table's +x edge, and taken
off the table once its centre has crossed that edge.

The judgement is what the next station receives: the piece's highest node (its true max height), how far
its centre lies across the outfeed direction from the placement's y and how far its heading is from the
placement's (along the direction of travel the crossing itself fixes where it is), and its time in the
cell, from being laid at the infeed to reaching the outfeed.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from hwsim.pieces import Piece, cloth_pose, sheet_measures
from hwsim.scenario_flow import Placement


def leading_x_m(piece: Piece) -> float:
    return float(piece.cloth.positions_m()[..., 0].max())


def judge(piece: Piece, t_s: float, placement: Placement) -> dict[str, Any]:
    """The outfeed's record of a piece reaching it at t_s (GET /outfeed, one entry)."""
    x, y, theta = cloth_pose(piece.cloth)
    measures = sheet_measures(piece.cloth)
    heading_error = math.remainder(theta - placement.theta_rad, 2 * math.pi)
    return {
        "id": piece.id,
        "fabric": piece.fabric,
        "size_m": list(piece.cloth.spec.size_m),
        "flap": piece.flap,
        "laid_s": round(piece.laid_s, 6),
        "left_s": round(t_s, 6),
        "t_s": round(t_s - piece.laid_s, 6),
        "max_height_mm": round(measures["max_height_m"] * 1e3, 4),
        "pose_error_mm": round(abs(float(y) - placement.y_m) * 1e3, 4),
        "pose_error_deg": round(abs(math.degrees(heading_error)), 4),
        "pose": [round(float(x), 6), round(float(y), 6), round(math.degrees(float(theta)), 4)],
        "folded_ratio": round(measures["folded_ratio"], 6),
    }


def past_edge(piece: Piece, x_max_m: float) -> bool:
    """Its centre has crossed the outfeed edge: the next station has it."""
    return bool(np.mean(piece.cloth.positions_m()[..., 0]) > x_max_m)
