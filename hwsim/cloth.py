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
    FOLD_STRAIN,
    GRAVITY_M_S2,
    LAY_IN_DAMPING_1_S,
    LAY_IN_S,
    ON_TABLE_M,
    VIBRATION_REF_SPEED_M_S,
    YARN_FRICTION_STIFFNESS,
)
from hwsim.cloth_grid import FLAP_THICKNESS_M, ClothGrid, bends_in_own_frames
from hwsim.scenario import ClothSpec, Pose, TableSpec

vec2d = ti.types.vector(2, ti.f64)


@ti.func
def _swept(k: ti.i32, n: ti.i32, flip: ti.i32) -> ti.i32:
    """Loop index k of n, run backwards when flip is 1."""
    return ti.select(flip == 1, n - 1 - k, k)


@ti.data_oriented
class ClothSim:
    """XPBD cloth. Positions are world metres; call `advance(dt_s, module_speed, module_heading)`."""

    def __init__(self, spec: ClothSpec, table: TableSpec, pose: Pose, substep_s: float, seed: int) -> None:
        self.spec = spec
        self.substep_s = substep_s
        self._substeps_done = 0
        self.table = table
        self.grid = ClothGrid.from_spec(spec)
        g = self.grid
        shape = (g.ny, g.nx)
        self._rng = np.random.default_rng(seed)
        self.x = ti.Vector.field(3, ti.f64, shape=shape)
        self.v = ti.Vector.field(3, ti.f64, shape=shape)
        self.x_prev = ti.Vector.field(3, ti.f64, shape=shape)
        self.inv_mass = ti.field(ti.f64, shape=shape)
        self.stuck = ti.field(ti.i32, shape=shape)  # 1: held by static friction, moving with its belt
        self.reaction = ti.Vector.field(3, ti.f64, shape=shape)  # impulse the constraints ask of a stuck node
        self.held = ti.field(ti.i32, shape=shape)  # 1: pressed by a hand, moving with it (a push)
        self.hand_v = ti.Vector.field(3, ti.f64, shape=shape)
        self.kick = ti.field(ti.f64, shape=shape)
        self.floor = ti.field(ti.f64, shape=shape)  # what a node rests on: the table, or a flap's cloth
        self.folded = ti.field(ti.i32, shape=shape)  # 1: folded over by a flap
        # Where the yarns' friction holds each bend (its stick point, a second difference), in the bend's own
        # frame (along its chord, across it, up) so that it turns with the cloth.
        self.set_along_s = ti.Vector.field(3, ti.f64, shape=(g.ny, g.nx - 2))
        self.set_along_t = ti.Vector.field(3, ti.f64, shape=(g.ny - 2, g.nx))
        n_mod = table.modules_x * table.modules_y
        self.mod_speed = ti.field(ti.f64, shape=n_mod)
        self.mod_direction = ti.Vector.field(2, ti.f64, shape=n_mod)  # cos, sin of heading
        self.mass_kg = g.node_masses_kg(spec.areal_density_kg_m2)
        self.inv_mass.from_numpy(1.0 / self.mass_kg)
        self.lay(pose, np.zeros(n_mod))

    def lay(self, pose: Pose, module_heading_rad: np.ndarray) -> None:
        """Lay the cloth down at rest at `pose` on the stopped belts (at the given headings), as a hand does:
        yarns settled in the laid shape, what lies on a belt stuck to it, a ridge settled quasi-statically."""
        x = self.grid.placed(pose)
        self.held.fill(0)
        self.set_positions(x)
        folded = self.grid.folded(pose)
        self.folded.from_numpy(folded.astype(np.int32))
        floor = np.where(folded, FLAP_THICKNESS_M, 0.0)
        self.floor.from_numpy(floor)
        self.stuck.from_numpy((x[..., 2] < floor + ON_TABLE_M).astype(np.int32))
        if pose.ridges or pose.flaps:
            stopped = np.zeros(len(module_heading_rad))
            self.advance(LAY_IN_S, stopped, module_heading_rad, damping_1_s=LAY_IN_DAMPING_1_S)
            self.v.fill(0.0)

    def set_positions(self, x_m: np.ndarray) -> None:
        """Place the cloth at rest at the given node positions (ny, nx, 3), its yarns settled in that shape
        (the frictional element holds every bend as it is); nothing sticks until it has come to rest on a
        belt."""
        self.x.from_numpy(np.ascontiguousarray(x_m, dtype=np.float64))
        self.v.fill(0.0)
        self.stuck.fill(0)
        self.set_along_s.from_numpy(bends_in_own_frames(x_m))
        self.set_along_t.from_numpy(bends_in_own_frames(x_m.transpose(1, 0, 2)).transpose(1, 0, 2))

    def hold(self, held: np.ndarray, velocity_m_s: np.ndarray) -> None:
        """Hands hold the nodes where `held` (ny, nx) is set and move them at velocity_m_s (ny, nx, 3) until
        `release`."""
        self.held.from_numpy(held.astype(np.int32))
        self.hand_v.from_numpy(np.ascontiguousarray(velocity_m_s, dtype=np.float64))

    def release(self) -> None:
        """The hands let go where they stopped. The cloth comes to rest with them (what they dragged along
        slid no faster than they moved), so whatever lies on a belt stays there, held by static friction:
        a hand lifts off a cloth at rest; it does not throw it."""
        on_table = self.positions_m()[..., 2] < self.floor.to_numpy() + ON_TABLE_M
        self.v.fill(0.0)
        self.stuck.from_numpy(on_table.astype(np.int32))
        self.held.fill(0)

    def positions_m(self) -> np.ndarray:
        return np.asarray(self.x.to_numpy())

    def velocities_m_s(self) -> np.ndarray:
        return np.asarray(self.v.to_numpy())

    def advance(
        self,
        dt_s: float,
        module_speed_m_s: np.ndarray,
        module_heading_rad: np.ndarray,
        damping_1_s: float | None = None,
    ) -> None:
        """Advance by dt_s (a whole number of substeps) with the belts at the given signed speeds and
        headings. The belts' vertical shake is drawn once per call. damping_1_s: instead of the cloth's."""
        self.mod_speed.from_numpy(np.asarray(module_speed_m_s, dtype=np.float64))
        heading = np.asarray(module_heading_rad, dtype=np.float64)
        self.mod_direction.from_numpy(np.stack([np.cos(heading), np.sin(heading)], axis=1))
        self.kick.from_numpy(
            self._rng.standard_normal((self.grid.ny, self.grid.nx)) * self.spec.vibration_m_s
        )
        s, t = self.spec, self.table
        substeps = max(1, round(dt_s / self.substep_s))
        friction_k = YARN_FRICTION_STIFFNESS * s.bending_stiffness_n_m if s.bending_hysteresis_n > 0 else 0.0
        h = dt_s / substeps
        # Sweep directions alternate across calls too, so no direction wins over a run.
        parity = self._substeps_done % 2, (self._substeps_done * s.stretch_iterations) % 2
        self._substeps_done += substeps
        self._advance(
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
    def _free_inv_mass(self, a: ti.template()) -> ti.f64:
        """A stuck node is anchored to its belt, a held one to its hand: the solve moves them not at all."""
        return self.inv_mass[a] * ti.cast(1 - ti.max(self.stuck[a], self.held[a]), ti.f64)

    @ti.func
    def _distance(self, a: ti.template(), b: ti.template(), rest: ti.f64, alpha: ti.f64):
        """An edge across a flap's fold is bent round the crease, not compressed: it only resists stretch."""
        wa, wb = self._free_inv_mass(a), self._free_inv_mass(b)
        d = self.x[a] - self.x[b]
        length = d.norm()
        slack_in_crease = self.folded[a] != self.folded[b] and length < rest
        if length > 1e-12 and wa + wb > 0.0 and not slack_in_crease:
            dlam = -(length - rest) / (wa + wb + alpha)
            n = d / length
            self.x[a] += wa * dlam * n
            self.x[b] -= wb * dlam * n
            # The anchor of a stuck end supplies the impulse the constraint asks of it.
            self.reaction[a] += ti.cast(self.stuck[a], ti.f64) * dlam * n
            self.reaction[b] -= ti.cast(self.stuck[b], ti.f64) * dlam * n

    @ti.func
    def _anchored_spring(self, a: ti.template(), b: ti.template(), rest: ti.f64, k_h2: ti.f64):
        """Neither end of an edge between two anchors (stuck, or held by a hand) can move, so the solve skips
        it; its true elastic force k·C acts on each stuck end instead."""
        if ti.max(self.stuck[a], self.held[a]) == 1 and ti.max(self.stuck[b], self.held[b]) == 1:
            d = self.x[a] - self.x[b]
            length = d.norm()
            if length > 1e-12:
                impulse = -k_h2 * (length - rest) * d / length
                self.reaction[a] += ti.cast(self.stuck[a], ti.f64) * impulse
                self.reaction[b] -= ti.cast(self.stuck[b], ti.f64) * impulse

    @ti.func
    def _diagonal(
        self, j: ti.i32, i: ti.i32, second: ti.template(), rest: ti.f64, alpha: ti.f64, k_h2: ti.f64
    ):
        """Shear on one diagonal of cell (j, i) (00-11, or 10-01 when `second`): its length along the cloth,
        which is the straight length unless the cell is bent across it, and then the path through the other
        diagonal's midpoint (on the bend). In a flat cell (the diagonals bisect each other) the two agree,
        so which diagonal counts as bent (the shorter) matters only in a bent cell; the choice is blended
        over FOLD_STRAIN, and both diagonals are always held. Free ends move as XPBD moves them; when every
        end that could move is anchored, the true elastic force k·C goes to the stuck ones' reactions."""
        cell = ti.Matrix([[j, i], [j, i + 1], [j + 1, i], [j + 1, i + 1]])  # 00, 10 (along s), 01, 11
        ends = ti.Vector([0, 3, 1, 2])  # this diagonal's ends, then the other's
        if ti.static(second):
            ends = ti.Vector([1, 2, 0, 3])
        a, b = self.x[cell[ends[0], 0], cell[ends[0], 1]], self.x[cell[ends[1], 0], cell[ends[1], 1]]
        c, d = self.x[cell[ends[2], 0], cell[ends[2], 1]], self.x[cell[ends[3], 0], cell[ends[3], 1]]
        straight = (a - b).norm()
        mid = (c + d) / 2.0
        via = (a - mid).norm() + (b - mid).norm()
        bent = 1.0 / (
            1.0 + ti.exp(-ti.math.clamp(((c - d).norm() - straight) / (FOLD_STRAIN * rest), -50.0, 50.0))
        )
        n = (a - b) / straight
        ua, ub = (a - mid).normalized(), (b - mid).normalized()
        grad = ti.Matrix.zero(ti.f64, 4, 3)  # rows in the order of `ends`
        grad[0, :] = bent * ua + (1.0 - bent) * n
        grad[1, :] = bent * ub - (1.0 - bent) * n
        grad[2, :] = -bent * (ua + ub) / 2.0
        grad[3, :] = grad[2, :]
        constraint = bent * via + (1.0 - bent) * straight - rest
        free = ti.f64(0.0)
        for k in ti.static(range(4)):
            node = ti.Vector([cell[ends[k], 0], cell[ends[k], 1]])
            free += self._free_inv_mass(node) * grad[k, :].norm_sqr()
        scale = -k_h2 * constraint
        if free > 0.0:
            scale = -constraint / (free + alpha)
        for k in ti.static(range(4)):
            node = ti.Vector([cell[ends[k], 0], cell[ends[k], 1]])
            step = grad[k, :] * scale
            if free > 0.0:
                self.x[node] += self._free_inv_mass(node) * step
            self.reaction[node] += ti.cast(self.stuck[node], ti.f64) * step

    @ti.func
    def _bend_frame(self, a: ti.template(), c: ti.template()) -> ti.types.matrix(3, 3, ti.f64):
        """Rows: along the bend's chord a -> c (level), across it (level), up. A stick point kept in this
        frame turns with the cloth on the table."""
        chord = vec2d(self.x[c][0] - self.x[a][0], self.x[c][1] - self.x[a][1]).normalized(1e-24)
        return ti.Matrix([[chord[0], chord[1], 0.0], [-chord[1], chord[0], 0.0], [0.0, 0.0, 1.0]])

    @ti.func
    def _bend(
        self,
        a: ti.template(),
        b: ti.template(),
        c: ti.template(),
        set_local: ti.template(),
        alpha: ti.f64,
        set_share: ti.f64,
    ):
        """The elastic bend towards straight and the yarns' frictional element towards its stick point
        set_local, as one constraint towards set_local·set_share (set_share = k_f / (B + k_f)). Across a
        flap's fold the crease is set (a plastic crease): it carries no bending moment."""
        wa, wb, wc = self._free_inv_mass(a), self._free_inv_mass(b), self._free_inv_mass(c)
        creased = self.folded[a] != self.folded[b] or self.folded[b] != self.folded[c]
        if wa + wb + wc > 0.0 and not creased:
            rest = ti.Vector([0.0, 0.0, 0.0], dt=ti.f64)
            if set_share > 0.0:
                rest = self._bend_frame(a, c).transpose() @ set_local * set_share
            dlam = -(self.x[a] - 2.0 * self.x[b] + self.x[c] - rest) / (wa + 4.0 * wb + wc + alpha)
            self.x[a] += wa * dlam
            self.x[b] -= 2.0 * wb * dlam
            self.x[c] += wc * dlam
            self.reaction[a] += ti.cast(self.stuck[a], ti.f64) * dlam
            self.reaction[b] -= 2.0 * ti.cast(self.stuck[b], ti.f64) * dlam
            self.reaction[c] += ti.cast(self.stuck[c], ti.f64) * dlam

    @ti.func
    def _elastic_bend(self, a: ti.template(), b: ti.template(), c: ti.template(), set_local: ti.template()):
        """How far the bend a-b-c is from its stick point, in its own frame; zero across a flap's crease,
        which bends freely."""
        elastic = ti.Vector([0.0, 0.0, 0.0], dt=ti.f64)
        if self.folded[a] == self.folded[b] and self.folded[b] == self.folded[c]:
            elastic = self._bend_frame(a, c) @ (self.x[a] - 2.0 * self.x[b] + self.x[c]) - set_local
        return elastic

    @ti.func
    def _slip_yarns(self, j: ti.i32, i: ti.i32, yield_s: ti.f64, yield_t: ti.f64):
        """Let the yarns at node (j, i) slip as far as its bend asks. The frictional couples of the two bends
        centred there (along s and t) slip together, on their size: sqrt((Ms/HB)² + (Mt/HB)²) <= 1, an
        ellipse in the stretch of the frictional elements with semi-axes yield_s and yield_t: one node's
        yarns slip as one, whatever the direction of the bend. The return mapping scales both stretches
        back onto the ellipse and moves the stick points by the rest."""
        nx, ny = ti.static(self.grid.nx, self.grid.ny)
        along_s = ti.Vector([0.0, 0.0, 0.0], dt=ti.f64)
        along_t = ti.Vector([0.0, 0.0, 0.0], dt=ti.f64)
        if 0 < i < nx - 1:
            along_s = self._elastic_bend(
                ti.Vector([j, i - 1]), ti.Vector([j, i]), ti.Vector([j, i + 1]), self.set_along_s[j, i - 1]
            )
        if 0 < j < ny - 1:
            along_t = self._elastic_bend(
                ti.Vector([j - 1, i]), ti.Vector([j, i]), ti.Vector([j + 1, i]), self.set_along_t[j - 1, i]
            )
        size = ti.sqrt(along_s.norm_sqr() / yield_s**2 + along_t.norm_sqr() / yield_t**2)
        if size > 1.0:
            slip = 1.0 - 1.0 / size
            if 0 < i < nx - 1:
                self.set_along_s[j, i - 1] += slip * along_s
            if 0 < j < ny - 1:
                self.set_along_t[j - 1, i] += slip * along_t

    @ti.func
    def _belt_velocity(self, p: ti.template(), pitch: ti.f64, half_belt: ti.f64) -> belt_hit:
        """(vx, vy, on_belt, 0): surface velocity of the belt under world point p; zero over the deck."""
        hit = belt_at(
            p[0], p[1], self.mod_direction, pitch, half_belt, self.table.modules_x, self.table.modules_y
        )
        vel = belt_hit(0.0, 0.0, 0.0, 0.0)
        if hit[3] > 0.0:
            m = ti.cast(hit[0], ti.i32)
            speed = self.mod_speed[m]
            vel = belt_hit(speed * self.mod_direction[m][0], speed * self.mod_direction[m][1], 1.0, 0.0)
        return vel

    @ti.kernel
    def _advance(
        self,
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
        nx, ny = ti.static(self.grid.nx, self.grid.ny)
        dx, dy = ti.static(self.grid.dx_m, self.grid.dy_m)
        diag = ti.static((self.grid.dx_m**2 + self.grid.dy_m**2) ** 0.5)
        ti.loop_config(serialize=True)
        for step in range(substeps):
            for j, i in ti.ndrange(ny, nx):
                self.x_prev[j, i] = self.x[j, i]
                self.reaction[j, i] = ti.Vector([0.0, 0.0, 0.0])
                belt = self._belt_velocity(self.x[j, i], pitch, half_belt)
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
                        self.v[j, i][2] += shake * ti.abs(self.kick[j, i])
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
                if 0 < flap < 4 or bisect < FLAT_CELL * diag:
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
                    self._slip_yarns(j, i, yield_s, yield_t)
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
                    belt = self._belt_velocity(self.x[j, i], pitch, half_belt)
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
