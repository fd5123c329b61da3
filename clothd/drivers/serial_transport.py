"""What the stepper link asks of its serial transport (serial_asyncio_fast's) beyond writing to it."""

from __future__ import annotations

import asyncio
import contextlib


def line_busy(writer: asyncio.StreamWriter | None) -> bool:
    """The transport still holds bytes the port has not taken."""
    transport = writer.transport if writer is not None else None
    return transport is not None and transport.get_write_buffer_size() > 0


def discard_unsent(writer: asyncio.StreamWriter | None) -> None:
    """Drop the bytes not yet on the line: the transport's buffer (serial_asyncio_fast's flush()) and the
    port driver's output queue (tcflush; on a pty, what the other end has not read). What they cut
    midway, the next delimiter ends."""
    transport = writer.transport if writer is not None else None
    if transport is None:
        return
    with contextlib.suppress(Exception):
        transport.flush()  # type: ignore[attr-defined]
    port = transport.get_extra_info("serial")
    with contextlib.suppress(Exception):
        port.reset_output_buffer()
