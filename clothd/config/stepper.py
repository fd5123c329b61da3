"""The stepper controllers' section of the configuration: `stepper:` with one `port` (one controller
drives every module), or `controllers:`, a list of controllers, each on its own port with the module ids
it drives (a table larger than one board). `check_controllers` holds the list to the cell: every module
driven by exactly one controller. Each controller numbers its own modules 0..k-1 in the order its
`modules` lists them (docs/serial-protocol.md, "Several controllers").
"""

from __future__ import annotations

import re
from dataclasses import dataclass

from pydantic import Field, field_validator

from clothd.config.strict import Strict

MAX_CONTROLLERS = 16
CELL_MODULES = "the configured cell has {n} (cell.modules_x x cell.modules_y)"
_RANGE = re.compile(r"^\s*(\d+)\s*-\s*(\d+)\s*$")


class ControllerConfig(Strict):
    """One controller of `stepper.controllers`: its port, and the cell's module ids it drives, in the order
    of its own numbering (its module 0 first). Items are ids or inclusive ranges as text, "0-23"."""

    port: str = Field(min_length=1, max_length=1024, description="as stepper.port")
    modules: list[int] = Field(
        min_length=1, max_length=4096, description='module ids, or inclusive ranges "A-B", in its order'
    )

    @field_validator("modules", mode="before")
    @classmethod
    def _expand_ranges(cls, value: object) -> object:
        if not isinstance(value, list):
            return value
        out: list[object] = []
        for item in value:
            m = _RANGE.match(item) if isinstance(item, str) else None
            if m is None:
                out.append(item)
                continue
            first, last = int(m[1]), int(m[2])
            if last < first or last - first >= 4096:
                raise ValueError(f"range {item!r}: A-B with A <= B, at most 4096 ids")
            out.extend(range(first, last + 1))
        return out


class StepperConfig(Strict):
    port: str = Field("/dev/ttyACM0", min_length=1, max_length=1024)
    controllers: list[ControllerConfig] | None = Field(
        None,
        min_length=1,
        max_length=MAX_CONTROLLERS,
        description="several controllers, each on its own port with the modules it drives; "
        "null: one controller on `port` drives every module",
    )
    baud: int = Field(921600, ge=1200, le=12_000_000)
    ack_timeout_s: float = Field(0.05, gt=0.001, le=1, description="retransmit an unacknowledged command")
    # Unanswered for ack_timeout_s x (max_retransmits + 1), 150 ms by default, the link is lost: well inside
    # the controller's 250 ms watchdog, so the host knows first.
    max_retransmits: int = Field(2, ge=0, le=20, description="then the link is lost and reopened")
    handshake_timeout_s: float = Field(0.5, gt=0.01, le=10)
    reconnect_initial_s: float = Field(0.2, gt=0, le=60)
    reconnect_max_s: float = Field(5.0, gt=0, le=600)

    def links(self, n_modules: int) -> list[ControllerLink]:
        """Every controller: its link's settings (this section with its port) and the module ids it
        drives, in its own order. One controller on `port` drives 0..n_modules-1."""
        if self.controllers is None:
            return [ControllerLink(self, tuple(range(n_modules)), CELL_MODULES)]
        return [
            ControllerLink(
                self.model_copy(update={"port": c.port, "controllers": None}),
                tuple(c.modules),
                f"stepper.controllers[{k}].modules lists {{n}}",
            )
            for k, c in enumerate(self.controllers)
        ]


@dataclass(frozen=True)
class ControllerLink:
    """One controller as the daemon links to it: its settings and the cell's module ids, by its index."""

    cfg: StepperConfig
    modules: tuple[int, ...]
    n_from: str  # where its module count comes from, in words, with {n} for the count


def check_controllers(stepper: StepperConfig, n_modules: int) -> None:
    """Raise ValueError naming the key when `stepper.port` and `stepper.controllers` are both given, or the
    controllers do not drive every module of the cell exactly once, or share a port."""
    controllers = stepper.controllers
    if controllers is None:
        return
    if "port" in stepper.model_fields_set:
        raise ValueError(
            "stepper.port and stepper.controllers are both given: one controller takes stepper.port, "
            "several take stepper.controllers (each with its own port); remove one"
        )
    driver: dict[int, int] = {}
    ports: dict[str, int] = {}
    for k, c in enumerate(controllers):
        if c.port in ports:
            raise ValueError(f"stepper.controllers[{k}].port: {c.port} is controller {ports[c.port]}'s too")
        ports[c.port] = k
        for m in c.modules:
            if not 0 <= m < n_modules:
                raise ValueError(
                    f"stepper.controllers[{k}].modules: module {m} is not on the cell "
                    f"(ids 0..{n_modules - 1}, cell.modules_x x cell.modules_y)"
                )
            if m in driver:
                where = "twice" if driver[m] == k else f"by controllers {driver[m]} and {k}"
                raise ValueError(f"stepper.controllers[{k}].modules: module {m} is driven {where}")
            driver[m] = k
    missing = [m for m in range(n_modules) if m not in driver]
    if missing:
        shown = ", ".join(str(m) for m in missing[:8]) + (", ..." if len(missing) > 8 else "")
        raise ValueError(
            f"stepper.controllers: module(s) {shown} driven by no controller "
            f"({len(missing)} of the cell's {n_modules})"
        )
