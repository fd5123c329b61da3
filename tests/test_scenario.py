from pathlib import Path

import pytest

from hwsim import scenario as scenarios
from hwsim.cli import main

pytestmark = pytest.mark.clock_free


@pytest.mark.parametrize("name", scenarios.shipped_names())
def test_shipped_scenarios_load(name: str) -> None:
    sc = scenarios.load(name)
    assert sc.name == name
    frames_expected = round(sc.duration_s * sc.fps) + 1
    assert sc.frame_count == frames_expected


def test_every_issue_scenario_is_shipped() -> None:
    assert {"translate", "rotate", "compress", "occlude", "random"} <= set(scenarios.shipped_names())


def test_random_runs_a_minute() -> None:
    assert scenarios.load("random").frame_count == 60 * 30 + 1


def _write(tmp_path: Path, text: str) -> Path:
    path = tmp_path / "bad.yaml"
    path.write_text(text)
    return path


@pytest.mark.parametrize(
    ("text", "must_name"),
    [
        ("name: x\nduration_s: 1\ncloth: {spacing_mm: 3}\n", "cloth.spacing_mm"),
        ("name: x\nduration_s: -1\n", "duration_s"),
        ("name: x\nduration_s: 1\ncamera: {f_px: 0}\n", "camera.f_px"),
        ("name: x\nduration_s: 1\ntable: {module_size_m: 0.2}\n", "table"),
        (
            "name: x\nduration_s: 1\ntimeline:\n  - {t_s: 0, modules: {}, speed_m_s: 0.1, heading_rad: 0}\n",
            "timeline.0.modules",
        ),
        (
            "name: x\nduration_s: 1\ntimeline:\n"
            "  - {t_s: 0, modules: {ids: [99]}, speed_m_s: 0.1, heading_rad: 0}\n",
            "timeline[0].modules.ids",
        ),
        ("duration_s: 1\n", "name"),
        ("name: x\nduration_s: 1\ntable: {miscalibrated: [{module: 1, offset: 3}]}\n", "0.offset"),
        ("name: x\nduration_s: 1\ntable: {miscalibrated: [{module: 1, speed_scale: 3}]}\n", "speed_scale"),
        ("name: x\nduration_s: 1\ntable: {miscalibrated: [{module: 48}]}\n", "out of range"),
        ("name: x\nduration_s: 1\ntable: {miscalibrated: [{module: 2}, {module: 2}]}\n", "listed twice"),
    ],
)
def test_bad_scenario_names_the_key(tmp_path: Path, text: str, must_name: str) -> None:
    with pytest.raises(scenarios.ScenarioError) as err:
        scenarios.load(_write(tmp_path, text))
    assert must_name in str(err.value)
    assert "bad.yaml" in str(err.value)


def test_bad_yaml_and_missing_file(tmp_path: Path) -> None:
    with pytest.raises(scenarios.ScenarioError, match="not valid YAML"):
        scenarios.load(_write(tmp_path, "name: [unclosed\n"))
    with pytest.raises(scenarios.ScenarioError, match="no such file"):
        scenarios.load(tmp_path / "nope.yaml")
    with pytest.raises(scenarios.ScenarioError, match="a mapping"):
        scenarios.load(_write(tmp_path, "- just\n- a list\n"))


def test_cli_reports_bad_scenario_without_traceback(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    bad = _write(tmp_path, "name: x\nduration_s: 1\nnoise: {sigma: 1000}\n")
    assert main(["record", str(bad), "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err
    assert "noise.sigma" in err
    assert "Traceback" not in err
    assert not (tmp_path / "out").exists()
