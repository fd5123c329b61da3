"""What a fresh clone holds besides the code: its licence, what git leaves out, and `make run`'s port."""

from __future__ import annotations

import os
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent


def test_the_licence_is_mit_held_by_the_clothd_authors() -> None:
    text = (ROOT / "LICENSE").read_text()
    assert text.startswith("MIT License\n") and "Copyright (c) 2026 the clothd authors" in text
    assert "Permission is hereby granted, free of charge" in text
    assert "[LICENSE](LICENSE)" in (ROOT / "README.md").read_text()


def test_the_readmes_recordings_stay_out_of_git() -> None:
    """The README records into rec/ (`hwsim record ... --out rec/translate`, `--record rec/session`)."""
    assert "/rec/" in (ROOT / ".gitignore").read_text().splitlines()


@pytest.mark.parametrize(
    ("make_args", "flags"),
    [
        (["PORT=8081"], " --port 8081"),
        ([], ""),
        (["PORT=8081", "OPCUA_PORT=4841"], " --port 8081 --opcua-endpoint opc.tcp://127.0.0.1:4841/clothd/"),
    ],
)
def test_make_run_takes_a_port(make_args: list[str], flags: str) -> None:
    # Run from `make test`, a nested make would print its directory and inherit the outer one's flags.
    env = {k: v for k, v in os.environ.items() if k not in ("MAKEFLAGS", "MAKELEVEL", "MFLAGS")}
    done = subprocess.run(
        ["make", "--no-print-directory", "-n", "run", *make_args],
        cwd=ROOT,
        capture_output=True,
        text=True,
        check=True,
        env=env,
    )
    assert done.stdout.splitlines()[-1].rstrip() == f".venv/bin/clothd run --sim --config config.yaml{flags}"
