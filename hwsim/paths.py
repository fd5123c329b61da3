"""File layout of a recording directory (docs/recording-format.md)."""

from pathlib import Path

FRAME_DIGITS = 6


def frame_path(recording: Path, index: int) -> Path:
    """DIR/frames/NNNNNN.png, frames numbered from 0."""
    return recording / "frames" / f"{index:0{FRAME_DIGITS}d}.png"


def camera_dir(out_dir: Path, index: int, name: str) -> Path:
    """Where camera `index` is written: the directory itself for the first, cameras/NAME/ for others
    (a recording's, and hwsim charuco's calibration pictures)."""
    return out_dir if index == 0 else out_dir / "cameras" / name
