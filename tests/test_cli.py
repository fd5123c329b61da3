"""The command line's own parsing: `--version`, and what `clothd bench speed` picks from --features and
--mesh."""

from __future__ import annotations

import json
from importlib.metadata import version
from pathlib import Path

import pytest

from clothd.cli import build_parser
from clothd.errors import InvalidRequestError
from clothd.tools.bench_speed import STAGES, Row, format_rows, plot, read_rows, rows_json

pytestmark = pytest.mark.clock_free


def test_version_is_the_installed_packages(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as done:
        build_parser().parse_args(["--version"])
    assert done.value.code == 0 and capsys.readouterr().out == f"clothd {version('clothd')}\n"


def test_bench_speed_takes_feature_budgets_and_mesh_sizes_repeated_or_listed() -> None:
    args = build_parser().parse_args(
        ["bench", "speed", "--features", "1000", "2000", "--mesh", "32x32", "24X24", "--mesh", "12x12"]
    )
    assert args.features == [1000, 2000]
    assert args.mesh == [(32, 32), (24, 24), (12, 12)]
    defaults = build_parser().parse_args(["bench", "speed"])
    assert defaults.features is None and defaults.mesh is None


@pytest.mark.parametrize("bad", ["32", "32x", "1x12", "12x65", "axb"])
def test_a_bad_mesh_size_is_refused_with_its_form(bad: str, capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as done:
        build_parser().parse_args(["bench", "speed", "--mesh", bad])
    assert done.value.code == 2 and "NXxNY" in capsys.readouterr().err


def test_bench_speed_plots_its_rows_beside_a_baseline_read_back_from_json(tmp_path: Path) -> None:
    args = build_parser().parse_args(["bench", "speed", "--plot", "p.png", "--baseline", "old.json"])
    assert args.plot == Path("p.png") and args.baseline == Path("old.json")
    rows = [
        Row(budget, mesh, "clothd", stage, 1.0 + n, 2.0 + n, budget - 1)
        for budget in (1000, 2000)
        for n, mesh in enumerate(("12x12", "24x24", "32x32"))
        for stage in STAGES
    ]
    (tmp_path / "old.json").write_text(json.dumps(rows_json(rows)))
    before = read_rows(tmp_path / "old.json", " before")
    assert {r.impl for r in before} == {"clothd before"} and len(before) == len(rows)
    assert "clothd before" in format_rows(rows + before)
    plot(rows, tmp_path / "p.png", before)
    assert (tmp_path / "p.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


@pytest.mark.parametrize("bad", ["-1", "101", "ten"])
def test_bench_flatten_refuses_a_skew_outside_what_hwsim_renders(
    bad: str, capsys: pytest.CaptureFixture[str]
) -> None:
    with pytest.raises(SystemExit) as done:
        build_parser().parse_args(["bench", "flatten", "--lockstep", "--skew-ms", bad])
    assert done.value.code == 2 and "milliseconds, 0 to 100" in capsys.readouterr().err


@pytest.mark.parametrize(
    ("extra", "reason"),
    [([], "needs --lockstep"), (["--lockstep", "--cameras", "1"], "needs a second camera")],
)
def test_bench_flatten_takes_a_skew_only_where_it_can_render_one(extra: list[str], reason: str) -> None:
    args = build_parser().parse_args(["bench", "flatten", "--skew-ms", "10", *extra])
    with pytest.raises(InvalidRequestError, match=reason):
        args.func(args)


def test_bench_accuracy_takes_a_skew_only_beside_a_second_camera() -> None:
    args = build_parser().parse_args(["bench", "accuracy", "--skew-ms", "10"])
    with pytest.raises(InvalidRequestError, match="needs a second camera"):
        args.func(args)
