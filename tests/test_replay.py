import json
from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np
import pytest

from clothd.cli import main

pytestmark = pytest.mark.clock_free

Recorder = Callable[[str], Path]


@pytest.mark.parametrize(("model", "flags"), [("mesh", []), ("rigid", ["--no-input"]), ("none", [])])
def test_replay_writes_estimates_summary_and_overlay(
    short_recording: Recorder, tmp_path: Path, model: str, flags: list[str]
) -> None:
    rec = short_recording("translate")
    out = tmp_path / model
    assert main(["replay", str(rec), "--out", str(out), "--model", model, *flags]) == 0
    n_frames = len(list((rec / "frames").glob("*.png")))
    with np.load(out / "estimates.npz") as z:
        assert z["t_s"].shape == (n_frames,) and z["pose"].shape == (n_frames, 3)
        n = len(z["feature_id"])
        assert z["meas_px"].shape == (n_frames, n, 2) and z["pred_px"].shape == (n_frames, n, 2)
        alive_per_frame = (~np.isnan(z["pred_px"][:, :, 0])).sum(axis=1)
        if model == "none":  # no model, no nodes; the rigid model's are its rest mesh moved rigidly
            assert "nodes_m" not in z
        else:
            assert z["nodes_m"].shape == (n_frames, 12, 12, 3)
    summary = json.loads((out / "summary.json").read_text())
    assert summary["model"] == model and summary["use_input"] is not bool(flags)
    assert summary["steady_realtime_factor"] > 0
    assert len(summary["per_frame"]) == n_frames
    # NaN exactly where a feature is not alive: the counts match what the tracker reported per frame.
    assert list(alive_per_frame) == [f["features"] for f in summary["per_frame"]]
    assert alive_per_frame[-1] > 300
    assert {"klt", "predict", "update", "tick"} <= set(summary["timing"])
    cap = cv2.VideoCapture(str(out / "overlay.mp4"))
    assert int(cap.get(cv2.CAP_PROP_FRAME_COUNT)) == n_frames
    cap.release()


def test_replay_of_an_image_directory_says_which_camera_it_assumed(
    short_recording: Recorder, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    recording = short_recording("translate")
    src = tmp_path / "imgs"
    src.mkdir()
    for k, p in enumerate(sorted((recording / "frames").glob("*.png"))[:8]):
        (src / f"img_{k}.png").write_bytes(p.read_bytes())
    assert main(["replay", str(src), "--out", str(tmp_path / "o"), "--model", "rigid"]) == 0
    summary = json.loads((tmp_path / "o" / "summary.json").read_text())
    assert summary["frames"] == 8
    assert summary["camera"].startswith("assumed ideal (no camera.json): straight down from 1.0 m")
    assert "camera: assumed ideal" in capsys.readouterr().out
    camera = recording / "camera.json"
    assert (
        main(["replay", str(src), "--out", str(tmp_path / "c"), "--model", "rigid", "--camera", str(camera)])
        == 0
    )
    assert json.loads((tmp_path / "c" / "summary.json").read_text())["camera"] == str(camera)


def test_replay_of_a_missing_source_is_a_clear_error(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["replay", str(tmp_path / "nope"), "--out", str(tmp_path / "o")]) == 2
    assert "no such file" in capsys.readouterr().err
