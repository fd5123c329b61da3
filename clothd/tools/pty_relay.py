"""A man in the middle on a serial line, for fault injection: the daemon opens the relay's pty, the relay
opens the controller's, and bytes pass both ways unless told otherwise.

    relay = PtyRelay(controller_port, tmp / "ttyRELAY")   # the daemon's stepper.port: tmp / "ttyRELAY"
    relay.drop_replies = True                            # the controller hears, the host hears nothing
    relay.drop_commands = True                           # the host talks, the controller hears nothing
    relay.delay_s = 0.1                                  # both ways, each chunk this much later
    relay.on_read = seen                                 # seen(from_host, bytes, time.monotonic())

Counts what it dropped, so a test can tell that the fault really happened.
"""

from __future__ import annotations

import contextlib
import os
import select
import threading
import time
import tty
from collections import deque
from collections.abc import Callable
from pathlib import Path

POLL_S = 0.002


class PtyRelay:
    def __init__(self, target: str | Path, link_path: Path) -> None:
        self.drop_replies = False
        self.drop_commands = False
        self.delay_s = 0.0
        self.on_read: Callable[[bool, bytes, float], None] | None = None  # each chunk, as it is read
        self.dropped_bytes = {"replies": 0, "commands": 0}
        self._target = os.open(str(target), os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
        tty.setraw(self._target)
        self._master, self._slave = os.openpty()
        tty.setraw(self._slave)  # a byte pipe, as a USB CDC port is
        os.set_blocking(self._master, False)
        link_path.unlink(missing_ok=True)
        link_path.symlink_to(os.ttyname(self._slave))
        self.link_path = link_path
        self._due: deque[tuple[float, int, bytes]] = deque()  # (when, to fd, bytes), in order
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="pty-relay", daemon=True)
        self._thread.start()

    def inject(self, data: bytes) -> None:
        """Bytes to the host as if the controller had sent them (line noise, a babbling device)."""
        self._due.append((time.monotonic(), self._master, data))

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=2)
        for fd in (self._target, self._master, self._slave):
            with contextlib.suppress(OSError):
                os.close(fd)
        self.link_path.unlink(missing_ok=True)

    def _run(self) -> None:
        while not self._stop.is_set():
            ready, _, _ = select.select([self._master, self._target], [], [], POLL_S)
            for fd in ready:
                try:
                    data = os.read(fd, 4096)
                except OSError:  # the other end is not open (yet, or any more)
                    time.sleep(POLL_S)
                    continue
                from_host = fd == self._master
                if self.on_read is not None:
                    self.on_read(from_host, data, time.monotonic())
                if (self.drop_commands if from_host else self.drop_replies) and data:
                    self.dropped_bytes["commands" if from_host else "replies"] += len(data)
                    continue
                self._due.append(
                    (time.monotonic() + self.delay_s, self._target if from_host else self._master, data)
                )
            now = time.monotonic()
            while self._due and self._due[0][0] <= now:
                _, to, data = self._due.popleft()
                with contextlib.suppress(OSError):
                    os.write(to, data)
