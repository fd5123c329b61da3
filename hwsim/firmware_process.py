"""hwsim's stepper controller in a process of its own, the stand-in for the cell's microcontroller.

A microcontroller answers the host whatever the PC runs. A firmware thread inside hwsim did not: it
waited for the GIL and for the world's lock while the world stepped the cloth and rendered the camera,
and on a loaded PC the host's link timed out on the simulator, not on itself. Here the firmware has a
process, and where Linux permits it the real-time class (SCHED_FIFO, FIRMWARE_RT_PRIORITY): it sleeps
in select() between frames, so it never takes a core from anything for long. The world reads what it
set through hwsim.drive_bus. hwsim talks to it on its stdin, one JSON object a line; when hwsim goes,
stdin closes and so does the firmware.

    python -m hwsim.firmware_process LINK_PATH BUS_PATH N_MODULES
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import threading
from pathlib import Path

import numpy as np

from hwsim.drive_bus import DriveBus
from hwsim.firmware import Counters, Firmware

FIRMWARE_RT_PRIORITY = 40
START_TIMEOUT_S = 30.0


class FirmwareProcess:
    """Starts the firmware's process and waits until its pty is behind `link_path`. `modules`: the table's
    module ids it drives, by its own index (a cell of several controllers); default 0..n_modules-1."""

    def __init__(
        self, n_modules: int, link_path: Path, bus_path: Path, modules: np.ndarray | None = None
    ) -> None:
        self.link_path = link_path
        self.modules = np.arange(n_modules) if modules is None else np.asarray(modules, dtype=int)
        self.bus = DriveBus(bus_path, n_modules, create=True)
        cmd = [sys.executable, "-m", "hwsim.firmware_process", str(link_path), str(bus_path), str(n_modules)]
        self.process = subprocess.Popen(cmd, stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
        self._lock = threading.Lock()  # HTTP handlers tell it things from their own threads
        assert self.process.stdout is not None
        if self.process.stdout.readline().strip() != "ready":
            self.stop()
            raise RuntimeError(f"hwsim's firmware process did not start (exit code {self.process.poll()})")

    def counters(self) -> Counters:
        return self.bus.counters()

    def unplug(self, seconds: float) -> None:
        """Pull the cable for `seconds`: the host sees the port vanish, the modules stop on the watchdog."""
        self._tell({"unplug_s": seconds})

    def report_fault(self, code: int, module: int, text: str) -> None:
        self._tell({"fault": [code, module, text]})

    def stop(self) -> None:
        if self.process.stdin is not None:
            self.process.stdin.close()  # its cue to stop
        try:
            self.process.wait(timeout=3)
        except subprocess.TimeoutExpired:
            self.process.kill()
            self.process.wait()

    def _tell(self, message: dict[str, object]) -> None:
        assert self.process.stdin is not None
        with self._lock:
            self.process.stdin.write(json.dumps(message) + "\n")
            self.process.stdin.flush()


def _claim_realtime() -> None:
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(FIRMWARE_RT_PRIORITY))
    except PermissionError:
        print(
            "hwsim: the firmware runs at normal priority (SCHED_FIFO needs root or CAP_SYS_NICE)",
            file=sys.stderr,
        )


def main(argv: list[str]) -> None:
    link_path, bus_path, n_modules = Path(argv[0]), Path(argv[1]), int(argv[2])
    _claim_realtime()  # before the firmware's thread starts: it inherits the class
    bus = DriveBus(bus_path, n_modules)
    firmware = Firmware(bus, link_path, on_change=bus.publish)
    bus.publish(firmware.counters())
    firmware.start()
    print("ready", flush=True)
    for line in sys.stdin:
        message = json.loads(line)
        if "unplug_s" in message:
            firmware.unplug(float(message["unplug_s"]))
        elif "fault" in message:
            code, module, text = message["fault"]
            firmware.report_fault(int(code), int(module), str(text))
    firmware.stop()


if __name__ == "__main__":
    main(sys.argv[1:])


def start_firmwares(n_modules: int, controllers: int, state_dir: Path) -> list[FirmwareProcess]:
    """One firmware process on STATE_DIR/ttyCELL driving every module, or `controllers` of them on
    ttyCELL-K, controller K driving the K-th equal share of the module ids, in order."""
    if controllers == 1:
        return [FirmwareProcess(n_modules, state_dir / "ttyCELL", state_dir / "drives.bin")]
    if not 1 <= controllers <= n_modules:
        raise ValueError(f"--controllers {controllers}: the cell has {n_modules} modules")
    shares = np.array_split(np.arange(n_modules), controllers)
    return [
        FirmwareProcess(len(ids), state_dir / f"ttyCELL-{k}", state_dir / f"drives-{k}.bin", ids)
        for k, ids in enumerate(shares)
    ]
