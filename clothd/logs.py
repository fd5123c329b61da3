"""Logging for the daemon's processes: one line per event, the level and the logger's name.

Under systemd (JOURNAL_STREAM set) journald stamps every line itself, so we add no time of our own.
Libraries that log every request at INFO (httpx, uvicorn's access log, asyncua) are kept to warnings.
Every line is rate-limited by where it comes from (`RateLimit`): a peer that sends a thousand malformed
messages must not write a thousand tracebacks, nor hold the GIL the tick needs while it does. Lines are
written to stderr by a thread of their own (a `QueueListener`): a stderr that does not drain (a stalled
journald, a full pipe) holds that thread, never the thread that logged, the tick's among them.
"""

import atexit
import logging
import os
import time
from logging.handlers import QueueHandler, QueueListener
from queue import SimpleQueue

QUIET_LIBRARIES = ("httpx", "httpcore", "uvicorn.access", "asyncua")
BURST = 5  # lines from one place let through per window
WINDOW_S = 10.0


class RateLimit(logging.Filter):
    """At most `burst` records per `window_s` from one place (logger and message template); the next
    one let through says how many were dropped. Only the first record of a window keeps its traceback."""

    def __init__(self, burst: int = BURST, window_s: float = WINDOW_S) -> None:
        super().__init__()
        self.burst, self.window_s = burst, window_s
        self._windows: dict[tuple[str, str], tuple[float, int, int]] = {}  # start, let through, dropped

    def filter(self, record: logging.LogRecord) -> bool:
        key = (record.name, str(record.msg))
        now = time.monotonic()
        start, passed, dropped = self._windows.get(key, (now, 0, 0))
        if now - start >= self.window_s:
            start, passed = now, 0
        if passed >= self.burst:
            self._windows[key] = (start, passed, dropped + 1)
            return False
        if passed > 0:
            record.exc_info, record.exc_text = None, None
        if dropped:
            record.msg = f"{record.msg} ({dropped} more like this dropped)"
        self._windows[key] = (start, passed + 1, 0)
        return True


def configure_logging() -> None:
    """Once per process: INFO and up, rate-limited, written by a thread of its own. Where logging was set
    up already (a test runner's handlers), those handlers are rate-limited instead."""
    root = logging.getLogger()
    for name in QUIET_LIBRARIES:
        logging.getLogger(name).setLevel(logging.WARNING)
    if root.handlers:
        for handler in root.handlers:
            if not any(isinstance(f, RateLimit) for f in handler.filters):
                handler.addFilter(RateLimit())
        return
    stamp = "" if os.environ.get("JOURNAL_STREAM") else "%(asctime)s "
    writer = logging.StreamHandler()
    writer.setFormatter(logging.Formatter(stamp + "%(levelname)s %(name)s: %(message)s"))
    queue: SimpleQueue[logging.LogRecord] = SimpleQueue()
    handler = QueueHandler(queue)
    handler.addFilter(RateLimit())  # before the record is formatted: a dropped one costs nothing more
    root.addHandler(handler)
    root.setLevel(logging.INFO)
    listener = QueueListener(queue, writer)
    listener.start()
    atexit.register(listener.stop)  # what is queued is written before the process ends
