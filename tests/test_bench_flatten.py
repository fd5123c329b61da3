"""`clothd bench flatten --lockstep`: its JSON interface from one short start, the two controllers run in
processes of their own on the same seeded start."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from clothd.tools.bench_flatten import run_bench, write_json

pytestmark = pytest.mark.clock_free


def test_one_lockstep_start_writes_both_controllers_and_the_realtime_factor(tmp_path: Path) -> None:
    result = run_bench(starts=1, seed=0, flatten_s=3.0, move_s=2.0, lockstep=True, cameras=1)
    out = tmp_path / "flatten.json"
    write_json(result, out)
    written = json.loads(out.read_text())
    assert written["realtime_factor"] > 0
    flatten, rigid = written["flatten"], written["rigid"]
    assert flatten["summary"]["starts"] == rigid["summary"]["starts"] == 1
    # The same draws, judged the same way: the wrinkles each controller was given are one and the same.
    assert [r["start_height_mm"] for r in flatten["runs"] if r["wrinkled"]] == pytest.approx(
        [r["start_height_mm"] for r in rigid["runs"] if r["wrinkled"]]
    )
    assert flatten["summary"]["success_pct"] == 100.0  # the flatness controller takes it out within 3 s
    assert rigid["summary"]["success_pct"] == 0.0  # holding the pose leaves it in
