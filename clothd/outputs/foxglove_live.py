"""The compute process's live Foxglove output: the Foxglove WebSocket server (`foxglove.enabled`) and
recordings straight to MCAP (`recording.format: mcap`), both fed the channels of foxglove_channels.py,
the same topics and schemas as `clothd export` writes.

Nothing here runs on the tick. The tick hands each new frame (the image, the commands in force, the
estimate) to `add`, which only queues it; one writer thread of its own JPEG-encodes the image (at most
once per camera frame, and only while a recording or a subscribed client wants /camera), builds the
messages and logs them to one foxglove.Context, whose sinks (the MCAP writer, the server) take them.
When the writer falls FRAME_QUEUE frames behind, new frames are dropped, and counted in the recording's
`dropped_frames`, rather than wait. The server is foxglove-sdk's own (Rust, on threads of its own): each
client has a bounded backlog (CLIENT_BACKLOG messages) whose oldest message is dropped when the client
does not read, so a client that never reads holds at most that and delays nothing.

Live log times, and the JSON messages' t_s, are the frame's capture time as Unix time (ns and s).

An MCAP recording is one file, written as chunks of one frame each: every frame's chunk is flushed to the
file as soon as it is logged, so a file cut short (the process killed, the disk full) still holds every
frame up to the last flushed one for a reader that reads it front to back (mcap's stream reader); a
normal stop writes the summary (indexes, statistics) that a seeking reader and Foxglove use. The
recording stops by itself before its file would pass `max_bytes` (the summary still to come included) and
on any write error, with the reason in its status.
"""

from __future__ import annotations

import io
import logging
import threading
import time
from collections import deque
from dataclasses import dataclass
from pathlib import Path

import foxglove
import numpy as np
from foxglove.mcap import MCAPWriteOptions, MCAPWriter

from clothd.config import FoxgloveConfig, RecordingFormat
from clothd.core.messages import Estimate, ModuleCommands
from clothd.drivers.priority import leave_realtime
from clothd.errors import ConfigError
from clothd.outputs.foxglove_channels import CellChannels, encode_jpeg, residual_mean_px
from clothd.outputs.recorder import RecordingStatus

log = logging.getLogger(__name__)

FRAME_QUEUE = 8  # frames waiting for the writer (~0.27 s at 30 Hz); a frame past that is dropped
CLIENT_BACKLOG = 150  # messages per WebSocket client: ~1 s of the five topics at 30 Hz
JOIN_TIMEOUT_S = 10.0
SERVER_STOP_S = 1.0
# The file's size is checked before each frame is written: the frame's JPEG, what the rest of a frame
# has taken at most so far (FIRST_FRAME_REST_BYTES before the first), and the summary a stop will write:
# the schemas and channels once, and a chunk index and message indexes per chunk (one chunk a frame).
# Measured with foxglove-sdk 0.30 (tests/test_foxglove_live.py checks the file stays within max_bytes):
# ~8 kB of summary (the five schemas and channels), ~130 bytes more per chunk; the reserve keeps about
# twice that.
FIRST_FRAME_REST_BYTES = 64_000
SUMMARY_BYTES = 20_000
SUMMARY_BYTES_PER_CHUNK = 250


class _CountingFile(io.RawIOBase):
    """The MCAP file as the writer sees it: keeps the file's size and the first write error (foxglove's
    own error says only that there was one)."""

    def __init__(self, path: Path) -> None:
        self._f = path.open("wb")
        self.bytes = 0
        self.error: OSError | None = None

    def writable(self) -> bool:
        return True

    def seekable(self) -> bool:
        return True

    def write(self, data: bytes | bytearray | memoryview) -> int:  # type: ignore[override]
        try:
            n = self._f.write(data)
        except OSError as err:
            raise self._failed(err) from None
        self.bytes = max(self.bytes, self._f.tell())  # the writer seeks back to patch records it wrote
        return n

    def seek(self, offset: int, whence: int = io.SEEK_SET) -> int:
        try:
            return self._f.seek(offset, whence)  # writes out what is buffered first
        except OSError as err:
            raise self._failed(err) from None

    def tell(self) -> int:
        return self._f.tell()

    def flush(self) -> None:
        try:
            self._f.flush()
        except OSError as err:
            raise self._failed(err) from None

    def _failed(self, err: OSError) -> OSError:
        self.error = self.error or err
        return err

    def close(self) -> None:
        try:
            super().close()  # flushes first
        finally:
            self._f.close()


@dataclass
class _Session:
    """One MCAP recording: what its status says. Written by both threads, under LiveFoxglove._lock. It is
    active until its file is finished: a stopped recording's file is complete."""

    path: Path
    max_bytes: int
    active: bool = True
    frames: int = 0
    bytes: int = 0
    dropped_frames: int = 0
    stopped_reason: str | None = None
    stop_requested: str | None = None  # why it was asked to stop, until the writer has finished it

    def status(self) -> RecordingStatus:
        return RecordingStatus(
            self.active,
            str(self.path),
            self.frames,
            self.bytes,
            self.max_bytes,
            self.stopped_reason,
            format=RecordingFormat.MCAP,
            dropped_frames=self.dropped_frames,
        )


@dataclass(frozen=True)
class _Frame:
    image: np.ndarray
    t_mono_s: float
    commands: ModuleCommands
    estimate: Estimate | None


@dataclass(frozen=True)
class _Start:
    session: _Session


@dataclass(frozen=True)
class _Stop:
    pass


class LiveFoxglove:
    """The server (when `server` is given and enabled) and MCAP recordings, fed by `add` from the tick."""

    def __init__(self, server: FoxgloveConfig | None) -> None:
        self._server_cfg = server if server is not None and server.enabled else None
        self._ctx = foxglove.Context()
        self.channels = CellChannels(self._ctx)
        self._server: foxglove.WebSocketServer | None = None
        # Monotonic capture times to Unix time, fixed once: log times stay monotonic with the frames.
        self._unix_offset_ns = time.time_ns() - time.monotonic_ns()
        self._lock = threading.Lock()
        self._wake = threading.Condition(self._lock)
        self._items: deque[_Frame | _Start | _Stop | None] = deque()
        self._queued_frames = 0
        self._session: _Session | None = None  # the newest recording: its status is the tick's
        self.dropped_frames = 0  # frames the writer was too far behind to take, since start
        self._thread = threading.Thread(target=self._run, name="foxglove-writer", daemon=True)
        # The writer thread's own: the open recording.
        self._writing: _Session | None = None
        self._writer: MCAPWriter | None = None
        self._file: _CountingFile | None = None
        self._rest_bytes: int | None = None  # the most a frame has taken besides its JPEG, once one has
        self._chunks = 0

    def start(self) -> None:
        """Start the writer and, when enabled, the server; ConfigError when its port cannot be had."""
        cfg = self._server_cfg
        if cfg is not None:
            try:
                self._server = foxglove.start_server(
                    name="clothd",
                    host=cfg.host,
                    port=cfg.port,
                    context=self._ctx,
                    message_backlog_size=CLIENT_BACKLOG,
                )
            except RuntimeError as err:
                raise ConfigError(
                    f"cannot serve Foxglove on {cfg.host}:{cfg.port}: {err}; "
                    "choose another address with foxglove.host/foxglove.port"
                ) from None
            log.info("serving Foxglove on ws://%s:%d", cfg.host, self._server.port)
        self._thread.start()

    def close(self, reason: str = "daemon stopped") -> None:
        """Stop any recording (its file is finished), the writer and the server."""
        self.stop_recording(reason)
        self._put(None)
        if self._thread.is_alive():
            self._thread.join(JOIN_TIMEOUT_S)
        if self._server is not None:
            # foxglove-sdk's stop waits for every client to take its last messages: one that never reads
            # would hold it until its connection dies. The process ends soon after; it need not wait.
            stopper = threading.Thread(target=self._server.stop, name="foxglove-stop", daemon=True)
            stopper.start()
            stopper.join(SERVER_STOP_S)
            if stopper.is_alive():
                log.warning("a Foxglove client did not read its last messages; not waiting for it")
            self._server = None

    # -- the tick's side: each call only queues ----------------------------------------------------

    def add(self, image: np.ndarray, t_mono_s: float, commands: ModuleCommands, est: Estimate | None) -> None:
        """A new frame, the commands in force with it and the estimate made from it."""
        with self._lock:
            session = self._session
            recording = session is not None and session.active and session.stop_requested is None
            if not recording and not self.channels.has_sinks():
                return  # nobody listens: not even queued
            if self._queued_frames >= FRAME_QUEUE:
                self.dropped_frames += 1
                if recording:
                    assert session is not None
                    session.dropped_frames += 1
                return
            self._queued_frames += 1
            self._items.append(_Frame(image, t_mono_s, commands, est))
            self._wake.notify()

    def start_recording(self, path: Path, max_bytes: int) -> None:
        """Record into the .mcap file `path` from the next frame on (a running one is stopped first)."""
        self.stop_recording("a new recording started")
        session = _Session(path, max_bytes)
        with self._lock:
            self._session = session
        self._put(_Start(session))

    def stop_recording(self, reason: str = "stopped") -> None:
        """Stop recording after the frames already given; the writer finishes the file, then the status
        turns inactive."""
        with self._lock:
            session = self._session
            if session is None or not session.active or session.stop_requested is not None:
                return
            session.stop_requested = reason
        self._put(_Stop())

    def recording_status(self) -> RecordingStatus | None:
        with self._lock:
            return None if self._session is None else self._session.status()

    def _put(self, item: _Start | _Stop | None) -> None:
        with self._lock:
            self._items.append(item)
            self._wake.notify()

    # -- the writer thread ---------------------------------------------------------------------------

    def _run(self) -> None:
        leave_realtime()  # a writer, not the tick: it must not take a core from the loop
        while True:
            with self._lock:
                while not self._items:
                    self._wake.wait()
                item = self._items.popleft()
                if isinstance(item, _Frame):
                    self._queued_frames -= 1
            if item is None:
                self._finish(None)
                return
            try:
                if isinstance(item, _Frame):
                    self._write_frame(item)
                elif isinstance(item, _Start):
                    self._open(item.session)
                else:
                    self._finish(None)
            except Exception as err:  # a bug here must not end the writer, nor the recording's status
                log.exception("Foxglove output failed")
                self._finish(f"the MCAP writer failed: {err}")

    def _open(self, session: _Session) -> None:
        self._finish(None)  # any recording before it
        try:
            self._file = _CountingFile(session.path)
            # Chunks end only where flush() ends them: one per frame (see the module's docstring).
            options = MCAPWriteOptions(chunk_size=None, compression_threads=0)
            self._writer = foxglove.open_mcap(self._file, context=self._ctx, writer_options=options)
        except (OSError, RuntimeError) as err:
            self._writing = session
            self._finish(f"cannot write {session.path}: {_why(err, self._file)}")
            return
        self._writing = session
        self._chunks = 0
        self._rest_bytes = None
        self._update_session()
        log.info("recording to %s", session.path)

    def _write_frame(self, frame: _Frame) -> None:
        log_time = round(frame.t_mono_s * 1e9) + self._unix_offset_ns
        jpeg = None
        if self._writer is not None or self.channels.camera.has_sinks():
            jpeg = encode_jpeg(frame.image)
        if self._writer is not None and self._file is not None and self._writing is not None:
            before = self._file.bytes
            needed = (
                before
                + (len(jpeg) if jpeg else 0)
                + (FIRST_FRAME_REST_BYTES if self._rest_bytes is None else self._rest_bytes)
                + SUMMARY_BYTES
                + SUMMARY_BYTES_PER_CHUNK * (self._chunks + 1)
            )
            if needed > self._writing.max_bytes:
                self._finish(f"size limit reached ({self._writing.max_bytes} bytes)")
        if jpeg is not None:
            self.channels.log_camera(jpeg, log_time)
        c = frame.commands
        self.channels.log_commands(c.speed_m_s, c.heading_rad, log_time)
        est = frame.estimate
        if est is not None:
            features, residual = residual_mean_px(est.meas_px, est.pred_px)
            self.channels.log_estimate(est.pose, est.nodes_m, features, residual, log_time)
        if self._writer is None or self._file is None:
            return
        before = self._file.bytes
        try:
            self._writer.flush()  # this frame's chunk, on disk
        except RuntimeError as err:
            self._finish(f"write failed: {_why(err, self._file)}")
            return
        self._chunks += 1
        rest = self._file.bytes - before - (len(jpeg) if jpeg else 0)
        self._rest_bytes = rest if self._rest_bytes is None else max(self._rest_bytes, rest)
        with self._lock:
            if self._writing is not None:
                self._writing.frames += 1
        self._update_session()

    def _update_session(self) -> None:
        with self._lock:
            if self._writing is not None and self._file is not None:
                self._writing.bytes = self._file.bytes

    def _finish(self, reason: str | None) -> None:
        """Close the open recording, if any: its summary is written. `reason` says why the writer stops it
        by itself (the size limit, a write error); None: as requested."""
        session, writer, f = self._writing, self._writer, self._file
        if session is None:
            return
        self._writing = self._writer = self._file = None
        problem = None
        if writer is not None:
            try:
                writer.close()
            except RuntimeError as err:  # the file holds its frames; only the summary is missing
                problem = f"summary not written: {_why(err, f)}"
        if f is not None:
            try:
                f.close()
            except OSError as err:
                problem = problem or f"closing failed: {_why(err)}"
        with self._lock:
            if f is not None:
                session.bytes = f.bytes
            if session.active:
                session.active = False
                session.stopped_reason = reason or session.stop_requested or "stopped"
            if problem is not None:
                session.stopped_reason = f"{session.stopped_reason}; {problem}"
        log.info("recording %s stopped: %s (%d frames)", session.path, session.stopped_reason, session.frames)


def _why(err: BaseException, f: _CountingFile | None = None) -> str:
    """The cause in words: the file's own write error when there was one, else the error's text."""
    cause = f.error if f is not None and f.error is not None else err
    if isinstance(cause, OSError):
        return cause.strerror or str(cause)
    return str(cause)
