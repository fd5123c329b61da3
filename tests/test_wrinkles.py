"""Ridges laid into hwsim's cloth: anywhere, in any direction, without stretching the sheet; a ridge
that would overhang is refused with its key."""

import math

import numpy as np
import pytest

from hwsim import scenario as scenarios
from hwsim.cloth import ClothGrid
from hwsim.ridges import lay_ridges


def test_ridges_are_laid_without_stretching_the_sheet() -> None:
    grid = ClothGrid.from_spec(scenarios.ClothSpec())
    ridges = [
        scenarios.Ridge(height_m=0.012, at_m=(0.05, 0.0), direction_rad=1.2),
        scenarios.Ridge(height_m=0.008, sigma_m=0.010, at_m=(-0.08, 0.0), direction_rad=math.pi / 2),
    ]
    centre = np.array([(grid.nx - 1) * grid.dx_m, (grid.ny - 1) * grid.dy_m]) / 2.0
    xy, z = lay_ridges(grid.st_m - centre, ridges)
    x = np.concatenate([xy, z[..., None]], axis=-1)
    for axis, rest_m in ((1, grid.dx_m), (0, grid.dy_m)):
        strain = np.linalg.norm(np.diff(x, axis=axis), axis=-1) / rest_m - 1.0
        assert np.abs(strain).max() < 0.01
    assert z.max() == pytest.approx(0.012, rel=0.02)
    assert z[grid.ny // 2, grid.nx // 2 - round(0.08 / grid.dx_m)] == pytest.approx(0.008, rel=0.02)


def test_an_overhanging_ridge_is_refused_with_its_key() -> None:
    with pytest.raises(scenarios.ScenarioError, match=r"initial_pose\.ridges\.0"):
        scenarios.parse(
            {
                "name": "t",
                "duration_s": 1.0,
                "initial_pose": {"ridges": [{"height_m": 0.02, "sigma_m": 0.01}]},
            }
        )
