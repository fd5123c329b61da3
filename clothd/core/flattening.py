"""The flattening regulator: per-module belt velocities that pull each ridge's two sides apart.

The derivation is in docs/flattening.md. In short: a ridge holds the slack s (m) of the cloth that is
short across it, along its compressed direction ĉ. A module under the cloth on the + side of the ridge
(within `reach_m` of it, and not under the ridge itself) drives its material at +v ĉ, one on the - side
at -v ĉ; friction carries the material, so the slack closes at 2v. With v = s / (2τ) the slack decays
like exp(-t/τ) (a first-order loop), limited to `max_speed_m_s`; the pull fades as the ridge comes down
and stops when it is gone. The field is then made free of rigid motion (its least-squares translation
and rotation about the cloth's centre are taken out), so that it changes the cloth's shape and leaves
its pose to the pose controller. As the estimate's most stretched edge nears `strain_limit`, the whole
field is scaled down to nothing, so that the cloth is never torn and never slips.
"""

from __future__ import annotations

import math

import numpy as np

from clothd.config import FlattenConfig
from clothd.core.flatness import Flatness, Ridge

STRAIN_GUARD_SPAN = 0.5  # the field fades out over the last half of the way to strain_limit


def rigid_part(velocities: np.ndarray, points_m: np.ndarray, centre_m: np.ndarray) -> np.ndarray:
    """The least-squares rigid field V + ω ẑ × (p - centre) of velocities (n, 2) at points (n, 2)."""
    if len(points_m) == 0:
        return np.zeros_like(velocities)
    r = points_m - centre_m
    v_mean = velocities.mean(axis=0)
    r_mean = r.mean(axis=0)
    rc = r - r_mean
    spread = float((rc**2).sum())
    omega = (
        0.0
        if spread < 1e-12
        else float((rc[:, 0] * velocities[:, 1] - rc[:, 1] * velocities[:, 0]).sum()) / spread
    )
    v0 = v_mean - omega * np.array([-r_mean[1], r_mean[0]])
    return np.asarray(v0 + omega * np.stack([-r[:, 1], r[:, 0]], axis=1))


def max_tensile_strain(nodes_xy_m: np.ndarray, rest_spacing_m: tuple[float, float]) -> float:
    """The most stretched row or column edge of the mesh (ny, nx, 2), as strain (0 when none is)."""
    return max(
        0.0,
        *(
            float((np.linalg.norm(np.diff(nodes_xy_m, axis=axis), axis=-1) / rest - 1.0).max())
            for axis, rest in ((1, rest_spacing_m[0]), (0, rest_spacing_m[1]))
        ),
    )


class FlatteningRegulator:
    """Per-module velocities (n_modules, 2) that flatten the ridges of an estimate.

    centres_m (n_modules, 2): the module centres; module_size_m: the side of a belt."""

    def __init__(
        self, cfg: FlattenConfig, centres_m: np.ndarray, module_size_m: float, strain_limit: float
    ) -> None:
        self.cfg = cfg
        self.centres_m = centres_m
        self.half_belt_m = module_size_m / 2.0
        self.strain_limit = strain_limit

    def velocities(
        self,
        flatness: Flatness,
        nodes_m: np.ndarray,
        cloth_size_m: tuple[float, float],
        under: np.ndarray,
        centre_m: np.ndarray,
    ) -> np.ndarray:
        """The flattening field for the modules `under` the cloth (bool, n_modules); zero elsewhere."""
        v = np.zeros_like(self.centres_m)
        for ridge in flatness.ridges:
            v[under] += self._pull(ridge, self.centres_m[under])
        if not v.any():
            return v
        v[under] -= rigid_part(v[under], self.centres_m[under], centre_m)
        ny, nx = nodes_m.shape[:2]
        spacing = (cloth_size_m[0] / (nx - 1), cloth_size_m[1] / (ny - 1))
        strain = max_tensile_strain(nodes_m[..., :2], spacing)
        guard = np.clip((self.strain_limit - strain) / (STRAIN_GUARD_SPAN * self.strain_limit), 0.0, 1.0)
        return np.asarray(v * guard)

    def _pull(self, ridge: Ridge, centres_m: np.ndarray) -> np.ndarray:
        """The pull of one ridge on modules at centres_m (k, 2): ±v ĉ on either side of it."""
        c = self.cfg
        across = np.array(
            [math.cos(ridge.compressed_direction_rad), math.sin(ridge.compressed_direction_rad)]
        )
        along = np.array([-across[1], across[0]])
        speed = min(c.max_speed_m_s, ridge.slack_m / (2.0 * c.time_constant_s))
        rel = centres_m[:, None, :] - ridge.quad_centres_m[None, :, :]  # (k, q, 2)
        lateral = np.abs(rel @ along)
        side = rel @ across
        # Each module is measured against the ridge's nearest stretch of line beside it.
        beside = lateral <= self.half_belt_m + c.ridge_margin_m
        dist = np.where(beside, np.abs(side), np.inf)
        nearest = np.argmin(dist, axis=1)
        s = side[np.arange(len(centres_m)), nearest]
        d = dist[np.arange(len(centres_m)), nearest]
        pulls = (d > self.half_belt_m) & (d <= c.reach_m)  # not under the ridge itself, and not too far
        return np.asarray(np.where(pulls[:, None], np.sign(s)[:, None] * speed * across, 0.0))
