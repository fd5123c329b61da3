"""Pieces in, out and rejected, counted from the statuses an interface sees (metrics, OPC UA).

A status lists every piece on the table, then only the last pieces gone (clothd/core/pieces.py keeps 50):
its length says nothing of how many passed. So each piece is counted by its transitions, once: in when
first seen, rejected when first seen rejected (still on the table, being driven out, or gone), out when
first seen left. A piece is known by its id and when it was first found, so a flow started afresh (its ids
from 0 again) counts its pieces anew. Only the pieces of the last status are remembered: one that has
dropped off the list never comes back.

A piece still on the table, not rejected, when its flow ends (mode flow left, or a flow started afresh)
is counted abandoned: the operator takes it off, or a new flow finds it and counts it in again as a piece
of its own. Counted so, in = out + rejected + abandoned + the pieces on the table not rejected.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Sequence

from clothd.core.modes import PieceState
from clothd.loop.status import PieceStatus

ON_TABLE_STATES = tuple(s for s in PieceState if s != PieceState.LEFT)  # a piece that left is gone


def on_table(pieces: Sequence[PieceStatus] | None) -> list[PieceStatus]:
    """The pieces still on the table (not yet let go), oldest first."""
    return [p for p in pieces or () if p.left_t_mono_s is None and p.state != PieceState.LEFT]


def by_state(pieces: Sequence[PieceStatus] | None) -> dict[PieceState, int]:
    """How many pieces on the table are in each state (every state a piece on the table can be in)."""
    counts = Counter(p.state for p in on_table(pieces))
    return {state: counts[state] for state in ON_TABLE_STATES}


class PieceCounts:
    def __init__(self) -> None:
        self.pieces_in = 0
        self.pieces_out = 0
        self.rejected = 0
        self.abandoned = 0
        self._marks: dict[tuple[int, float], set[str]] = {}  # the last status's pieces: what was counted

    def see(self, pieces: Sequence[PieceStatus] | None) -> list[PieceStatus]:
        """Count what is new in this status's pieces (None outside mode flow), and the pieces its flow
        abandoned; the pieces that have gone (left or rejected, let go over the outfeed edge) since the last
        status, oldest first."""
        marks: dict[tuple[int, float], set[str]] = {}
        gone = []
        for p in pieces or ():
            key = (p.id, p.found_t_mono_s)
            seen = marks[key] = self._marks.get(key, set())
            if not seen:
                self.pieces_in += 1
                seen.add("in")
            if p.state == PieceState.REJECTED and "rejected" not in seen:
                self.rejected += 1
                seen.add("rejected")
            if (p.left_t_mono_s is not None or p.state == PieceState.LEFT) and "gone" not in seen:
                if p.state == PieceState.LEFT:
                    self.pieces_out += 1
                seen.add("gone")
                gone.append(p)
        # Gone from the list neither left nor rejected: only a flow's end takes a piece off it so.
        self.abandoned += sum(
            not seen & {"gone", "rejected"} for k, seen in self._marks.items() if k not in marks
        )
        self._marks = marks
        return gone
