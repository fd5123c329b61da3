"""`hwsim stretch`: how much the truth cloth's solver stretches a sheet that should not stretch.

The belts turn the cloth rigidly about its centre (each module at the rigid velocity of its centre) while
it also translates. Real denim (tens of kN/m) stretches about 1e-5 under such friction loads, so whatever
the truth's grid edges show is the solver's: the figure to watch when choosing substeps and sweeps
(docs/hwsim.md, "Substeps")."""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from hwsim import scenario as scenarios
from hwsim.world import World

TURN_RAD_S = 0.5
DRIFT_M_S = 0.03
SKIP_FRAMES = 10  # the belts' acceleration ramp


@dataclass(frozen=True)
class Stretch:
    substep_s: float
    sweeps: int
    ms_per_frame: float  # median physics time per frame
    max_strain: float  # the largest truth edge strain over the frames
    p99_strain: float  # the median over the frames of each frame's 99th percentile


def stretch_under_turn(scenario: str, substep_s: float, sweeps: int, frames: int = 60) -> Stretch:
    sc = scenarios.load(scenario)
    cloth = sc.cloth.model_copy(update={"substep_s": substep_s, "stretch_iterations": sweeps})
    world = World(sc.model_copy(update={"cloth": cloth}), log_commands=False)
    table, grid = world.table, world.cloth.grid
    every = np.arange(table.n_modules)
    worst, p99, took_s = [], [], []
    for frame in range(frames):
        r = table.centres_m - world.cloth_centre_m()
        v = np.stack([DRIFT_M_S - TURN_RAD_S * r[:, 1], TURN_RAD_S * r[:, 0]], axis=1)
        table.command(every, np.linalg.norm(v, axis=1), np.arctan2(v[:, 1], v[:, 0]))
        t0 = time.perf_counter()
        world.step()
        took_s.append(time.perf_counter() - t0)
        if frame >= SKIP_FRAMES:
            strain = grid.edge_strains(world.cloth.positions_m())
            worst.append(strain.max())
            p99.append(np.percentile(strain, 99))
    return Stretch(
        substep_s,
        sweeps,
        float(np.median(took_s[SKIP_FRAMES:]) * 1e3),
        float(max(worst)),
        float(np.median(p99)),
    )


def format_stretch(rows: list[Stretch], scenario: str) -> str:
    lines = [
        f"hwsim stretch ({scenario}'s cloth, belts turning it at {TURN_RAD_S} rad/s and moving it "
        f"{DRIFT_M_S * 1e3:.0f} mm/s)",
        f"  {'substep':>9} {'sweeps':>6} {'ms/frame':>9} {'max strain':>11} {'p99 strain':>11}",
    ]
    for r in rows:
        lines.append(
            f"  {r.substep_s * 1e3:7.2f}ms {r.sweeps:6d} {r.ms_per_frame:9.1f} "
            f"{r.max_strain * 100:10.2f}% {r.p99_strain * 100:10.2f}%"
        )
    return "\n".join(lines)
