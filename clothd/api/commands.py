"""The daemon's commands as every API gives them: the REST handlers (app.py) and the OPC UA methods
(opcua_server.py) call these, so both answer and refuse alike.

Each runs on the daemon's loop (the Cell, cell.py) and returns the answer in words, or raises the
daemon's ClothdError: RequestError (not possible in the present state: HTTP 409), InvalidRequestError
(never possible as given: 422). Each API maps those to its own codes.
"""

from __future__ import annotations

import re
from collections.abc import Sequence
from typing import Any

import numpy as np
from pydantic import ValidationError

from clothd.api.cell import Cell
from clothd.api.schemas import DriveSetpoint, MoveSetpoint, SetpointRequest
from clothd.errors import InvalidRequestError

# An unknown mode is named in the answer only when it is a plain word: the input may be huge, markup, or
# not even serialisable (NaN, a lone surrogate).
_NAMEABLE = re.compile(r"[A-Za-z0-9_-]{1,32}")


def describe_invalid(errors: Sequence[Any]) -> str:
    """pydantic's errors as one line: where and what, never the input but an unknown mode's plain name."""
    where = (".".join(str(part) for part in e["loc"]) for e in errors)
    return "; ".join(f"{w}: {_message(e)} ({e['type']})" for w, e in zip(where, errors, strict=True))


def _message(error: Any) -> str:
    if error["type"] == "union_tag_invalid":  # pydantic names the tags by their repr: say the words
        ctx = error["ctx"]
        tags = ", ".join(re.findall(r"'([^']*)'", ctx["expected_tags"]))
        field = ctx["discriminator"].strip("'")
        tag = str(ctx["tag"])
        named = f"{field} {tag!r}" if _NAMEABLE.fullmatch(tag) else f"the {field} given"
        return f"{named} is none of: {tags}"
    return str(error["msg"])


class Commands:
    def __init__(self, cell: Cell) -> None:
        self.cell = cell

    async def setpoint(self, body: SetpointRequest) -> str:
        pose = (
            np.array([body.x_m, body.y_m, body.theta_rad], dtype=float)
            if isinstance(body, MoveSetpoint)
            else None
        )
        script = body.script if isinstance(body, DriveSetpoint) else None
        await self.cell.set_setpoint(body.mode, pose, script)
        return f"mode {body.mode}"

    async def move(self, x_m: float, y_m: float, theta_rad: float) -> str:
        """A move validated as PUT /setpoint validates its body (the same bounds, the same words)."""
        try:
            move = {"mode": "move", "x_m": x_m, "y_m": y_m, "theta_rad": theta_rad}
            body = MoveSetpoint.model_validate(move)
        except ValidationError as err:
            raise InvalidRequestError(describe_invalid(err.errors())) from None
        return await self.setpoint(body)

    async def estop(self) -> str:
        await self.cell.estop()
        return "emergency stop latched"

    async def estop_clear(self) -> str:
        if await self.cell.estop_clear():
            return "emergency stop cleared; mode is idle"
        return "no emergency stop was latched"

    async def reset(self) -> str:
        await self.cell.reset()
        return "tracking re-initialises on the next frame"
