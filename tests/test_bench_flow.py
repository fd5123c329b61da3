"""`clothd bench flow`: its JSON interface from a short lockstep run judged by hwsim's outfeed, and the
plot of success against rate."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import pytest

from clothd.cli import main
from clothd.tools.bench_flow import plot_rates

pytestmark = pytest.mark.clock_free

INTERFACE_KEYS = (
    "pieces_in",
    "pieces_out",
    "success_pct",
    "rejects",
    "throughput_per_min",
    "multi_piece_time_pct",
    "missed_tick_pct",
)


def test_a_short_flow_writes_the_interface_keys_and_every_piece_judged(tmp_path: Path) -> None:
    out = tmp_path / "flow.json"
    # 12 s: piece 0, lying flat at the start, is placed and leaves; the infeed lays piece 1 at 10 s.
    argv = ["bench", "flow", "--minutes", "0.2", "--rate", "6", "--seed", "0", "--cameras", "1"]
    assert main([*argv, "--json", str(out)]) == 0
    result = json.loads(out.read_text())
    assert all(key in result for key in INTERFACE_KEYS)
    assert result["pieces_in"] == 2 and result["pieces_out"] == len(result["pieces"]) >= 1
    first = result["pieces"][0]
    assert first["id"] == 0 and first["ok"] and first["max_height_mm"] <= 1.0
    assert first["pose_error_mm"] <= 5.0 and first["pose_error_deg"] <= 1.0
    assert result["success_pct"] == 100.0 and result["rejects"] == 0
    assert result["throughput_per_min"] == result["pieces_out"] / 0.2
    assert result["laid_per_min"] == 1 / 0.2 and result["waiting_at_end"] == 0  # piece 1, laid at 10 s


def test_the_plot_draws_success_against_rate(tmp_path: Path) -> None:
    def run(rate: float, success: float) -> dict[str, float]:
        laid = min(rate, 6.0)
        return {
            "rate_per_min": rate,
            "success_pct": success,
            "throughput_per_min": laid * success / 100,
            "laid_per_min": laid,
        }

    result = {"minutes": 5.0, "seed": 0, "cameras": 2, "rates": [run(6, 100.0), run(9, 97.0), run(12, 80.0)]}
    path = tmp_path / "rates.png"
    plot_rates(result, path)
    image = cv2.imread(str(path))
    assert image is not None and image.shape[1] > 500 and image.std() > 10
