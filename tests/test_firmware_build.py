"""The firmware's host build remembers the compiler and flags it last used: the same ones leave the
objects as they are, other ones (a quote in them too) rebuild every object."""

from __future__ import annotations

import os
import shutil
import subprocess
from pathlib import Path

import pytest

pytestmark = pytest.mark.clock_free

FIRMWARE_DIR = Path(__file__).resolve().parents[1] / "deploy" / "firmware"


def _make(build: Path, cflags: str) -> None:
    # Run from `make test`, a nested make would inherit the outer one's flags.
    env = {k: v for k, v in os.environ.items() if k not in ("MAKEFLAGS", "MAKELEVEL", "MFLAGS")}
    done = subprocess.run(
        [
            "make",
            "--no-print-directory",
            "-C",
            str(FIRMWARE_DIR),
            "host",
            f"BUILD={build}",
            f"CFLAGS={cflags}",
        ],
        capture_output=True,
        text=True,
        env=env,
        timeout=120,
    )
    assert done.returncode == 0, f"make host failed:\n{done.stdout}\n{done.stderr}"


def _objects(build: Path) -> dict[str, int]:
    """Each object file and when it was last written (ns): a rebuilt one was written again."""
    return {str(p.relative_to(build)): p.stat().st_mtime_ns for p in sorted((build / "obj").rglob("*.o"))}


def test_objects_are_rebuilt_when_the_flags_change_and_kept_when_not(tmp_path: Path) -> None:
    if shutil.which("gcc") is None or shutil.which("make") is None:
        pytest.fail("the C firmware's host build needs gcc and make (Debian: apt-get install gcc make)")
    build = tmp_path / "build"
    _make(build, "-O2")
    first = _objects(build)
    stamp = (build / "obj" / "flags").read_text()
    assert first and " -O2 " in stamp
    _make(build, "-O2")
    assert _objects(build) == first and (build / "obj" / "flags").read_text() == stamp
    quoted = "-O2 -DCLOTHD_BUILD_NOTE='\"quoted\"'"
    _make(build, quoted)
    assert (build / "obj" / "flags").read_text() == stamp.replace(" -O2 ", f" {quoted} ")
    again = _objects(build)
    assert set(again) == set(first) and all(again[name] != first[name] for name in first)
