"""The cell's control law: a setpoint, an estimate and the time in; module commands, the loop's state
and why a hold or move stopped out. Pure: no I/O, no clock, no processes, so that it runs the same in
the compute process, in a replay and in a test.

It owns what control keeps between ticks: the pose controller, the flatness monitor, the flattening
regulator and the workspace. A mode is entered here, in one place: a setpoint the controller has not
seen (by `Setpoint.started_mono_s`) starts its regulator afresh, so that what one flatten learned does
not carry into the next. `flatten` means hold and take the slack out; `control.flatten` lets hold and
move take it out too, and the workspace's edge stops it (shaping pulls outwards as well as in).
"""

from __future__ import annotations

from dataclasses import dataclass

from clothd.config import CellConfig, ControlConfig
from clothd.core.control import PoseController, Setpoint
from clothd.core.conveyor import ConveyorLayout
from clothd.core.flatness import Flatness, FlatnessMonitor
from clothd.core.flattening import FlatteningRegulator
from clothd.core.messages import Estimate, ModuleCommands
from clothd.core.modes import LoopState, Mode
from clothd.core.workspace import Workspace


@dataclass(frozen=True)
class ControlStep:
    state: LoopState
    commands: ModuleCommands
    halt_reason: str | None  # why these commands stop a hold or move (None when they do not)


class CellController:
    def __init__(
        self,
        control: ControlConfig,
        cell: CellConfig,
        layout: ConveyorLayout,
        workspace: Workspace,
        period_s: float,
        strain_limit: float,
        estimates_shape: bool,
    ) -> None:
        self.cfg = control
        self.pose = PoseController(control, cell, layout.centres_m)
        self.flatness_monitor = FlatnessMonitor(control.flatness)
        self.regulator = FlatteningRegulator(
            control.flattening, layout.centres_m, layout.module_size_m, strain_limit
        )
        self.workspace = workspace
        self.period_s = period_s
        self.estimates_shape = estimates_shape  # the tracker follows the cloth's shape: flatness is seen
        self._entered_mono_s: float | None = None  # the setpoint in force, by when it began

    def reset(self) -> None:
        """Tracking starts afresh: nothing learned about this cloth carries over."""
        self.pose.reset()
        self.flatness_monitor.reset()
        self.regulator.reset()
        self._entered_mono_s = None

    def stop(self) -> ModuleCommands:
        return self.pose.stop()

    def read_flatness(self, est: Estimate) -> Flatness | None:
        """The flatness of a new estimate; None when its model does not follow the shape or it is lost."""
        if not self.estimates_shape or not est.tracking or est.nodes_m is None or est.cloth_size_m is None:
            return None
        return self.flatness_monitor.update(
            est.nodes_m, est.cloth_size_m, est.quad_seen, est.flatness_basis, est.quad_height_m
        )

    def step(
        self,
        have_frame: bool,
        est: Estimate | None,
        sp: Setpoint,
        flatness: Flatness | None,
        now_mono_s: float,
    ) -> ControlStep:
        if sp.started_mono_s != self._entered_mono_s:
            self._enter(sp)
        if not have_frame:
            return ControlStep(LoopState.CAMERA_LOST, self.stop(), "the camera is lost")
        if est is None or not est.tracking:
            return ControlStep(LoopState.TRACKING_LOST, self.stop(), "the cloth is not tracked")
        if sp.drive is not None and est.outline_m is not None:  # a drive script, stopped as a move is
            off_limits = self.workspace.leaves(est.outline_m)
            if off_limits is not None:
                return self._at_edge(off_limits)
            return ControlStep(LoopState.TRACKING, sp.drive.commands_at(now_mono_s - sp.started_mono_s), None)
        if sp.mode == Mode.IDLE or sp.pose is None or est.outline_m is None:
            return ControlStep(LoopState.TRACKING, self.stop(), None)
        twist = self.pose.plan_twist(est.pose, sp.pose, self.period_s)
        space = self.workspace
        off_limits = space.leaves(est.outline_m)
        if off_limits is not None and not space.comes_back(est.outline_m, est.pose, twist, self.period_s):
            return self._at_edge(off_limits)
        under = self.pose.modules_under(est.outline_m)
        shaping = None
        # Past the edge only the rigid motion that brings the cloth back runs: shaping pulls outwards too.
        flattens = off_limits is None and (sp.mode == Mode.FLATTEN or self.cfg.flatten)
        if flattens and flatness is not None and est.nodes_m is not None and est.cloth_size_m is not None:
            shaping = self.regulator.velocities(
                flatness, est.nodes_m, est.cloth_size_m, under, est.pose, est.frame_t_s
            )
        commands = self.pose.module_commands(est.pose, twist, under, shaping)
        return ControlStep(LoopState.TRACKING, commands, None)

    def _enter(self, sp: Setpoint) -> None:
        self.regulator.reset()
        self._entered_mono_s = sp.started_mono_s

    def _at_edge(self, off_limits: str) -> ControlStep:
        return ControlStep(LoopState.TRACKING, self.stop(), f"at the workspace's edge: {off_limits}")
