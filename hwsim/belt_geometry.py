"""Where the belts are: the one definition of the module footprint, shared by physics and renderer.

Module (col, row) sits at ((col - (mx-1)/2)·pitch, (row - (my-1)/2)·pitch). Its belt is a square of side
2·half_belt, turned to the module's heading, clipped by the turntable of diameter `pitch`. Outside every
belt is the static deck.
"""

import taichi as ti

belt_hit = ti.types.vector(4, ti.f64)


@ti.func
def _on_table(x: ti.f64, y: ti.f64, pitch: ti.f64, mx: ti.template(), my: ti.template()) -> belt_hit:
    """(module id, x and y from its centre, on its turntable) at world point (x, y): the module whose cell
    holds the point; (-1, 0, 0, 0) off the table."""
    col = ti.round(x / pitch + (mx - 1) / 2.0, ti.i32)
    row = ti.round(y / pitch + (my - 1) / 2.0, ti.i32)
    out = belt_hit(-1.0, 0.0, 0.0, 0.0)
    if 0 <= col < mx and 0 <= row < my:
        rx = x - (col - (mx - 1) / 2.0) * pitch
        ry = y - (row - (my - 1) / 2.0) * pitch
        turntable = rx * rx + ry * ry <= pitch * pitch / 4.0
        out = belt_hit(ti.cast(row * mx + col, ti.f64), rx, ry, ti.select(turntable, 1.0, 0.0))
    return out


@ti.func
def belt_at(
    x: ti.f64,
    y: ti.f64,
    direction: ti.template(),
    pitch: ti.f64,
    half_belt: ti.f64,
    mx: ti.template(),
    my: ti.template(),
) -> belt_hit:
    """(module id, along-belt coordinate, across-belt coordinate, on_belt) at world point (x, y), metres.
    `direction` holds each module's (cos, sin) of heading. The module id is -1 and on_belt 0 outside the
    table; on_belt is 0 over the deck between belts."""
    cell = _on_table(x, y, pitch, mx, my)
    hit = belt_hit(-1.0, 0.0, 0.0, 0.0)
    if cell[0] >= 0.0:
        hit = belt_on_module(ti.cast(cell[0], ti.i32), cell[1], cell[2], direction, half_belt)
        hit[3] = ti.select(cell[3] > 0.0, hit[3], 0.0)
    return hit


@ti.func
def module_at(x: ti.f64, y: ti.f64, pitch: ti.f64, mx: ti.template(), my: ti.template()) -> belt_hit:
    """What of `belt_at` no heading changes, for a renderer to keep per pixel: (module id, x and y from the
    module's centre, 1.0) at world point (x, y); (-1, 0, 0, 0) off the table and off the module's
    turntable, where no heading puts its belt."""
    cell = _on_table(x, y, pitch, mx, my)
    out = belt_hit(-1.0, 0.0, 0.0, 0.0)
    if cell[3] > 0.0:
        out = cell
    return out


@ti.func
def belt_on_module(
    m: ti.i32, rx: ti.f64, ry: ti.f64, direction: ti.template(), half_belt: ti.f64
) -> belt_hit:
    """The belt of module m at a point (rx, ry) from its centre, on its turntable: (module id, along,
    across, on_belt)."""
    ch, sh = direction[m][0], direction[m][1]
    along = ch * rx + sh * ry
    across = -sh * rx + ch * ry
    inside = ti.abs(along) <= half_belt and ti.abs(across) <= half_belt
    return belt_hit(ti.cast(m, ti.f64), along, across, ti.select(inside, 1.0, 0.0))
