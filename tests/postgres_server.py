"""A throwaway PostgreSQL server for a test: Debian's `postgresql` binaries (initdb, pg_ctl; `make postgres`
installs them), a cluster in a fresh temporary folder, on a free loopback port, stopped and removed after.

PostgreSQL refuses to run as root, so as root (CI) the cluster belongs to the `postgres` user the package
creates, and every command runs as that user; anyone else runs it as themselves.
"""

from __future__ import annotations

import contextlib
import glob
import os
import pwd
import shutil
import socket
import subprocess
import tempfile
from collections.abc import Iterator
from pathlib import Path

START_TIMEOUT_S = 60


def _binary(name: str) -> str:
    """Debian keeps the server's programs out of PATH, under /usr/lib/postgresql/VERSION/bin."""

    def version(path: str) -> list[int]:
        return [int(part) for part in Path(path).parts[-3].split(".")]

    debian = sorted(glob.glob(f"/usr/lib/postgresql/*/bin/{name}"), key=version, reverse=True)
    found = shutil.which(name) or next(iter(debian), None)
    if found is None:
        raise RuntimeError(f"PostgreSQL's {name} not found: `make postgres` installs Debian's postgresql")
    return found


def _run_as_owner(command: list[str]) -> None:
    if os.geteuid() == 0:
        command = ["runuser", "-u", "postgres", "--", *command]
    subprocess.run(command, check=True, capture_output=True, text=True, timeout=START_TIMEOUT_S)


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@contextlib.contextmanager
def postgres_server() -> Iterator[str]:
    """A running server; yields its URL (user postgres, database postgres, no password: trust on loopback)."""
    root = Path(tempfile.mkdtemp(prefix="clothd-pg-"))
    if os.geteuid() == 0:
        owner = pwd.getpwnam("postgres")
        os.chown(root, owner.pw_uid, owner.pw_gid)
    data, port = root / "data", _free_port()
    _run_as_owner([_binary("initdb"), "-D", str(data), "-U", "postgres", "-A", "trust"])
    options = f"-p {port} -k {root} -c listen_addresses=127.0.0.1"
    pg_ctl = _binary("pg_ctl")
    _run_as_owner([pg_ctl, "-D", str(data), "-o", options, "-l", str(root / "server.log"), "-w", "start"])
    try:
        yield f"postgresql://postgres@127.0.0.1:{port}/postgres"
    finally:
        _run_as_owner([pg_ctl, "-D", str(data), "-m", "fast", "-w", "stop"])
        shutil.rmtree(root, ignore_errors=True)
