"""Procedural textures for the simulated camera: denim cloth, conveyor belts, the deck, mip pyramids.

Every texture is an (H, W, 3) float32 BGR array in [0, 1] laid out on material coordinates: texel (r, c) has
its centre at s = (c + 0.5) / texels_per_m (columns, x) and t = (r + 0.5) / texels_per_m (rows, y). All
randomness comes from ``np.random.default_rng(seed)``, so a seed always gives a bit-identical texture.

The renderer samples the mip level picked by :func:`mip_level_for` bilinearly, so detail finer than the render
Nyquist is removed by the pyramid; the structure the tracker needs therefore lives at the 2-6 mm scale.
"""

from __future__ import annotations

from pathlib import Path
from typing import Literal

import cv2
import numpy as np

TextureKind = Literal["denim", "plain_twill", "gingham"]

# Wale spacing across the wales. Real denim's ~1 mm wales blur away at ~1 px/mm; at 5 mm the twill stays
# visible without sitting near the camera's Nyquist limit, where a patch's correlation would collapse
# under a few degrees of rotation (hwsim verify on `rotate`: 3 mm gave a median NCC of 0.950, 5 mm 0.964).
TWILL_PERIOD_M = 5.0e-3
TWILL_ANGLE_DEG = 63.0  # wale direction from the weft (x) axis; right-hand twill rising to the right
WARP_BGR = (0.46, 0.30, 0.19)  # indigo warp
WEFT_BGR = (0.80, 0.83, 0.85)  # undyed ecru weft
LIGHT_BGR = (0.86, 0.84, 0.82)  # worn spots, light flecks and loose white threads
DARK_BGR = (0.24, 0.12, 0.06)  # dark flecks and stitch-like marks
# Gingham: a check of dyed and undyed bands in warp and weft, CHECK_PERIOD_M apart (half of each dyed),
# woven as the plain twill. At ~0.9 px/mm a period is ~5.4 px: a belt at 90 mm/s moves the cloth half a
# period a frame at 30 fps, where LK started from the last position is as near the next check as its own.
CHECK_PERIOD_M = 6.0e-3
CHECK_BGR = (0.22, 0.18, 0.62)  # red-dyed yarn
MIN_MIP_SIDE = 8  # mip_pyramid stops before a side would drop below this many texels


def _shape_px(size_m: tuple[float, float], texels_per_m: float) -> tuple[int, int]:
    """(H, W) in texels for a (width, height) in metres; rejects empty textures early."""
    if texels_per_m <= 0:
        raise ValueError(f"texels_per_m must be positive, got {texels_per_m}")
    w_px, h_px = round(size_m[0] * texels_per_m), round(size_m[1] * texels_per_m)
    if w_px < 1 or h_px < 1:
        raise ValueError(f"texture of {size_m} m at {texels_per_m} texels/m would be empty")
    return h_px, w_px


def _noise(
    rng: np.random.Generator,
    shape_px: tuple[int, int],
    sigmas_px: list[tuple[float, float]],
    periodic: bool = False,
) -> list[np.ndarray]:
    """Unit-std Gaussian-filtered white noise, one (H, W) float32 field per (sigma_x, sigma_y) in texels.

    periodic=True filters in the Fourier domain, so the fields wrap exactly (the belt must tile). Otherwise
    each field is drawn on a grid decimated to ~1.5 sigma per cell, blurred there and resized up: the same
    spectrum at a fraction of the cost, since the smooth fields dominate the build time.
    """
    h_px, w_px = shape_px
    fields: list[np.ndarray] = []
    if periodic:
        white = rng.standard_normal((len(sigmas_px), h_px, w_px), dtype=np.float32)
        fy2 = np.fft.fftfreq(h_px).astype(np.float32)[:, None] ** 2
        fx2 = np.fft.rfftfreq(w_px).astype(np.float32)[None, :] ** 2
        gains = np.stack(
            [np.exp(np.float32(-2.0 * np.pi**2) * (sx**2 * fx2 + sy**2 * fy2)) for sx, sy in sigmas_px]
        )
        fields = list(np.fft.irfft2(np.fft.rfft2(white) * gains, s=shape_px).astype(np.float32, copy=False))
    else:
        for sx, sy in sigmas_px:
            kx, ky = max(1, int(sx / 1.5)), max(1, int(sy / 1.5))
            white = rng.standard_normal((-(-h_px // ky) + 2, -(-w_px // kx) + 2), dtype=np.float32)
            low = cv2.GaussianBlur(
                white, (0, 0), sigmaX=sx / kx, sigmaY=sy / ky, borderType=cv2.BORDER_REFLECT
            )
            up = cv2.resize(low, (low.shape[1] * kx, low.shape[0] * ky), interpolation=cv2.INTER_CUBIC)
            fields.append(np.asarray(up[ky : ky + h_px, kx : kx + w_px], dtype=np.float32))
    return [(f - f.mean()) / (f.std() + np.float32(1e-12)) for f in fields]


def _blend(img: np.ndarray, weight: np.ndarray, bgr: tuple[float, float, float]) -> np.ndarray:
    """Blend towards a colour with a per-texel weight in [0, 1]."""
    w = np.clip(weight, 0.0, 1.0)[..., None]
    return img * (1.0 - w) + np.asarray(bgr, np.float32) * w


def _finish(img: np.ndarray) -> np.ndarray:
    return np.ascontiguousarray(np.clip(img, 0.0, 1.0), dtype=np.float32)


def _denim_marks(rng: np.random.Generator, shape_px: tuple[int, int], px_per_mm: float) -> np.ndarray:
    """Signed mark layer (>0 lighter, <0 darker): flecks, worn spots and short threads at several scales.

    These are what make every 15x15 px patch at ~1 px/mm unique; sizes are in mm so that they keep the same
    physical scale whatever the texel density.
    """
    h_px, w_px = shape_px
    area_mm2 = h_px * w_px / px_per_mm**2
    marks = np.zeros(shape_px, np.float32)
    # Flecks (nep/dirt specks): impulses blurred to ~0.6-1.2 mm, scaled so that the peak is ~amplitude.
    for sigma_mm, per_mm2 in ((0.5, 0.020), (1.0, 0.006)):
        n = rng.poisson(per_mm2 * area_mm2)
        sigma_px = max(sigma_mm * px_per_mm, 0.7)
        impulses = np.zeros(shape_px, np.float32)
        rows, cols = rng.integers(0, h_px, n), rng.integers(0, w_px, n)
        amps = rng.choice([-1.0, 1.0], n, p=[0.4, 0.6]) * rng.uniform(0.4, 0.9, n) * 2.0 * np.pi * sigma_px**2
        np.add.at(impulses, (rows, cols), amps.astype(np.float32))
        marks += cv2.GaussianBlur(impulses, (0, 0), sigma_px)
    # Worn spots: soft light ellipses of 2-7 mm.
    worn = np.zeros(shape_px, np.float32)
    for _ in range(rng.poisson(0.003 * area_mm2)):
        centre = (int(rng.integers(0, w_px)), int(rng.integers(0, h_px)))
        axes = (
            max(1, round(rng.uniform(1.0, 3.5) * px_per_mm)),
            max(1, round(rng.uniform(1.0, 2.5) * px_per_mm)),
        )
        cv2.ellipse(worn, centre, axes, float(rng.uniform(0, 180)), 0, 360, float(rng.uniform(0.2, 0.5)), -1)
    marks += cv2.GaussianBlur(worn, (0, 0), 0.8 * px_per_mm)
    # Short stitch-like or loose-thread marks, 3-12 mm, light or dark, slightly blurred.
    threads = np.zeros(shape_px, np.float32)
    for _ in range(rng.poisson(0.003 * area_mm2)):
        x0, y0 = rng.uniform(0, w_px), rng.uniform(0, h_px)
        length_px, angle = rng.uniform(3.0, 12.0) * px_per_mm, rng.uniform(0, np.pi)
        x1, y1 = x0 + length_px * np.cos(angle), y0 + length_px * np.sin(angle)
        value = float(rng.choice([-1.0, 1.0]) * rng.uniform(0.4, 0.8))
        thickness = max(1, round(rng.uniform(0.4, 0.8) * px_per_mm))
        cv2.line(threads, (round(x0), round(y0)), (round(x1), round(y1)), value, thickness, cv2.LINE_AA)
    marks += cv2.GaussianBlur(threads, (0, 0), max(0.25 * px_per_mm, 0.5))
    return marks


def _twill_phase(
    kind: TextureKind, rng: np.random.Generator, shape_px: tuple[int, int], texels_per_m: float
) -> tuple[np.ndarray, list[np.ndarray]]:
    """Phase across the wales (H, W), in twill periods, and denim's noise fields (none for the strictly
    periodic kinds, plain_twill and gingham).

    The first draws from rng are always these fields, so cloth_texture and weave_height get the same
    wales from the same seed."""
    px_per_mm = texels_per_m / 1000.0
    s_m = ((np.arange(shape_px[1], dtype=np.float32) + 0.5) / texels_per_m)[None, :]
    t_m = ((np.arange(shape_px[0], dtype=np.float32) + 0.5) / texels_per_m)[:, None]
    angle = np.deg2rad(TWILL_ANGLE_DEG)
    # Phase across the wales, in twill periods (the normal to the wale direction (cos a, -sin a)).
    phase = (s_m * np.sin(angle) + t_m * np.cos(angle)) / TWILL_PERIOD_M
    if kind != "denim":
        return phase, []
    # Noise fields (sigma in mm, x then y): wale waviness, slub streaks along the warp (narrow in x, long
    # in y), a finer slub component, 2-6 mm mottling that gives 2-D corners, and wash blotches.
    sig_mm = [(6.0, 6.0), (0.35, 6.0), (0.8, 2.5), (1.2, 1.2), (14.0, 14.0)]
    fields = _noise(rng, shape_px, [(a * px_per_mm, b * px_per_mm) for a, b in sig_mm])
    return phase + 0.12 * fields[0], fields


def weave_slopes(
    kind: TextureKind, seed: int, size_m: tuple[float, float], texels_per_m: float, relief_m: float
) -> np.ndarray:
    """(H, W, 2) float32: the slopes (dh/ds, dh/dt) of the weave's relief, texel for texel with
    cloth_texture(kind, seed, size_m, texels_per_m).

    The wales stand proud of the weft between them: height h = relief_m / 2 x cos(2 pi phase + pi), so
    that the weft band (phase 0, where cloth_texture shows the weft) is the groove and relief_m the
    peak-to-peak depth. Under light from straight above a slope hardly changes the shading; under low
    side light one flank of each wale is lit and the other shaded, and how strongly depends on how the
    wales lie to the light, so a patch's look changes as the cloth turns."""
    shape_px = _shape_px(size_m, texels_per_m)
    phase, _ = _twill_phase(kind, np.random.default_rng(seed), shape_px, texels_per_m)
    height = (0.5 * relief_m) * np.cos(2.0 * np.pi * phase + np.pi)
    # np.gradient along columns (s) and rows (t), in metres per metre.
    dh_dt, dh_ds = np.gradient(height.astype(np.float64), 1.0 / texels_per_m)
    return np.ascontiguousarray(np.stack([dh_ds, dh_dt], axis=-1), dtype=np.float32)


def cloth_texture(
    kind: TextureKind, seed: int, size_m: tuple[float, float], texels_per_m: float
) -> np.ndarray:
    """(H, W, 3) float32 BGR in [0, 1]. size_m = (width along s / x, height along t / y).

    W = round(size_m[0]*texels_per_m), H = round(size_m[1]*texels_per_m). Texel (r, c) has its centre at
    material coordinates s = (c + 0.5)/texels_per_m, t = (r + 0.5)/texels_per_m. "denim" is an indigo 3/1
    twill with slubs, fading and non-repeating marks; "plain_twill" is the bare, strictly periodic twill;
    "gingham" is a strictly periodic red and white check, corners everywhere and every one like the next
    (its relief, if any, is the twill's wales).
    """
    if kind not in ("denim", "plain_twill", "gingham"):
        raise ValueError(f"unknown cloth texture kind {kind!r}")
    shape_px = _shape_px(size_m, texels_per_m)
    px_per_mm = texels_per_m / 1000.0
    rng = np.random.default_rng(seed)
    denim = kind == "denim"
    phase, fields = _twill_phase(kind, rng, shape_px, texels_per_m)
    if denim:
        _, slub, slub2, mottle, blotch = fields
    # 3/1 twill: the weft shows on one band per period; a raised cosine keeps the profile band-limited.
    weft_w = 0.55 * ((1.0 + np.cos(2.0 * np.pi * phase)) / 2.0) ** 3
    warp: np.ndarray = np.broadcast_to(np.asarray(WARP_BGR, np.float32), (*shape_px, 3))
    if denim:
        # Slub yarns: per-thread brightness along the warp, heavy-tailed so that some threads stand out.
        slub_gain = 1.0 + 0.22 * np.tanh(0.8 * (slub + 0.6 * slub2)) + 0.10 * mottle
        warp = warp * slub_gain[..., None]
    if kind == "gingham":
        return _finish(_gingham(shape_px, texels_per_m))
    img = _blend(warp, weft_w, WEFT_BGR)
    if not denim:
        return _finish(img)
    img = _blend(img, 0.22 * np.clip(blotch + 0.3, 0.0, None), LIGHT_BGR)  # faded / washed areas
    img = img * (1.0 + 0.10 * mottle - 0.06 * np.clip(-blotch, 0.0, None))[..., None]
    marks = _denim_marks(rng, shape_px, px_per_mm)
    img = _blend(img, marks, LIGHT_BGR)
    img = _blend(img, -marks, DARK_BGR)
    return _finish(img)


def _gingham(shape_px: tuple[int, int], texels_per_m: float) -> np.ndarray:
    """The check: where warp and weft are both dyed the cloth is the dye, where one is, half of it, where
    neither, undyed. The bands' edges are smoothed over ~0.4 mm (band-limited, as a camera sees yarns).
    Nothing else: strictly periodic."""
    s_m = (np.arange(shape_px[1], dtype=np.float32) + 0.5) / texels_per_m
    t_m = (np.arange(shape_px[0], dtype=np.float32) + 0.5) / texels_per_m
    sharpness = CHECK_PERIOD_M / 0.4e-3

    def dyed(x_m: np.ndarray) -> np.ndarray:
        return np.asarray(0.5 + 0.5 * np.tanh(sharpness * np.sin(2.0 * np.pi * x_m / CHECK_PERIOD_M) / np.pi))

    cover = 0.5 * (dyed(s_m)[None, :] + dyed(t_m)[:, None])  # 0, 1/2 or 1 dyed yarns in each direction
    undyed = np.broadcast_to(np.asarray(WEFT_BGR, np.float32), (*shape_px, 3))
    return np.asarray(_blend(undyed, cover, CHECK_BGR), np.float32)


def image_texture(path: str | Path, size_m: tuple[float, float], texels_per_m: float) -> np.ndarray:
    """Loads any image file (cv2.imread) and resamples it to the cloth_texture shape and convention.

    The image is stretched to (W, H); cv2.INTER_AREA when shrinking (no aliasing), bilinear when enlarging.
    Raises ValueError naming the path if it cannot be read.
    """
    h_px, w_px = _shape_px(size_m, texels_per_m)
    raw = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if raw is None:
        raise ValueError(f"cannot read texture image {str(path)!r} (missing file or unsupported format)")
    shrink = w_px <= raw.shape[1] and h_px <= raw.shape[0]
    resized = cv2.resize(raw, (w_px, h_px), interpolation=cv2.INTER_AREA if shrink else cv2.INTER_LINEAR)
    return _finish(resized.astype(np.float32) / 255.0)


def belt_texture(seed: int, length_m: float, width_m: float, texels_per_m: float) -> np.ndarray:
    """(H, W, 3) float32 BGR grey rubber conveyor belt, periodic along the columns (direction of travel).

    Columns run along length_m, rows across width_m. Transverse ribs (a whole number per length) and periodic
    noise make the belt tile seamlessly when scrolled with np.mod, and make a moving belt a visible
    distractor for optical flow.
    """
    h_px, w_px = _shape_px((length_m, width_m), texels_per_m)
    px_per_mm = texels_per_m / 1000.0
    rng = np.random.default_rng(seed)
    n_ribs = max(1, round(length_m / 8.0e-3))  # ~8 mm rib pitch, rounded so that the length holds whole ribs
    rib_phase = 2.0 * np.pi * n_ribs * (np.arange(w_px, dtype=np.float32) + 0.5) / w_px
    groove = ((1.0 + np.cos(rib_phase)) / 2.0) ** 8  # narrow dark groove
    edge = np.sin(rib_phase) * ((1.0 + np.cos(rib_phase)) / 2.0) ** 4  # lit flank on one side of it
    sig_mm = [(0.6, 0.6), (2.0, 2.0), (25.0, 10.0)]  # fine grit, mottling, lengthwise wear
    fine, grain, wear = _noise(
        rng, (h_px, w_px), [(a * px_per_mm, b * px_per_mm) for a, b in sig_mm], periodic=True
    )
    grey = 0.30 - 0.14 * groove[None, :] + 0.05 * edge[None, :] + 0.025 * fine + 0.035 * grain + 0.03 * wear
    tint = np.asarray([1.02, 1.0, 0.97], np.float32)  # rubber is very slightly cool
    return _finish(grey[..., None] * tint)


def deck_texture(seed: int, size_m: tuple[float, float], texels_per_m: float) -> np.ndarray:
    """(H, W, 3) float32 BGR: the static table frame between modules: dark grey, mild noise, a few scuffs."""
    h_px, w_px = _shape_px(size_m, texels_per_m)
    px_per_mm = texels_per_m / 1000.0
    rng = np.random.default_rng(seed)
    fine, coarse = _noise(rng, (h_px, w_px), [(0.8 * px_per_mm,) * 2, (20.0 * px_per_mm,) * 2])
    grey = 0.18 + 0.015 * fine + 0.02 * coarse
    scuffs = np.zeros((h_px, w_px), np.float32)
    area_m2 = size_m[0] * size_m[1]
    for _ in range(rng.poisson(60.0 * area_m2) + 2):  # a few per frame piece, ~60 per square metre
        x0, y0 = rng.uniform(0, w_px), rng.uniform(0, h_px)
        length_px, angle = rng.uniform(10.0, 60.0) * px_per_mm, rng.uniform(0, np.pi)
        end = (round(x0 + length_px * np.cos(angle)), round(y0 + length_px * np.sin(angle)))
        thickness = max(1, round(rng.uniform(0.5, 2.0) * px_per_mm))
        cv2.line(scuffs, (round(x0), round(y0)), end, float(rng.uniform(0.06, 0.14)), thickness, cv2.LINE_AA)
    grey = grey + cv2.GaussianBlur(scuffs, (0, 0), max(0.5 * px_per_mm, 0.5))
    return _finish(np.repeat(grey[..., None], 3, axis=2))


def mip_pyramid(texture: np.ndarray, levels: int) -> list[np.ndarray]:
    """[level0 = texture, level1 = half size, ...]: at most `levels` arrays in all (level 0 included).

    Each level is cv2.pyrDown of the previous one (Gaussian low-pass before decimation); building stops early
    when a side of the next level would fall below MIN_MIP_SIDE texels.
    """
    if levels < 1:
        raise ValueError(f"levels must be >= 1, got {levels}")
    pyramid = [texture]
    while len(pyramid) < levels:
        h_px, w_px = pyramid[-1].shape[:2]
        if min((h_px + 1) // 2, (w_px + 1) // 2) < MIN_MIP_SIDE:
            break
        pyramid.append(cv2.pyrDown(pyramid[-1]))
    return pyramid


def mip_level_for(texels_per_m: float, render_px_per_m: float) -> int:
    """The pyramid level whose texel density is the smallest one still >= render_px_per_m (never negative).

    Level L has texels_per_m / 2**L; the renderer samples it bilinearly, so the texture is never undersampled.
    A relative tolerance of 1e-9 absorbs float noise in a density computed by the caller.
    """
    if texels_per_m <= 0 or render_px_per_m <= 0:
        raise ValueError(f"densities must be positive, got {texels_per_m} and {render_px_per_m}")
    level = 0
    while texels_per_m / 2.0 ** (level + 1) >= render_px_per_m * (1.0 - 1e-9):
        level += 1
    return level
