"""The renderer keeps per pixel what of `belt_at` no heading changes (`module_at`) and turns the belts each
frame (`belt_on_module`): the two together must answer as `belt_at` does, bit for bit, or frames change."""

from __future__ import annotations

import numpy as np
import pytest
import taichi as ti

from hwsim.belt_geometry import belt_at, belt_hit, belt_on_module, module_at
from hwsim.taichi_runtime import ensure_taichi

pytestmark = pytest.mark.clock_free

MX, MY, PITCH, HALF_BELT = 5, 4, 0.1, 0.035


def test_split_answers_as_belt_at() -> None:
    ensure_taichi("cpu")
    rng = np.random.default_rng(0)
    n = 200_000  # over the table and past its edges, every heading
    xy = ti.Vector.field(2, ti.f32, shape=n)
    xy.from_numpy(rng.uniform([-0.3, -0.25], [0.3, 0.25], (n, 2)).astype(np.float32))
    direction = ti.Vector.field(2, ti.f64, shape=MX * MY)
    heading = rng.uniform(-np.pi, np.pi, MX * MY)
    direction.from_numpy(np.stack([np.cos(heading), np.sin(heading)], axis=1))
    whole, split = (ti.Vector.field(4, ti.f64, shape=n) for _ in range(2))

    @ti.kernel
    def answer():
        for k in xy:
            p = xy[k]
            whole[k] = belt_at(p[0], p[1], direction, PITCH, HALF_BELT, MX, MY)
            at = module_at(p[0], p[1], PITCH, MX, MY)
            split[k] = belt_hit(-1.0, 0.0, 0.0, 0.0)
            if at[0] >= 0.0:
                split[k] = belt_on_module(ti.cast(at[0], ti.i32), at[1], at[2], direction, HALF_BELT)

    answer()
    a, b = whole.to_numpy(), split.to_numpy()
    on = a[:, 3] > 0
    assert 0.2 * n < on.sum() < 0.8 * n  # belts and deck both sampled
    np.testing.assert_array_equal(b[:, 3] > 0, on)
    np.testing.assert_array_equal(b[on], a[on])  # module, along, across: what a frame samples
