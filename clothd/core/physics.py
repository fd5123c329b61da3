"""The tracker's cloth model: a Provot mass–spring on the tracking mesh, driven by the conveyors (Taichi).

Nodes carry mass from the cloth's areal density. Springs (Provot 1995): structural (grid edges), shear
(cell diagonals) and flexion (every second node along rows and columns), with Provot's strain limiting:
after each substep a structural or shear spring stretched past (1 + strain_limit) of its rest length is
pulled back, half from each end.

The springs are a woven fabric's, not Hooke's: slack up to `slack_strain` (the crimp of the yarns), and
soft in compression (`compression_k_ratio`), because cloth buckles rather than push. This matters more
than it seems: a 0.14 g node's friction on a belt is ~1.4 mN, which a 50 N/m spring exceeds at 0.03 mm
of strain. Hookean springs snapped the mesh back to its rest shape every tick, against the features,
whenever the cloth was compressed or its rest lengths (measured at initialisation) were a little off
(docs/architecture.md, "Folds").

Height is kinematic: the model moves the nodes in the plane and keeps the heights it is given (folds.py
computes them from inextensibility after each correction), so the springs see the fold in 3-D and a
folded edge, back at its rest length, pushes on nothing. A spring whose ends differ in height by more than
its rest length (the folds give a node its row's or its column's climb, whichever is higher, so a
neighbour across can lie far below) cannot be made whole by any move in the plane; it is left out, where
its strain limit had dragged its ends together and past each other, and folded the mesh over itself.
A spring with both ends up in a fold does not push in compression: the fold's top is narrower in the
plane than the cloth between its nodes, which arches up over the straight line (a tall fold's crest
stands well above its nodes), and that arch is bending, not compression. Pushing, it drove a fold's two
top nodes apart by ~4 mm a tick, and once no feature saw them, back past their neighbours on the table
(docs/benchmarks.md, "A fold's top, seen and predicted").

A node on the table rests on it (normal force m·g) and feels friction against the belt under it: Coulomb
with a regularised stick zone, applied implicitly on the velocity so it is stable at any step; the belt's
surface velocity, from the module commands, is the control input u. A node up in a fold feels no belt.
Symplectic Euler with at least `substeps` per tick, more when the springs need it for stability.

`step` advances the state in place; `transition_blocks` gives the per-node linearisation the filter
propagates its covariance with (see mesh_ekf.py for why the spring couplings are not linearised).
"""

import math

import numpy as np
import taichi as ti

from clothd.config import PhysicsConfig

GRAVITY_M_S2 = 9.81
# Substeps keep h·ω_max at or below this (symplectic Euler is stable below 2; see set_rest).
H_OMEGA_MAX = 1.5
# A node this close to the table rests on it.
CONTACT_HEIGHT_M = 1e-4
WARM_UP_SPACING_M = 0.01
vec3d = ti.types.vector(3, ti.f64)
_Material = ti.types.struct(
    mass=ti.f64,
    mu=ti.f64,
    stick_speed=ti.f64,
    damping=ti.f64,
    strain_limit=ti.f64,
    slack=ti.f64,
    compression_ratio=ti.f64,
)


def stick_time_s(cfg: PhysicsConfig) -> float:
    """How fast friction brings cloth to the belt's speed: the stick zone's width over the largest
    deceleration Coulomb friction can give, stick_speed / (μ g)."""
    return cfg.stick_speed_m_s / (cfg.friction_mu * GRAVITY_M_S2)


def spring_pairs(nx: int, ny: int) -> dict[str, np.ndarray]:
    """Flat node index pairs (k, 2) of each spring family on an nx x ny grid (node n = j·nx + i)."""
    idx = np.arange(nx * ny).reshape(ny, nx)

    def pairs(a: np.ndarray, b: np.ndarray) -> np.ndarray:
        return np.stack([a.ravel(), b.ravel()], axis=1)

    return {
        "structural": np.concatenate([pairs(idx[:, :-1], idx[:, 1:]), pairs(idx[:-1, :], idx[1:, :])]),
        "shear": np.concatenate([pairs(idx[:-1, :-1], idx[1:, 1:]), pairs(idx[:-1, 1:], idx[1:, :-1])]),
        "flexion": np.concatenate([pairs(idx[:, :-2], idx[:, 2:]), pairs(idx[:-2, :], idx[2:, :])]),
    }


@ti.data_oriented
class MassSpring:
    """Mass–spring cloth on an nx x ny mesh. The Taichi fields are allocated once, for the mesh's shape;
    `set_rest` lays a new rest mesh into them, so re-initialising tracking allocates nothing and
    compiles nothing."""

    def __init__(self, cfg: PhysicsConfig, nx: int, ny: int) -> None:
        if ti.lang.impl.get_runtime().prog is None:
            raise RuntimeError("Taichi is not started: call clothd.taichi_runtime.start_taichi first")
        self.n = nx * ny
        families = spring_pairs(nx, ny)
        self._family_sizes = tuple(len(families[f]) for f in ("structural", "shear", "flexion"))
        self._pairs = np.concatenate(list(families.values()))
        self.n_limited = len(families["structural"]) + len(families["shear"])  # Provot limits these
        self.x = ti.Vector.field(3, ti.f64, shape=self.n)
        self.v = ti.Vector.field(3, ti.f64, shape=self.n)
        self.belt = ti.Vector.field(3, ti.f64, shape=self.n)  # vx, vy, on_belt
        self.pair = ti.Vector.field(2, ti.i32, shape=len(self._pairs))
        self.rest = ti.field(ti.f64, shape=len(self._pairs))
        self.k = ti.field(ti.f64, shape=len(self._pairs))
        self.force = ti.Vector.field(3, ti.f64, shape=self.n)
        self.material = _Material.field(shape=())
        self.pair.from_numpy(self._pairs.astype(np.int32))
        self.set_material(cfg)
        self.mass_kg = 0.0
        self.omega_max_rad_s = 0.0
        # The state crosses into the kernel as one array, [x, v, belt vx, belt vy, on belt] per node: one
        # kernel launch per tick, where a field copy in and out cost a launch each.
        self._io = np.zeros((self.n, 9))
        self._compile(nx, ny)

    def _compile(self, nx: int, ny: int) -> None:
        """Compile the kernel now, on a throw-away rest mesh, so that no tick pays for it (~0.2 s): a
        live tick that long stops a move for a silent compute."""
        i, j = np.meshgrid(np.arange(nx), np.arange(ny))
        self.set_rest(np.stack([i, j], axis=-1) * WARM_UP_SPACING_M)
        self._advance(self._io, 1, 0.0)
        self._io[:] = 0.0

    def set_material(self, cfg: PhysicsConfig) -> None:
        """Take the constants of cfg, for the fields already allocated and the kernel already compiled
        (`clothd tune` tries hundreds); set_rest follows, which derives the mass and the material."""
        self.cfg = cfg
        structural, shear, flexion = self._family_sizes
        self._stiffness = np.concatenate(
            [
                np.full(structural, cfg.stretch_k_n_m),
                np.full(shear, cfg.shear_k_n_m),
                np.full(flexion, cfg.flexion_k_n_m),
            ]
        )
        self.k.from_numpy(self._stiffness)

    def set_rest(self, rest_xy_m: np.ndarray) -> None:
        """Lay the rest mesh rest_xy_m (ny, nx, 2) (node positions in cloth space) into the model."""
        cfg = self.cfg
        rest = rest_xy_m.reshape(-1, 2)
        pairs = self._pairs
        lengths = np.linalg.norm(rest[pairs[:, 0]] - rest[pairs[:, 1]], axis=1)
        # Lumped mass: the cloth's area shared equally (the mesh covers the whole cloth).
        self.mass_kg = cfg.areal_density_kg_m2 * _polygon_area(rest_xy_m) / self.n
        self.material[None] = _Material(
            mass=self.mass_kg,
            mu=cfg.friction_mu,
            stick_speed=cfg.stick_speed_m_s,
            damping=cfg.damping_1_s,
            strain_limit=cfg.strain_limit,
            slack=cfg.slack_strain,
            compression_ratio=cfg.compression_k_ratio,
        )
        # Symplectic Euler is stable for h < 2/ω; the stiffest node (all 12 springs) sets ω, which bounds
        # the lattice's fastest mode (a row of nodes against the next, every spring in tension: ω·0.98).
        # Substeps are raised to keep h <= 1.5/ω, a margin of 1.35. A margin of 2 (h <= 1/ω) cost 119
        # substeps a tick at 32 x 32 nodes (ω grows with the node count: the mass per node falls). Against
        # 4x the substeps a tick's nodes differ by 57 µm p99 at h·ω = 1.5 and 26 µm at 1, where the
        # filter's process noise is 500 µm a tick (docs/benchmarks.md, "Speed and scaling").
        per_node = np.bincount(pairs.ravel(), weights=np.repeat(self._stiffness, 2), minlength=self.n)
        self.omega_max_rad_s = float(np.sqrt(per_node.max() / self.mass_kg))
        self.rest.from_numpy(lengths)

    def set_state(self, x_m: np.ndarray, v_m_s: np.ndarray) -> None:
        """x_m, v_m_s: (n, 3)."""
        self._io[:, :3] = x_m
        self._io[:, 3:6] = v_m_s

    def state(self) -> tuple[np.ndarray, np.ndarray]:
        return self._io[:, :3].copy(), self._io[:, 3:6].copy()

    def step(self, dt_s: float, belt_velocity_m_s: np.ndarray, on_belt: np.ndarray) -> None:
        """Advance one tick. belt_velocity_m_s (n, 2) and on_belt (n,) bool: the input u at each node."""
        self._io[:, 6:8] = belt_velocity_m_s
        self._io[:, 8] = on_belt
        substeps = max(self.cfg.substeps, math.ceil(dt_s * self.omega_max_rad_s / H_OMEGA_MAX))
        self._advance(self._io, substeps, dt_s / substeps)

    def transition_blocks(self, dt_s: float, in_contact: np.ndarray) -> np.ndarray:
        """Per-node F_i (n, 6, 6) for [p_i, v_i]: v⁺ = α_i v + (1 − α_i)·(input), p⁺ = p + dt·v⁺.

        α_i is how much of its own velocity a node keeps over a tick: on a belt, friction pulls it to the
        belt speed within about stick_speed/(μ g) s; elsewhere only the damping acts."""
        c = self.cfg
        alpha = np.where(in_contact, math.exp(-dt_s / stick_time_s(c)), math.exp(-dt_s * c.damping_1_s))
        F = np.tile(np.eye(6), (self.n, 1, 1))
        F[:, 3:, 3:] *= alpha[:, None, None]
        F[:, :3, 3:] = dt_s * alpha[:, None, None] * np.eye(3)
        return F

    @ti.kernel
    def _advance(
        self,
        io: ti.types.ndarray(dtype=ti.f64, ndim=2),
        substeps: ti.i32,
        h: ti.f64,
    ):
        # One serial kernel for all substeps: the mesh is small, and a launch per substep would cost more
        # than the arithmetic.
        for i in range(self.n):
            self.x[i] = vec3d(io[i, 0], io[i, 1], io[i, 2])
            self.v[i] = vec3d(io[i, 3], io[i, 4], io[i, 5])
            self.belt[i] = vec3d(io[i, 6], io[i, 7], io[i, 8])
        ti.loop_config(serialize=True)
        for _ in range(substeps):
            self._substep(h)
        for i in range(self.n):
            for j in ti.static(range(3)):
                io[i, j] = self.x[i][j]
                io[i, 3 + j] = self.v[i][j]

    @ti.func
    def _substep(self, h: ti.f64):
        m = self.material[None]
        for i in range(self.n):
            self.force[i] = vec3d(0.0, 0.0, 0.0)
        for s in range(self.rest.shape[0]):
            a, b = self.pair[s][0], self.pair[s][1]
            d = self.x[b] - self.x[a]
            length = d.norm()
            # Ends further apart in height than the spring is long: the kinematic heights are not
            # consistent there, and no move in the plane could make the spring whole (see _substep's
            # strain limiting); it is left out rather than let it drag its ends together.
            if length > 1e-12 and ti.abs(d[2]) < self.rest[s]:
                # Cloth pulls only once its crimp is taken up, and buckles rather than push.
                extension = ti.max(length - (1.0 + m.slack) * self.rest[s], 0.0)
                compression = ti.min(length - self.rest[s], 0.0)
                if self.x[a][2] > CONTACT_HEIGHT_M and self.x[b][2] > CONTACT_HEIGHT_M:
                    # Both ends up in a fold: the cloth between them arches over the straight line the
                    # nodes give, and bends rather than push them apart.
                    compression = 0.0
                f = self.k[s] * (extension + m.compression_ratio * compression) * d / length
                self.force[a] += f
                self.force[b] -= f
        for i in range(self.n):
            v = self.v[i] + h * self.force[i] / m.mass
            v[0] *= 1.0 / (1.0 + h * m.damping)
            v[1] *= 1.0 / (1.0 + h * m.damping)
            v[2] = 0.0  # height is kinematic
            # On the table, gravity's normal force m·g lets friction take up to μ·g·h of slip speed per
            # substep from a node on a belt; a node up in a fold feels no belt.
            if self.x[i][2] <= CONTACT_HEIGHT_M and self.belt[i][2] > 0.0:
                budget = m.mu * GRAVITY_M_S2 * h
                slip = ti.Vector([v[0] - self.belt[i][0], v[1] - self.belt[i][1]])
                speed = slip.norm()
                keep = ti.max(1.0 - budget / ti.max(speed, 1e-15), 1.0 / (1.0 + budget / m.stick_speed))
                v[0] = self.belt[i][0] + keep * slip[0]
                v[1] = self.belt[i][1] + keep * slip[1]
            self.v[i] = v
            self.x[i] += h * v
        # Provot's strain limiting on structural and shear springs (one Gauss-Seidel pass).
        for s in range(self.n_limited):
            a, b = self.pair[s][0], self.pair[s][1]
            d = self.x[b] - self.x[a]
            length = d.norm()
            limit = (1.0 + m.strain_limit) * self.rest[s]
            if length > limit and ti.abs(d[2]) < self.rest[s]:
                fix = 0.5 * (length - limit) * d / length
                fix[2] = 0.0
                self.x[a] += fix
                self.x[b] -= fix


def _polygon_area(grid_xy: np.ndarray) -> float:
    """Area of the quad grid's outline (shoelace over its boundary)."""
    b = np.concatenate([grid_xy[0, :], grid_xy[1:, -1], grid_xy[-1, -2::-1], grid_xy[-2:0:-1, 0]])
    x, y = b[:, 0], b[:, 1]
    return float(0.5 * abs(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1))))
