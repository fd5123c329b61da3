"""The production flow's control law: every piece on the table taken in, flattened, placed and driven out,
each by the modules under it alone (docs/flow.md). Pure, as the cell controller is.

Each piece has its own cell controller (core/cell_controller.py): its pose controller, flatness monitor,
regulator and workspace, so every rule of a single cloth holds per piece. A piece's path:

- `entering`: the belts under what is in view pull it in at `flow.intake_speed_m_s`, until all of it lies
  in the workspace; then they stop, and its tracking starts once it is still (core/pieces.py);
- `tracked` -> `flattening`: held where it is and flattened, until flat for `flow.flat_for_s`;
- `placing`: moved to `flow.placement` (still flattened as it goes) once the way there is clear: every
  piece ahead is driven out and its trailing edge is `flow.gap_m` past where this one will reach;
- `leaving`: driven out over the +x edge at `flow.exit_speed_m_s`, its y and heading held to the
  placement's, until its centre has crossed the edge;
- `rejected`: a folded-over corner seen for `flow.flap_for_s`, or not flat or placed in time: driven out
  as it is, once the way is clear, and reported with the reason.

A module goes to at most one piece: the one over it. A module under two pieces' outlines, or under none,
stops, so the modules between pieces hold them apart. A piece that is not tracked (its tracking is
starting, or was lost) gets no motion but its intake or its way out.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from clothd.config import CellConfig, ControlConfig, FlowConfig
from clothd.core.cell_controller import CellController
from clothd.core.control import STILL_SPEED_M_S, Setpoint
from clothd.core.conveyor import ConveyorLayout
from clothd.core.flatness import Flatness
from clothd.core.messages import ModuleCommands
from clothd.core.modes import Mode, PieceState
from clothd.core.pieces import Piece
from clothd.core.workspace import Workspace

DRIVEN_OUT = (PieceState.LEAVING, PieceState.REJECTED)


@dataclass
class _PieceControl:
    cell: CellController
    tracked_since_s: float | None = None  # the tracking its controller's state belongs to
    estimate_t_s: float | None = None  # the last estimate read for flatness
    flatness: Flatness | None = None
    hold_pose: np.ndarray | None = None  # where flattening holds it
    flat_since_s: float | None = None
    flat_seen_s: float | None = None  # when it last read flat
    flap_since_s: float | None = None
    out_speed_m_s: float = 0.0  # a piece driven out speeds up within the acceleration limit
    driving_out: bool = False  # a reject, once its way is clear


class FlowController:
    def __init__(
        self,
        cfg: FlowConfig,
        control: ControlConfig,
        cell: CellConfig,
        layout: ConveyorLayout,
        workspace: Workspace,
        period_s: float,
        strain_limit: float,
        estimates_shape: bool,
    ) -> None:
        self.cfg = cfg
        self.control = control
        self.layout = layout
        self.workspace = workspace
        self.period_s = period_s
        self.placement = np.array(cfg.placement.pose)
        # The table's edge, the outer turntables' (half a pitch past the outer centres): past that the
        # next station has it. Let go at the end of the belts, 5 mm short, a piece lay there until the next
        # one pushed it off.
        self.exit_x_m = cell.modules_x / 2 * cell.pitch_m
        self.half_belt_m = cell.module_size_m / 2
        self._new_cell = lambda: CellController(
            control, cell, layout, workspace, period_s, strain_limit, estimates_shape
        )
        self._pieces: dict[int, _PieceControl] = {}
        self.heading_rad = np.zeros(layout.n_modules)  # stopped modules keep their heading

    def reset(self) -> None:
        self._pieces.clear()

    def stop(self) -> ModuleCommands:
        return ModuleCommands.all_stop(self.layout.n_modules, self.heading_rad)

    def flatness(self, piece: Piece) -> Flatness | None:
        ctl = self._pieces.get(piece.id)
        return None if ctl is None else ctl.flatness

    def step(self, pieces: list[Piece], now_s: float) -> tuple[ModuleCommands, list[Piece]]:
        """Module commands for this tick, and the pieces that have gone (their centre past the edge)."""
        for gone_id in set(self._pieces) - {p.id for p in pieces}:
            del self._pieces[gone_id]
        velocities, claims = [], np.zeros(self.layout.n_modules, int)
        gone = []
        for piece in pieces:
            v, under = self._piece_step(piece, pieces, now_s)
            if piece.state in DRIVEN_OUT and piece.centre_m[0] > self.exit_x_m:
                gone.append(piece)
                piece.left_s = now_s
                if piece.state == PieceState.LEAVING:
                    piece.enter(PieceState.LEFT, now_s)
                continue
            velocities.append(np.where(under[:, None], v, 0.0))
            claims += under
        v_all = np.sum(velocities, axis=0) if velocities else np.zeros((self.layout.n_modules, 2))
        v_all[claims > 1] = 0.0  # under two pieces: it would drag one into the other
        speed = np.linalg.norm(v_all, axis=1)
        moving = speed > STILL_SPEED_M_S
        self.heading_rad = np.where(moving, np.arctan2(v_all[:, 1], v_all[:, 0]), self.heading_rad)
        return ModuleCommands(speed, self.heading_rad.copy()), gone

    # -- one piece ------------------------------------------------------------------------------------

    def _piece_step(self, piece: Piece, pieces: list[Piece], now_s: float) -> tuple[np.ndarray, np.ndarray]:
        """This piece's velocities (n_modules, 2) and the modules under it (n_modules,) bool."""
        ctl = self._control_of(piece)
        piece.driven_out = piece.state == PieceState.LEAVING or ctl.driving_out
        if piece.state == PieceState.ENTERING:
            return self._enter(piece, ctl)
        if not piece.tracking:
            if piece.state == PieceState.REJECTED and piece.tracked_since_s is None and not ctl.driving_out:
                # Rejected before any tracking (pieces touching, core/pieces.py): out as it is, when clear.
                ctl.driving_out = self._way_clear(piece, pieces, float(piece.outline_m[:, 0].max()))
            return self._blind(piece, ctl)
        est = piece.estimate
        assert est is not None and est.outline_m is not None
        if est.frame_t_s != ctl.estimate_t_s:
            ctl.estimate_t_s = est.frame_t_s
            ctl.flatness = ctl.cell.read_flatness(est)
        under = ctl.cell.pose.modules_under(est.outline_m)
        if piece.state == PieceState.TRACKED:
            piece.enter(PieceState.FLATTENING, now_s)
            ctl.hold_pose = est.pose.copy()
        self._judge(piece, ctl, pieces, now_s)
        if piece.state in DRIVEN_OUT:
            touched = self._touched(ctl, est.outline_m)
            return self._out(piece, ctl, est.pose, touched), touched
        target = ctl.hold_pose if piece.state == PieceState.FLATTENING else self.placement
        mode = Mode.FLATTEN if piece.state == PieceState.FLATTENING else Mode.MOVE
        sp = Setpoint(mode, target, started_mono_s=piece.since_s)
        step = ctl.cell.step(True, est, sp, ctl.flatness, now_s)
        return _velocities(step.commands), under

    def _control_of(self, piece: Piece) -> _PieceControl:
        ctl = self._pieces.get(piece.id)
        if ctl is None:
            ctl = self._pieces[piece.id] = _PieceControl(self._new_cell())
        if piece.tracked_since_s != ctl.tracked_since_s:  # tracking began afresh: nothing learned holds
            ctl.cell.reset()
            ctl.tracked_since_s = piece.tracked_since_s
            ctl.flatness = ctl.flat_since_s = ctl.flat_seen_s = ctl.flap_since_s = None
            ctl.estimate_t_s = None
            if piece.state == PieceState.FLATTENING and piece.estimate is not None:
                ctl.hold_pose = piece.estimate.pose.copy()
        return ctl

    def _judge(self, piece: Piece, ctl: _PieceControl, pieces: list[Piece], now_s: float) -> None:
        """The piece's next state, from its flatness, its pose and the pieces ahead of it."""
        f, cfg = ctl.flatness, self.cfg
        in_state_s = now_s - piece.since_s
        if piece.state == PieceState.FLATTENING:
            ctl.flap_since_s = (ctl.flap_since_s or now_s) if f is not None and f.flaps else None
            ctl.flat_since_s = (ctl.flat_since_s or now_s) if f is not None and f.flat else None
            if ctl.flat_since_s is not None:
                ctl.flat_seen_s = now_s
            # Not flat for the whole timeout: since it began flattening, or since it last read flat (a flat
            # piece waiting for its way may read not flat a frame or two; that is no reason to reject it).
            unflat_s = now_s - max(piece.since_s, ctl.flat_seen_s or piece.since_s)
            if ctl.flap_since_s is not None and now_s - ctl.flap_since_s >= cfg.flap_for_s:
                piece.enter(PieceState.REJECTED, now_s, "a corner is folded over")
            elif unflat_s > cfg.flatten_timeout_s:
                piece.enter(PieceState.REJECTED, now_s, f"not flat for {cfg.flatten_timeout_s:g} s")
            elif self._flat_enough(ctl, now_s) and self._way_clear(
                piece, pieces, self._reach_at_placement(piece)
            ):
                piece.enter(PieceState.PLACING, now_s)
        elif piece.state == PieceState.PLACING:
            assert piece.estimate is not None
            pose = piece.estimate.pose
            off_mm = float(np.linalg.norm(pose[:2] - self.placement[:2])) * 1e3
            off_deg = abs(math.degrees(math.remainder(float(pose[2] - self.placement[2]), 2 * math.pi)))
            if off_mm <= cfg.placed_mm and off_deg <= cfg.placed_deg:
                piece.enter(PieceState.LEAVING, now_s)
            elif in_state_s > cfg.place_timeout_s:
                piece.enter(PieceState.REJECTED, now_s, f"not placed after {cfg.place_timeout_s:g} s")
        if piece.state == PieceState.REJECTED and not ctl.driving_out:
            ctl.driving_out = self._way_clear(piece, pieces, float(piece.outline_m[:, 0].max()))

    def _flat_enough(self, ctl: _PieceControl, now_s: float) -> bool:
        return ctl.flat_since_s is not None and now_s - ctl.flat_since_s >= self.cfg.flat_for_s

    def _reach_at_placement(self, piece: Piece) -> float:
        """How far +x the piece reaches once placed (its extent ahead of its centre, turned as it is)."""
        return float(self.placement[0] + (piece.outline_m[:, 0] - piece.centre_m[0]).max())

    def _way_clear(self, piece: Piece, pieces: list[Piece], reach_x_m: float) -> bool:
        """Every piece ahead is being driven out, its trailing edge `gap_m` beyond reach_x_m."""
        for other in pieces:
            if other is piece or other.centre_m[0] <= piece.centre_m[0]:
                continue
            driven = other.state == PieceState.LEAVING or (
                other.state == PieceState.REJECTED and self._pieces[other.id].driving_out
            )
            if not driven or float(other.outline_m[:, 0].min()) < reach_x_m + self.cfg.gap_m:
                return False
        return True

    def _out(self, piece: Piece, ctl: _PieceControl, pose: np.ndarray, under: np.ndarray) -> np.ndarray:
        """A leaving piece's velocities: out along +x, its drift from the placement's y and heading
        corrected (a reject's is not); nothing until a reject's way is clear."""
        if piece.state == PieceState.REJECTED and not ctl.driving_out:
            return np.zeros((self.layout.n_modules, 2))
        ctl.out_speed_m_s = min(
            self.cfg.exit_speed_m_s, ctl.out_speed_m_s + self.control.max_accel_m_s2 * self.period_s
        )
        twist = np.array([ctl.out_speed_m_s, 0.0, 0.0])
        if piece.state == PieceState.LEAVING:
            g = self.cfg.exit_gain_1_s
            twist[1] = g * (self.placement[1] - pose[1])
            twist[2] = g * math.remainder(float(self.placement[2] - pose[2]), 2 * math.pi)
        return _velocities(ctl.cell.pose.module_commands(pose, twist, under))

    def _touched(self, ctl: _PieceControl, outline_m: np.ndarray) -> np.ndarray:
        """The modules whose belt reaches under the outline. A piece driven out runs on all of them: a
        stopped belt under its edge brakes it, and a 221 x 207 mm piece on 4 running belts and the edges of
        8 stopped ones stood still."""
        return ctl.cell.pose.modules_under(outline_m, margin_m=-self.half_belt_m)

    def _blind(self, piece: Piece, ctl: _PieceControl) -> tuple[np.ndarray, np.ndarray]:
        """A piece not tracked: one being driven out goes on out where it was last seen, moved on as its
        belts move it; any other is stopped until its tracking starts again."""
        if piece.state not in DRIVEN_OUT or not (ctl.driving_out or piece.state == PieceState.LEAVING):
            return np.zeros((self.layout.n_modules, 2)), ctl.cell.pose.modules_under(piece.outline_m)
        under = self._touched(ctl, piece.outline_m)
        # A reject never tracked starts from rest.
        ctl.out_speed_m_s = min(
            self.cfg.exit_speed_m_s, ctl.out_speed_m_s + self.control.max_accel_m_s2 * self.period_s
        )
        piece.outline_m = piece.outline_m + np.array([ctl.out_speed_m_s * self.period_s, 0.0])
        v = np.zeros((self.layout.n_modules, 2))
        v[:, 0] = ctl.out_speed_m_s
        return v, under

    def _enter(self, piece: Piece, ctl: _PieceControl) -> tuple[np.ndarray, np.ndarray]:
        """The intake: +x under what is in view, until all of it is in; the outline moves on with it. A
        piece touching a tracked one is held: pulled on, it would be pushed into (or over) that piece."""
        under = ctl.cell.pose.modules_under(piece.outline_m)
        v = np.zeros((self.layout.n_modules, 2))
        pulled = self.workspace.leaves(piece.outline_m) is not None and piece.slot is None
        if pulled and not piece.beside:
            v[:, 0] = self.cfg.intake_speed_m_s
            piece.outline_m = piece.outline_m + np.array([self.cfg.intake_speed_m_s * self.period_s, 0.0])
        return v, under


def _velocities(commands: ModuleCommands) -> np.ndarray:
    """(n_modules, 2) from speeds and headings."""
    return np.stack(
        [
            commands.speed_m_s * np.cos(commands.heading_rad),
            commands.speed_m_s * np.sin(commands.heading_rad),
        ],
        axis=1,
    )
