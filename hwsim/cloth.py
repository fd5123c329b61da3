"""Ground-truth cloth: a fine XPBD sheet on the conveyor table (Taichi, float64, one thread).

A different model from the tracker's: extended position-based dynamics with small steps (Macklin et al.
2019) on a mesh at least 3x finer; stretch, shear measured along the cloth (`_diagonal`), bending with the
yarns' friction (`_slip_yarns`), table contact, Coulomb friction with a stick state against the belts,
gravity, damping and the belts' vibration (docs/hwsim.md, "The cloth", derives each). The whole frame is
one serial kernel: no launch overhead per substep, and bit-for-bit reproducible, as a ground truth must be.
The grid is in hwsim/cloth_grid.py, the solver's constants in hwsim/cloth_constants.py.
"""

import math

import numpy as np
import taichi as ti

from hwsim.belt_geometry import belt_at, belt_hit
from hwsim.cloth_constants import (
    FLAT_CELL,
    GRAVITY_M_S2,
    LAY_IN_DAMPING_1_S,
    LAY_IN_S,
    ON_TABLE_M,
    VIBRATION_REF_SPEED_M_S,
    YARN_FRICTION_STIFFNESS,
)
from hwsim.cloth_constraints import ClothConstraints
from hwsim.cloth_grid import FLAP_THICKNESS_M, ClothGrid, bends_in_own_frames
from hwsim.scenario import ClothSpec, Pose, TableSpec

vec2d = ti.types.vector(2, ti.f64)


@ti.func
def _swept(k: ti.i32, n: ti.i32, flip: ti.i32) -> ti.i32:
    """Loop index k of n, run backwards when flip is 1."""
    return ti.select(flip == 1, n - 1 - k, k)


def _put(field: ti.Field, values: np.ndarray) -> None:
    """Write values into the leading corner of a field that may be larger (a reused cloth's capacity)."""
    shape = tuple(field.shape) + tuple(values.shape[2:])
    if tuple(values.shape) != shape:
        padded = np.zeros(shape, dtype=values.dtype)
        padded[tuple(slice(0, n) for n in values.shape[:2])] = values
        values = padded
    field.from_numpy(np.ascontiguousarray(values))


@ti.data_oriented
class ClothSim(ClothConstraints):
    """XPBD cloth. Positions are world metres; call `advance(dt_s, module_speed, module_heading)`.

    `capacity` (ny, nx): allocate for a grid that large, so that `reuse` can take another piece of cloth
    up to that size without compiling the solver again (several seconds a time); the grid's own size is
    a kernel argument."""

    def __init__(
        self,
        spec: ClothSpec,
        table: TableSpec,
        pose: Pose,
        substep_s: float,
        seed: int,
        capacity: tuple[int, int] | None = None,
    ) -> None:
        self.substep_s = substep_s
        self.table = table
        g = ClothGrid.from_spec(spec)
        shape = capacity or (g.ny, g.nx)
        self.capacity = shape
        self.x = ti.Vector.field(3, ti.f64, shape=shape)
        self.v = ti.Vector.field(3, ti.f64, shape=shape)
        self.x_prev = ti.Vector.field(3, ti.f64, shape=shape)
        self.inv_mass = ti.field(ti.f64, shape=shape)
        self.stuck = ti.field(ti.i32, shape=shape)  # 1: held by static friction, moving with its belt
        self.reaction = ti.Vector.field(3, ti.f64, shape=shape)  # impulse the constraints ask of a stuck node
        self.held = ti.field(ti.i32, shape=shape)  # 1: pressed by a hand, moving with it (a push)
        self.hand_v = ti.Vector.field(3, ti.f64, shape=shape)
        self.floor = ti.field(ti.f64, shape=shape)  # what a node rests on: the table, or a flap's cloth
        self.folded = ti.field(ti.i32, shape=shape)  # 1: folded over by a flap
        # Where the yarns' friction holds each bend (its stick point, a second difference), in the bend's own
        # frame (along its chord, across it, up) so that it turns with the cloth.
        self.set_along_s = ti.Vector.field(3, ti.f64, shape=(shape[0], shape[1] - 2))
        self.set_along_t = ti.Vector.field(3, ti.f64, shape=(shape[0] - 2, shape[1]))
        n_mod = table.modules_x * table.modules_y
        # A flow's infeed conveyor (hwsim/infeed.py): x below its end, |y| within its half width, its speed.
        self.infeed_belt = ti.field(ti.f64, shape=3)
        self.infeed_belt.from_numpy(np.array([-math.inf, 0.0, 0.0]))
        self.reuse(spec, pose, seed, np.zeros(n_mod))

    def reuse(self, spec: ClothSpec, pose: Pose, seed: int, module_heading_rad: np.ndarray) -> None:
        """Become a new piece of cloth of `spec` (its grid within the capacity), laid at `pose`."""
        grid = ClothGrid.from_spec(spec)
        if grid.ny > self.capacity[0] or grid.nx > self.capacity[1]:
            raise ValueError(f"a {grid.ny} x {grid.nx} grid exceeds this cloth's capacity {self.capacity}")
        self.spec, self.grid = spec, grid
        self._substeps_done = 0
        self._rng = np.random.default_rng(seed)
        self.mass_kg = grid.node_masses_kg(spec.areal_density_kg_m2)
        inv_mass = np.ones(self.capacity)  # beyond the grid: never read, but no division by zero
        inv_mass[: grid.ny, : grid.nx] = 1.0 / self.mass_kg
        self.inv_mass.from_numpy(inv_mass)
        self.lay(pose, module_heading_rad)

    def lay(self, pose: Pose, module_heading_rad: np.ndarray) -> None:
        """Lay the cloth down at rest at `pose` on the stopped belts (at the given headings), as a hand does:
        yarns settled in the laid shape, what lies on a belt stuck to it, a ridge settled quasi-statically."""
        x = self.grid.placed(pose)
        self.held.fill(0)
        self.set_positions(x)
        folded = self.grid.folded(pose)
        _put(self.folded, folded.astype(np.int32))
        floor = np.where(folded, FLAP_THICKNESS_M, 0.0)
        _put(self.floor, floor)
        _put(self.stuck, (x[..., 2] < floor + ON_TABLE_M).astype(np.int32))
        if pose.ridges or pose.flaps:
            stopped = np.zeros(len(module_heading_rad))
            self.advance(LAY_IN_S, stopped, module_heading_rad, damping_1_s=LAY_IN_DAMPING_1_S)
            self.v.fill(0.0)

    def set_positions(self, x_m: np.ndarray) -> None:
        """Place the cloth at rest at the given node positions (ny, nx, 3), its yarns settled in that shape
        (the frictional element holds every bend as it is); nothing sticks until it has come to rest on a
        belt."""
        _put(self.x, np.asarray(x_m, dtype=np.float64))
        self.v.fill(0.0)
        self.stuck.fill(0)
        _put(self.set_along_s, bends_in_own_frames(x_m))
        _put(self.set_along_t, bends_in_own_frames(x_m.transpose(1, 0, 2)).transpose(1, 0, 2))

    def hold(self, held: np.ndarray, velocity_m_s: np.ndarray) -> None:
        """Hands hold the nodes where `held` (ny, nx) is set and move them at velocity_m_s (ny, nx, 3) until
        `release`."""
        _put(self.held, held.astype(np.int32))
        _put(self.hand_v, np.asarray(velocity_m_s, dtype=np.float64))

    def release(self) -> None:
        """The hands let go where they stopped. The cloth comes to rest with them (what they dragged along
        slid no faster than they moved), so whatever lies on a belt stays there, held by static friction:
        a hand lifts off a cloth at rest; it does not throw it."""
        on_table = self.positions_m()[..., 2] < self._node_values(self.floor) + ON_TABLE_M
        self.v.fill(0.0)
        _put(self.stuck, on_table.astype(np.int32))
        self.held.fill(0)

    def _node_values(self, field: ti.Field) -> np.ndarray:
        return np.asarray(field.to_numpy()[: self.grid.ny, : self.grid.nx])

    def positions_m(self) -> np.ndarray:
        return self._node_values(self.x)

    def velocities_m_s(self) -> np.ndarray:
        return self._node_values(self.v)

    def advance(
        self,
        dt_s: float,
        module_speed_m_s: np.ndarray,
        module_heading_rad: np.ndarray,
        damping_1_s: float | None = None,
    ) -> None:
        """Advance by dt_s (a whole number of substeps) with the belts at the given signed speeds and
        headings. The belts' vertical shake is drawn once per call. damping_1_s: instead of the cloth's."""
        # The belts and their shake go in as arguments, not fields: a field's upload is a kernel of its own.
        speed = np.ascontiguousarray(module_speed_m_s, dtype=np.float64)
        heading = np.asarray(module_heading_rad, dtype=np.float64)
        direction = np.ascontiguousarray(np.stack([np.cos(heading), np.sin(heading)], axis=1))
        kick = self._rng.standard_normal((self.grid.ny, self.grid.nx)) * self.spec.vibration_m_s
        s, t = self.spec, self.table
        substeps = max(1, round(dt_s / self.substep_s))
        friction_k = YARN_FRICTION_STIFFNESS * s.bending_stiffness_n_m if s.bending_hysteresis_n > 0 else 0.0
        h = dt_s / substeps
        # Sweep directions alternate across calls too, so no direction wins over a run.
        parity = self._substeps_done % 2, (self._substeps_done * s.stretch_iterations) % 2
        self._substeps_done += substeps
        g = self.grid
        # The rest lengths were compile-time constants, which Taichi takes at its default precision, f32;
        # kept so, the truth stays bit-for-bit what it was.
        dx, dy, diag = (np.float32(r) for r in (g.dx_m, g.dy_m, (g.dx_m**2 + g.dy_m**2) ** 0.5))
        self._advance(
            speed,
            direction,
            kick,
            g.nx,
            g.ny,
            float(dx),
            float(dy),
            float(diag),
            FLAT_CELL * (g.dx_m**2 + g.dy_m**2) ** 0.5,
            substeps,
            parity[0],
            parity[1],
            s.stretch_iterations,
            h,
            1.0 / s.stretch_stiffness_n_m / h**2,
            1.0 / s.shear_stiffness_n_m / h**2,
            # Bending compliance h⁴/((B + k_f)·cell area), with dx ≈ dy: dx·dy/(B + k_f).
            self.grid.dx_m * self.grid.dy_m / (s.bending_stiffness_n_m + friction_k) / h**2,
            friction_k / (s.bending_stiffness_n_m + friction_k),
            self._yield_m(self.grid.dx_m, friction_k),
            self._yield_m(self.grid.dy_m, friction_k),
            s.friction.mu,
            s.friction.mu_static,
            s.stretch_stiffness_n_m * h**2,
            s.shear_stiffness_n_m * h**2,
            float(np.exp(-(s.damping_1_s if damping_1_s is None else damping_1_s) * h)),
            t.pitch_m,
            t.module_size_m / 2.0,
        )

    def _yield_m(self, spacing_m: float, friction_k: float) -> float:
        """How far the frictional element stretches before its couple k_f·|Δ²x - r|/Δs² reaches HB."""
        return self.spec.bending_hysteresis_n * spacing_m**2 / friction_k if friction_k > 0 else math.inf

    @ti.func
    def _belt_velocity(
        self,
        p: ti.template(),
        speeds: ti.template(),
        directions: ti.template(),
        pitch: ti.f64,
        half_belt: ti.f64,
    ) -> belt_hit:
        """(vx, vy, on_belt, 0): surface velocity of the belt under world point p; zero over the deck.
        speeds and directions: each module's signed speed and (cos, sin) of heading."""
        hit = belt_at(p[0], p[1], directions, pitch, half_belt, self.table.modules_x, self.table.modules_y)
        vel = belt_hit(0.0, 0.0, 0.0, 0.0)
        if hit[3] > 0.0:
            m = ti.cast(hit[0], ti.i32)
            speed = speeds[m]
            vel = belt_hit(speed * directions[m][0], speed * directions[m][1], 1.0, 0.0)
        elif p[0] < self.infeed_belt[0] and ti.abs(p[1]) < self.infeed_belt[1]:
            vel = belt_hit(self.infeed_belt[2], 0.0, 1.0, 0.0)
        return vel

    @ti.kernel
    def _advance(
        self,
        speeds: ti.types.ndarray(dtype=ti.f64, ndim=1),
        directions: ti.types.ndarray(dtype=vec2d, ndim=1),
        kick: ti.types.ndarray(dtype=ti.f64, ndim=2),
        nx: ti.i32,
        ny: ti.i32,
        dx: ti.f64,
        dy: ti.f64,
        diag: ti.f64,
        flat_bisect: ti.f64,
        substeps: ti.i32,
        substeps_done: ti.i32,
        sweeps_done: ti.i32,
        stretch_iterations: ti.i32,
        h: ti.f64,
        alpha_stretch: ti.f64,
        alpha_shear: ti.f64,
        alpha_bend: ti.f64,
        set_share: ti.f64,
        yield_s: ti.f64,
        yield_t: ti.f64,
        mu: ti.f64,
        mu_static: ti.f64,
        stretch_k_h2: ti.f64,
        shear_k_h2: ti.f64,
        damping: ti.f64,
        pitch: ti.f64,
        half_belt: ti.f64,
    ):
        ti.loop_config(serialize=True)
        for step in range(substeps):
            for j, i in ti.ndrange(ny, nx):
                self.x_prev[j, i] = self.x[j, i]
                self.reaction[j, i] = ti.Vector([0.0, 0.0, 0.0])
                belt = self._belt_velocity(self.x[j, i], speeds, directions, pitch, half_belt)
                if self.held[j, i] == 1:
                    self.stuck[j, i] = 0
                    self.v[j, i] = self.hand_v[j, i]
                elif self.stuck[j, i] == 1 and belt[2] > 0.0:
                    # Static friction: the node rides its belt, on the table.
                    self.v[j, i] = ti.Vector([belt[0], belt[1], 0.0])
                else:
                    self.stuck[j, i] = 0
                    self.v[j, i][2] -= GRAVITY_M_S2 * h
                    if step == 0 and self.x[j, i][2] <= self.floor[j, i] + 1e-6:
                        shake = ti.min(1.0, vec2d(belt[0], belt[1]).norm() / VIBRATION_REF_SPEED_M_S)
                        self.v[j, i][2] += shake * ti.abs(kick[j, i])
                self.x[j, i] += h * self.v[j, i]
            # Gauss-Seidel sweeps alternate direction: a one-way sweep pushes the cloth sideways.
            for it in range(stretch_iterations):
                flip = (sweeps_done + step * stretch_iterations + it) % 2
                for jj, ii in ti.ndrange(ny, nx - 1):
                    j, i = _swept(jj, ny, flip), _swept(ii, nx - 1, flip)
                    self._distance(ti.Vector([j, i]), ti.Vector([j, i + 1]), dx, alpha_stretch)
                for jj, ii in ti.ndrange(ny - 1, nx):
                    j, i = _swept(jj, ny - 1, flip), _swept(ii, nx, flip)
                    self._distance(ti.Vector([j, i]), ti.Vector([j + 1, i]), dy, alpha_stretch)
            flip = (substeps_done + step) % 2
            for jj, ii in ti.ndrange(ny - 1, nx - 1):
                j, i = _swept(jj, ny - 1, flip), _swept(ii, nx - 1, flip)
                flap = (
                    self.folded[j, i]
                    + self.folded[j, i + 1]
                    + self.folded[j + 1, i]
                    + self.folded[j + 1, i + 1]
                )
                bisect = (self.x[j, i] + self.x[j + 1, i + 1] - self.x[j, i + 1] - self.x[j + 1, i]).norm()
                if 0 < flap < 4 or bisect < flat_bisect:
                    # Flat (its diagonals bisect each other), where the two measures agree, or across a
                    # flap's crease: plain distances (slack in the crease).
                    self._distance(ti.Vector([j, i]), ti.Vector([j + 1, i + 1]), diag, alpha_shear)
                    self._distance(ti.Vector([j, i + 1]), ti.Vector([j + 1, i]), diag, alpha_shear)
                    self._anchored_spring(ti.Vector([j, i]), ti.Vector([j + 1, i + 1]), diag, shear_k_h2)
                    self._anchored_spring(ti.Vector([j, i + 1]), ti.Vector([j + 1, i]), diag, shear_k_h2)
                elif flip == 0:
                    # Each diagonal goes first every other substep: a mirror image swaps them.
                    self._diagonal(j, i, False, diag, alpha_shear, shear_k_h2)
                    self._diagonal(j, i, True, diag, alpha_shear, shear_k_h2)
                else:
                    self._diagonal(j, i, True, diag, alpha_shear, shear_k_h2)
                    self._diagonal(j, i, False, diag, alpha_shear, shear_k_h2)
            for jj, ii in ti.ndrange(ny, nx - 2):
                j, i = _swept(jj, ny, flip), _swept(ii, nx - 2, flip)
                a, b, c = ti.Vector([j, i]), ti.Vector([j, i + 1]), ti.Vector([j, i + 2])
                self._bend(a, b, c, self.set_along_s[j, i], alpha_bend, set_share)
            for jj, ii in ti.ndrange(ny - 2, nx):
                j, i = _swept(jj, ny - 2, flip), _swept(ii, nx, flip)
                a, b, c = ti.Vector([j, i]), ti.Vector([j + 1, i]), ti.Vector([j + 2, i])
                self._bend(a, b, c, self.set_along_t[j, i], alpha_bend, set_share)
            if set_share > 0.0:
                for j, i in ti.ndrange(ny, nx):
                    self._slip_yarns(j, i, nx, ny, yield_s, yield_t)
            for j, i in ti.ndrange(ny, nx - 1):
                self._anchored_spring(ti.Vector([j, i]), ti.Vector([j, i + 1]), dx, stretch_k_h2)
            for j, i in ti.ndrange(ny - 1, nx):
                self._anchored_spring(ti.Vector([j, i]), ti.Vector([j + 1, i]), dy, stretch_k_h2)
            for j, i in ti.ndrange(ny, nx):
                m = 1.0 / self.inv_mass[j, i]
                if self.held[j, i] == 1:
                    pass  # the hand holds it where it is
                elif self.stuck[j, i] == 1:
                    # Coulomb: the anchor holds while the pull it resists stays within μ_static·N; the
                    # normal force is the weight less what the constraints lift (impulses over h).
                    r = self.reaction[j, i]
                    normal = m * GRAVITY_M_S2 * h * h - r[2]
                    if normal <= 0.0 or vec2d(r[0], r[1]).norm() > mu_static * normal:
                        self.stuck[j, i] = 0
                elif self.x[j, i][2] < self.floor[j, i]:
                    depth = self.floor[j, i] - self.x[j, i][2]  # the normal correction; impulse m·depth/h
                    self.x[j, i][2] = self.floor[j, i]
                    belt = self._belt_velocity(self.x[j, i], speeds, directions, pitch, half_belt)
                    if belt[2] > 0.0:
                        # Kinetic friction (Macklin et al. 2014): the substep's slip against the belt shrinks
                        # by μ·depth; where that stops it, the node sticks from the next substep on.
                        slip = vec2d(
                            self.x[j, i][0] - self.x_prev[j, i][0] - belt[0] * h,
                            self.x[j, i][1] - self.x_prev[j, i][1] - belt[1] * h,
                        )
                        slip_m = slip.norm()
                        keep = ti.f64(0.0)
                        if slip_m > mu * depth:
                            keep = 1.0 - mu * depth / slip_m
                        else:
                            self.stuck[j, i] = 1
                        self.x[j, i][0] -= (1.0 - keep) * slip[0]
                        self.x[j, i][1] -= (1.0 - keep) * slip[1]
                self.v[j, i] = (self.x[j, i] - self.x_prev[j, i]) / h * damping
