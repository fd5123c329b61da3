"""Where the belts are: the one definition of the module footprint, shared by physics and renderer.

Module (col, row) sits at ((col - (mx-1)/2)·pitch, (row - (my-1)/2)·pitch). Its belt is a square of side
2·half_belt, turned to the module's heading, clipped by the turntable of diameter `pitch`. Outside every
belt is the static deck.
"""

import taichi as ti

belt_hit = ti.types.vector(4, ti.f64)


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
    col = ti.round(x / pitch + (mx - 1) / 2.0, ti.i32)
    row = ti.round(y / pitch + (my - 1) / 2.0, ti.i32)
    hit = belt_hit(-1.0, 0.0, 0.0, 0.0)
    if 0 <= col < mx and 0 <= row < my:
        m = row * mx + col
        rx = x - (col - (mx - 1) / 2.0) * pitch
        ry = y - (row - (my - 1) / 2.0) * pitch
        ch, sh = direction[m][0], direction[m][1]
        along = ch * rx + sh * ry
        across = -sh * rx + ch * ry
        inside = (
            ti.abs(along) <= half_belt
            and ti.abs(across) <= half_belt
            and rx * rx + ry * ry <= pitch * pitch / 4.0
        )
        hit = belt_hit(ti.cast(m, ti.f64), along, across, ti.select(inside, 1.0, 0.0))
    return hit


@ti.func
def module_at(x: ti.f64, y: ti.f64, pitch: ti.f64, mx: ti.template(), my: ti.template()) -> belt_hit:
    """What of `belt_at` no heading changes, for a renderer to keep per pixel: (module id, x and y from the
    module's centre, 1.0) at world point (x, y); (-1, 0, 0, 0) off the table and off the module's
    turntable, where no heading puts its belt."""
    col = ti.round(x / pitch + (mx - 1) / 2.0, ti.i32)
    row = ti.round(y / pitch + (my - 1) / 2.0, ti.i32)
    out = belt_hit(-1.0, 0.0, 0.0, 0.0)
    if 0 <= col < mx and 0 <= row < my:
        rx = x - (col - (mx - 1) / 2.0) * pitch
        ry = y - (row - (my - 1) / 2.0) * pitch
        if rx * rx + ry * ry <= pitch * pitch / 4.0:
            out = belt_hit(ti.cast(row * mx + col, ti.f64), rx, ry, 1.0)
    return out


@ti.func
def belt_on_module(
    m: ti.i32, rx: ti.f64, ry: ti.f64, direction: ti.template(), half_belt: ti.f64
) -> belt_hit:
    """`belt_at` at a point (rx, ry) of module m's turntable (`module_at`): the same (module id, along,
    across, on_belt), bit for bit."""
    ch, sh = direction[m][0], direction[m][1]
    along = ch * rx + sh * ry
    across = -sh * rx + ch * ry
    inside = ti.abs(along) <= half_belt and ti.abs(across) <= half_belt
    return belt_hit(ti.cast(m, ti.f64), along, across, ti.select(inside, 1.0, 0.0))
