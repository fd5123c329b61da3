"""Prometheus metrics (GET /metrics), read at scrape time from the status the last tick published: the
snapshot is immutable, so the API never reads the daemon's live state, and the daemon pays nothing per
tick. The pieces of mode flow are counted from every status the hub takes (piece_counts.py), so a
flow no scrape saw is counted all the same."""

from __future__ import annotations

from collections.abc import Iterator

from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily, Metric
from prometheus_client.registry import Collector, CollectorRegistry

from clothd.api.piece_counts import PieceCounts, by_state
from clothd.api.stream import StreamHub
from clothd.core.modes import FlatnessBasis, LoopState
from clothd.loop.status import FPS_DOC, GAP_DOC, Status


class StatusCollector(Collector):
    def __init__(self, hub: StreamHub) -> None:
        self.hub = hub
        self.counts = PieceCounts()
        hub.listeners.append(self._count)

    def _count(self, status: Status) -> None:
        self.counts.see(status.pieces)

    def collect(self) -> Iterator[Metric]:
        s = self.hub.status
        if s is None:
            return
        t = s.timing
        yield CounterMetricFamily("clothd_ticks", "Ticks run", value=t.ticks)
        yield CounterMetricFamily(
            "clothd_missed_ticks", "Tick deadlines missed and skipped", value=t.missed_ticks
        )
        yield CounterMetricFamily(
            "clothd_compute_overruns", "Ticks sent with the previous commands", value=t.compute_overruns
        )
        stage = GaugeMetricFamily(
            "clothd_stage_seconds", "Compute time per stage", labels=["stage", "quantile"]
        )
        for name, window in t.stages.items():
            for q, value in (("0.5", window.p50_ms), ("0.99", window.p99_ms)):
                if value is not None:
                    stage.add_metric([name, q], value / 1e3)
        yield stage
        if t.frame_to_command.p50_ms is not None:
            yield GaugeMetricFamily(
                "clothd_frame_to_command_seconds",
                "Median frame-capture to command-sent latency",
                value=t.frame_to_command.p50_ms / 1e3,
            )
        state = GaugeMetricFamily("clothd_state", "1 for the daemon's current state", labels=["state"])
        for name in LoopState:
            state.add_metric([name.value], 1.0 if s.state == name else 0.0)
        yield state
        yield GaugeMetricFamily("clothd_estop", "Emergency stop latched", value=float(s.estop))
        yield GaugeMetricFamily(
            "clothd_camera_up", "Camera delivering fresh frames", value=float(s.camera.healthy)
        )
        yield from _cameras(s)
        yield GaugeMetricFamily(
            "clothd_link_up", "Stepper link connected", value=float(s.link.state == "connected")
        )
        c = s.link.counters
        for name in ("sent", "retransmitted", "acked", "invalid", "nacked", "faults", "reconnects", "losses"):
            yield CounterMetricFamily(
                f"clothd_link_{name}", f"Stepper link frames/events: {name}", value=getattr(c, name)
            )
        yield GaugeMetricFamily("clothd_features", "Features tracked", value=float(s.features))
        yield from self._pieces(s)
        if s.flatness is not None:
            f = s.flatness
            yield GaugeMetricFamily(
                "clothd_flatness_max_height_meters",
                "Estimated height of the highest point of the cloth",
                value=f.max_height_mm / 1e3,
            )
            yield GaugeMetricFamily(
                "clothd_flatness_compressed_area_ratio",
                "Share of the mesh holding slack",
                value=f.compressed_area_pct / 100,
            )
            yield GaugeMetricFamily("clothd_flat", "The cloth is flat (with hysteresis)", value=float(f.flat))
            yield GaugeMetricFamily(
                "clothd_ridges", "Ridges found in the estimate", value=float(len(f.ridges))
            )
            yield GaugeMetricFamily("clothd_flaps", "Folded-over corners found", value=float(len(f.flaps)))
            basis = GaugeMetricFamily(
                "clothd_flatness_basis",
                "1 for what the flatness rests on (status flatness.basis)",
                labels=["basis"],
            )
            for name in FlatnessBasis:
                basis.add_metric([name.value], 1.0 if f.basis == name else 0.0)
            yield basis

    def _pieces(self, s: Status) -> Iterator[Metric]:
        """Mode flow's pieces: on the table by state, and in, out and rejected, each counted once."""
        on_table = GaugeMetricFamily(
            "clothd_pieces", "Pieces on the table by state (mode flow; 0 in any other)", labels=["state"]
        )
        for state, n in by_state(s.pieces).items():
            on_table.add_metric([state.value], float(n))
        yield on_table
        c = self.counts
        yield CounterMetricFamily("clothd_pieces_in", "Pieces first seen coming in", value=c.pieces_in)
        yield CounterMetricFamily(
            "clothd_pieces_out", "Pieces that left flat and placed, to the next station", value=c.pieces_out
        )
        yield CounterMetricFamily(
            "clothd_pieces_rejected",
            "Pieces rejected (a flap, not flat or not placed in time)",
            value=c.rejected,
        )
        yield CounterMetricFamily(
            "clothd_pieces_abandoned",
            "Pieces on the table, not rejected, when their flow ended (counted in again by a new flow)",
            value=c.abandoned,
        )


def _cameras(s: Status) -> Iterator[Metric]:
    """Each camera's health, and each further camera's pairing with the first (status cameras[])."""
    up = GaugeMetricFamily("clothd_camera_healthy", "Camera delivering fresh frames", labels=["camera"])
    skew = GaugeMetricFamily(
        "clothd_camera_skew_ms",
        "Median of a further camera's frame time minus the first camera's, recent pairs",
        labels=["camera"],
    )
    paired = GaugeMetricFamily(
        "clothd_camera_paired_ratio",
        "Share of the first camera's recent frames a further camera had a frame within max_skew_ms of",
        labels=["camera"],
    )
    fps = GaugeMetricFamily("clothd_camera_fps", FPS_DOC, labels=["camera"])
    gap = GaugeMetricFamily("clothd_camera_longest_gap_ms", GAP_DOC, labels=["camera"])
    for cam in s.cameras:
        up.add_metric([cam.name], float(cam.healthy))
        if cam.fps is not None and cam.longest_gap_ms is not None:
            fps.add_metric([cam.name], cam.fps)
            gap.add_metric([cam.name], cam.longest_gap_ms)
        if cam.skew_ms is not None:
            skew.add_metric([cam.name], cam.skew_ms)
        if cam.paired_pct is not None:
            paired.add_metric([cam.name], cam.paired_pct / 100)
    yield from (up, fps, gap, skew, paired)


def registry_for(hub: StreamHub) -> CollectorRegistry:
    registry = CollectorRegistry()
    registry.register(StatusCollector(hub))
    return registry
