"""Run a command on a pseudo-terminal, as a person at a shell would, or piped, as a script would."""

from __future__ import annotations

import fcntl
import os
import pty
import struct
import subprocess
import termios


def on_terminal(cmd: list[str], timeout_s: float = 300) -> str:
    """The command's stdout and stderr together, as the terminal showed them; it must exit 0."""
    main, child = pty.openpty()
    fcntl.ioctl(child, termios.TIOCSWINSZ, struct.pack("HHHH", 30, 100, 0, 0))  # a terminal has a size
    proc = subprocess.Popen(cmd, stdout=child, stderr=child, stdin=subprocess.DEVNULL)
    os.close(child)
    output = b""
    while True:
        try:
            chunk = os.read(main, 4096)
        except OSError:  # the child closed the terminal
            break
        if not chunk:
            break
        output += chunk
    os.close(main)
    assert proc.wait(timeout=timeout_s) == 0
    return output.decode(errors="replace")


def piped(cmd: list[str], timeout_s: float = 300) -> str:
    """The command's stderr, with its output piped; it must exit 0."""
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout_s)
    assert done.returncode == 0, done.stderr
    return done.stderr
