"""`clothd bench flow --realtime`: its figures from what the daemon's API says (a client that answers as
the daemon would, so that the arithmetic is checked apart from a live run's timing)."""

from __future__ import annotations

from typing import Any

import pytest

from clothd.tools import bench_flow_live


def _timing(ticks: int, missed: int, overruns: int) -> dict[str, Any]:
    return {
        "ticks": ticks,
        "missed_ticks": missed,
        "compute_overruns": overruns,
        "frame_to_command": {"p50_ms": 11.0, "p99_ms": 19.0},
    }


def _piece(pid: int, state: str, left: float | None, reason: str | None = None) -> dict[str, Any]:
    return {"id": pid, "state": state, "left_t_mono_s": left, "reason": reason}


class _Daemon:
    """Two pieces on the table at every poll; then three gone (the second rejected) and one on the table."""

    def __init__(self, halts: bool = False) -> None:
        self.modes: list[str] = []
        self.polls = 0
        self.halts = halts
        self.truths = 0

    def sim_truth(self) -> dict[str, Any]:
        """hwsim's lag: before the run, then 246 more frames dropped and 1.5 s more lost for good."""
        self.truths += 1
        first = self.truths == 1
        return {"camera_frames_dropped": 4 if first else 250, "behind_real_time_s": 0.5 if first else 2.0}

    def status(self) -> dict[str, Any]:
        self.polls += 1
        if self.halts and self.polls > 2:
            return {"timing": _timing(150, 1, 2), "pieces": None, "mode": "idle", "halt_reason": "lost"}
        if self.polls == 1:
            return {"timing": _timing(100, 1, 2), "pieces": [], "cameras": [{}, {}], "mode": "idle"}
        gone = [_piece(0, "left", 5.0), _piece(1, "rejected", 9.0, "a corner is folded over")]
        gone.append(_piece(2, "left", 12.0))
        on_table = [_piece(3, "flattening", None), _piece(4, "entering", None)]
        timing = _timing(1100, 3, 6)
        camera = {"fps": 15.0 if self.polls % 2 else 9.0}  # frames dropped every other 5 s window
        pieces = on_table + gone
        return {"timing": timing, "pieces": pieces, "cameras": [{}, {}], "camera": camera, "mode": "flow"}

    def set_mode(self, mode: str) -> None:
        self.modes.append(mode)

    def outfeed(self) -> list[dict[str, Any]]:
        judged = {"max_height_mm": 0.4, "pose_error_mm": 0.5, "pose_error_deg": 0.2, "flap": False}
        bumpy = {**judged, "max_height_mm": 3.0}
        return [
            {**judged, "id": 0, "t_s": 10.0},
            {**judged, "id": 1, "t_s": 11.0},
            {**bumpy, "id": 2, "t_s": 12.0},
        ]


def test_the_live_figures_come_from_the_api(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(bench_flow_live, "POLL_S", 0.01)
    monkeypatch.setattr(bench_flow_live, "DRAIN_S", 0.0)
    daemon = _Daemon()
    r = bench_flow_live._run(daemon, 0.003, 6.0, 0)  # type: ignore[arg-type]
    assert daemon.modes == ["flow"]
    assert r["pieces_in"] == 5 and r["pieces_out"] == 3 and r["cameras"] == 2
    # The rejected piece left flat and placed, yet it is no success; the third left with a ridge.
    assert r["matched_rejects"] and [p["ok"] for p in r["pieces"]] == [True, False, False]
    assert r["pieces"][1]["rejected"] == "a corner is folded over"
    assert r["success_pct"] == pytest.approx(100 / 3, abs=0.01) and r["rejects"] == 1
    # Of the 1002 ticks due since flow began, 2 were missed and 4 went out with the last commands.
    assert r["ticks"] == 1002 and r["missed_tick_pct"] == pytest.approx(100 * 6 / 1002, abs=1e-3)
    assert r["multi_piece_time_pct"] == 100.0
    assert r["sim_camera_frames_dropped"] == 246 and r["sim_behind_real_time_s"] == 1.5
    assert "hwsim dropped 246 camera frames" in bench_flow_live.format_live(r)
    assert r["camera_fps_min"] == 9.0 and 9.0 <= r["camera_fps_median"] <= 15.0


def test_a_flow_that_halts_is_reported_with_its_reason_and_the_pieces_seen(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.setattr(bench_flow_live, "POLL_S", 0.01)
    monkeypatch.setattr(bench_flow_live, "DRAIN_S", 0.0)
    r = bench_flow_live._run(_Daemon(halts=True), 1.0, 6.0, 0)  # type: ignore[arg-type]
    assert r["halt_reason"] == "lost" and r["halted_after_s"] is not None and r["halted_after_s"] < 5
    assert r["pieces_in"] == 5  # seen before the halt, though the status lists none after it
