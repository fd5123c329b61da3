"""The closed loop in lockstep (clothd/tools/lockstep.py): hwsim's cell and clothd's tracker and cell
controller in one process, tick by tick, judged by hwsim's truth, with no clock and no machine load in
the result."""

from __future__ import annotations

import numpy as np
import pytest
import yaml

from clothd.config import load_config
from clothd.tools.bench_flatten import FLAT_AREA_RATIO, FLAT_HEIGHT_M, PUSH_REACH_M, PUSH_S
from clothd.tools.lockstep import LockstepCell, scenario_cameras
from clothd.tools.recordings import with_cameras
from hwsim import scenario as scenarios
from hwsim.world import World

pytestmark = pytest.mark.clock_free

PUSH = {
    "at_m": [0.01, 0.0],
    "direction_rad": 1.2,
    "slack_m": 0.008,
    "duration_s": PUSH_S,
    "reach_m": PUSH_REACH_M,
}


@pytest.fixture(scope="module")
def cell() -> LockstepCell:
    return LockstepCell(load_config(None))


def test_flatten_takes_out_a_ridge_pushed_in_after_tracking_began(cell: LockstepCell) -> None:
    cell.lay([0.0, 0.0, 0.3])
    cell.push(PUSH, then_s=2.0)
    assert cell.truth()["max_height_m"] > 0.003  # the hands left a ridge
    cell.setpoint_request({"mode": "flatten"})
    started_s = cell.now()

    def flat() -> bool:
        t = cell.truth()
        return bool(t["max_height_m"] <= FLAT_HEIGHT_M and t["area_ratio"] >= FLAT_AREA_RATIO)

    while not flat() and cell.now() - started_s < 10.0:
        cell.sleep(0.1)
    assert flat(), cell.truth()
    assert cell.status()["state"] == "tracking" and cell.status()["halt_reason"] is None


def test_a_move_ends_where_the_truth_says_and_a_restarted_cell_gives_the_same_numbers() -> None:
    """The same requests on a cell, then on the same cell restarted after them: the same estimate and
    truth, bit for bit (no clock, no threads' timing, nothing carried over from the first run)."""
    twin = LockstepCell(load_config(None))
    runs = []
    for restarted in (False, True):
        if restarted:
            twin.restart()
        twin.lay([0.0, 0.0, 0.0])
        twin.setpoint_request({"mode": "move", "x_m": 0.03, "y_m": -0.02, "theta_rad": 0.1})
        twin.sleep(3.0)
        status, truth = twin.status(), twin.truth()
        runs.append(([status["pose"][k] for k in ("x_m", "y_m", "theta_rad")], truth["pose"], twin.now()))
        pose = truth["pose"]
        assert np.hypot(pose[0] - 0.03, pose[1] + 0.02) < 0.005 and abs(pose[2] - 0.1) < np.radians(1.0)
    assert runs[0] == runs[1]
    assert twin.simulated_s == pytest.approx(2 * runs[0][2])


def test_a_folded_corner_is_reported_as_a_flap_and_not_pulled(cell: LockstepCell) -> None:
    cell.lay([0.0, 0.0, 0.0], flaps=[{"corner": "+s+t", "size_m": 0.06}])
    folded = cell.truth()["folded_ratio"]
    assert folded > 0.02
    # The flatness is null until the first estimate after the reset has been read.
    cell.wait(lambda: bool((cell.status()["flatness"] or {}).get("flaps")), 10, "the flap reported")
    seen = cell.status()["flatness"]
    assert len(seen["flaps"]) == 1 and not seen["flat"]
    # The cloth lies square at the origin: its +s+t corner is the +x +y one, 60 mm legs.
    assert seen["flaps"][0]["kind"] == "flap"
    assert 0.07 < seen["flaps"][0]["x_m"] < 0.125 and 0.05 < seen["flaps"][0]["y_m"] < 0.10
    cell.setpoint_request({"mode": "flatten"})
    fastest_m_s = 0.0
    for _ in range(30):  # 3 s
        cell.sleep(0.1)
        fastest_m_s = max(fastest_m_s, float(np.abs(cell.truth()["module_speed_m_s"]).max()))
    assert fastest_m_s < 0.005  # only the pose hold's trims: nothing pulls
    assert cell.truth()["folded_ratio"] >= 0.95 * folded
    assert cell.status()["flatness"]["flaps"]


def test_a_skew_given_delays_every_further_camera_and_never_the_first() -> None:
    sc = scenarios.load("cell")
    world = World(sc, log_commands=False)
    as_set = [c.capture_skew_s for c in sc.camera_specs]
    assert [s.skew_s for s in scenario_cameras(sc, world, None)[0]] == as_set
    sensors, models = scenario_cameras(sc, world, None, 0.01)
    assert len(sensors) == len(models) == 2 and [s.skew_s for s in sensors] == [0.0, 0.01]


def test_a_recording_takes_the_cells_second_camera_skewed_and_its_scenario_reads_back() -> None:
    seen = with_cameras(scenarios.load("translate"), 2, 0.01)
    assert [s.capture_skew_s for s in seen.camera_specs] == [0.0, 0.01]
    assert seen.camera_specs[1] == scenarios.load("cell").camera_specs[1].model_copy(
        update={"capture_skew_s": 0.01}
    )
    again = scenarios.parse(yaml.safe_load(yaml.safe_dump(seen.model_dump(mode="json"))))
    assert again.camera_specs == seen.camera_specs
    assert (
        with_cameras(scenarios.load("translate"), 1).camera_specs == scenarios.load("translate").camera_specs
    )
