"""File layout of a recording directory (docs/recording-format.md)."""

from pathlib import Path

FRAME_DIGITS = 6


def frame_path(recording: Path, index: int) -> Path:
    """DIR/frames/NNNNNN.png, frames numbered from 0."""
    return recording / "frames" / f"{index:0{FRAME_DIGITS}d}.png"
