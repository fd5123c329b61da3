"""Correcting the commands for what each module does with them (`clothd check-modules` measures it).

A module that runs its belt the wrong way round, turns `heading_offset_deg` past the heading it is told
and runs at `speed_scale` times the speed it is told is sent, for a wanted (speed, heading), the speed
divided by its scale at the heading less its offset (and less half a turn when reversed). The commands
in force, which the tracker predicts with and recordings keep, stay the wanted ones: they are what the
belts then do.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from clothd.core.messages import ModuleCommands
from clothd.core.module_check import ModuleCalibrationEntry


@dataclass(frozen=True)
class ModuleCalibration:
    heading_error_rad: np.ndarray  # (n_modules,) what each module adds to a heading (π more when reversed)
    speed_scale: np.ndarray  # (n_modules,) its belt speed over the speed it is told

    @classmethod
    def of(cls, entries: Sequence[ModuleCalibrationEntry], n_modules: int) -> ModuleCalibration:
        """Modules not listed are taken as calibrated."""
        error, scale = np.zeros(n_modules), np.ones(n_modules)
        for e in entries:
            error[e.module] = math.radians(e.heading_offset_deg) + (math.pi if e.reversed else 0.0)
            scale[e.module] = e.speed_scale
        return cls(error, scale)

    def to_send(self, wanted: ModuleCommands) -> ModuleCommands:
        """What to tell the modules so that they do `wanted`."""
        heading = np.remainder(wanted.heading_rad - self.heading_error_rad + math.pi, 2 * math.pi) - math.pi
        return ModuleCommands(wanted.speed_m_s / self.speed_scale, heading)
