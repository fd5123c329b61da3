"""`clothd bench estop`: from `POST /api/v1/estop` to the ESTOP frame on the serial line, against the
reference firmware's host build (deploy/firmware, `make firmware`).

`hwsim serve` gives the camera; `clothd run` drives `clothd-fw-host` through a relay pty
(tools/pty_relay.py) that timestamps every chunk it reads from the daemon, on this host's monotonic
clock. Each sample: a move (COMMANDs with speeds on the line), a pause of random length so the POST
lands anywhere in the tick, then the POST on a kept-alive connection (as the dashboard's), the clock
started just before the client sends it; then /estop/clear. Reported: POST to the ESTOP frame read off
the line, and POST to the response, median / p99 / max.
"""

from __future__ import annotations

import contextlib
import json
import os
import random
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import yaml

from clothd.drivers import wire
from clothd.errors import HardwareError
from clothd.tools.cli_args import Subparsers, positive_int
from clothd.tools.procfs import stop_group
from clothd.tools.pty_relay import PtyRelay

if TYPE_CHECKING:  # imported when the bench runs, not whenever the command line is read
    import httpx

FIRMWARE = Path(__file__).resolve().parents[2] / "deploy" / "firmware" / "build" / "host" / "clothd-fw-host"
N_MODULES = 48  # hwsim's cell, and the firmware's --modules
READY_TIMEOUT_S = 180.0
WIRE_TIMEOUT_S = 10.0
MOVE = {"mode": "move", "x_m": 0.05, "y_m": 0.03, "theta_rad": 0.25}
BAR_MS = 20.0  # an e-stop must be on the wire within this of the request (docs/benchmarks.md)


class Line:
    """The ESTOP frames the relay read from the daemon, each with when its chunk was read."""

    def __init__(self) -> None:
        self.splitter = wire.FrameSplitter()
        self.estops: list[float] = []
        self.arrived = threading.Condition()

    def seen(self, from_host: bool, data: bytes, t_s: float) -> None:
        if not from_host:
            return
        for packet in self.splitter.feed(data):
            with contextlib.suppress(ValueError):
                if wire.decode(packet).type == wire.MsgType.ESTOP:
                    with self.arrived:
                        self.estops.append(t_s)
                        self.arrived.notify_all()

    def first_after(self, t0: float) -> float:
        deadline = time.monotonic() + WIRE_TIMEOUT_S
        with self.arrived:
            while True:
                found = next((t for t in self.estops if t >= t0), None)
                if found is not None:
                    return found
                if not self.arrived.wait(max(0.0, deadline - time.monotonic())):
                    raise HardwareError(f"no ESTOP on the line within {WIRE_TIMEOUT_S:.0f} s of the POST")


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _until(check: Callable[[], bool], what: str, timeout_s: float = READY_TIMEOUT_S) -> None:
    deadline = time.monotonic() + timeout_s
    while not check():
        if time.monotonic() > deadline:
            raise HardwareError(f"{what}: not within {timeout_s:.0f} s")
        time.sleep(0.2)


@contextlib.contextmanager
def _process(cmd: list[str], **kw: Any) -> Iterator[subprocess.Popen[bytes]]:
    proc = subprocess.Popen(cmd, start_new_session=True, **kw)
    try:
        yield proc
    finally:
        stop_group(proc)


def _hwsim_ready(proc: subprocess.Popen[bytes]) -> dict[str, Any]:
    assert proc.stdout is not None
    line = b""
    while not line.startswith(b"{"):  # Taichi announces itself on stdout first
        line = proc.stdout.readline()
        if not line:
            raise HardwareError("hwsim serve exited before it was ready")
    return dict(json.loads(line))


def _daemon_config(work: Path, ready: dict[str, Any], port: str, api_port: int) -> Path:
    cfg = {
        "cameras": [
            {"name": c["name"], "source": c["video_url"], "calibration": c["camera_json"]}
            for c in ready["cameras"][:1]
        ],
        "stepper": {"port": port},
        "api": {"port": api_port},
        "opcua": {"endpoint": f"opc.tcp://127.0.0.1:{free_port()}/clothd/"},
        "recording": {"dir": str(work / "recordings")},
    }
    path = work / "clothd.yaml"
    path.write_text(yaml.safe_dump(cfg))
    return path


def _tracking(client: httpx.Client) -> bool:
    import httpx

    with contextlib.suppress(httpx.HTTPError, ValueError):
        s = client.get("/api/v1/status").json()
        return bool(s["state"] == "tracking" and s["link"]["state"] == "connected" and not s["estop"])
    return False


def _sample(client: httpx.Client, line: Line, rng: random.Random) -> tuple[float, float]:
    """One e-stop during a move: (POST to the ESTOP on the line, POST to the response), seconds."""
    _until(lambda: client.put("/api/v1/setpoint", json=MOVE).status_code == 200, "a move accepted", 60)
    time.sleep(0.2 + rng.random() * 0.1)
    t0 = time.monotonic()
    client.post("/api/v1/estop").raise_for_status()
    answered = time.monotonic()
    on_line = line.first_after(t0)
    client.post("/api/v1/estop/clear").raise_for_status()
    _until(lambda: _tracking(client), "the daemon tracking again after the clear", 60)
    return on_line - t0, answered - t0


def run_bench(samples: int, firmware: Path = FIRMWARE, seed: int = 0) -> dict[str, Any]:
    import httpx

    if not firmware.exists():
        raise HardwareError(f"{firmware} is not built: make firmware (or make -C deploy/firmware host)")
    rng = random.Random(seed)
    line = Line()
    load_before = os.getloadavg()[0]
    with tempfile.TemporaryDirectory(prefix="clothd-bench-estop-") as tmp:
        work = Path(tmp)
        hwsim = [sys.executable, "-m", "hwsim.cli", "serve", "--scenario", "cell", "--state-dir", str(work)]
        fw_cmd = [str(firmware), "--link", str(work / "ttyFW"), "--modules", str(N_MODULES)]
        with (
            _process(hwsim, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL) as sim,
            _process(
                [*fw_cmd, "--exit-on-stdin-eof"],
                stdin=subprocess.PIPE,
                stdout=subprocess.DEVNULL,
                stderr=subprocess.DEVNULL,
            ),
        ):
            ready = _hwsim_ready(sim)
            _until(lambda: (work / "ttyFW").exists(), "clothd-fw-host's pty", 10)
            relay = PtyRelay(work / "ttyFW", work / "ttyRELAY")
            relay.on_read = line.seen
            api_port = free_port()
            config = _daemon_config(work, ready, str(work / "ttyRELAY"), api_port)
            daemon = [sys.executable, "-m", "clothd.cli", "run", "--config", str(config)]
            try:
                with (
                    _process(daemon, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL),
                    httpx.Client(base_url=f"http://127.0.0.1:{api_port}", timeout=10) as client,
                ):
                    _until(lambda: _tracking(client), "the daemon tracking with the link up")
                    taken = [_sample(client, line, rng) for _ in range(samples)]
            finally:
                relay.close()
    wire_ms = np.array([t[0] for t in taken]) * 1e3
    answer_ms = np.array([t[1] for t in taken]) * 1e3
    return {
        "firmware": firmware.name,
        "samples": samples,
        **{f"post_to_wire_{k}_ms": float(f(wire_ms)) for k, f in _STATS.items()},
        **{f"post_to_response_{k}_ms": float(f(answer_ms)) for k, f in _STATS.items()},
        "within_bar": int(np.sum(wire_ms <= BAR_MS)),
        "load_avg_1min": [load_before, os.getloadavg()[0]],  # this machine's load, before and after
        "bar_ms": BAR_MS,
    }


_STATS: dict[str, Callable[[np.ndarray], Any]] = {
    "p50": np.median,
    "p99": lambda a: np.percentile(a, 99),
    "max": np.max,
}


def format_result(r: dict[str, Any]) -> str:
    def row(what: str, key: str) -> str:
        p50, p99, top = (r[f"{key}_{k}_ms"] for k in _STATS)
        return f"  {what:<28} p50 {p50:6.2f} ms   p99 {p99:6.2f} ms   max {top:6.2f} ms"

    return "\n".join(
        [
            f"e-stop, clothd run -> {r['firmware']} ({r['samples']} e-stops during a move, kept-alive POST)",
            row("POST to ESTOP on the line", "post_to_wire"),
            row("POST to its response", "post_to_response"),
            f"  {r['within_bar']} of {r['samples']} on the line within {r['bar_ms']:.0f} ms; "
            "load average {:.1f} before, {:.1f} after".format(*r["load_avg_1min"]),
        ]
    )


def _cmd(args: Any) -> int:
    signal.signal(signal.SIGTERM, signal.default_int_handler)  # a stop still stops the children
    result = run_bench(args.samples, args.firmware, args.seed)
    print(format_result(result))
    if args.json is not None:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(result, indent=2) + "\n")
        print(f"written {args.json}")
    return 0


def add_estop(bsub: Subparsers) -> None:
    be = bsub.add_parser("estop", help="POST /api/v1/estop to the ESTOP frame on the line (host firmware)")
    be.add_argument("--samples", type=positive_int, default=50, help="e-stops to take (default 50)")
    be.add_argument("--firmware", type=Path, default=FIRMWARE, help="the host build of deploy/firmware")
    be.add_argument("--seed", type=int, default=0, help="the pauses' random seed")
    be.add_argument("--json", type=Path, default=Path("out/bench/estop.json"), help="the figures as JSON")
    be.set_defaults(func=_cmd)
