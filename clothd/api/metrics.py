"""Prometheus metrics (GET /metrics), read from the daemon at scrape time: nothing is paid per tick."""

from __future__ import annotations

from collections.abc import Iterator
from typing import TYPE_CHECKING

from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily, Metric
from prometheus_client.registry import Collector, CollectorRegistry

if TYPE_CHECKING:
    from clothd.daemon import Daemon


class DaemonCollector(Collector):
    def __init__(self, daemon: Daemon) -> None:
        self.daemon = daemon

    def collect(self) -> Iterator[Metric]:
        d = self.daemon
        s = d.stats
        yield CounterMetricFamily("clothd_ticks", "Ticks run", value=s.ticks)
        yield CounterMetricFamily(
            "clothd_missed_ticks", "Tick deadlines missed and skipped", value=s.missed_ticks
        )
        yield CounterMetricFamily(
            "clothd_compute_overruns", "Ticks sent with the previous commands", value=s.compute_overruns
        )
        stage = GaugeMetricFamily(
            "clothd_stage_seconds", "Compute time per stage", labels=["stage", "quantile"]
        )
        for name, window in s.stages.items():
            summary = window.summary()
            for q, key in (("0.5", "p50_ms"), ("0.99", "p99_ms")):
                value = summary[key]
                if value is not None:
                    stage.add_metric([name, q], value / 1e3)
        yield stage
        latency = s.latency.summary()["p50_ms"]
        if latency is not None:
            yield GaugeMetricFamily(
                "clothd_frame_to_command_seconds",
                "Median frame-capture to command-sent latency",
                value=latency / 1e3,
            )
        state = GaugeMetricFamily("clothd_state", "1 for the daemon's current state", labels=["state"])
        for name in ("starting", "tracking", "tracking_lost", "camera_lost", "fault"):
            state.add_metric([name], 1.0 if d.state == name else 0.0)
        yield state
        yield GaugeMetricFamily("clothd_estop", "Emergency stop latched", value=float(d.link.estopped))
        yield GaugeMetricFamily(
            "clothd_camera_up", "Camera delivering fresh frames", value=float(d.camera.healthy)
        )
        yield GaugeMetricFamily("clothd_link_up", "Stepper link connected", value=float(d.link.connected))
        c = d.link.counters
        for name, value in (
            ("sent", c.sent),
            ("retransmitted", c.retransmitted),
            ("acked", c.acked),
            ("invalid", c.invalid),
            ("nacked", c.nacked),
            ("faults", c.faults),
            ("reconnects", c.reconnects),
            ("losses", c.losses),
        ):
            yield CounterMetricFamily(
                f"clothd_link_{name}", f"Stepper link frames/events: {name}", value=value
            )
        features = d.status.features if d.status is not None else 0
        yield GaugeMetricFamily("clothd_features", "Features tracked", value=float(features))


def registry_for(daemon: Daemon) -> CollectorRegistry:
    registry = CollectorRegistry()
    registry.register(DaemonCollector(daemon))
    return registry
