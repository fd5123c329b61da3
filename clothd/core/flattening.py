"""The flattening regulator: per-module belt velocities that pull each ridge's two sides apart.

The derivation is in docs/flattening.md. In short: a ridge holds the slack s (m) of the cloth that is
short across it, along its compressed direction ĉ. A module under the cloth beside the ridge, on the +
side of its line (more than `ridge_margin_m` off it and within `reach_m`), drives its material at +v ĉ,
one on the - side at -v ĉ; friction carries the material, so the slack closes at 2v. With v = s / (2τ)
the slack decays like exp(-t/τ) (a first-order loop), limited to `max_speed_m_s`; the pull fades as the
ridge comes down and stops when it is gone, but not below `min_speed_m_s` while the ridge is seen: a ridge
held by the yarns' friction is a dead zone, which a pull fading with the slack stalls in. The field is
then made free of rigid motion (its least-squares translation and rotation about the cloth's centre are
taken out), so that it changes the cloth's shape and leaves its pose to the pose controller. As the
cloth as a whole (the median row or column of the mesh) is stretched towards `strain_limit`, the whole
field is scaled down to nothing, so that the cloth is never torn and never pulled to slip.

A ridge the estimate stops seeing is pulled on for `finish_s` more, at `max_speed_m_s`: below about
5 mm a 12 x 12 mesh's edge is shortened by under 1 %, so the estimate calls the cloth flat while a ridge
held by the yarns' friction stays wherever the pull stops (docs/flattening.md, "Finishing"). Each ridge is
remembered in the cloth's frame, so the finishing pull follows the cloth while it moves, and at its widest:
the estimate loses a ridge from its ends inwards, so every pull, seen or finishing, runs along the longest
line the ridge was seen on.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from clothd.config import FlattenConfig
from clothd.core.flatness import Flatness, Ridge
from clothd.core.rigid import body_coordinates, rotation

STRAIN_GUARD_SPAN = 0.5  # the field fades out over the last half of the way to strain_limit
# A ridge seen in this tick is one seen before when one of its quads lies this near one of the other's, in
# the cloth's frame (m): the mesh's quads are fixed in the material, so the same quad's centre moves by the
# filter's noise and, as the slack comes out, by millimetres (against the ridge as seen last tick, too),
# while the nearest quads of two ridges a belt apart are a quad apart (20 mm or more).
SAME_QUAD_M = 0.008
# Ridges seen longer ago than this (the regulator was not asked in between: idle, or tracking lost) are
# forgotten rather than finished: the cloth may have been flattened or moved by hand since.
SEEN_STALE_S = 0.5
# A ridge's widest extent is held this long after it was last seen that wide: long enough for a ridge held
# by friction to be pulled down while its ends fade from the estimate (flat within 0.4-0.9 s, p50-p90), and
# no longer, so a line the cloth showed once in a move does not pull for good on the fragment left of it.
WIDEST_HOLD_S = 2.0


@dataclass(frozen=True)
class _Remembered:
    """A ridge in the cloth's frame: as seen last, and at its widest (the most quads) since it was first
    seen; when it is being finished, when that ends (s)."""

    last: Ridge
    widest: Ridge
    widest_t_s: float  # when it was last seen that wide
    until_s: float = math.inf

    def is_seen_in(self, ridge: Ridge) -> bool:
        """Whether `ridge` (cloth frame) shares a quad with this one as seen last or at its widest."""
        known = np.concatenate([self.last.quad_centres_m, self.widest.quad_centres_m])
        gap = np.linalg.norm(ridge.quad_centres_m[:, None] - known[None], axis=-1)
        return bool(gap.min() < SAME_QUAD_M)

    def seen_as(self, ridge: Ridge, t_s: float) -> _Remembered:
        wider = len(ridge.quad_centres_m) >= len(self.widest.quad_centres_m)
        if wider or t_s - self.widest_t_s > WIDEST_HOLD_S:
            return _Remembered(ridge, ridge, t_s)
        return _Remembered(ridge, self.widest, self.widest_t_s)


def _ridge_in_cloth(ridge: Ridge, pose: np.ndarray) -> Ridge:
    """A ridge seen in the world, in the frame of the cloth at pose (X, Y, θ)."""
    position = body_coordinates(np.asarray([ridge.position_m], float), pose)[0]
    return replace(
        ridge,
        position_m=(float(position[0]), float(position[1])),
        direction_rad=(ridge.direction_rad - float(pose[2])) % math.pi,
        quad_centres_m=body_coordinates(ridge.quad_centres_m, pose),
    )


def _ridge_in_world(ridge: Ridge, pose: np.ndarray) -> Ridge:
    """A ridge remembered in the cloth's frame, in the world for the cloth at pose (X, Y, θ)."""
    turn = rotation(float(pose[2]))
    position = np.asarray(ridge.position_m, float) @ turn.T + pose[:2]
    return replace(
        ridge,
        position_m=(float(position[0]), float(position[1])),
        direction_rad=(ridge.direction_rad + float(pose[2])) % math.pi,
        quad_centres_m=ridge.quad_centres_m @ turn.T + pose[:2],
    )


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


def overall_strain(nodes_xy_m: np.ndarray, rest_spacing_m: tuple[float, float]) -> float:
    """How far the cloth is stretched as a whole: along each mesh axis, the median over its rows (columns)
    of the row's length on the table over its rest length, less 1; the larger of the two. A single edge's
    strain is the filter's noise at this mesh size (a few %); a whole row's is not. Negative while the
    cloth holds slack across every row (or column)."""
    strains = []
    for axis, rest in ((1, rest_spacing_m[0]), (0, rest_spacing_m[1])):
        length = np.linalg.norm(np.diff(nodes_xy_m, axis=axis), axis=-1).sum(axis=axis)
        strains.append(float(np.median(length / (rest * (nodes_xy_m.shape[axis] - 1)) - 1.0)))
    return max(strains)


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
        self._seen: list[_Remembered] = []  # the last call's ridges
        self._seen_t_s = -math.inf
        self._finishing: list[_Remembered] = []

    def reset(self) -> None:
        """Forget the ridges seen (a new cloth, or tracking began again)."""
        self._seen = []
        self._seen_t_s = -math.inf
        self._finishing = []

    def velocities(
        self,
        flatness: Flatness,
        nodes_m: np.ndarray,
        cloth_size_m: tuple[float, float],
        under: np.ndarray,
        pose: np.ndarray,
        t_s: float,
    ) -> np.ndarray:
        """The flattening field at time t_s for the modules `under` the cloth (bool, n_modules), less those
        under or beside a flap; zero elsewhere. pose (X, Y, θ): the cloth's, whose centre the field leaves
        where it is and in whose frame ridges are remembered."""
        # Belts cannot unfold a flap, and a belt under one would drag it about: the modules under a flap,
        # or at its edge, are left out.
        shaping = under.copy()
        for flap in flatness.flaps:
            gap = np.linalg.norm(self.centres_m[:, None, :] - flap.quad_centres_m[None], axis=-1).min(axis=1)
            shaping &= gap > self.half_belt_m + self.cfg.ridge_margin_m
        v = np.zeros_like(self.centres_m)
        seen, finishing = self._remember(flatness.ridges, pose, t_s)
        c = self.cfg
        for ridge in seen:
            speed = float(
                np.clip(ridge.last.slack_m / (2.0 * c.time_constant_s), c.min_speed_m_s, c.max_speed_m_s)
            )
            v[shaping] += self._pull(_ridge_in_world(ridge.widest, pose), self.centres_m[shaping], speed)
        for lost in finishing:
            v[shaping] += self._pull(
                _ridge_in_world(lost.widest, pose), self.centres_m[shaping], c.max_speed_m_s
            )
        if not v.any():
            return v
        centre_m = np.asarray(pose[:2], float)
        v[shaping] -= rigid_part(v[shaping], self.centres_m[shaping], centre_m)
        ny, nx = nodes_m.shape[:2]
        spacing = (cloth_size_m[0] / (nx - 1), cloth_size_m[1] / (ny - 1))
        strain = overall_strain(nodes_m[..., :2], spacing)
        guard = np.clip((self.strain_limit - strain) / (STRAIN_GUARD_SPAN * self.strain_limit), 0.0, 1.0)
        return np.asarray(v * guard)

    def _remember(
        self, ridges: tuple[Ridge, ...], pose: np.ndarray, t_s: float
    ) -> tuple[list[_Remembered], list[_Remembered]]:
        """The ridges seen now, each with its widest extent since first seen, and those still to be pulled
        on after the estimate lost sight of them: ridges seen last call and not in this one start their
        finishing pull; one seen again ends it. All in the cloth's frame."""
        recent = t_s - self._seen_t_s <= SEEN_STALE_S
        known = (self._seen if recent else []) + self._finishing
        matched: set[int] = set()  # ids of the known ridges seen again
        seen = []
        for ridge in ridges:
            local = _ridge_in_cloth(ridge, pose)
            # One ridge seen as two parts: the first (the highest) carries its extent on.
            before = next((m for m in known if id(m) not in matched and m.is_seen_in(local)), None)
            if before is None:
                seen.append(_Remembered(local, local, t_s))
            else:
                matched.add(id(before))
                seen.append(before.seen_as(local, t_s))
        unseen = [m for m in known if id(m) not in matched]
        finishing = [m for m in unseen if m.until_s < math.inf]
        lost = [replace(m, until_s=t_s + self.cfg.finish_s) for m in unseen if m.until_s == math.inf]
        self._finishing = [m for m in finishing + lost if m.until_s > t_s]
        self._seen, self._seen_t_s = seen, t_s
        return seen, self._finishing

    def _pull(self, ridge: Ridge, centres_m: np.ndarray, speed_m_s: float) -> np.ndarray:
        """The pull of one ridge on modules at centres_m (k, 2): ±speed ĉ on either side of its line."""
        c = self.cfg
        across = np.array(
            [math.cos(ridge.compressed_direction_rad), math.sin(ridge.compressed_direction_rad)]
        )
        along = np.array([-across[1], across[0]])
        # The line runs through the middle of the ridge's quads; it reaches as far as they do.
        middle = ridge.quad_centres_m.mean(axis=0)
        reach = (ridge.quad_centres_m - middle) @ along
        rel = centres_m - middle
        s = rel @ across
        t = rel @ along
        beside = (t >= reach.min() - self.half_belt_m - c.ridge_margin_m) & (
            t <= reach.max() + self.half_belt_m + c.ridge_margin_m
        )
        # A module pulls its material away from the line: the ridge itself is off the table, so a belt
        # under its flank carries only the cloth on its own side. Not one right under the line, nor too far.
        pulls = beside & (np.abs(s) > c.ridge_margin_m) & (np.abs(s) <= c.reach_m)
        return np.asarray(np.where(pulls[:, None], np.sign(s)[:, None] * speed_m_s * across, 0.0))
