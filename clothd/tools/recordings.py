"""hwsim recordings of the shipped scenarios for the benchmarks, recorded into a cache once and reused."""

from __future__ import annotations

from pathlib import Path

from hwsim import scenario as scenarios
from hwsim.recording import record


def scenario_recording(cache: Path, scenario: str, duration_s: float | None = None) -> Path:
    out = cache / (scenario if duration_s is None else f"{scenario}-{duration_s:g}s")
    if not (out / "truth.npz").exists():
        print(f"recording {scenario} into {out} ...", flush=True)
        record(scenarios.load(scenario, duration_s=duration_s), out)
    return out
