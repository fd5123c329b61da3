"""Argument types and defaults of the `clothd` command's options, shared by its subcommands."""

from __future__ import annotations

import argparse
from typing import TypeAlias

# Trials per search for clothd tune and clothd bench tune: the one count that met the held-out bar on every
# seed tried (docs/commissioning.md, "How many trials").
TUNE_TRIALS = 100

Subparsers: TypeAlias = "argparse._SubParsersAction[argparse.ArgumentParser]"


def add_cameras(parser: argparse.ArgumentParser, default: int | None, help_text: str) -> None:
    """--cameras N: the first N cameras (1 or 2) of what `help_text` names; default None: all."""
    parser.add_argument("--cameras", type=int, choices=[1, 2], default=default, help=help_text)


def positive_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        value = 0
    if value < 1:
        raise argparse.ArgumentTypeError(f"{text!r}: a whole number, at least 1")
    return value


def skew_ms(text: str) -> float:
    """A capture skew in milliseconds, 0-100 (hwsim's scenarios allow up to 0.1 s)."""
    try:
        value = float(text)
    except ValueError:
        value = -1.0
    if not 0.0 <= value <= 100.0:
        raise argparse.ArgumentTypeError(f"{text!r}: milliseconds, 0 to 100")
    return value


def numbers(text: str, count: int) -> tuple[float, ...]:
    try:
        values = tuple(float(v) for v in text.split(","))
    except ValueError:
        values = ()
    if len(values) != count:
        raise argparse.ArgumentTypeError(f"{text!r}: {count} numbers separated by commas")
    return values


def xy_m(text: str) -> tuple[float, float]:
    """'-0.21,0.12' -> (-0.21, 0.12), for --flat-origin-m."""
    x, y = numbers(text, 2)
    return x, y


def dist(text: str) -> tuple[float, float, float, float, float]:
    """'k1,k2,p1,p2,k3', for --dist."""
    k1, k2, p1, p2, k3 = numbers(text, 5)
    return k1, k2, p1, p2, k3


def board_size(text: str) -> tuple[int, int]:
    """'9x6' -> (9, 6) squares, for --board."""
    nx, sep, ny = text.lower().partition("x")
    if not (sep and nx.isdigit() and ny.isdigit() and 3 <= int(nx) <= 40 and 3 <= int(ny) <= 40):
        raise argparse.ArgumentTypeError(f"{text!r}: a board is SQUARES_XxSQUARES_Y, each 3..40 (e.g. 9x6)")
    return int(nx), int(ny)


# Options whose value is a comma-separated list that may start with a minus sign.
SIGNED_LISTS = ("--flat-origin-m", "--dist")


def glue_signed_lists(argv: list[str]) -> list[str]:
    """argparse reads '-0.21,0.12' as an unknown option, not a value: join it to its flag with '='."""
    out: list[str] = []
    for arg in argv:
        if out and out[-1] in SIGNED_LISTS and arg.startswith("-") and "," in arg:
            out[-1] = f"{out[-1]}={arg}"
        else:
            out.append(arg)
    return out


def mesh_size(text: str) -> tuple[int, int]:
    """'32x24' -> (32, 24), for --mesh."""
    nx, sep, ny = text.lower().partition("x")
    if not (sep and nx.isdigit() and ny.isdigit() and 2 <= int(nx) <= 64 and 2 <= int(ny) <= 64):
        raise argparse.ArgumentTypeError(f"{text!r}: a mesh is NXxNY, each 2..64 (e.g. 32x24)")
    return int(nx), int(ny)
