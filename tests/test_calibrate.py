"""clothd calibrate: the camera hwsim renders through is recovered within bench calibrate's bars, bad pictures
get their reason, the command's interface works end to end and writes a camera.json the tracker loads,
and live pictures come through the camera driver."""

from __future__ import annotations

import json
import shutil
import sys
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
from terminal import on_terminal, piped

from clothd.cli import main
from clothd.core.camera_model import CameraModel
from clothd.formats import read_camera
from clothd.tools.bench_calibrate import BARS, grade_camera, run_bench
from clothd.tools.calibrate import Calibration, ViewFit
from clothd.tools.calibration_report import coverage_counts, coverage_map, outliers
from hwsim.calibration_set import FLAT_NAME, write_calibration_set
from hwsim.charuco import BoardSpec
from hwsim.cli import main as hwsim_main
from hwsim.scenario import CameraSpec, Scenario

VIEWS = 8  # tilted views besides the flat one: few, to keep the test quick
TILTED = CameraSpec(tilt_rad=0.15, yaw_rad=0.3, dist=(-0.12, 0.05, 0.001, -0.0005, 0.0))


@pytest.fixture(scope="module")
def bench(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    """hwsim's pictures through a tilted, distorted camera (seeded), calibrated and graded."""
    return run_bench(tmp_path_factory.mktemp("charuco"), views=VIEWS, seed=0)


def _calibrate(images: Path, origin_m: list[float], out: Path, *extra: str) -> int:
    x, y = origin_m
    return main(
        [
            "calibrate", "--images", str(images), "--board", "9x6", "--square-m", "0.060",
            "--marker-m", "0.045", "--dictionary", "DICT_5X5_100", "--flat", FLAT_NAME,
            "--flat-origin-m", f"{x:g},{y:g}", "--out", str(out), *extra,
        ]
    )  # fmt: skip


def test_finding_the_board_shows_progress_on_a_terminal_only(bench: dict[str, Any], tmp_path: Path) -> None:
    x, y = bench["flat_origin_m"]
    cmd = [
        sys.executable, "-m", "clothd.cli", "calibrate", "--images", bench["pictures"], "--board", "9x6",
        "--square-m", "0.060", "--marker-m", "0.045", "--dictionary", "DICT_5X5_100", "--flat", FLAT_NAME,
        f"--flat-origin-m={x:g},{y:g}", "--out", str(tmp_path / "camera.json"),
    ]  # fmt: skip
    shown = on_terminal(cmd)
    assert "finding the board" in shown and f"{VIEWS + 1}/{VIEWS + 1}" in shown
    assert "finding the board" not in piped(cmd)


def _pictures_dir(src: Path, dst: Path, names: list[str]) -> Path:
    dst.mkdir()
    for name in names:
        shutil.copy(src / name, dst / name)
    return dst


def test_calibrate_recovers_the_hwsim_camera_within_the_bars(bench: dict[str, Any]) -> None:
    assert bench["views_used"] == VIEWS + 1
    failed = {k: bench["graded"][k] for k, ok in bench["pass"].items() if not ok}
    assert not failed, f"over the bars {BARS}: {failed}"


def test_the_command_writes_a_camera_the_tracker_loads_and_a_report(
    bench: dict[str, Any], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    pictures = Path(bench["pictures"])
    assert bench["flat_origin_m"][0] < 0  # so the flag's value starts with a minus, as argparse dislikes
    out, report = tmp_path / "camera.json", tmp_path / "report.json"
    assert _calibrate(pictures, bench["flat_origin_m"], out, "--json", str(report)) == 0
    graded = grade_camera(read_camera(out), read_camera(pictures / "camera.json"))
    assert all(graded[k] <= bar for k, bar in BARS.items()), graded
    r = json.loads(report.read_text())
    assert r["views_used"] == VIEWS + 1 and 0 < r["rms_px"] < 0.2
    cov = r["coverage"]
    assert cov["cells_covered"] > 0.8 * cov["cells"]
    assert Path(r["picture"]).is_file() and Path(r["picture"]).parent == tmp_path
    printed = capsys.readouterr().out
    assert "RMS reprojection error" in printed
    # Cells no picture covered are named as a gap to fill, not left for the reader to count.
    short = cov["cells_covered"] < cov["cells"]
    assert ("add pictures of the board there" in printed) == short


@pytest.mark.parametrize(
    ("case", "reason"),
    [
        ("flat missing", "flat view missing"),
        ("no board in the flat view", "board not found in the flat view"),
        ("too few views", "too few views"),
    ],
)
def test_bad_pictures_are_refused_with_their_reason(
    case: str, reason: str, bench: dict[str, Any], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    pictures = Path(bench["pictures"])
    if case == "flat missing":
        images = _pictures_dir(pictures, tmp_path / "p", [f"view_{k:02d}.png" for k in range(1, VIEWS + 1)])
    elif case == "no board in the flat view":
        images = _pictures_dir(pictures, tmp_path / "p", [f"view_{k:02d}.png" for k in range(1, VIEWS + 1)])
        cv2.imwrite(str(images / FLAT_NAME), np.full((480, 640), 100, dtype=np.uint8))
    else:
        images = _pictures_dir(pictures, tmp_path / "p", [FLAT_NAME, "view_01.png", "view_02.png"])
    assert _calibrate(images, bench["flat_origin_m"], tmp_path / "camera.json") == 2
    err = capsys.readouterr().err
    assert err.startswith("clothd: ") and reason in err and err.count("\n") == 1
    assert not (tmp_path / "camera.json").exists()


def test_boards_all_parallel_are_refused_as_degenerate(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """The board slid about flat on the table: every plane the same, so the focal length is free."""
    origin = (-0.25, 0.26)
    slid = tuple(
        (origin[0] + dx, origin[1] + dy) for dx, dy in [(0.04, 0), (-0.04, 0), (0, 0.04), (0, -0.04)]
    )
    scenario = Scenario(name="parallel", duration_s=1.0, camera=TILTED)
    write_calibration_set(scenario, tmp_path, BoardSpec(), 0, origin, seed=1, extra_flat_origins_m=slid)
    assert _calibrate(tmp_path, list(origin), tmp_path / "camera.json") == 2
    err = capsys.readouterr().err
    assert "degenerate views" in err and "parallel" in err


def test_a_bad_board_is_refused_naming_the_flag(
    bench: dict[str, Any], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert _calibrate(Path(bench["pictures"]), [0.0, 0.0], tmp_path / "c.json", "--marker-m", "0.07") == 2
    assert "--marker-m" in capsys.readouterr().err


def test_live_pictures_are_taken_when_the_board_is_held_still_in_a_new_pose(
    bench: dict[str, Any], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A camera that shows each pose for 2 s (an image directory, played at 30 fps by the driver): time
    for 5 still frames even on a loaded machine."""
    pictures = Path(bench["pictures"])
    poses = [FLAT_NAME, *(f"view_{k:02d}.png" for k in range(1, 5))]
    feed = tmp_path / "feed"
    feed.mkdir()
    for k, name in enumerate(p for p in poses for _ in range(60)):
        (feed / f"frame_{k:04d}.png").symlink_to(pictures / name)
    taken = tmp_path / "taken"
    args = ("--camera", str(feed), "--views", str(len(poses)), "--timeout-s", "60")
    assert _calibrate(taken, bench["flat_origin_m"], tmp_path / "camera.json", *args) == 0
    out = capsys.readouterr().out
    assert out.count("took ") == len(poses) and "coverage" in out
    assert sorted(p.name for p in taken.iterdir()) == poses
    # Each picture is the pose it was taken in, the flat one first.
    for mine, shown in zip(sorted(taken.iterdir()), poses, strict=True):
        assert np.array_equal(
            np.asarray(cv2.imread(str(mine))), np.asarray(cv2.imread(str(pictures / shown)))
        )
    read_camera(tmp_path / "camera.json")


def test_outliers_are_named_and_coverage_counted() -> None:
    rng = np.random.default_rng(3)
    pixels = rng.uniform([0, 0], [640, 240], (30, 2))  # the top half of a 640 x 480 image

    def fit(name: str, sigma_px: float) -> ViewFit:
        return ViewFit(name, pixels, rng.normal(0, sigma_px, pixels.shape))

    views = [fit(f"v{k}", 0.05) for k in range(6)] + [fit("blurred", 2.0)]
    cal = Calibration(CameraModel.ideal(640, 480, 900.0, 1.0), views, views[0], [])
    assert outliers(cal) == ["blurred"]
    counts = coverage_counts([pixels], 640, 480)
    assert counts.shape == (6, 8) and counts.sum() == 30
    assert coverage_map(counts)[3:] == ["........"] * 3


def test_hwsim_charuco_writes_the_pictures_the_truth_and_the_command(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    scenario = tmp_path / "tilted.yaml"
    scenario.write_text("name: tilted\nduration_s: 1.0\ncamera: {tilt_rad: 0.15, yaw_rad: 0.3}\n")
    out = tmp_path / "set"
    assert hwsim_main(["charuco", "--scenario", str(scenario), "--out", str(out), "--views", "0"]) == 0
    assert sorted(p.name for p in out.iterdir()) == ["board.json", "camera.json", FLAT_NAME]
    truth = json.loads((out / "board.json").read_text())
    assert truth["flat"] == FLAT_NAME and set(truth["T_cam_board"]) == {FLAT_NAME}
    assert read_camera(out / "camera.json").K[0, 0] == 900.0
    x, y = truth["flat_origin_m"]
    printed = capsys.readouterr().out
    assert f"clothd calibrate --images {out}" in printed and f"--flat-origin-m={x:g},{y:g}" in printed


def test_a_camera_that_never_opens_is_named_not_the_flat_view(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    missing = tmp_path / "no-such-camera.mp4"
    args = ("--camera", str(missing), "--views", "3", "--timeout-s", "1.5")
    assert _calibrate(tmp_path / "taken", [0.0, 0.0], tmp_path / "camera.json", *args) == 2
    err = capsys.readouterr().err
    assert f"camera '{missing}': no frame came in 1.5 s" in err and "flat view" not in err


def test_a_camera_that_never_shows_the_board_says_so(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    feed = tmp_path / "feed"
    feed.mkdir()
    for k in range(5):
        cv2.imwrite(str(feed / f"frame_{k:04d}.png"), np.full((480, 640), 90 + k, dtype=np.uint8))
    args = ("--camera", str(feed), "--views", "3", "--timeout-s", "1")
    assert _calibrate(tmp_path / "taken", [0.0, 0.0], tmp_path / "camera.json", *args) == 2
    assert "the board was in no frame held still" in capsys.readouterr().err
