"""The socket between the daemon and its API process (api/process.py, api/serve_api.py): a Unix
SOCK_SEQPACKET pair, so each message arrives whole or not at all, carrying pickled tuples. Neither end
ever waits on it: a send the other end has no room for is refused at once and the sender decides what
to drop.

The messages, by their first item:
- daemon -> API: ("status", json bytes) each published status; ("view", jpeg bytes) each new annotated
  view while someone watches; ("reply", call id, True, answer) or ("reply", call id, False, (error class
  name, message)).
- API -> daemon: ("ready",) once it serves; ("call", call id, name, args, deadline on the monotonic
  clock, past which the caller was told the daemon did not answer); ("watchers", n) as the number
  of views open changes; ("error", error class name, message, traceback or None) when it fails.
"""

from __future__ import annotations

import pickle
import socket

import clothd.errors as errors

SEND_BUFFER_BYTES = 4 * 1024 * 1024  # room for several views (a JPEG is tens to hundreds of kB)
MAX_MESSAGE_BYTES = SEND_BUFFER_BYTES  # the receive buffer: one message at most this long is sent
CLOTHD_ERRORS: dict[str, type[errors.ClothdError]] = {
    c.__name__: c for c in vars(errors).values() if isinstance(c, type) and issubclass(c, errors.ClothdError)
}


def clothd_error(name: str, message: str) -> errors.ClothdError | None:
    """A clothd error that crossed as its class's name and message, as itself; None for any other."""
    cls = CLOTHD_ERRORS.get(name)
    return None if cls is None else cls(message)


def channel_pair() -> tuple[socket.socket, socket.socket]:
    """The two ends, neither blocking: the daemon's, then the API process's."""
    ends = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
    for end in ends:
        # The kernel caps it at net.core.wmem_max; a message longer than the buffer is refused (dropped).
        end.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, SEND_BUFFER_BYTES)
        end.setblocking(False)
    return ends


class Channel:
    """One end of the pair."""

    def __init__(self, sock: socket.socket) -> None:
        sock.setblocking(False)
        self.sock = sock
        self.closed = False  # the other end has closed (receive() saw the end)
        self._buffer = bytearray(MAX_MESSAGE_BYTES)  # reused: no allocation per message

    def send(self, message: object) -> bool:
        """True when sent whole; False, at once, when the other end has no room for it now, it is too
        long, or the other end is gone (receive() then sees the end)."""
        data = pickle.dumps(message, protocol=pickle.HIGHEST_PROTOCOL)
        if len(data) > MAX_MESSAGE_BYTES:
            return False
        try:
            self.sock.send(data)
        except OSError:  # BlockingIOError (no room), EMSGSIZE (over the buffer), EPIPE (gone)
            return False
        return True

    def send_waiting(self, message: object, timeout_s: float) -> bool:
        """As send(), waiting up to timeout_s for room: only for a process's last words."""
        data = pickle.dumps(message, protocol=pickle.HIGHEST_PROTOCOL)
        self.sock.settimeout(timeout_s)
        try:
            self.sock.send(data)
        except OSError:
            return False
        finally:
            self.sock.setblocking(False)
        return True

    def receive(self) -> list[object]:
        """Every message waiting, oldest first, without waiting for more. Sets `closed` at the end."""
        messages: list[object] = []
        while not self.closed:
            try:
                n, _, flags, _ = self.sock.recvmsg_into([self._buffer])
            except BlockingIOError:
                break
            except ConnectionError:
                n, flags = 0, 0
            if n == 0:  # a pickle is never empty: the other end closed
                self.closed = True
            elif not flags & socket.MSG_TRUNC:  # never longer than the buffer, by send()
                messages.append(pickle.loads(memoryview(self._buffer)[:n]))
        return messages

    def close(self) -> None:
        self.sock.close()
