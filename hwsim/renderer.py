"""The simulated camera's image: a Taichi rasteriser for the cloth, belts and deck, and arm occluders.

Per frame, at `supersample` times the output resolution:
1. every cloth triangle is rasterised into a z-buffer of packed (depth, triangle) keys (atomic min);
2. each pixel is shaded: cloth pixels sample the cloth texture at the perspective-correct material
   coordinate (bilinear, on the mip level that matches the pixel density, so nothing aliases) and are
   lit by their interpolated normal, which makes folds visible; other pixels show the moving belt under
   them, scrolled by how far it has run, or the static deck; arms are drawn on top;
3. blocks of supersample x supersample pixels are averaged into the output (area filter).
Motion blur averages several such renders across the exposure. Sensor noise is added last.

The cloth surface is the truth mesh split into triangles along each cell's (j, i)-(j+1, i+1) diagonal,
exactly as docs/recording-format.md states for grading. Several pieces of cloth (a flow's) each take a slot
of fixed capacity, their grids' sizes and fabrics being data, so a new piece compiles nothing.
"""

import numpy as np
import taichi as ti

from hwsim.belt_geometry import belt_on_module, module_at
from hwsim.camera import Camera
from hwsim.cloth_grid import ClothGrid
from hwsim.infeed import largest_specs
from hwsim.pieces import capacity_for
from hwsim.render_textures import DECK_TILE_M, RenderTextures, render_textures
from hwsim.scenario import Scenario
from hwsim.scene import SceneState

MAX_ARMS = 4
_EMPTY_KEY = 2**62
_TRI_BITS = 21  # triangle index bits in a z-buffer key; depth in micrometres above them
_VISIBLE_DEPTH_TOL_M = 0.003
# Per-node fields of every slot, with their channels.
_VERTEX_ARRAYS = (("vpx", 2), ("vdepth", 1), ("vnormal", 3), ("vtan_s", 3), ("vtan_t", 3))
ARM_BGR = (0.30, 0.42, 0.55)  # a sleeve
vec3f = ti.types.vector(3, ti.f32)


def vertex_normals(nodes_m: np.ndarray) -> np.ndarray:
    """Unit normals (ny, nx, 3) of a node grid from central differences, oriented along +s x +t."""
    ds = np.gradient(nodes_m, axis=1)
    dt = np.gradient(nodes_m, axis=0)
    n = np.cross(ds, dt)
    return np.asarray(n / np.maximum(np.linalg.norm(n, axis=-1, keepdims=True), 1e-12))


@ti.func
def _bilinear(tex: ti.template(), x: ti.f32, y: ti.f32, wrap_x: ti.template()) -> vec3f:
    """Sample tex at continuous texel coordinates (x along columns, y along rows; centres at integers).
    Columns wrap when wrap_x, else clamp; rows clamp."""
    h, w = tex.shape[0], tex.shape[1]
    x0f, y0f = ti.floor(x), ti.floor(y)
    fx, fy = x - x0f, y - y0f
    x0, y0 = ti.cast(x0f, ti.i32), ti.cast(y0f, ti.i32)
    x1 = x0 + 1
    if ti.static(wrap_x):
        x0, x1 = x0 % w, x1 % w
    else:
        x0, x1 = ti.math.clamp(x0, 0, w - 1), ti.math.clamp(x1, 0, w - 1)
    y1 = ti.math.clamp(y0 + 1, 0, h - 1)
    y0 = ti.math.clamp(y0, 0, h - 1)
    top = tex[y0, x0] * (1 - fx) + tex[y0, x1] * fx
    bottom = tex[y1, x0] * (1 - fx) + tex[y1, x1] * fx
    return top * (1 - fy) + bottom * fy


@ti.func
def _bilinear2(tex: ti.template(), x: ti.f32, y: ti.f32) -> ti.types.vector(2, ti.f32):
    """As _bilinear, for a 2-channel field, clamped on both axes."""
    h, w = tex.shape[0], tex.shape[1]
    x0f, y0f = ti.floor(x), ti.floor(y)
    fx, fy = x - x0f, y - y0f
    x0 = ti.math.clamp(ti.cast(x0f, ti.i32), 0, w - 1)
    x1 = ti.math.clamp(ti.cast(x0f, ti.i32) + 1, 0, w - 1)
    y0 = ti.math.clamp(ti.cast(y0f, ti.i32), 0, h - 1)
    y1 = ti.math.clamp(ti.cast(y0f, ti.i32) + 1, 0, h - 1)
    top = tex[y0, x0] * (1 - fx) + tex[y0, x1] * fx
    bottom = tex[y1, x0] * (1 - fx) + tex[y1, x1] * fx
    return top * (1 - fy) + bottom * fy


def render_px_per_m(scenario: Scenario, camera: Camera) -> float:
    """Pixel density on a flat cloth under the camera, at the render's (supersampled) resolution."""
    hi = camera.scaled(scenario.supersample)
    return float(hi.K[0, 0] / abs(hi.centre_m[2]))


def _slots(scenario: Scenario, grid: ClothGrid) -> tuple[int, tuple[int, int]]:
    """One slot per piece on the table, and the capacity (rows, columns) of each slot's grid."""
    if scenario.infeed is None:
        return 1, (grid.ny, grid.nx)
    return scenario.infeed.max_pieces, capacity_for(largest_specs(scenario))


def layout_key(
    scenario: Scenario, camera: Camera, grid: ClothGrid, textures: RenderTextures
) -> tuple[object, ...]:
    """What a Renderer's fields' shapes and its kernels' constants depend on: two renders with the same key
    can share one Renderer (`Renderer.load`)."""
    tab = scenario.table
    table = (tab.modules_x, tab.modules_y, tab.pitch_m, tab.module_size_m)
    size = (camera.height, camera.width)
    return (scenario.supersample, size, _slots(scenario, grid), table, textures.layout())


@ti.data_oriented
class Renderer:
    """A camera's renders of a scenario. hwsim/renderer_spares.py hands a gone camera's Renderer to the next
    of the same `layout_key`, its kernels compiled already."""

    def __init__(
        self, scenario: Scenario, camera: Camera, grid: ClothGrid, textures: RenderTextures | None = None
    ) -> None:
        textures = textures or render_textures(scenario, render_px_per_m(scenario, camera))
        self.ss = scenario.supersample
        self.hi = camera.scaled(self.ss)
        self.slots, self.cap = _slots(scenario, grid)
        self.tris_per_slot = 2 * (self.cap[0] - 1) * (self.cap[1] - 1)
        self.table_spec = scenario.table
        H, W = self.hi.height, self.hi.width
        self.key = ti.field(ti.i64, shape=(H, W))
        self.accum = ti.Vector.field(3, ti.f32, shape=(H, W))
        self.out = ti.Vector.field(3, ti.f32, shape=(camera.height, camera.width))
        self.table_xy = ti.Vector.field(2, ti.f32, shape=(H, W))
        # What each pixel sees of the table that the belts' headings do not change (`_table_statics`).
        self.table_module = ti.field(ti.i32, shape=(H, W))
        self.table_rxy = ti.Vector.field(2, ti.f64, shape=(H, W))
        self.deck_colour = ti.Vector.field(3, ti.f32, shape=(H, W))
        shape = (self.slots, *self.cap)
        self.slot_dims = ti.field(ti.i32, shape=(self.slots, 3))  # nx, ny, texture
        self.slot_spacing = ti.field(ti.f32, shape=(self.slots, 2))  # dx, dy
        self.vpx = ti.Vector.field(2, ti.f32, shape=shape)
        self.vdepth = ti.field(ti.f32, shape=shape)
        self.vnormal = ti.Vector.field(3, ti.f32, shape=shape)
        # Unit tangents along s and t, for the weave's relief (texture.relief_m) to tilt the normal.
        self.vtan_s = ti.Vector.field(3, ti.f32, shape=shape)
        self.vtan_t = ti.Vector.field(3, ti.f32, shape=shape)
        self.visible = ti.field(ti.i32, shape=shape)
        n_mod = self.table_spec.modules_x * self.table_spec.modules_y
        self.direction = ti.Vector.field(2, ti.f64, shape=n_mod)  # cos, sin of each module's heading
        self.travel = ti.field(ti.f32, shape=n_mod)
        self.arm_seg = ti.Vector.field(4, ti.f32, shape=MAX_ARMS)  # shoulder px, hand px
        self.arm_radius = ti.field(ti.f32, shape=MAX_ARMS)  # px; 0 = no arm
        # The textures' sizes and samplers' constants are the kernels'; `load` fills them.
        fabrics = textures.fabrics
        self.cloth_tex = [ti.Vector.field(3, ti.f32, shape=f.colour.shape[:2]) for f in fabrics]
        self.cloth_slopes = [ti.Vector.field(2, ti.f32, shape=f.slopes.shape[:2]) for f in fabrics]
        self.cloth_texels_per_m = [f.texels_per_m for f in fabrics]
        self.cloth_texel_offset = [f.texel_offset for f in fabrics]
        self.relief = [f.relief for f in fabrics]
        self.belt_tex = ti.Vector.field(3, ti.f32, shape=textures.belt.shape[:2])
        self.deck_tex = ti.Vector.field(3, ti.f32, shape=textures.deck.shape[:2])
        self.belt_texels_per_m = textures.table_texels_per_m
        self.table_texel_offset = textures.table_texel_offset
        self.load(scenario, camera, grid, textures)

    def load(self, scenario: Scenario, camera: Camera, grid: ClothGrid, textures: RenderTextures) -> None:
        """Render this camera's view of this scenario from now on; its `layout_key` must be this Renderer's.
        Every field a frame does not write is written here, so a Renderer loaded again renders bit for bit
        as a new one."""
        self.camera = camera
        self._uploaded: dict[str, np.ndarray] = {}  # what `_upload_changed` last wrote into each field
        self.hi = camera.scaled(self.ss)
        self.grid = grid  # the lead piece's at the start: the visibility `render` returns is the lead's
        self.table_spec = scenario.table
        self.table_xy.from_numpy(np.nan_to_num(self.hi.table_points(), nan=1e3).astype(np.float32))
        for fabric, colour, slopes in zip(textures.fabrics, self.cloth_tex, self.cloth_slopes, strict=True):
            colour.from_numpy(fabric.colour)
            slopes.from_numpy(fabric.slopes)
        self.belt_tex.from_numpy(textures.belt)
        self.deck_tex.from_numpy(textures.deck)
        self._table_statics()
        light = np.asarray(scenario.light.direction, dtype=float)
        self.light = light / np.linalg.norm(light)
        self.ambient = scenario.light.ambient

    def render(self, states: list[SceneState]) -> tuple[np.ndarray, np.ndarray]:
        """Average renders of `states` (one per motion-blur sample; the last is the frame's instant).
        Returns the image (height, width, 3) float32 BGR in [0, 1] and node visibility (ny, nx) bool of
        the last state: in view, not behind other cloth, not under an arm."""
        self.accum.fill(0.0)
        weight = 1.0 / len(states)
        for state in states:
            self._upload(state)
            self._clear()
            self._raster(len(state.cloths))
            self._shade(weight, len(state.arms), *self._lighting())
        if self.ss > 1:  # else the average is the image already
            self._downsample()
        cloths = states[-1].cloths
        self._node_visibility(len(states[-1].arms), len(cloths))
        ny, nx = cloths[0].nodes_m.shape[:2] if cloths else (self.grid.ny, self.grid.nx)
        image = (self.out if self.ss > 1 else self.accum).to_numpy()
        return image, self.visible.to_numpy()[0, :ny, :nx].astype(bool)

    def _lighting(self) -> tuple[float, float, float, float, float]:
        flat = self.ambient + (1.0 - self.ambient) * max(0.0, float(self.light[2]))
        return (float(self.light[0]), float(self.light[1]), float(self.light[2]), self.ambient, flat)

    def _upload(self, state: SceneState) -> None:
        if len(state.cloths) > self.slots:
            raise ValueError(f"at most {self.slots} pieces of cloth in view at once, got {len(state.cloths)}")
        arrays = {name: np.zeros((self.slots, *self.cap, n), np.float32) for name, n in _VERTEX_ARRAYS}
        dims = np.zeros((self.slots, 3), np.int32)
        spacing = np.ones((self.slots, 2), np.float32)
        for k, cloth in enumerate(state.cloths):
            ny, nx = cloth.nodes_m.shape[:2]
            dims[k], spacing[k] = (nx, ny, cloth.texture), cloth.spacing_m
            for name, values in self._vertex_values(cloth.nodes_m).items():
                arrays[name][k, :ny, :nx] = values.reshape(ny, nx, -1)
        self._upload_changed("slot_dims", dims)
        self._upload_changed("slot_spacing", spacing)
        for name, _ in _VERTEX_ARRAYS:
            values = arrays[name]
            self._upload_changed(name, values[..., 0] if values.shape[-1] == 1 else values)
        hi = self.hi
        heading = state.heading_rad
        self._upload_changed("direction", np.stack([np.cos(heading), np.sin(heading)], axis=1))
        self._upload_changed("travel", state.travel_m.astype(np.float32))
        seg = np.zeros((MAX_ARMS, 4), np.float32)
        radius = np.zeros(MAX_ARMS, np.float32)
        if len(state.arms) > MAX_ARMS:
            raise ValueError(f"at most {MAX_ARMS} arms in view at once, got {len(state.arms)}")
        for k, arm in enumerate(state.arms):
            ends = hi.project(np.stack([arm.shoulder_m, arm.hand_m]))
            seg[k] = ends.ravel()
            radius[k] = hi.K[0, 0] * arm.radius_m / hi.to_camera(arm.hand_m[None])[0, 2]
        self._upload_changed("arm_seg", seg)
        self._upload_changed("arm_radius", radius)

    def _upload_changed(self, name: str, values: np.ndarray) -> None:
        """Write values into the field `name` unless it holds them already: each upload is a kernel launch
        of its own, and the belts' headings, the slots and the arms rarely change."""
        last = self._uploaded.get(name)
        if last is None or not np.array_equal(last, values):
            getattr(self, name).from_numpy(values)
            self._uploaded[name] = values.copy()

    def _vertex_values(self, nodes_m: np.ndarray) -> dict[str, np.ndarray]:
        """One cloth's per-node data for the render: pixels, depth, normals and (for relief) tangents."""
        hi = self.hi
        out = {"vpx": hi.project(nodes_m), "vdepth": hi.to_camera(nodes_m)[..., 2:]}
        normals = vertex_normals(nodes_m)
        # Light the side that faces the camera: the cloth's back is the same fabric.
        to_cam = hi.centre_m - nodes_m
        flip = np.sign(np.sum(normals * to_cam, axis=-1, keepdims=True))
        sign = np.where(flip == 0, 1, flip)
        out["vnormal"] = normals * sign
        if any(self.relief):
            # The relief stands out of the sheet's front: seen from its back, tangents flip with the normal.
            for name, axis in (("vtan_s", 1), ("vtan_t", 0)):
                tan = np.gradient(nodes_m, axis=axis)
                out[name] = tan / np.maximum(np.linalg.norm(tan, axis=-1, keepdims=True), 1e-12) * sign
        return {k: v.astype(np.float32) for k, v in out.items()}

    @ti.func
    def _corners(self, tri: ti.i32) -> ti.types.matrix(3, 3, ti.i32):
        """(slot, j, i) of the three nodes of triangle `tri` (slot-major); cell (j, i) splits along
        (j, i)-(j+1, i+1). A triangle past its slot's grid has j beyond it."""
        slot, local = tri // ti.static(self.tris_per_slot), tri % ti.static(self.tris_per_slot)
        nxc = self.slot_dims[slot, 0] - 1
        cell, upper = local // 2, local % 2
        j, i = cell // nxc, cell % nxc
        m = ti.Matrix([[slot, j, i], [slot, j, i + 1], [slot, j + 1, i + 1]], ti.i32)
        if upper == 1:
            m = ti.Matrix([[slot, j, i], [slot, j + 1, i + 1], [slot, j + 1, i]], ti.i32)
        return m

    @ti.func
    def _barycentric(self, c: ti.template(), u: ti.f32, v: ti.f32) -> vec3f:
        a = self.vpx[c[0, 0], c[0, 1], c[0, 2]]
        b = self.vpx[c[1, 0], c[1, 1], c[1, 2]]
        d = self.vpx[c[2, 0], c[2, 1], c[2, 2]]
        area = (b[0] - a[0]) * (d[1] - a[1]) - (b[1] - a[1]) * (d[0] - a[0])
        w0 = ((b[0] - u) * (d[1] - v) - (b[1] - v) * (d[0] - u)) / area
        w1 = ((d[0] - u) * (a[1] - v) - (d[1] - v) * (a[0] - u)) / area
        return vec3f(w0, w1, 1.0 - w0 - w1)

    @ti.kernel
    def _clear(self):
        for v, u in self.key:
            self.key[v, u] = ti.i64(_EMPTY_KEY)

    @ti.kernel
    def _raster(self, n_cloths: ti.i32):
        H, W = ti.static(self.hi.height, self.hi.width)
        for tri in range(n_cloths * ti.static(self.tris_per_slot)):
            c = self._corners(tri)
            if c[2, 1] >= self.slot_dims[c[0, 0], 1]:
                continue  # past this slot's grid
            lo = ti.Vector([1e9, 1e9])
            hi = ti.Vector([-1e9, -1e9])
            for k in ti.static(range(3)):
                p = self.vpx[c[k, 0], c[k, 1], c[k, 2]]
                lo = ti.min(lo, p)
                hi = ti.max(hi, p)
            u0, v0 = ti.max(0, ti.cast(ti.ceil(lo[0]), ti.i32)), ti.max(0, ti.cast(ti.ceil(lo[1]), ti.i32))
            u1 = ti.min(W - 1, ti.cast(ti.floor(hi[0]), ti.i32))
            v1 = ti.min(H - 1, ti.cast(ti.floor(hi[1]), ti.i32))
            for v in range(v0, v1 + 1):
                for u in range(u0, u1 + 1):
                    w = self._barycentric(c, ti.cast(u, ti.f32), ti.cast(v, ti.f32))
                    if w.min() >= -1e-6 and w.max() <= 1.0 + 1e-6:
                        inv_z = 0.0
                        for k in ti.static(range(3)):
                            inv_z += w[k] / self.vdepth[c[k, 0], c[k, 1], c[k, 2]]
                        depth_um = ti.cast(1e6 / inv_z, ti.i64)
                        ti.atomic_min(self.key[v, u], (depth_um << _TRI_BITS) | ti.cast(tri, ti.i64))

    @ti.func
    def _cloth_colour(self, key: ti.i64, u: ti.f32, v: ti.f32, light: vec3f, ambient: ti.f32) -> vec3f:
        c = self._corners(ti.cast(key & ((1 << _TRI_BITS) - 1), ti.i32))
        w = self._barycentric(c, u, v)
        # Perspective-correct weights: interpolate attribute/z and 1/z linearly on screen.
        pw = vec3f(0.0, 0.0, 0.0)
        for k in ti.static(range(3)):
            pw[k] = w[k] / self.vdepth[c[k, 0], c[k, 1], c[k, 2]]
        pw /= pw.sum()
        s, t = 0.0, 0.0
        n = vec3f(0.0, 0.0, 0.0)
        slot = c[0, 0]
        for k in ti.static(range(3)):
            s += pw[k] * c[k, 2] * self.slot_spacing[slot, 0]
            t += pw[k] * c[k, 1] * self.slot_spacing[slot, 1]
            n += pw[k] * self.vnormal[c[k, 0], c[k, 1], c[k, 2]]
        fabric = self.slot_dims[slot, 2]
        albedo = vec3f(0.0, 0.0, 0.0)
        for q in ti.static(range(len(self.cloth_tex))):
            if fabric == q:
                tpm = ti.static(self.cloth_texels_per_m[q])
                off = ti.static(self.cloth_texel_offset[q])
                if ti.static(self.relief[q]):
                    # Tilt the normal by the relief's slopes: n - dh/ds T_s - dh/dt T_t (a height field on
                    # the sheet).
                    ts = vec3f(0.0, 0.0, 0.0)
                    tt = vec3f(0.0, 0.0, 0.0)
                    for k in ti.static(range(3)):
                        ts += pw[k] * self.vtan_s[c[k, 0], c[k, 1], c[k, 2]]
                        tt += pw[k] * self.vtan_t[c[k, 0], c[k, 1], c[k, 2]]
                    g = _bilinear2(self.cloth_slopes[q], s * tpm - off, t * tpm - off)
                    n = n.normalized() - g[0] * ts.normalized() - g[1] * tt.normalized()
                albedo = _bilinear(self.cloth_tex[q], s * tpm - off, t * tpm - off, False)
        n = n.normalized()
        return albedo * (ambient + (1.0 - ambient) * ti.max(0.0, n.dot(light)))

    @ti.kernel
    def _table_statics(self):
        """Per pixel, its module and where on it (`module_at`), and the deck's colour there: a frame's belts
        then only turn and scroll."""
        dt = ti.static(self.belt_texels_per_m)
        off = ti.static(self.table_texel_offset)
        for v, u in self.table_xy:
            p = self.table_xy[v, u]
            at = module_at(
                p[0], p[1], self.table_spec.pitch_m, self.table_spec.modules_x, self.table_spec.modules_y
            )
            self.table_module[v, u] = ti.cast(at[0], ti.i32)
            self.table_rxy[v, u] = ti.Vector([at[1], at[2]])
            self.deck_colour[v, u] = _bilinear(
                self.deck_tex, p[0] * dt - off, (p[1] % DECK_TILE_M) * dt - off, True
            )

    @ti.func
    def _table_colour(self, v: ti.i32, u: ti.i32, flat_shade: ti.f32) -> vec3f:
        half_belt = ti.static(self.table_spec.module_size_m / 2.0)
        colour = self.deck_colour[v, u]
        m = self.table_module[v, u]
        if m >= 0:
            r = self.table_rxy[v, u]
            hit = belt_on_module(m, r[0], r[1], self.direction, half_belt)
            if hit[3] > 0.0:
                bt = ti.static(self.belt_texels_per_m)
                off = ti.static(self.table_texel_offset)
                # The surface runs along +heading, so its pattern sits at (along - travel).
                along = ti.cast(hit[1], ti.f32) - self.travel[m]
                across = ti.cast(hit[2], ti.f32) + half_belt
                colour = _bilinear(self.belt_tex, along * bt - off, across * bt - off, True)
        return colour * flat_shade

    @ti.func
    def _arm_cover(self, u: ti.f32, v: ti.f32, n_arms: ti.i32) -> ti.f32:
        """Cylinder shading term of the nearest arm covering (u, v), or -1 where none does."""
        cover = -1.0
        for k in range(n_arms):
            r = self.arm_radius[k]
            if r > 0.0:
                seg = self.arm_seg[k]
                a, b = ti.Vector([seg[0], seg[1]]), ti.Vector([seg[2], seg[3]])
                p = ti.Vector([u, v])
                ab = b - a
                along = ti.math.clamp((p - a).dot(ab) / ti.max(ab.dot(ab), 1e-6), 0.0, 1.0)
                d = (p - a - along * ab).norm()
                if d < r:
                    cover = ti.max(cover, ti.sqrt(1.0 - (d / r) ** 2))
        return cover

    @ti.kernel
    def _shade(
        self,
        weight: ti.f32,
        n_arms: ti.i32,
        lx: ti.f32,
        ly: ti.f32,
        lz: ti.f32,
        ambient: ti.f32,
        flat_shade: ti.f32,
    ):
        light = vec3f(lx, ly, lz)
        arm_colour = vec3f(ARM_BGR[0], ARM_BGR[1], ARM_BGR[2])
        for v, u in self.accum:
            uf, vf = ti.cast(u, ti.f32), ti.cast(v, ti.f32)
            key = self.key[v, u]
            colour = vec3f(0.0, 0.0, 0.0)
            if key != ti.i64(_EMPTY_KEY):
                colour = self._cloth_colour(key, uf, vf, light, ambient)
            else:
                colour = self._table_colour(v, u, flat_shade)
            cover = self._arm_cover(uf, vf, n_arms)
            if cover >= 0.0:
                colour = arm_colour * (0.35 + 0.65 * cover)
            self.accum[v, u] += weight * colour

    @ti.kernel
    def _downsample(self):
        ss = ti.static(self.ss)
        for v, u in self.out:
            total = vec3f(0.0, 0.0, 0.0)
            for dv, du in ti.static(ti.ndrange(ss, ss)):
                total += self.accum[v * ss + dv, u * ss + du]
            self.out[v, u] = total / (ss * ss)

    @ti.kernel
    def _node_visibility(self, n_arms: ti.i32, n_cloths: ti.i32):
        H, W = ti.static(self.hi.height, self.hi.width)
        for slot, j, i in self.visible:
            p = self.vpx[slot, j, i]
            u, v = ti.cast(ti.round(p[0]), ti.i32), ti.cast(ti.round(p[1]), ti.i32)
            seen = 0
            in_grid = slot < n_cloths and j < self.slot_dims[slot, 1] and i < self.slot_dims[slot, 0]
            if in_grid and 0 <= u < W and 0 <= v < H and self._arm_cover(p[0], p[1], n_arms) < 0.0:
                seen = 1
                key = self.key[v, u]
                # An empty pixel means the node sits on the silhouette with nothing in front of it.
                if key != ti.i64(_EMPTY_KEY):
                    front_m = ti.cast(key >> _TRI_BITS, ti.f32) * 1e-6
                    if self.vdepth[slot, j, i] - front_m > _VISIBLE_DEPTH_TOL_M:
                        seen = 0
            self.visible[slot, j, i] = seen
