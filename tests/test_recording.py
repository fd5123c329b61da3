"""Recordings of every shipped scenario: format, the truth-vs-pixels check, preview, and the CLI."""

import csv
import json
import shutil
from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np
import pytest

from hwsim import scenario as scenarios
from hwsim.camera import Camera
from hwsim.cli import main
from hwsim.paths import frame_path
from hwsim.preview import write_preview
from hwsim.verify import verify

pytestmark = pytest.mark.clock_free

Recorder = Callable[[str], Path]


@pytest.mark.parametrize("name", ["translate", "rotate", "compress", "occlude", "random"])
def test_verify_passes_on_each_shipped_scenario(short_recording: Recorder, name: str) -> None:
    result = verify(short_recording(name))
    assert result.points == 200
    assert result.pairs >= 300
    assert result.ok, result


def test_recording_format(short_recording: Recorder) -> None:
    rec = short_recording("translate")
    sc = scenarios.load("translate", duration_s=1.0)
    n = sc.frame_count
    frames = sorted((rec / "frames").glob("*.png"))
    assert [p.name for p in frames[:2]] == ["000000.png", "000001.png"] and len(frames) == n
    img = cv2.imread(str(frames[0]), cv2.IMREAD_UNCHANGED)
    assert img.shape == (480, 640, 3) and img.dtype == np.uint8
    cam = json.loads((rec / "camera.json").read_text())
    assert set(cam) == {"K", "dist", "width", "height", "T_cam_world"}
    assert np.asarray(cam["K"]).shape == (3, 3) and len(cam["dist"]) == 5
    assert np.asarray(cam["T_cam_world"]).shape == (4, 4)
    with (rec / "commands.csv").open() as f:
        rows = list(csv.DictReader(f))
    assert list(rows[0]) == ["t_s", "module", "speed_m_s", "heading_rad"]
    # translate drives every module +y from 0.2 s: told after the frame at 0.2 s, in force from the next.
    drive = [r for r in rows if float(r["speed_m_s"]) > 0]
    assert len(drive) == 48 and all(abs(float(r["t_s"]) - (0.2 + 1 / 30)) < 1e-6 for r in drive)
    assert all(abs(float(r["heading_rad"]) - np.pi / 2) < 1e-6 for r in drive)
    with np.load(rec / "truth.npz") as z:
        ny, nx = z["st_m"].shape[:2]
        assert z["t_s"].shape == (n,) and z["nodes_m"].shape == (n, ny, nx, 3)
        assert z["visible"].shape == (n, ny, nx)
        # The truth mesh is at least 3x finer than a 12x12 tracker mesh over 250 x 200 mm.
        assert z["st_m"][0, 1, 0] <= 0.25 / 11 / 3 and z["st_m"][1, 0, 1] <= 0.20 / 11 / 3
        # The cloth moved +y by about 30 mm/s after 0.2 s.
        dy = z["nodes_m"][-1, ..., 1].mean() - z["nodes_m"][0, ..., 1].mean()
        assert 0.015 < dy < 0.025


def test_truth_nodes_land_on_the_cloth_in_the_image(short_recording: Recorder) -> None:
    rec = short_recording("translate")
    cam = Camera.load(rec / "camera.json")
    img = cv2.imread(str(frame_path(rec, 20)))
    with np.load(rec / "truth.npz") as z:
        px = cam.project(z["nodes_m"][20].astype(float))
    # Denim is blue: blue channel well above red where the truth says the cloth is.
    inner = np.round(px[2:-2, 2:-2].reshape(-1, 2)).astype(int)
    b, r = img[inner[:, 1], inner[:, 0], 0].astype(int), img[inner[:, 1], inner[:, 0], 2].astype(int)
    assert np.mean(b > r + 15) > 0.9


def test_occluded_nodes_are_marked(short_recording: Recorder) -> None:
    with np.load(short_recording("occlude") / "truth.npz") as z:
        hidden = 1.0 - z["visible"].mean(axis=(1, 2))
        t = z["t_s"]
    assert hidden[t < 0.85].max() < 0.02  # nothing over the cloth before the arm comes
    assert hidden[(t > 1.05) & (t < 1.5)].min() > 0.05


def test_verify_fails_when_pixels_disagree_with_truth(short_recording: Recorder, tmp_path: Path) -> None:
    bad = tmp_path / "bad"
    shutil.copytree(short_recording("translate"), bad)
    for p in sorted((bad / "frames").glob("*.png")):  # the image drifts 2 px away from the truth
        img = cv2.imread(str(p))
        k = int(p.stem)
        cv2.imwrite(str(p), np.roll(img, 2 * (k // 10), axis=1))
    assert not verify(bad).ok


def test_preview_writes_a_readable_video(short_recording: Recorder, tmp_path: Path) -> None:
    out = write_preview(short_recording("compress"), tmp_path / "p.mp4")
    cap = cv2.VideoCapture(str(out))
    ok, frame = cap.read()
    count = int(cap.get(cv2.CAP_PROP_FRAME_COUNT))
    cap.release()
    assert ok and frame.shape == (480, 640, 3) and count == 31


def test_cli_record_then_verify(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "rec"
    record_args = ["record", "rotate", "--out", str(out), "--duration", "0.4"]
    assert main(record_args) == 0
    assert main(["verify", str(out), "--json", str(tmp_path / "v.json")]) == 0
    printed = capsys.readouterr().out
    assert "PASS" in printed and "patch pairs" in printed
    assert json.loads((tmp_path / "v.json").read_text())["ok"] is True
