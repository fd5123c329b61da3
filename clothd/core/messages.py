"""Messages between the tracker and its callers: the control input and the estimate of one tick."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from clothd.core.ekf import UpdateStats
from clothd.core.modes import FlatnessBasis


@dataclass(frozen=True)
class ModuleCommands:
    """The control input u: each module's commanded belt speed and heading, indexed by module id."""

    speed_m_s: np.ndarray
    heading_rad: np.ndarray

    @classmethod
    def all_stop(cls, n_modules: int, heading_rad: np.ndarray | None = None) -> ModuleCommands:
        """Every module stopped. A stopped module keeps `heading_rad` (default 0): turning it back to
        zero would only wear the steering."""
        heading = np.zeros(n_modules) if heading_rad is None else np.array(heading_rad, dtype=float)
        return cls(np.zeros(n_modules), heading)

    @property
    def n_modules(self) -> int:
        return len(self.speed_m_s)


@dataclass(frozen=True)
class PairedView:
    """A further camera's frame paired with the first camera's: its BGR image and its capture time in the
    same clock as the first frame's (so skew_s = t_s - the first frame's time)."""

    image: np.ndarray
    t_s: float


@dataclass(frozen=True)
class Detections:
    """Features where they were detected: ids (m,), the capture time t_s (m,) of the frame each was
    detected in, and the pixel px (m, 2) there."""

    ids: np.ndarray
    t_s: np.ndarray
    px: np.ndarray

    @classmethod
    def none(cls) -> Detections:
        return cls(np.zeros(0, np.int64), np.zeros(0), np.zeros((0, 2)))

    @classmethod
    def join(cls, parts: list[Detections]) -> Detections:
        if not parts:
            return cls.none()
        return cls(
            np.concatenate([d.ids for d in parts]),
            np.concatenate([d.t_s for d in parts]),
            np.concatenate([d.px for d in parts]),
        )

    def subset(self, keep: np.ndarray) -> Detections:
        return Detections(self.ids[keep], self.t_s[keep], self.px[keep])


@dataclass(frozen=True, kw_only=True)
class Estimate:
    """What the tracker believes after one frame. Everything a consumer needs is here, so that nothing
    reaches into the tracker.

    frame_t_s: the frame's capture time in its source's clock (host monotonic live, footage time offline).
    pose (3,) [X_m, Y_m, theta_rad] and pose_cov (3, 3); NaN when lost.
    nodes_m (ny, nx, 3): the mesh nodes in the world, z the height above the table; the rigid model gives
    its rest mesh moved rigidly; None without a model. outline_m (k, 2): the cloth's outline on the table,
    in order around it; None without a model. cloth_size_m: the cloth's (width, height) at rest.
    Feature arrays are indexed like feature_id: pred_px is where the estimate places each feature,
    meas_px where LK measured it this frame (NaN if not). `detected`: the features this estimate is the
    first to carry, where they were detected (in this frame, or in the previous one's upkeep)."""

    frame_t_s: float
    status: str  # "tracking" or "lost"
    pose: np.ndarray
    pose_cov: np.ndarray
    nodes_m: np.ndarray | None
    outline_m: np.ndarray | None
    cloth_size_m: tuple[float, float] | None
    feature_id: np.ndarray  # (n,)
    meas_px: np.ndarray  # (n, 2)
    pred_px: np.ndarray  # (n, 2)
    stats: UpdateStats
    timing_s: dict[str, float] = field(default_factory=dict)
    # (ny - 1, nx - 1): whether the cloth is seen at each mesh quad's centre; None without a model or when
    # the cloth's colour is not known (a folded-over corner leaves its quads' place showing the table).
    quad_seen: np.ndarray | None = None
    detected: Detections = field(default_factory=Detections.none)
    # What the mesh's rest shape rests on: a surface measured through a second view, or the first frame's.
    flatness_basis: FlatnessBasis = FlatnessBasis.SINCE_START
    # (ny - 1, nx - 1): the highest point of each quad as a second view measured it this frame; None: not.
    quad_height_m: np.ndarray | None = None

    @classmethod
    def lost(cls, t_s: float, timing_s: dict[str, float]) -> Estimate:
        """The estimate of a frame the cloth was not found in."""
        empty = np.zeros((0, 2))
        return cls(
            frame_t_s=t_s,
            status="lost",
            pose=np.full(3, np.nan),
            pose_cov=np.full((3, 3), np.nan),
            nodes_m=None,
            outline_m=None,
            cloth_size_m=None,
            feature_id=np.zeros(0, np.int64),
            meas_px=empty,
            pred_px=empty,
            stats=UpdateStats(0, 0, 0.0),
            timing_s=timing_s,
        )

    @property
    def tracking(self) -> bool:
        return self.status == "tracking"

    @property
    def residual_px(self) -> np.ndarray:
        ok = ~np.isnan(self.meas_px[:, 0])
        return np.asarray(np.linalg.norm(self.meas_px[ok] - self.pred_px[ok], axis=1))


def feature_detections(estimates: Sequence[Estimate]) -> dict[int, tuple[int, np.ndarray]]:
    """Feature id -> (index into `estimates` of the frame it was detected in, its pixel (2,) there), for
    every feature detected in one of these frames (those detected earlier are left out)."""
    frame_at = {e.frame_t_s: k for k, e in enumerate(estimates)}
    out: dict[int, tuple[int, np.ndarray]] = {}
    for e in estimates:
        d = e.detected
        for fid, t_s, px in zip(d.ids.tolist(), d.t_s.tolist(), d.px, strict=True):
            if t_s in frame_at:
                out[fid] = (frame_at[t_s], px)
    return out
