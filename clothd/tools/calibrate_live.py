"""`clothd calibrate --camera SOURCE`: take the calibration pictures from a live camera.

The camera is read through the daemon's own driver (clothd/drivers/camera.py: a device, a stream URL,
a video file or a directory of images). A picture is taken when the board has been found in
STILL_FRAMES frames running, no corner moving more than STILL_PX from one to the next, and its pose is
new: against every picture taken, fewer than half of its corners are shared, or the shared ones lie
NEW_POSE_PX or more away on average. The first picture taken is the flat view (the board lying on the
table at --flat-origin-m), saved as the --flat name; the others are view_NN.png. After each, the image's
coverage so far is printed. It stops after `views` pictures, at the time limit, or on Ctrl-C, and the
pictures are then calibrated as a directory would be.
"""

from __future__ import annotations

import time
from pathlib import Path

import cv2
import numpy as np

from clothd.config import CameraSourceConfig
from clothd.drivers.camera import VideoCaptureSource
from clothd.drivers.footage import IMAGE_SUFFIXES
from clothd.errors import InputError
from clothd.tools.calibration_report import coverage_counts, coverage_map
from clothd.tools.charuco import MIN_CORNERS, Board, CornerFinder, Detection

STILL_FRAMES = 5
STILL_PX = 1.0
NEW_POSE_PX = 40.0
_POLL_S = 0.005


def _shared(a: Detection, b: Detection) -> tuple[np.ndarray, np.ndarray]:
    """The pixels of the corners both found, in the same order."""
    _, ia, ib = np.intersect1d(a.ids, b.ids, return_indices=True)
    return a.pixels[ia], b.pixels[ib]


class ViewPicker:
    """Decides frame by frame when to take a picture: the board held still in a pose not yet taken."""

    def __init__(self) -> None:
        self.taken: list[Detection] = []
        self._still: list[Detection] = []

    def offer(self, found: Detection | None) -> bool:
        """The board as found in the next frame (None: not found); True when this frame is to be taken."""
        if found is None:
            self._still.clear()
            return False
        if self._still:
            pa, pb = _shared(self._still[-1], found)
            if len(pa) < MIN_CORNERS or np.linalg.norm(pa - pb, axis=1).max() > STILL_PX:
                self._still.clear()
        self._still.append(found)
        if len(self._still) < STILL_FRAMES or not all(self._is_new(found, t) for t in self.taken):
            return False
        self.taken.append(found)
        self._still.clear()
        return True

    @staticmethod
    def _is_new(found: Detection, taken: Detection) -> bool:
        pa, pb = _shared(found, taken)
        if len(pa) < 0.5 * min(len(found.ids), len(taken.ids)):
            return True
        return bool(np.linalg.norm(pa - pb, axis=1).mean() >= NEW_POSE_PX)


def capture_views(
    source: str,
    board: Board,
    out_dir: Path,
    flat_name: str,
    views: int,
    timeout_s: float,
) -> list[str]:
    """Take up to `views` pictures from the camera into out_dir (new, or without pictures); their names."""
    if out_dir.is_dir() and any(p.suffix.lower() in IMAGE_SUFFIXES for p in out_dir.iterdir()):
        raise InputError(f"{out_dir}: already holds pictures; give a new directory for a live calibration")
    out_dir.mkdir(parents=True, exist_ok=True)
    finder = CornerFinder(board)
    picker = ViewPicker()
    names: list[str] = []
    camera = VideoCaptureSource(CameraSourceConfig(source=source))
    print(
        f"lay the board flat on the table at the stated origin and hold still; then {views - 1} tilted views"
    )
    camera.start()
    deadline = time.monotonic() + timeout_s
    last_index = -1
    interrupted = False
    try:
        while len(names) < views and time.monotonic() < deadline:
            frame = camera.latest()
            if frame is None or frame.index == last_index:
                time.sleep(_POLL_S)
                continue
            last_index = frame.index
            found = finder.find(frame.image)
            if not picker.offer(found):
                continue
            assert found is not None
            name = flat_name if not names else f"view_{len(names):02d}.png"
            cv2.imwrite(str(out_dir / name), frame.image)
            names.append(name)
            h, w = frame.image.shape[:2]
            counts = coverage_counts([d.pixels for d in picker.taken], w, h)
            print(
                f"took {name} ({len(found.ids)} corners); coverage {np.count_nonzero(counts)} of "
                f"{counts.size} cells: {' '.join(coverage_map(counts))}",
                flush=True,
            )
    except KeyboardInterrupt:
        print(f"stopped with {len(names)} pictures")
        interrupted = True
    finally:
        camera.stop()
    spent = "until stopped" if interrupted else f"in {timeout_s:g} s"
    if last_index < 0:  # not one frame: the camera, not the board, is what to look at
        why = f" ({camera.last_error})" if camera.last_error else ""
        raise InputError(f"camera {camera.shown!r}: no frame came {spent}{why}")
    if not names:
        raise InputError(f"camera {camera.shown!r}: the board was in no frame held still ({spent})")
    return names
