from pathlib import Path

import cv2
import numpy as np
import pytest

from clothd.drivers.footage import CommandSchedule, natural_key, open_footage
from clothd.errors import InputError

pytestmark = pytest.mark.clock_free


def test_image_directory_in_natural_order(tmp_path: Path) -> None:
    for k in (10, 2, 1):
        img = np.full((8, 8, 3), k, np.uint8)
        cv2.imwrite(str(tmp_path / f"img_{k}.png"), img)
    (tmp_path / "notes.txt").write_text("not an image")
    footage = open_footage(tmp_path)
    values = [int(img[0, 0, 0]) for _, img in footage.frames()]
    assert values == [1, 2, 10]
    assert [t for t, _ in footage.frames()] == [0.0, 1 / 30, 2 / 30]
    assert sorted([Path("b10.png"), Path("b9.png")], key=natural_key) == [Path("b9.png"), Path("b10.png")]


def test_video_file(tmp_path: Path) -> None:
    path = tmp_path / "v.avi"
    w = cv2.VideoWriter(str(path), cv2.VideoWriter.fourcc(*"MJPG"), 15.0, (32, 24))
    for k in range(5):
        w.write(np.full((24, 32, 3), 40 * k, np.uint8))
    w.release()
    footage = open_footage(path)
    assert footage.fps == pytest.approx(15.0)
    assert len(list(footage.frames())) == 5


def test_bad_sources_are_clear_errors(tmp_path: Path) -> None:
    with pytest.raises(InputError, match="no such file"):
        open_footage(tmp_path / "missing.mp4")
    (tmp_path / "junk.mp4").write_bytes(b"not a video")
    mcap = tmp_path / "live.mcap"
    mcap.write_bytes(b"\x89MCAP0\r\n")  # what recording.format mcap writes begins so
    with pytest.raises(InputError, match=r"an MCAP recording .* cannot be replayed"):
        open_footage(mcap)
    with pytest.raises(InputError, match="not a video"):
        open_footage(tmp_path / "junk.mp4")
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(InputError, match="no images"):
        open_footage(empty)


def test_command_schedule_holds_each_modules_last_command(tmp_path: Path) -> None:
    path = tmp_path / "commands.csv"
    path.write_text(
        "t_s,module,speed_m_s,heading_rad\n0.0,0,0.0,0.0\n0.2,1,0.05,1.0\n0.5,1,0.0,1.0\n0.3,0,0.02,-1.0\n"
    )
    sched = CommandSchedule(path, n_modules=3)
    at0 = sched.at(0.0)
    assert list(at0.speed_m_s) == [0.0, 0.0, 0.0]
    at = sched.at(0.35)
    np.testing.assert_allclose(at.speed_m_s, [0.02, 0.05, 0.0])
    np.testing.assert_allclose(at.heading_rad, [-1.0, 1.0, 0.0])
    assert sched.at(0.6).speed_m_s[1] == 0.0
    bad = tmp_path / "bad.csv"
    bad.write_text("t_s,module,speed_m_s,heading_rad\n0.0,7,0.1,0.0\n")
    with pytest.raises(InputError, match="module ids"):
        CommandSchedule(bad, n_modules=3)


def test_read_ahead_yields_the_same_frames(tmp_path: Path) -> None:
    for k in range(9):
        cv2.imwrite(str(tmp_path / f"f{k}.png"), np.full((4, 4, 3), 20 * k, np.uint8))
    footage = open_footage(tmp_path)
    ahead = [(t, int(img[0, 0, 0])) for t, img in footage.frames()]
    plain = [(t, int(img[0, 0, 0])) for t, img in footage.frames(read_ahead=False)]
    assert ahead == plain and [v for _, v in ahead] == [20 * k for k in range(9)]
