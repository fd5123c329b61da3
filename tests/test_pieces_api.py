"""Mode flow's pieces over REST, the WebSocket and /metrics, in process over a daemon built but not started
(statuses with pieces published into its hub as the loop would); and GET /api/v1/sim/outfeed relaying
hwsim's own HTTP handler."""

from __future__ import annotations

import random
import threading
from collections.abc import Iterator
from http.server import ThreadingHTTPServer
from typing import Any, ClassVar

import pytest
from fastapi.testclient import TestClient
from flow_statuses import FLAP, piece, publish
from local_api import local_app
from prometheus_client.parser import text_string_to_metric_families

from clothd.api.stream import StreamHub
from clothd.config import ApiConfig, Config
from clothd.core.modes import Mode, PieceState
from clothd.loop.status import PieceStatus
from clothd.run import build
from hwsim.serve import _Handler

BASE = "http://127.0.0.1:8080"
WS_OWN = {"Host": "127.0.0.1:8080"}
GONE_KEPT = 50  # the status keeps the last 50 pieces gone (clothd/core/pieces.py)


def _client(sim_truth_url: str | None = None) -> tuple[TestClient, StreamHub]:
    parts = build(Config())
    app = local_app(parts, ApiConfig(), sim_truth_url)
    return TestClient(app, base_url=BASE), parts.hub


def _metrics(client: TestClient) -> dict[str, float]:
    """Every sample of /metrics by name, with its labels: 'clothd_pieces{state=entering}'."""
    out = {}
    for family in text_string_to_metric_families(client.get("/metrics").text):
        for s in family.samples:
            labels = ",".join(f"{k}={v}" for k, v in s.labels.items())
            out[s.name + (f"{{{labels}}}" if labels else "")] = s.value
    return out


def _counts(m: dict[str, float]) -> tuple[float, float, float]:
    return m["clothd_pieces_in_total"], m["clothd_pieces_out_total"], m["clothd_pieces_rejected_total"]


def test_rest_and_the_websocket_carry_the_pieces() -> None:
    client, hub = _client()
    assert client.get("/api/v1/pieces").json() == []  # not in mode flow
    pieces = [
        piece(1, PieceState.FLATTENING, 0.1),
        piece(0, PieceState.REJECTED, 0.5, gone=True, reason=FLAP),
    ]
    publish(hub, pieces)
    listed = client.get("/api/v1/pieces").json()
    assert [(p["id"], p["state"], p["reason"]) for p in listed] == [
        (1, "flattening", None),
        (0, "rejected", FLAP),
    ]
    assert (
        listed[0]["pose"] == {"x_m": 0.1, "y_m": 0.02, "theta_rad": 0.1} and listed[0]["max_height_mm"] == 2.5
    )
    with client.websocket_connect("/api/v1/stream", headers=WS_OWN) as ws:
        assert ws.receive_json()["pieces"] == listed


def test_metrics_show_the_pieces_on_the_table_by_state_and_count_each_once() -> None:
    client, hub = _client()
    m = _metrics(client)
    assert _counts(m) == (0, 0, 0) and m["clothd_pieces{state=entering}"] == 0
    assert "clothd_pieces{state=left}" not in m  # a piece that left is not on the table
    publish(hub, [piece(0, PieceState.PLACING, 0.1), piece(1, PieceState.ENTERING)])
    m = _metrics(client)
    assert _counts(m) == (2, 0, 0)
    assert (m["clothd_pieces{state=placing}"], m["clothd_pieces{state=entering}"]) == (1, 1)
    table = [piece(1, PieceState.REJECTED, 0.0, reason=FLAP), piece(2, PieceState.ENTERING)]
    publish(hub, [*table, piece(0, PieceState.LEFT, 0.5, gone=True)])
    for _ in range(2):  # scraped twice: nothing counted twice
        m = _metrics(client)
        assert _counts(m) == (3, 1, 1)
        assert (m["clothd_pieces{state=rejected}"], m["clothd_pieces{state=placing}"]) == (1, 0)
    gone = [piece(0, PieceState.LEFT, 0.5, gone=True), piece(1, PieceState.REJECTED, 0.5, True, FLAP)]
    publish(hub, [piece(2, PieceState.TRACKED, -0.2), *gone])  # the reject went out: counted already
    m = _metrics(client)
    assert _counts(m) == (3, 1, 1) and m["clothd_pieces{state=rejected}"] == 0


def _flow(n: int, rejects: set[int], found_s: float) -> Iterator[list[PieceStatus]]:
    """The statuses of n pieces passing one after another, two on the table at a time, each entering
    then leaving (or rejected); the status keeps only the last GONE_KEPT gone, as the daemon's does."""
    gone: list[PieceStatus] = []
    for k in range(n + 1):
        table = [piece(j, PieceState.PLACING, 0.1, found_s=found_s) for j in (k - 1,) if j >= 0]
        table += [piece(k, PieceState.ENTERING, found_s=found_s)] if k < n else []
        yield table + gone
        if k >= 1:
            j = k - 1
            state, reason = (PieceState.REJECTED, FLAP) if j in rejects else (PieceState.LEFT, None)
            gone = [*gone, piece(j, state, 0.5, True, reason, found_s)][-GONE_KEPT:]
    yield gone  # the table empty


def test_counts_follow_each_piece_past_the_statuss_last_fifty_and_a_flow_started_afresh() -> None:
    """120 pieces, scraped at random moments (seeded) and at the end: the counts are the pieces, though the
    status never lists more than 50 gone. Then two short flows, each started afresh with ids from 0, and no
    scrape saw the idle between them: the second's pieces are new ones all the same (first seen later)."""
    rng = random.Random(37)
    client, hub = _client()
    rejects = set(rng.sample(range(120), 9))
    for statuses in (_flow(120, rejects, 100.0), _flow(3, set(), 5000.0), _flow(3, set(), 6000.0)):
        for pieces in statuses:
            publish(hub, pieces)
            if rng.random() < 0.3:
                _metrics(client)
        _metrics(client)  # the flow's last status: every piece gone, the last 50 of them listed
        publish(hub, None, Mode.IDLE)  # left mode flow; no scrape sees it
    assert _counts(_metrics(client)) == (126, 126 - 9, 9)


def test_a_flow_no_scrape_saw_is_counted() -> None:
    client, hub = _client()
    for pieces in _flow(60, {3, 40}, 100.0):
        publish(hub, pieces)
    publish(hub, None, Mode.IDLE)  # the flow ended before the first scrape: its pieces are listed nowhere
    assert _counts(_metrics(client)) == (60, 58, 2)


def test_pieces_left_on_the_table_when_the_flow_ends_are_counted_abandoned() -> None:
    """A flow halted with pieces on the table: those not rejected are abandoned; a new flow finds them
    again and counts them in as pieces of its own, so in = out + rejected + abandoned + on the table."""
    client, hub = _client()
    table = [
        piece(1, PieceState.FLATTENING, 0.1, found_s=10.0),
        piece(2, PieceState.REJECTED, -0.1, reason=FLAP, found_s=12.0),
        piece(0, PieceState.LEFT, 0.5, gone=True, found_s=8.0),
    ]
    publish(hub, table)
    publish(hub, None, Mode.IDLE)  # halted
    m = _metrics(client)
    assert _counts(m) == (3, 1, 1) and m["clothd_pieces_abandoned_total"] == 1
    publish(
        hub,
        [piece(0, PieceState.TRACKED, 0.1, found_s=50.0), piece(1, PieceState.TRACKED, -0.1, found_s=50.0)],
    )
    m = _metrics(client)
    pieces_in, pieces_out, rejected = _counts(m)
    on_table = 2
    assert (
        pieces_in == 5 and pieces_in == pieces_out + rejected + m["clothd_pieces_abandoned_total"] + on_table
    )


class _StubCell:
    """hwsim's cell as its HTTP handler sees it, its outfeed as hwsim/outfeed.py's judge writes it."""

    streams: tuple[object, ...] = ()
    judged: ClassVar[list[dict[str, object]]] = [
        {
            "id": 2,
            "fabric": "cotton",
            "size_m": [0.2, 0.15],
            "flap": False,
            "laid_s": 1.5,
            "left_s": 21.5,
            "t_s": 20.0,
            "max_height_mm": 0.6,
            "pose_error_mm": 1.2,
            "pose_error_deg": 0.3,
            "pose": [0.95, 0.001, 0.3],
            "folded_ratio": 0.0,
        }
    ]

    def outfeed(self) -> list[dict[str, object]]:
        return self.judged

    def truth(self, with_nodes: bool) -> dict[str, Any]:
        return {"t_s": 3.0, "with_nodes": with_nodes}


@pytest.fixture
def hwsim_url() -> Iterator[str]:
    handler = type("Handler", (_Handler,), {"cell": _StubCell()})
    server = ThreadingHTTPServer(("127.0.0.1", 0), handler)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    try:
        yield f"http://127.0.0.1:{server.server_address[1]}/truth"  # as hwsim's ready line gives it
    finally:
        server.shutdown()
        server.server_close()


def test_sim_outfeed_relays_hwsims_judged_pieces_beside_its_truth(hwsim_url: str) -> None:
    client, _ = _client(hwsim_url)
    r = client.get("/api/v1/sim/outfeed")
    assert r.status_code == 200 and r.json() == _StubCell.judged
    assert client.get("/api/v1/sim/truth").json() == {"t_s": 3.0, "with_nodes": True}
    assert client.get("/api/v1/sim/truth?nodes=false").json() == {"t_s": 3.0, "with_nodes": False}


def test_sim_outfeed_is_404_without_hwsim_and_503_when_hwsim_does_not_serve_it(hwsim_url: str) -> None:
    client, _ = _client()
    r = client.get("/api/v1/sim/outfeed")
    assert r.status_code == 404 and "clothd run --sim" in r.json()["detail"]
    gone = hwsim_url.replace("/truth", "/nothing/truth")  # answers 404: not an outfeed
    r = _client(gone)[0].get("/api/v1/sim/outfeed")
    assert r.status_code == 503 and "hwsim's outfeed is not answering" in r.json()["detail"]
