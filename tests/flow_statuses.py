"""Statuses of mode flow made up for the API's tests: pieces as the status carries them, published into a
daemon's hub as its loop would publish them."""

from __future__ import annotations

from clothd.api.stream import StreamHub
from clothd.core.modes import Mode, PieceState
from clothd.loop.status import PieceStatus, Pose

FLAP = "a corner is folded over"


def piece(
    id: int,
    state: PieceState,
    x_m: float | None = None,
    gone: bool = False,
    reason: str | None = None,
    found_s: float = 100.0,
) -> PieceStatus:
    """A piece as the status carries it: posed at (x_m, 0.02 m, 0.1 rad) when x_m is given, flat unless
    flattening; first seen at found_s + id."""
    pose = None if x_m is None else Pose(x_m=x_m, y_m=0.02, theta_rad=0.1)
    return PieceStatus(
        id=id,
        state=state,
        pose=pose,
        flat=None if pose is None else state != PieceState.FLATTENING,
        max_height_mm=None if pose is None else (2.5 if state == PieceState.FLATTENING else 0.4),
        reason=reason,
        found_t_mono_s=found_s + id,
        left_t_mono_s=found_s + 100.0 + id if gone else None,
    )


def publish(hub: StreamHub, pieces: list[PieceStatus] | None, mode: Mode = Mode.FLOW) -> None:
    """The last status again, in `mode` with these pieces, stamped a moment later."""
    s = hub.status
    assert s is not None
    hub.publish(s.model_copy(update={"mode": mode, "pieces": pieces, "t_unix_s": s.t_unix_s + 0.1}))
