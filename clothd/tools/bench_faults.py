"""`clothd bench faults`: faults injected into a running cell, measured from outside.

hwsim serve is the cell; a pty relay (pty_relay.py) sits between its controller and `clothd run`, which
is configured as on a real cell. For each fault, with the modules moving the cloth: the time until the
daemon reports it (its status), the time until every module of hwsim's table stands still, and, after
the fault has cleared and the daemon is back, whether anything moved again without a new command.
Then POST /reset is sent `resets` times, and the compute process's resident memory after 10 and after
all of them is read from /proc.
"""

from __future__ import annotations

import json
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import httpx
import yaml
from tqdm import tqdm

from clothd.loop.process_names import API_PROCESS_NAME
from clothd.tools.bench_loop import free_port
from clothd.tools.procfs import rss_mb, spawned_children
from clothd.tools.pty_relay import PtyRelay

POLL_S = 0.005
STILL_M_S = 1e-3  # a module slower than this stands still
WATCH_AFTER_S = 3.0  # how long to watch for a restart once the fault has cleared
RESET_RATE_HZ = 10.0  # slower than the camera's 15 frames/s, so that every reset is carried out
START_UP_S = 2.0  # let the first ticks' start-up pass
MOVE = {"mode": "move", "x_m": 0.06, "y_m": 0.02, "theta_rad": 0.15}


@dataclass(frozen=True)
class FaultRow:
    fault: str
    detect_ms: float | None  # until the status showed it
    stop_ms: float | None  # until every module stood still
    reported: str  # what the status said
    restarted: bool  # a module moved again, or the mode left idle, without a command


class Cell:
    """hwsim serve, the relay on its controller, and clothd run on the relay."""

    def __init__(self, work: Path) -> None:
        self.sim = subprocess.Popen(
            [sys.executable, "-m", "hwsim.cli", "serve", "--state-dir", str(work / "sim")],
            stdout=subprocess.PIPE,
            stderr=subprocess.DEVNULL,
            text=True,
        )
        assert self.sim.stdout is not None
        line = ""
        while not line.startswith("{"):  # Taichi announces itself on stdout first
            line = self.sim.stdout.readline()
            if not line:
                raise RuntimeError("hwsim serve exited before it was ready")
        self.ready = json.loads(line)
        self.relay = PtyRelay(self.ready["serial"], work / "ttyRELAY")
        port = free_port()
        cfg = {
            "camera": {"source": self.ready["video_url"], "calibration": self.ready["camera_json"]},
            "stepper": {"port": str(self.relay.link_path)},
            "api": {"port": port},
            "opcua": {"endpoint": f"opc.tcp://127.0.0.1:{free_port()}/clothd/"},  # never the shared 4840
        }
        (work / "clothd.yaml").write_text(yaml.safe_dump(cfg))
        self.daemon = subprocess.Popen(
            [sys.executable, "-m", "clothd.cli", "run", "--config", str(work / "clothd.yaml")],
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
        )
        self.api = f"http://127.0.0.1:{port}/api/v1"
        self.http = httpx.Client(timeout=5.0)

    def close(self) -> None:
        for proc in (self.daemon, self.sim):
            proc.terminate()
            try:
                proc.wait(timeout=20)
            except subprocess.TimeoutExpired:
                proc.kill()
        self.relay.close()
        self.http.close()

    def status(self) -> dict[str, Any]:
        return dict(self.http.get(f"{self.api}/status").json())

    def post(self, url: str, **params: float) -> None:
        self.http.post(url, params=params).raise_for_status()

    def truth(self) -> dict[str, Any]:
        return dict(self.http.get(f"{self.ready['http']}/truth").json())

    def moving(self) -> bool:
        return max(map(abs, self.truth()["module_speed_m_s"])) > STILL_M_S

    def ready_to_move(self) -> bool:
        try:
            s = self.status()
        except httpx.HTTPError:
            return False
        return s["state"] == "tracking" and s["link"]["state"] == "connected" and not s["estop"]

    def compute_pid(self) -> int:
        """The compute process: the daemon's spawned child that is not the API process."""
        for pid, name in spawned_children(self.daemon.pid).items():
            if name != API_PROCESS_NAME:
                return pid
        raise RuntimeError("no compute process found under the daemon")


def _until(check: Callable[[], bool], timeout_s: float, what: str) -> float:
    t0 = time.monotonic()
    while not check():
        if time.monotonic() - t0 > timeout_s:
            raise RuntimeError(f"{what}: not within {timeout_s} s")
        time.sleep(POLL_S)
    return time.monotonic() - t0


def _reported(s: dict[str, Any]) -> str | None:
    if s["estop"]:
        return "estop latched"
    if s["link"]["state"] != "connected":
        return f"link {s['link']['state']}: {s['link']['last_error']}"
    return s["halt_reason"]


def _fault(cell: Cell, name: str, inject: Callable[[], None], clear: Callable[[], None]) -> FaultRow:
    _until(cell.ready_to_move, 60, "the daemon ready to move")
    cell.http.put(f"{cell.api}/setpoint", json=MOVE).raise_for_status()
    _until(cell.moving, 10, "modules running")
    t0, t0_unix = time.monotonic(), time.time()
    inject()
    detect = stop = None
    reported = ""
    deadline = t0 + 10.0
    while (detect is None or stop is None) and time.monotonic() < deadline:
        s = cell.status() if detect is None else None
        if s is not None and (text := _reported(s)) is not None:
            # When the daemon published it (its own clock, this host's), not when the poll saw it.
            detect, reported = s["t_unix_s"] - t0_unix, text
        if stop is None and not cell.moving():
            stop = time.monotonic() - t0
        time.sleep(POLL_S)
    clear()
    _until(lambda: cell.ready_to_move() or cell.status()["estop"], 60, "the daemon back")
    watch_until = time.monotonic() + WATCH_AFTER_S
    restarted = False
    while time.monotonic() < watch_until and not restarted:
        restarted = cell.moving() or cell.status()["mode"] != "idle"
        time.sleep(0.05)
    return FaultRow(name, _ms(detect), _ms(stop), reported, restarted)


def _ms(seconds: float | None) -> float | None:
    return None if seconds is None else seconds * 1e3


def run_bench(resets: int = 500) -> dict[str, Any]:
    with tempfile.TemporaryDirectory(prefix="clothd-faults-") as tmp:
        cell = Cell(Path(tmp))
        try:
            _until(cell.ready_to_move, 180, "the daemon tracking with the link up")
            time.sleep(START_UP_S)
            relay = cell.relay

            def post(url: str, **params: float) -> Callable[[], None]:
                return lambda: cell.post(url, **params)

            def flag(name: str, value: bool) -> Callable[[], None]:
                return lambda: setattr(relay, name, value)

            print("injecting faults ...", flush=True)
            rows = [
                _fault(
                    cell,
                    "controller silent (replies lost)",
                    flag("drop_replies", True),
                    flag("drop_replies", False),
                ),
                _fault(
                    cell,
                    "commands lost on the way",
                    flag("drop_commands", True),
                    flag("drop_commands", False),
                ),
                _fault(
                    cell,
                    "camera lost for 2 s",
                    post(f"{cell.ready['http']}/camera/drop", seconds=2),
                    lambda: None,
                ),
                _fault(cell, "e-stop", post(f"{cell.api}/estop"), post(f"{cell.api}/estop/clear")),
            ]
            memory = _resets(cell, resets)
        finally:
            cell.close()
    return {"faults": [asdict(r) for r in rows], "resets": memory}


def _resets(cell: Cell, n: int) -> dict[str, Any]:
    _until(cell.ready_to_move, 60, "the daemon ready")
    pid = cell.compute_pid()
    before = cell.status()["timing"]
    rss: dict[str, float] = {}
    for k in tqdm(range(1, n + 1), desc="resets", disable=None, leave=False):
        cell.post(f"{cell.api}/reset")
        time.sleep(1.0 / RESET_RATE_HZ)
        if k == 10:
            rss["after_10_mb"] = rss_mb(pid)
    time.sleep(1.0)
    rss[f"after_{n}_mb"] = rss_mb(pid)
    after = cell.status()["timing"]
    compute = after["stages"].get("compute", {})
    return {
        "resets": n,
        **rss,
        "growth_mb": rss[f"after_{n}_mb"] - rss["after_10_mb"],
        "compute_overruns": after["compute_overruns"] - before["compute_overruns"],
        "compute_max_ms": compute.get("max_ms"),
    }


def format_result(r: dict[str, Any]) -> str:
    out = [
        "clothd bench faults (hwsim serve, a pty relay on its controller, clothd run)",
        f"  {'fault':<34} {'detected':>10} {'stopped':>10}  restarted  reported",
    ]
    for f in r["faults"]:
        det = "n/a" if f["detect_ms"] is None else f"{f['detect_ms']:.0f} ms"
        stop = "n/a" if f["stop_ms"] is None else f"{f['stop_ms']:.0f} ms"
        restarted = "YES" if f["restarted"] else "no"
        out.append(f"  {f['fault']:<34} {det:>10} {stop:>10}  {restarted:<9}  {f['reported']}")
    m = r["resets"]
    n = m["resets"]
    out.append(
        f"  {n} resets: compute RSS {m['after_10_mb']:.1f} MB after 10, "
        f"{m[f'after_{n}_mb']:.1f} MB after {n} "
        f"({m['growth_mb']:+.1f} MB; bar 20 MB); compute overruns {m['compute_overruns']}, "
        f"compute max {m['compute_max_ms']:.0f} ms"
    )
    return "\n".join(out)
