"""hwsim's production flow (scenario keys `infeed` and `flow`): pieces laid at the -x edge at a rate from
seeded ranges, pulled in by the belts, several on the table at once, and judged from their truth as they
reach the +x edge. One seeded world runs a simulated minute with every belt carrying +x at the infeed
conveyor's speed; the tests read what it recorded."""

from __future__ import annotations

import json
import math
import threading
import urllib.request
from dataclasses import dataclass, field
from http.server import ThreadingHTTPServer
from typing import Any

import numpy as np
import pytest

from hwsim import scenario as scenarios
from hwsim.cloth_grid import ClothGrid
from hwsim.infeed import InfeedPlan
from hwsim.scenario import ScenarioError
from hwsim.serve import Cell, _Handler
from hwsim.world import World

SPEED_M_S = 0.2  # the modules' and the infeed conveyor's: matched, so nothing pulls a ridge flat
RUN_S = 60.0
X_MIN_M = -0.45  # flow.yaml's 12 modules at 0.075 m


def _scenario(**infeed: object) -> scenarios.Scenario:
    """flow.yaml on a coarser truth mesh (12.5 mm, 1 ms substeps), to keep a simulated minute short."""
    data = scenarios.load("flow").model_dump()
    data["cloth"].update(spacing_m=0.0125, substep_s=0.001)
    data.update(settle_s=0.0, seed=4)
    data["infeed"].update(
        {"first_s": 0.5, "speed_m_s": SPEED_M_S, "ridges": [1, 1], "ridge_height_mm": [10, 12]}
    )
    data["infeed"].update(infeed)
    return scenarios.parse(data)


@dataclass
class Run:
    world: World
    laid: list[tuple[int, float, np.ndarray]] = field(default_factory=list)  # id, t_s, its nodes then
    track: dict[int, list[tuple[float, float]]] = field(default_factory=dict)  # id: (t_s, leading x)
    most_at_once: int = 0


@pytest.fixture(scope="module")
def run() -> Run:
    world = World(_scenario(), log_commands=False)
    world.table.command(np.arange(world.table.n_modules), SPEED_M_S, 0.0)
    out = Run(world)
    seen = {p.id for p in world.pieces}
    for _ in range(round(RUN_S * world.scenario.fps)):
        world.step()
        for p in world.pieces:
            nodes = p.cloth.positions_m()
            if p.id not in seen:
                seen.add(p.id)
                out.laid.append((p.id, world.t_s, nodes))
            out.track.setdefault(p.id, []).append((world.t_s, float(nodes[..., 0].max())))
        out.most_at_once = max(out.most_at_once, len(world.pieces))
    return out


def test_infeed_draws_are_seeded_and_within_their_ranges() -> None:
    sc = _scenario(ridges=[1, 2], ridge_height_mm=[5, 15], fabrics=["denim", "shirting", "lining"])
    first = [InfeedPlan(sc, sc.infeed).draw() for _ in range(1)]  # type: ignore[arg-type]
    plan, again = InfeedPlan(sc, sc.infeed), InfeedPlan(sc, sc.infeed)  # type: ignore[arg-type]
    pieces = [plan.draw() for _ in range(30)]
    assert [again.draw() for _ in range(30)] == pieces
    assert pieces[0] == first[0]
    assert {p.fabric for p in pieces} == {"denim", "shirting", "lining"}
    for p in pieces:
        assert 0.22 <= p.spec.size_m[0] <= 0.28 and 0.18 <= p.spec.size_m[1] <= 0.22
        assert 1 <= len(p.pose.ridges) <= 2
        assert all(5.0 <= r.height_m * 1e3 <= 15.0 for r in p.pose.ridges)
        assert abs(math.degrees(p.pose.theta_rad)) <= 10.0 and abs(p.pose.y_m) <= 0.03
        # Laid with its leading edge one module pitch in over the -x edge, the rest off the table.
        nodes = ClothGrid.from_spec(p.spec).placed(p.pose)
        assert nodes[..., 0].max() == pytest.approx(X_MIN_M + 0.075, abs=1e-9)
        assert nodes[..., 0].min() < X_MIN_M - 0.1
    other = _scenario(ridges=[1, 2], ridge_height_mm=[5, 15])
    reseeded = scenarios.parse({**other.model_dump(), "seed": 5})
    assert InfeedPlan(reseeded, reseeded.infeed).draw() != InfeedPlan(other, other.infeed).draw()  # type: ignore[arg-type]


@pytest.mark.parametrize(
    ("change", "key"),
    [
        ({"infeed": {"rate_per_min": 0}}, "infeed.rate_per_min"),
        ({"infeed": {"size_s_m": [0.3, 0.2]}}, "infeed"),
        ({"infeed": {"ridges": [0, 5]}}, "infeed"),
        ({"infeed": {"y_m": [-0.3, 0.0]}}, "infeed.y_m"),
        ({"infeed": {"speed": 0.1}}, "infeed.speed"),
        ({"infeed": None, "flow": {}}, "flow: needs an infeed"),
        ({"flow": {"placement": {"x_m": 0.6}}}, "flow.placement"),
    ],
)
def test_bad_flow_keys_are_refused_naming_the_key(change: dict[str, Any], key: str) -> None:
    data = scenarios.load("flow").model_dump()
    for k, v in change.items():
        data[k] = {**data[k], **v} if isinstance(v, dict) and isinstance(data.get(k), dict) else v
    with pytest.raises(ScenarioError, match=key):
        scenarios.parse(data)


def test_a_laid_piece_enters_partly_in_view_and_the_belts_pull_it_in(run: Run) -> None:
    piece_id, t_laid, nodes = run.laid[0]
    assert piece_id == 1 and t_laid == pytest.approx(0.5, abs=0.034)  # the first frame from 0.5 s on
    assert nodes[..., 0].max() == pytest.approx(X_MIN_M + 0.075, abs=0.003)
    assert nodes[..., 0].min() < X_MIN_M - 0.1  # the rest still on the infeed conveyor
    track = np.array(run.track[1])
    one_s = track[(track[:, 0] >= t_laid + 1.0)][0]
    advanced_m = one_s[1] - track[0, 1]
    assert advanced_m == pytest.approx(SPEED_M_S * (one_s[0] - track[0, 0]), rel=0.05)


def test_two_pieces_lie_on_the_table_at_once(run: Run) -> None:
    assert run.most_at_once >= 2


def test_the_infeed_keeps_its_rate_over_a_minute(run: Run) -> None:
    # Due at 0.5, 10.5, ... 50.5 s: six pieces a minute, each laid when due (the entry is clear).
    assert abs(len(run.laid) - 6) <= 1
    gaps = np.diff([t for _, t, _ in run.laid])
    assert np.allclose(gaps, 10.0, atol=0.05)


def test_the_outfeed_judges_each_piece_from_its_truth(run: Run) -> None:
    out = {r["id"]: r for r in run.world.outfeed}
    assert set(out) >= {0, 1, 2, 3, 4}  # piece 0 and the infeed's first four have crossed by 60 s
    flat = out[0]  # the scenario's own cloth, laid flat
    assert float(flat["max_height_mm"]) < 1.0
    assert float(flat["pose_error_mm"]) < 1.0 and float(flat["pose_error_deg"]) < 0.2
    for k in (1, 2, 3, 4):
        r = out[k]
        assert float(r["max_height_mm"]) > 3.0  # laid with a 10-12 mm ridge, carried without a pull
        _, t_laid, nodes = run.laid[k - 1]
        # Laid one pitch in, carried at SPEED_M_S until the leading edge reaches the +x edge.
        assert float(r["t_s"]) == pytest.approx((0.9 - 0.075) / SPEED_M_S, abs=0.2)
        assert float(r["laid_s"]) == pytest.approx(t_laid)
        y_laid = float(nodes[..., 1].mean())
        assert float(r["pose_error_mm"]) == pytest.approx(abs(y_laid) * 1e3, abs=2.0)
    assert all(p.id not in (0, 1, 2, 3) for p in run.world.pieces)  # taken off the table


class _StubCell:
    streams: tuple[object, ...] = ()

    def outfeed(self) -> list[dict[str, object]]:
        return [{"id": 3, "max_height_mm": 0.4, "pose_error_mm": 1.5, "pose_error_deg": 0.2, "t_s": 12.0}]


def test_get_outfeed_serves_the_judged_pieces() -> None:
    handler = type("Handler", (_Handler,), {"cell": _StubCell()})
    server = ThreadingHTTPServer(("127.0.0.1", 0), handler)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    try:
        url = f"http://127.0.0.1:{server.server_address[1]}/outfeed"
        with urllib.request.urlopen(url, timeout=5) as reply:
            assert json.loads(reply.read()) == _StubCell().outfeed()
    finally:
        server.shutdown()
        server.server_close()


def test_the_truth_without_nodes_and_the_outfeed_answer_while_the_world_holds_its_lock() -> None:
    """A world behind real time takes its lock back at once after every step: a reader of the truth waited
    seconds for it. The truth without nodes and the outfeed are the last step's, read without the lock."""
    cell = Cell.__new__(Cell)  # the world thread's state only: no world, cameras or firmware
    cell.lock = threading.Lock()
    cell._truth_cache = {"t_s": 2.0, "behind_real_time_s": 0.5}
    cell._outfeed_cache = ({"id": 0, "max_height_mm": 0.2},)
    answered: list[object] = []

    def read() -> None:
        answered.extend([cell.truth(with_nodes=False), cell.outfeed()])

    with cell.lock:  # the world stepping
        reader = threading.Thread(target=read)
        reader.start()
        reader.join(timeout=5.0)
        assert answered == [{"t_s": 2.0, "behind_real_time_s": 0.5}, [{"id": 0, "max_height_mm": 0.2}]]
