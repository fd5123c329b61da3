"""hwsim recordings of the shipped scenarios for the benchmarks, recorded into a cache once and reused, and
what a recording's camera did."""

from __future__ import annotations

from pathlib import Path

import yaml

from hwsim import scenario as scenarios
from hwsim.recording import record


def scenario_recording(
    cache: Path, scenario: str, duration_s: float | None = None, cameras: int = 1, skew_s: float | None = None
) -> Path:
    """The recording of a shipped scenario (recorded into `cache` the first time). cameras: 2 records it
    through the live cell's second camera too (hwsim/scenarios/cell.yaml) where it has only one. skew_s:
    every further camera captures this long after the first (None: as the scenario and the cell set it)."""
    name = scenario if duration_s is None else f"{scenario}-{duration_s:g}s"
    name = name if cameras == 1 else f"{name}-{cameras}cam"
    out = cache / (name if skew_s is None else f"{name}-skew{skew_s * 1e3:g}ms")
    if not (out / "truth.npz").exists():
        print(f"recording {scenario} into {out} ...", flush=True)
        record(with_cameras(scenarios.load(scenario, duration_s=duration_s), cameras, skew_s), out)
    return out


def with_cameras(sc: scenarios.Scenario, cameras: int, skew_s: float | None = None) -> scenarios.Scenario:
    """The scenario seen by at least `cameras` cameras: the live cell's further ones (hwsim/scenarios/
    cell.yaml) where it has fewer; skew_s: every further camera captures this long after the first (None:
    as set). Validated afresh, as its scenario.yaml will be read back."""
    specs = sc.camera_specs
    specs = [*specs, *scenarios.load("cell").camera_specs[len(specs) : cameras]]
    if skew_s is not None:
        specs = [specs[0], *(s.model_copy(update={"capture_skew_s": skew_s}) for s in specs[1:])]
    data = sc.model_dump(mode="json", exclude={"camera"})
    return scenarios.parse({**data, "cameras": [s.model_dump(mode="json") for s in specs]}, sc.name)


def recorded_exposure_s(recording: Path) -> float:
    """The exposure a recording's frames were smeared over (its scenario.yaml's noise.exposure_s), 0 when
    each frame was rendered at one instant (motion_blur_samples 1)."""
    noise = (yaml.safe_load((recording / "scenario.yaml").read_text()) or {}).get("noise", {})
    return float(noise.get("exposure_s", 0.0)) if int(noise.get("motion_blur_samples", 1)) > 1 else 0.0
