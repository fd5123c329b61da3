"""hwsim recordings of the shipped scenarios for the benchmarks, recorded into a cache once and reused, and
what a recording's camera did."""

from __future__ import annotations

from pathlib import Path

import yaml

from hwsim import scenario as scenarios
from hwsim.recording import record


def scenario_recording(cache: Path, scenario: str, duration_s: float | None = None, cameras: int = 1) -> Path:
    """The recording of a shipped scenario (recorded into `cache` the first time). cameras: 2 records it
    through the live cell's second camera too (hwsim/scenarios/cell.yaml) where it has only one."""
    name = scenario if duration_s is None else f"{scenario}-{duration_s:g}s"
    out = cache / (name if cameras == 1 else f"{name}-{cameras}cam")
    if not (out / "truth.npz").exists():
        print(f"recording {scenario} into {out} ...", flush=True)
        sc = scenarios.load(scenario, duration_s=duration_s)
        if len(sc.camera_specs) < cameras:
            further = scenarios.load("cell").camera_specs[len(sc.camera_specs) : cameras]
            sc = sc.model_copy(update={"cameras": [*sc.camera_specs, *further]})
        record(sc, out)
    return out


def recorded_exposure_s(recording: Path) -> float:
    """The exposure a recording's frames were smeared over (its scenario.yaml's noise.exposure_s), 0 when
    each frame was rendered at one instant (motion_blur_samples 1)."""
    noise = (yaml.safe_load((recording / "scenario.yaml").read_text()) or {}).get("noise", {})
    return float(noise.get("exposure_s", 0.0)) if int(noise.get("motion_blur_samples", 1)) > 1 else 0.0
