"""An API in the daemon's own process (local_cell.py), served on a thread and event loop of its own:
requests into the daemon (`DaemonBridge.call`) run on the daemon's loop, and their answers (or their
errors) come back to the API's; the daemon's status crosses the other way as immutable bytes
(StreamHub.publish). `clothd run` serves its API from a process of its own instead (process.py).

Before the daemon's loop runs (the app built but not started, as in the API tests), calls run at once.
"""

from __future__ import annotations

import asyncio
import concurrent.futures
from collections.abc import Callable
from typing import TypeVar

T = TypeVar("T")


class DaemonBridge:
    def __init__(self) -> None:
        self.loop: asyncio.AbstractEventLoop | None = None  # the daemon's, once it runs

    async def call(self, fn: Callable[..., T], *args: object) -> T:
        """fn(*args) on the daemon's loop; its result, or its exception, here."""
        loop = self.loop
        if loop is None or not loop.is_running() or loop is asyncio.get_running_loop():
            return fn(*args)
        done: concurrent.futures.Future[T] = concurrent.futures.Future()

        def run() -> None:
            try:
                done.set_result(fn(*args))
            except Exception as err:  # handed back to the request that asked
                done.set_exception(err)

        loop.call_soon_threadsafe(run)
        return await asyncio.wrap_future(done)
