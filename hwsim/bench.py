"""`hwsim bench`: how fast the simulated cell runs on this machine.

- physics: ms per 1/fps frame of the ground-truth cloth (one serial kernel: one core by construction),
  and the real-time factor (frame period / median step time);
- render: ms per frame at the scenario's resolution and supersampling;
- record: wall time to record a 10 s scenario end to end (physics, render, noise, PNG writing).
"""

from __future__ import annotations

import tempfile
import time
from pathlib import Path

import numpy as np

from hwsim import scenario as scenarios
from hwsim.camera import Camera
from hwsim.recording import record, render_frame
from hwsim.renderer_spares import make_renderer
from hwsim.world import World


def _stats_ms(samples_s: list[float]) -> dict[str, float]:
    a = np.asarray(samples_s) * 1e3
    return {"p50_ms": float(np.median(a)), "p99_ms": float(np.percentile(a, 99)), "max_ms": float(a.max())}


def run_bench(scenario_name: str = "compress", frames: int = 90, record_s: float = 10.0) -> dict[str, object]:
    sc = scenarios.load(scenario_name)
    world = World(sc)
    renderer = make_renderer(sc, Camera.from_spec(sc.camera), world.cloth.grid, world)
    world.step()  # compile the physics kernel outside the timing
    render_frame(world, renderer)
    physics, render = [], []
    for _ in range(frames):
        t0 = time.perf_counter()
        world.step()
        t1 = time.perf_counter()
        render_frame(world, renderer)
        render.append(time.perf_counter() - t1)
        physics.append(t1 - t0)
    phys = _stats_ms(physics)
    with tempfile.TemporaryDirectory() as tmp:
        rec_sc = scenarios.load("translate", duration_s=record_s)
        stats = record(rec_sc, Path(tmp))
    grid = world.cloth.grid
    return {
        "scenario": scenario_name,
        "nodes": f"{grid.nx}x{grid.ny}",
        "substeps_per_frame": round(1.0 / sc.fps / sc.cloth.substep_s),
        "physics": phys,
        "realtime_factor": (1.0 / sc.fps) / (phys["p50_ms"] / 1e3),
        "render": _stats_ms(render),
        "record": {
            "scenario": "translate",
            "duration_s": record_s,
            "frames": stats.frames,
            "wall_s": stats.wall_s,
        },
    }


def format_bench(result: dict[str, object]) -> str:
    phys = result["physics"]
    rend = result["render"]
    rec = result["record"]
    assert isinstance(phys, dict) and isinstance(rend, dict) and isinstance(rec, dict)
    return "\n".join(
        [
            f"hwsim bench ({result['scenario']}, truth mesh {result['nodes']}, "
            f"{result['substeps_per_frame']} substeps/frame)",
            f"  physics per frame  p50 {phys['p50_ms']:6.1f} ms  p99 {phys['p99_ms']:6.1f} ms  "
            f"-> {result['realtime_factor']:.2f}x real time on one core",
            f"  render per frame   p50 {rend['p50_ms']:6.1f} ms  p99 {rend['p99_ms']:6.1f} ms",
            f"  record {rec['duration_s']:.0f} s of {rec['scenario']} ({rec['frames']} frames): "
            f"{rec['wall_s']:.1f} s wall",
        ]
    )
