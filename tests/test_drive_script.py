"""Drive scripts: the schema's bounds, compiling for a cell, the commands over time, the cloth's reach."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from pydantic import ValidationError

from clothd.config import load_config
from clothd.core.conveyor import ConveyorLayout
from clothd.core.drive_script import DrivePlan, DriveScript, cloth_reach_m, swept_box_m
from clothd.core.workspace import Workspace
from clothd.errors import InputError, InvalidRequestError
from clothd.tools.drive import RECORD_TAIL_S, drive, load_script
from hwsim import scenario as scenarios

pytestmark = pytest.mark.clock_free

LAYOUT = ConveyorLayout(8, 6, 0.075, 0.065)


def _script(**kw: object) -> DriveScript:
    body: dict[str, object] = {
        "duration_s": 2.0,
        "timeline": [
            {"t_s": 0.0, "modules": {"region_m": [-1, -1, 0, 1]}, "speed_m_s": 0.03, "heading_rad": 1.5},
            {"t_s": 1.0, "modules": {"ids": [0]}, "speed_m_s": 0.05, "heading_rad": -1.5},
        ],
    }
    return DriveScript.model_validate({**body, **kw})


def test_commands_hold_until_changed_and_stop_at_the_end() -> None:
    plan = DrivePlan.compile(_script(), LAYOUT, 0.2)
    left = LAYOUT.centres_m[:, 0] < 0
    at_half = plan.commands_at(0.5)
    assert np.all(at_half.speed_m_s[left] == 0.03) and np.all(at_half.speed_m_s[~left] == 0)
    assert np.all(at_half.heading_rad[left] == 1.5)
    at_one = plan.commands_at(1.2)
    assert at_one.speed_m_s[0] == 0.05 and at_one.heading_rad[0] == -1.5 and at_one.speed_m_s[1] == 0.03
    after = plan.commands_at(2.0)
    assert np.all(after.speed_m_s == 0) and after.heading_rad[0] == -1.5  # stopped where it was turned
    assert np.all(plan.commands_at(-0.1).speed_m_s == 0)


@pytest.mark.parametrize(
    ("change", "words"),
    [
        ({"duration_s": 301}, "duration_s"),
        ({"timeline": []}, "timeline"),
        (
            {
                "timeline": [
                    {"t_s": 0, "modules": {"all": True, "ids": [1]}, "speed_m_s": 0.1, "heading_rad": 0}
                ]
            },
            "ids",
        ),
        ({"timeline": [{"t_s": 0, "modules": {"all": True}, "speed_m_s": 0.1, "heading": 0}]}, "heading"),
        ({"speed": 1}, "speed"),
    ],
)
def test_the_schema_refuses_with_the_key(change: dict[str, object], words: str) -> None:
    with pytest.raises(ValidationError, match=words):
        _script(**change)


def test_compiling_refuses_what_the_cell_cannot_do() -> None:
    fast = {"timeline": [{"t_s": 0, "modules": {"all": True}, "speed_m_s": 0.3, "heading_rad": 0}]}
    with pytest.raises(InvalidRequestError, match=r"timeline\[0\]: speed_m_s 0.3 exceeds the modules' 0.2"):
        DrivePlan.compile(_script(**fast), LAYOUT, 0.2)
    with pytest.raises(InvalidRequestError, match=r"timeline\[1\]: start at or after duration_s \(0.5 s\)"):
        DrivePlan.compile(_script(duration_s=0.5), LAYOUT, 0.2)
    missing = {"timeline": [{"t_s": 0, "modules": {"ids": [3, 48]}, "speed_m_s": 0.1, "heading_rad": 0}]}
    with pytest.raises(InvalidRequestError, match=r"modules \[48\] out of range"):
        DrivePlan.compile(_script(**missing), LAYOUT, 0.2)
    off_table = {
        "timeline": [{"t_s": 0, "modules": {"region_m": [5, 5, 6, 6]}, "speed_m_s": 0.1, "heading_rad": 0}]
    }
    with pytest.raises(
        InvalidRequestError, match=r"timeline\[0\]: modules.region_m holds no module's centre"
    ):
        DrivePlan.compile(_script(**off_table), LAYOUT, 0.2)


def test_reach_counts_only_the_modules_near_the_cloth() -> None:
    outline = np.array([[-0.125, -0.1], [0.125, -0.1], [0.125, 0.1], [-0.125, 0.1]])
    near = {
        "duration_s": 2.0,
        "timeline": [{"t_s": 0, "modules": {"ids": [27]}, "speed_m_s": 0.02, "heading_rad": 0}],
    }
    assert cloth_reach_m(
        DrivePlan.compile(DriveScript.model_validate(near), LAYOUT, 0.2), outline, LAYOUT
    ) == (pytest.approx(0.04))
    # Module 0's belt, 0.1 m beyond the corner, is out of reach of 40 mm of travel: it carries nothing.
    far = {
        "duration_s": 2.0,
        "timeline": [{"t_s": 0, "modules": {"ids": [0]}, "speed_m_s": 0.02, "heading_rad": 0}],
    }
    assert (
        cloth_reach_m(DrivePlan.compile(DriveScript.model_validate(far), LAYOUT, 0.2), outline, LAYOUT) == 0.0
    )
    np.testing.assert_allclose(swept_box_m(outline, 0.04)[2], [0.165, 0.14])


def test_a_script_file_is_refused_naming_the_key(tmp_path: Path) -> None:
    path = tmp_path / "shear.yaml"
    path.write_text(
        "duration_s: 1\ntimeline:\n  - {t_s: 0, modules: {all: true}, speed: 0.1, heading_rad: 0}\n"
    )
    with pytest.raises(
        InputError, match=r"shear.yaml: timeline.0.speed_m_s: Field required; timeline.0.speed: Extra inputs"
    ):
        load_script(path)


def test_the_example_in_the_api_docs_plays_on_make_runs_cell() -> None:
    """docs/api.md's example is what a new user sends first: on the default cell, with hwsim's cell cloth
    at its centre, it must not be refused for the workspace."""
    text = (Path(__file__).resolve().parents[1] / "docs" / "api.md").read_text()
    block = text.split("```json\n", 1)[1].split("```", 1)[0]
    assert '"mode": "drive"' in block
    cfg = load_config(None)
    layout = ConveyorLayout.of_cell(cfg.cell)
    plan = DrivePlan.compile(
        DriveScript.model_validate(json.loads(block)["script"]), layout, cfg.cell.max_speed_m_s
    )
    w, h = scenarios.load("cell").cloth.size_m
    outline = np.array([[-w, -h], [w, -h], [w, h], [-w, h]]) / 2
    assert (
        Workspace.of_cell(cfg.cell).leaves(swept_box_m(outline, cloth_reach_m(plan, outline, layout))) is None
    )


@pytest.mark.parametrize("name", ["shear", "squeeze", "twist"])
def test_the_shipped_drive_scripts_are_the_documented_ones_and_play_on_make_runs_cell(name: str) -> None:
    root = Path(__file__).resolve().parents[1]
    path = root / "deploy" / "drive-scripts" / f"{name}.yaml"
    assert path.read_text() in (root / "docs" / "commissioning.md").read_text()
    cfg = load_config(None)
    layout = ConveyorLayout.of_cell(cfg.cell)
    plan = DrivePlan.compile(load_script(path), layout, cfg.cell.max_speed_m_s)
    w, h = scenarios.load("cell").cloth.size_m
    outline = np.array([[-w, -h], [w, -h], [w, h], [-w, h]]) / 2
    assert (
        Workspace.of_cell(cfg.cell).leaves(swept_box_m(outline, cloth_reach_m(plan, outline, layout))) is None
    )
    assert (plan.speed_m_s > 0).sum(axis=1).max() >= layout.n_modules // 2  # half the table or more driven


@pytest.mark.parametrize(
    ("modules", "words"),
    [
        ({"all": True, "ids": [1]}, "exactly one of all, ids, region_m"),
        ({}, "exactly one of all, ids, region_m"),
        ({"ids": [9999]}, "less than or equal to 4095"),
        ({"region_m": [0, 0, 1]}, "region_m.3"),
    ],
)
def test_a_bad_module_choice_is_refused_with_one_reason(modules: dict[str, object], words: str) -> None:
    """The key picks the way of choosing, so the answer is that way's reason, not every way's."""
    entry = {"t_s": 0, "modules": modules, "speed_m_s": 0.1, "heading_rad": 0}
    with pytest.raises(ValidationError) as refused:
        _script(timeline=[entry])
    (error,) = refused.value.errors()
    assert words in f"{'.'.join(map(str, error['loc']))}: {error['msg']}"


class _Cell:
    """What `drive` asks of the daemon, in order."""

    def __init__(self) -> None:
        self.calls: list[str] = []

    def record_start(self, name: str) -> Path:
        self.calls.append("record_start")
        return Path("recordings") / name

    def play(self, script: DriveScript) -> None:
        self.calls.append("play")

    def record_stop(self) -> None:
        self.calls.append("record_stop")


def test_a_recorded_drive_is_recorded_past_its_end() -> None:
    """The stop's commands and the last frames arrive after the status reads idle."""
    cell = _Cell()
    where = drive(cell, _script(), "fabric/shear", sleep=lambda s: cell.calls.append(f"wait {s:g} s"))  # type: ignore[arg-type]
    assert where == Path("recordings/fabric/shear")
    assert cell.calls == ["record_start", "play", f"wait {RECORD_TAIL_S:g} s", "record_stop"]
    unrecorded = _Cell()
    drive(unrecorded, _script(), None, sleep=lambda s: unrecorded.calls.append("wait"))  # type: ignore[arg-type]
    assert unrecorded.calls == ["play"]
