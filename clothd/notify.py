"""systemd's service notification protocol (sd_notify): a datagram to $NOTIFY_SOCKET. Without systemd
(no variable) every call is a no-op."""

from __future__ import annotations

import contextlib
import os
import socket


class SystemdNotifier:
    def __init__(self) -> None:
        address = os.environ.get("NOTIFY_SOCKET")
        self._address = None if not address else ("\0" + address[1:] if address.startswith("@") else address)
        self._sock: socket.socket | None = None
        if self._address is not None:
            self._sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM | socket.SOCK_CLOEXEC)

    def notify(self, state: str) -> None:
        if self._sock is None or self._address is None:
            return
        with contextlib.suppress(OSError):  # systemd went away; it will notice by itself
            self._sock.sendto(state.encode(), self._address)

    def ready(self) -> None:
        self.notify("READY=1")

    def watchdog(self) -> None:
        self.notify("WATCHDOG=1")

    def stopping(self) -> None:
        self.notify("STOPPING=1")
