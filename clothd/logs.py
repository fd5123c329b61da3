"""Logging for the daemon's processes: one line per event, the level and the logger's name.

Under systemd (JOURNAL_STREAM set) journald stamps every line itself, so we add no time of our own.
Libraries that log every request at INFO (httpx, uvicorn's access log, asyncua) are kept to warnings.
"""

import logging
import os

QUIET_LIBRARIES = ("httpx", "httpcore", "uvicorn.access", "asyncua")


def configure_logging() -> None:
    stamp = "" if os.environ.get("JOURNAL_STREAM") else "%(asctime)s "
    logging.basicConfig(level=logging.INFO, format=stamp + "%(levelname)s %(name)s: %(message)s")
    for name in QUIET_LIBRARIES:
        logging.getLogger(name).setLevel(logging.WARNING)
