"""The production flow as one object (docs/flow.md): the pieces' tracking (core/pieces.py) and the flow's
control law (core/flow.py) together, frame in, module commands and the pieces' reports out. Pure: the
compute process runs it in mode `flow`, the lockstep bench runs it against hwsim."""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np

from clothd.config import CellConfig, ControlConfig, FlowConfig, TrackerConfig
from clothd.core.camera_model import CameraModel
from clothd.core.conveyor import ConveyorLayout
from clothd.core.flow import FlowController
from clothd.core.messages import ModuleCommands, PairedView
from clothd.core.pieces import Piece, PieceReport, PieceTracking
from clothd.core.tracker import Tracker
from clothd.core.workspace import Workspace


class FlowCell:
    def __init__(
        self,
        flow: FlowConfig,
        tracker: TrackerConfig,
        control: ControlConfig,
        cell: CellConfig,
        camera_model: CameraModel,
        other_cameras: Sequence[CameraModel],
        period_s: float,
        clock: Callable[[], float] | None = None,
    ) -> None:
        layout = ConveyorLayout.of_cell(cell)
        workspace = Workspace.of_cell(cell)
        self.tracking = PieceTracking(
            flow,
            camera_model,
            workspace,
            lambda: Tracker(tracker, camera_model, layout, clock=clock, other_cameras=other_cameras),
        )
        self.controller = FlowController(
            flow,
            control,
            cell,
            layout,
            workspace,
            period_s,
            tracker.physics.strain_limit,
            tracker.estimates_shape,
        )

    @property
    def pieces(self) -> list[Piece]:
        return self.tracking.pieces

    def reset(self) -> None:
        """Forget every piece (tracking starts afresh on each)."""
        self.tracking.reset()
        self.controller.reset()

    def track(
        self,
        image: np.ndarray,
        t_s: float,
        commands: ModuleCommands | None,
        views: Sequence[PairedView | None] = (),
    ) -> None:
        self.tracking.track(image, t_s, commands, views)

    def upkeep(self) -> None:
        """This frame's work that its commands do not wait for (PieceTracking.upkeep): call after `step`."""
        self.tracking.upkeep()

    def step(self, now_s: float) -> ModuleCommands:
        """This tick's commands; the pieces that have gone are let go."""
        commands, gone = self.controller.step(self.tracking.pieces, now_s)
        for piece in gone:
            self.tracking.leave(piece, now_s)
        return commands

    def stop(self) -> ModuleCommands:
        return self.controller.stop()

    def reports(self) -> tuple[PieceReport, ...]:
        """Every piece on the table, then those gone (oldest first)."""
        # A piece's flatness is read from its estimate: none while it is not tracked, as its pose.
        on_table = [
            PieceReport.of(p, self.controller.flatness(p) if p.tracking else None)
            for p in self.tracking.pieces
        ]
        return tuple(on_table + [PieceReport.of(p, None) for p in self.tracking.gone])
