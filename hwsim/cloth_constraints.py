# mypy: disable-error-code="valid-type,no-untyped-def"
"""The truth cloth's constraints (hwsim/cloth.py's solver): stretch and shear distances, the shear measured
along a bent cell, bending with the yarns' friction, and the true elastic force on anchored ends. A base
class of `ClothSim`, whose fields (x, inv_mass, stuck, held, reaction, folded, set_along_s/t) they act on
(docs/hwsim.md, "The cloth")."""

import taichi as ti

from hwsim.cloth_constants import FOLD_STRAIN

vec2d = ti.types.vector(2, ti.f64)


class ClothConstraints:
    """The solver's per-constraint projections, as Taichi functions of the subclass's fields."""

    x: ti.MatrixField
    inv_mass: ti.Field
    stuck: ti.Field
    held: ti.Field
    reaction: ti.MatrixField
    folded: ti.Field
    set_along_s: ti.MatrixField
    set_along_t: ti.MatrixField

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
    def _slip_yarns(self, j: ti.i32, i: ti.i32, nx: ti.i32, ny: ti.i32, yield_s: ti.f64, yield_t: ti.f64):
        """Let the yarns at node (j, i) slip as far as its bend asks. The frictional couples of the two bends
        centred there (along s and t) slip together, on their size: sqrt((Ms/HB)² + (Mt/HB)²) <= 1, an
        ellipse in the stretch of the frictional elements with semi-axes yield_s and yield_t: one node's
        yarns slip as one, whatever the direction of the bend. The return mapping scales both stretches
        back onto the ellipse and moves the stick points by the rest."""
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
