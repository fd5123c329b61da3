"""`clothd check-modules` against a live simulated cell whose module 9 is wired the wrong way round, 10°
off and 20 % slow (hwsim's cell-miscalibrated): it finds all three, finds a good module good, and
refuses a module under the cloth by name."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest
from live_cell import Cell, Daemon, serve_cell, start_daemon

from clothd.cli import main
from clothd.tools.cell_client import CellClient, CellError
from clothd.tools.check_modules import check_modules
from clothd.tools.commissioning_cli import SIM_FRAME_PERIOD_S


@pytest.fixture(scope="module")
def cell(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Cell]:
    yield from serve_cell(tmp_path_factory, "cell-miscalibrated")


@pytest.fixture
def daemon(cell: Cell, tmp_path: Path) -> Iterator[Daemon]:
    d = start_daemon(cell, tmp_path, config={"recording": {"max_bytes": 500_000_000}})
    try:
        yield d
    finally:
        d.stop()


def test_check_modules_finds_a_miswired_module_and_refuses_one_under_the_cloth(daemon: Daemon) -> None:
    client = CellClient(daemon.base)
    try:
        with pytest.raises(CellError, match="module 27 lies under the cloth"):
            check_modules(client, [9, 27])
        # hwsim's camera, on hwsim's clock: it falls behind real time on a loaded machine.
        results, _, recording = check_modules(client, [9, 1], SIM_FRAME_PERIOD_S)
    finally:
        client.close()
    wrong, good = (r.entry for r in results)
    assert wrong.module == 9 and wrong.reversed
    assert wrong.heading_offset_deg == pytest.approx(10.0, abs=2.0)
    assert not good.reversed and good.heading_offset_deg == pytest.approx(0.0, abs=2.0)
    assert wrong.speed_scale == pytest.approx(0.8, rel=0.03)
    assert good.speed_scale == pytest.approx(1.0, rel=0.03)
    assert (recording / "frames.csv").exists()


def test_a_simulated_cell_that_cannot_start_says_why(capsys: pytest.CaptureFixture[str]) -> None:
    """`check-modules --sim` starts `clothd run --sim`: its reason, not only its exit code, is shown."""
    assert main(["check-modules", "--sim", "no-such-scenario"]) == 2
    err = capsys.readouterr().err
    assert "exited with 2: hwsim: no-such-scenario: no such file, and not a shipped scenario" in err
