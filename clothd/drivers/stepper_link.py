"""The host end of the stepper link (protocol: docs/serial-protocol.md), on asyncio.

Commands are latest-value: every tick sends a fresh COMMAND; only the newest unacknowledged one is worth
retransmitting, at most `max_retransmits` times, after which the link is declared lost, closed and
reopened with backoff. The controller's own watchdog stops the modules while the host is away.
A COMMAND goes out only onto an idle transport: one that still holds earlier bytes (the line is slower
than the ticks) would hold this one behind them, stale before it left, so it is dropped and the next tick
sends a fresh one. The emergency stop discards whatever has not left yet (the transport's buffer and the
port driver's output queue: stale commands), writes a delimiter that ends any frame the discard cut
midway, and the ESTOP right after it; it is repeated until the controller acknowledges it with its
e-stop flag set.
"""

from __future__ import annotations

import asyncio
import contextlib
import itertools
import logging
import math
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass

import serial_asyncio_fast

from clothd.config import StepperConfig
from clothd.config.stepper import CELL_MODULES
from clothd.core.messages import ModuleCommands
from clothd.drivers import wire
from clothd.drivers.ports import ControllerFault, Handover, LinkCounters
from clothd.drivers.serial_transport import discard_unsent, line_busy
from clothd.errors import HardwareError

log = logging.getLogger(__name__)

ESTOP_REPEAT_S = 0.02
CLOCK_SLACK_S = 0.001  # a wake this much before its time counts as on time (the loop's clock granularity)
# Woken this much later than asked, the link's thread was held up, not the controller silent.
HELD_UP_S = 0.01
REREAD_S = 0.002  # then wait this long, through one wait for the port, before judging the silence
STOP_DRAIN_TIMEOUT_S = 0.2  # on the way out, wait this long for the all-stop to leave the port
FAULTS_KEPT = 20


@dataclass
class _Pending:
    seq: int
    packet: bytes
    sent_t_s: float


class StepperLink:
    """The ModuleLink on a serial port. `run()` is the connection task; the other methods never block."""

    def __init__(
        self,
        cfg: StepperConfig,
        n_modules: int,
        clock: Callable[[], float] = time.monotonic,
        n_modules_from: str = CELL_MODULES,
    ) -> None:
        self.cfg = cfg
        self.n_modules = n_modules
        self.n_modules_from = n_modules_from  # where n_modules comes from, in words, for a mismatch
        self.clock = clock
        self.counters = LinkCounters()
        self.faults: deque[ControllerFault] = deque(maxlen=FAULTS_KEPT)
        self.state = "starting"  # starting (never up yet) | connecting | connected | disconnected
        self._was_up = False
        self.last_error: str | None = None
        self.firmware: str | None = None
        self.controller_flags = 0
        self._estop_latched = False
        self._clear_seq: int | None = None  # an ESTOP_CLEAR not answered: earlier answers show the latch
        self._clear_on_connect = False  # an e-stop cleared while the link was down: the controller is told
        self._estop_sent_s = -math.inf  # when an ESTOP was last written: it is repeated ESTOP_REPEAT_S apart
        self._writer: asyncio.StreamWriter | None = None
        self._seqs = itertools.count(1)
        self._pending: _Pending | None = None  # the newest unacknowledged COMMAND
        # Liveness: when the oldest message still waiting for a reply was sent (None: every one answered),
        # and how often the newest command has been sent again since. A fresh command every tick replaces
        # the pending one, so the age of the last reply, not of one command, says whether the controller
        # is there.
        self._unanswered_since_s: float | None = None
        self._retries = 0
        self._waiters: dict[int, asyncio.Future[wire.Message]] = {}
        self._lost = asyncio.Event()
        self._stopping = False
        self.on_fault: Callable[[ControllerFault], None] | None = None  # each FAULT, as it arrives
        self.on_lost: Callable[[], None] | None = None  # the link was up and is lost

    # -- public -----------------------------------------------------------------------------------

    @property
    def connected(self) -> bool:
        return self.state == "connected"

    @property
    def estopped(self) -> bool:
        """The e-stop is latched: nothing moves until estop_clear()."""
        return self._estop_latched

    @property
    def controller_estopped(self) -> bool:
        return bool(self.controller_flags & wire.FLAG_ESTOP)

    def send_commands(self, commands: ModuleCommands) -> Handover:
        """Send this tick's module commands. Not running: the link is down (the controller's watchdog then
        stops the modules) or the e-stop is latched, when a PING goes instead, which keeps the
        controller's watchdog fed and the link's liveness measured. Not fresh: the line still holds what
        went before, which stays in force."""
        if not self.connected:
            return Handover.of(False, False, self.n_modules)
        if line_busy(self._writer):
            return Handover.of(not self._estop_latched, False, self.n_modules)
        if self._estop_latched:
            self._write(wire.encode(wire.MsgType.PING, self._next_seq()), expect_reply=True)
            return Handover.of(False, False, self.n_modules)
        seq = self._next_seq()
        payload = wire.command_payload(commands.speed_m_s, commands.heading_rad)
        packet = wire.encode(wire.MsgType.COMMAND, seq, payload)
        self._pending = _Pending(seq, packet, self.clock())
        self._write(packet, expect_reply=True)
        return Handover.of(True, True, self.n_modules)

    def estop(self) -> None:
        """Stop every module now: the commands not yet gone are discarded, so the ESTOP goes next on the
        line; repeated until acknowledged."""
        self._estop_latched = True
        self._clear_on_connect = False
        self._clear_seq = None
        self._pending = None
        if self.connected:  # (while connecting, what waits is the HELLO, and the handshake sends ESTOP)
            discard_unsent(self._writer)
        self._send_estop(lead=wire.DELIMITER)

    def estop_clear(self) -> None:
        """Release the e-stop; while the link is down, as soon as it is up again (the controller keeps its
        latch across a lost link, and would otherwise refuse every command)."""
        self._estop_latched = False
        if self.connected:
            self._send_clear()
        else:
            self._clear_on_connect = True

    def _send_estop(self, lead: bytes = b"", expect_reply: bool = False) -> None:
        self._write(lead + wire.encode(wire.MsgType.ESTOP, self._next_seq()), expect_reply=expect_reply)
        self._estop_sent_s = self.clock()

    def _send_clear(self) -> None:
        self._clear_seq = self._next_seq()
        self._write(wire.encode(wire.MsgType.ESTOP_CLEAR, self._clear_seq))

    async def stop(self) -> None:
        """Stop the modules, then close the port."""
        self._stopping = True
        if self.connected:
            self._write(self._all_stop_packet())
            with contextlib.suppress(Exception):
                assert self._writer is not None
                await asyncio.wait_for(self._writer.drain(), STOP_DRAIN_TIMEOUT_S)
        self._close()

    async def run(self) -> None:
        """Connect, serve, and reconnect with backoff until cancelled."""
        delay = self.cfg.reconnect_initial_s
        while not self._stopping:
            try:
                await self._session()
                delay = self.cfg.reconnect_initial_s
            except (TimeoutError, OSError, HardwareError) as err:
                self._set_error(str(err) or type(err).__name__)
            except Exception as err:  # a bug here must not end the link for good, unseen: tried again
                log.exception("stepper link on %s failed", self.cfg.port)
                self._set_error(f"{type(err).__name__}: {err}")
            finally:
                self._close()
            if self._stopping:
                return
            await asyncio.sleep(delay)
            delay = min(delay * 2, self.cfg.reconnect_max_s)
            if self._was_up:  # the tries before the first connection are the start, not reconnects
                self.counters.reconnects += 1

    # -- the connection ---------------------------------------------------------------------------

    async def _session(self) -> None:
        self._down("connecting")
        reader, writer = await asyncio.wait_for(
            serial_asyncio_fast.open_serial_connection(url=self.cfg.port, baudrate=self.cfg.baud), 2.0
        )
        self._writer = writer
        self._lost.clear()
        reading = asyncio.create_task(self._read(reader))
        try:
            await self._handshake()
            self.state = "connected"
            self._was_up = True
            self.last_error = None
            log.info("stepper link up on %s (%s)", self.cfg.port, self.firmware)
            supervising = asyncio.create_task(self._supervise())
            try:
                await self._lost.wait()
            finally:
                supervising.cancel()
        finally:
            reading.cancel()
            with contextlib.suppress(asyncio.CancelledError, Exception):
                await reading
        if not self._stopping:
            raise HardwareError(self.last_error or f"stepper link on {self.cfg.port} lost")

    async def _handshake(self) -> None:
        for _ in range(3):
            seq = self._next_seq()
            waiter: asyncio.Future[wire.Message] = asyncio.get_running_loop().create_future()
            self._waiters[seq] = waiter
            self._write(wire.encode(wire.MsgType.HELLO, seq, wire.hello_payload()))
            try:
                reply = await asyncio.wait_for(asyncio.shield(waiter), self.cfg.handshake_timeout_s)
            except TimeoutError:
                continue
            finally:
                self._waiters.pop(seq, None)
            if reply.type == wire.MsgType.NACK:
                raise HardwareError(
                    f"controller on {self.cfg.port} refused protocol v{wire.PROTOCOL_VERSION}"
                )
            try:
                if reply.type != wire.MsgType.HELLO_ACK:
                    raise wire.WireError(f"message type {reply.type:#04x} where its HELLO_ACK belongs")
                hello = wire.parse_hello_ack(reply.payload)
            except wire.WireError as err:
                raise HardwareError(f"controller on {self.cfg.port} answered HELLO wrongly: {err}") from None
            if hello.version != wire.PROTOCOL_VERSION:
                raise HardwareError(
                    f"controller on {self.cfg.port} speaks protocol v{hello.version}, "
                    f"clothd speaks v{wire.PROTOCOL_VERSION}"
                )
            if hello.n_modules != self.n_modules:
                raise HardwareError(
                    f"controller on {self.cfg.port} drives {hello.n_modules} modules, "
                    + self.n_modules_from.format(n=self.n_modules)
                )
            self.firmware = hello.firmware
            if self._estop_latched:
                self._send_estop()
            elif self._clear_on_connect:
                self._send_clear()
            self._clear_on_connect = False
            return
        if self.counters.invalid:
            raise HardwareError(
                f"the device on {self.cfg.port} answers, but not in the clothd stepper protocol "
                f"({self.counters.invalid} invalid frames); is it the right port?"
            )
        raise HardwareError(f"no answer to HELLO from {self.cfg.port}")

    async def _read(self, reader: asyncio.StreamReader) -> None:
        splitter = wire.FrameSplitter()
        try:
            while True:
                data = await reader.read(4096)
                if not data:
                    self._lose("the serial port closed")
                    return
                overflows = splitter.overflows
                packets = splitter.feed(data)
                self.counters.invalid += splitter.overflows - overflows  # overlong: dropped whole
                for packet in packets:
                    try:
                        self._dispatch(wire.decode(packet))
                    except wire.WireError as err:
                        self.counters.invalid += 1
                        log.debug("invalid frame: %s", err)
        except OSError as err:
            self._lose(f"serial read failed: {err.strerror or err}")

    def _dispatch(self, frame: wire.Message) -> None:
        # A FAULT answers nothing: its seq is the controller's own counter, not a request's.
        waiter = None if frame.type == wire.MsgType.FAULT else self._waiters.get(frame.seq)
        if waiter is not None and not waiter.done():
            waiter.set_result(frame)
        if frame.type in (wire.MsgType.ACK, wire.MsgType.NACK):  # an answer: the controller is there
            self._unanswered_since_s = None
            self._retries = 0
        if frame.type == wire.MsgType.ACK:
            self.controller_flags = wire.parse_ack(frame.payload)
            self.counters.acked += 1
            p = self._pending
            if p is not None and p.seq == frame.seq:
                self.counters.rtt_ms.append((self.clock() - p.sent_t_s) * 1e3)
                self._pending = None
            self._mirror_latch(frame.seq, bool(self.controller_flags & wire.FLAG_ESTOP))
        elif frame.type == wire.MsgType.NACK:
            self.counters.nacked += 1
            if self._pending is not None and self._pending.seq == frame.seq:
                self._pending = None
            self._mirror_latch(frame.seq, frame.payload[:1] == bytes([wire.NACK_ESTOPPED]))
        elif frame.type == wire.MsgType.FAULT:
            fault = wire.parse_fault(frame.payload)
            self.counters.faults += 1
            log.warning("controller fault %d on module %d: %s", fault.code, fault.module, fault.text)
            report = ControllerFault(time.time(), fault.code, fault.module, fault.text)
            self.faults.append(report)
            if self.on_fault is not None:
                self.on_fault(report)

    def _mirror_latch(self, seq: int, controller_latched: bool) -> None:
        """A controller latched while the host is not (its e-stop input opened and the FAULT was lost, it
        latched before this link came up, or it refused a clear while its input stays open): the host
        latches too and reports it as that input's FAULT, so no setpoint waits to run on a clear. An
        answer to a message sent before the last clear still shows the old latch, and counts for nothing."""
        if self._clear_on_connect:
            return  # a clear waits for the link to come up: every answer until then predates it
        if self._clear_seq is not None:
            if wire.seq_before(seq, self._clear_seq):
                return
            # The clear's answer, or (it was lost on the line) one to a message after it: the controller
            # answers in order, so this shows the latch as the clear left it.
            self._clear_seq = None
        if not controller_latched or self._estop_latched:
            return
        self.estop()
        text = "the controller's e-stop is latched: its e-stop input is open, or it refused the clear"
        report = ControllerFault(time.time(), wire.FAULT_ESTOP_INPUT, wire.WHOLE_CONTROLLER, text)
        log.warning("%s", text)
        self.faults.append(report)
        if self.on_fault is not None:
            self.on_fault(report)

    async def _supervise(self) -> None:
        """Watch the controller's answers: each `ack_timeout_s` without one, send the newest unanswered
        command again; after `max_retransmits` of them, the link is lost. Repeat an unacknowledged e-stop."""
        cfg = self.cfg
        lost_after_s = cfg.ack_timeout_s * (cfg.max_retransmits + 1)
        min_wait_s = 0.0
        while True:
            # Wake for the next retransmit, ESTOP or the deadline exactly, not on a coarse grid: the
            # deadline is a safety figure. (An ESTOP on every pass had flooded the controller's answers.)
            now_s = self.clock()
            wake_s = now_s + ESTOP_REPEAT_S
            if self._estop_latched and not self.controller_estopped:
                wake_s = min(wake_s, self._estop_sent_s + ESTOP_REPEAT_S)
            since = self._unanswered_since_s
            if since is not None:
                wake_s = min(wake_s, since + lost_after_s)
                if self._pending is not None:
                    wake_s = min(wake_s, since + cfg.ack_timeout_s * (self._retries + 1))
            wait_s = max(wake_s - now_s, min_wait_s)
            wake_s = now_s + wait_s
            await asyncio.sleep(wait_s)
            held_up = self.clock() - wake_s > HELD_UP_S
            min_wait_s = 0.0
            repeat_at_s = self._estop_sent_s + ESTOP_REPEAT_S - CLOCK_SLACK_S
            if self._estop_latched and not self.controller_estopped and self.clock() >= repeat_at_s:
                self._send_estop(expect_reply=True)
            since = self._unanswered_since_s
            if since is None:
                continue
            silent_s = self.clock() - since
            if held_up and silent_s < 2 * lost_after_s:
                # This thread woke late (a loaded PC, the GIL): an answer may be waiting in the port,
                # unread. One pass of the event loop reads it before the silence is judged.
                min_wait_s = REREAD_S
                continue
            if silent_s >= lost_after_s:
                self._lose(
                    f"no answer from the controller on {cfg.port} for {silent_s * 1e3:.0f} ms "
                    f"({self._retries} retransmits)"
                )
                return
            p = self._pending
            if p is not None and silent_s >= cfg.ack_timeout_s * (self._retries + 1):
                self._retries += 1
                p.sent_t_s = self.clock()
                self.counters.retransmitted += 1
                self._write(p.packet, count=False)

    # -- helpers ----------------------------------------------------------------------------------

    def _write(self, packet: bytes, count: bool = True, expect_reply: bool = False) -> None:
        if self._writer is None:
            return
        try:
            self._writer.write(packet)
        except (OSError, RuntimeError) as err:
            self._lose(f"serial write failed: {err}")
            return
        if count:
            self.counters.sent += 1
        if expect_reply and self._unanswered_since_s is None:
            self._unanswered_since_s = self.clock()

    def _next_seq(self) -> int:
        return next(self._seqs) & 0xFFFF

    def _lose(self, reason: str) -> None:
        """Declare the link lost: all-stop written on the way out (a controller that hears but cannot
        answer stops at once; one that hears nothing stops on its watchdog), then reconnect."""
        was_connected = self.state == "connected"
        self._down("disconnected")  # from now on no command goes out
        if was_connected:
            log.warning("stepper link lost: %s", reason)
            self.counters.losses += 1
            self._write(self._all_stop_packet())
        self.last_error = reason
        self._lost.set()
        if was_connected and self.on_lost is not None:
            self.on_lost()

    def _all_stop_packet(self) -> bytes:
        stop = ModuleCommands.all_stop(self.n_modules)
        payload = wire.command_payload(stop.speed_m_s, stop.heading_rad)
        return wire.encode(wire.MsgType.COMMAND, self._next_seq(), payload)

    def _set_error(self, reason: str) -> None:
        if reason != self.last_error:
            log.warning("stepper link: %s", reason)
        self.last_error = reason

    def _down(self, state: str) -> None:
        """Not connected: `state`, or `starting` while the link has never been up."""
        self.state = state if self._was_up else "starting"

    def _close(self) -> None:
        self._down("disconnected")
        if self._clear_seq is not None:  # a clear not answered may never have left: sent again on connect
            self._clear_seq = None
            self._clear_on_connect = True
        self._pending = None
        self._unanswered_since_s = None
        self._retries = 0
        self.controller_flags = 0
        if self._writer is not None:
            with contextlib.suppress(Exception):
                self._writer.close()
            self._writer = None
