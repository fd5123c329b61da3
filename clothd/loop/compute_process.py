"""The daemon's end of the compute process (clothd/loop/compute.py): start it, send a tick's request, take
its reply without blocking the event loop, and stop it."""

from __future__ import annotations

import asyncio
import contextlib
import multiprocessing
import os
from concurrent.futures import ThreadPoolExecutor
from typing import Any

from clothd.errors import ConfigError, HardwareError
from clothd.loop.compute import serve_compute
from clothd.loop.compute_messages import ComputeSpec, InForce, TickReply, TickRequest

START_TIMEOUT_S = 120.0
JOIN_TIMEOUT_S = 10.0


class ComputeProcess:
    def __init__(self, spec: ComputeSpec) -> None:
        self.spec = spec
        self._conn: Any = None
        self._process: Any = None
        # One thread blocks on the pipe, so the event loop never does.
        self._receiver = ThreadPoolExecutor(max_workers=1, thread_name_prefix="compute-reply")

    async def start(self) -> None:
        # One BLAS thread in the compute process: its pool, sized to every core, only contends with hwsim or
        # the camera here, and the matrices are small (set before it imports numpy). OpenCV's threads are
        # loop.compute_threads (serve_compute).
        for var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
            os.environ.setdefault(var, "1")
        ctx = multiprocessing.get_context("spawn")  # a fresh interpreter: no inherited threads or Taichi
        self._conn, child = ctx.Pipe()
        self._process = ctx.Process(
            target=serve_compute, args=(child, self.spec), name="clothd-compute", daemon=True
        )
        self._process.start()
        child.close()
        loop = asyncio.get_running_loop()
        ready = await asyncio.wait_for(loop.run_in_executor(self._receiver, self._conn.recv), START_TIMEOUT_S)
        if isinstance(ready, str) and ready.startswith("error: "):
            await self.stop()
            raise ConfigError(ready.removeprefix("error: "))
        if ready != "ready":
            raise HardwareError(f"the compute process did not start: {ready!r}")

    def request(self, req: TickRequest) -> asyncio.Future[TickReply]:
        """Send one tick's request; the future holds the reply. OSError or EOFError: the process died."""
        self._conn.send(req)
        return asyncio.ensure_future(
            asyncio.get_running_loop().run_in_executor(self._receiver, self._conn.recv)
        )

    def tell_in_force(self, in_force: InForce) -> None:
        """What the modules were just told, for the frames tracked before the next request (no reply).
        OSError: the process died."""
        if self.spec.track_ahead:
            self._conn.send(in_force)

    async def stop(self) -> None:
        """Ask the process to finish (it stops the camera and any recording), then make sure it has."""
        if self._process is not None:
            with contextlib.suppress(OSError, ValueError):
                self._conn.send(None)
            await asyncio.get_running_loop().run_in_executor(None, self._process.join, JOIN_TIMEOUT_S)
            if self._process.is_alive():
                self._process.kill()
        self._receiver.shutdown(wait=False, cancel_futures=True)
