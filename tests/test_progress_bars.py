"""Every progress bar is off when its output is not a terminal (README: a bench prints nothing extra when
piped or logged): tqdm's `disable=None` does that, and each call in clothd/ passes it."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

pytestmark = pytest.mark.clock_free

ROOT = Path(__file__).resolve().parents[1]


def _bars_shown_when_piped(tree: ast.AST) -> list[int]:
    """Lines of the tqdm(...) calls that do not pass disable=None."""
    lines = []
    for node in ast.walk(tree):
        func = node.func if isinstance(node, ast.Call) else None
        name = func.id if isinstance(func, ast.Name) else func.attr if isinstance(func, ast.Attribute) else ""
        if isinstance(node, ast.Call) and name in ("tqdm", "trange"):
            disable = next((k.value for k in node.keywords if k.arg == "disable"), None)
            if not (isinstance(disable, ast.Constant) and disable.value is None):
                lines.append(node.lineno)
    return lines


def test_every_progress_bar_is_off_when_piped() -> None:
    found = {
        str(path.relative_to(ROOT)): lines
        for path in sorted((ROOT / "clothd").rglob("*.py"))
        if (lines := _bars_shown_when_piped(ast.parse(path.read_text())))
    }
    assert not found, f"tqdm without disable=None: {found}"


def test_the_check_sees_a_bar_left_on() -> None:
    code = (
        "for _ in tqdm(range(3), leave=False):\n    pass\nbar = tqdm(total=3, disable=None)\n"
        "other = tqdm.tqdm(total=3)\nfor _ in trange(3):\n    pass\n"
    )
    assert _bars_shown_when_piped(ast.parse(code)) == [1, 4, 5]
