"""The command line's own parsing: what `clothd bench speed` picks from --features and --mesh."""

from __future__ import annotations

import pytest

from clothd.cli import build_parser


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
