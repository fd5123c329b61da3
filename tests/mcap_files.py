"""Reading clothd's MCAP files back with the `mcap` package, for the export and live-recording tests."""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from mcap.exceptions import EndOfFile, RecordLengthLimitExceeded
from mcap.reader import NonSeekingReader, make_reader

# The channels `clothd export` writes, and a live MCAP recording and the Foxglove server the same.
FOXGLOVE_SCHEMAS = {
    "/camera": "foxglove.CompressedImage",
    "/mesh": "foxglove.SceneUpdate",
    "/pose": "foxglove.PoseInFrame",
    "/commands": "clothd.ModuleCommands",
    "/status": "clothd.FrameStatus",
}
# `clothd export` adds the annotated view where the recording has a camera.json.
EXPORT_SCHEMAS = FOXGLOVE_SCHEMAS | {"/camera/annotated": "foxglove.CompressedImage"}


@dataclass
class McapContents:
    schemas: dict[str, str]  # topic: schema name
    times: dict[str, list[int]] = field(default_factory=dict)  # topic: log times, in file order
    json: dict[str, list[dict[str, Any]]] = field(default_factory=dict)  # the JSON topics' messages
    summary_messages: int | None = None  # the summary's statistics (a finished file)
    cut_short: bool = False  # the file ended inside a record


def read_mcap(path: Path) -> McapContents:
    """A finished file, through its summary (a seeking reader, as Foxglove reads it)."""
    with path.open("rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        assert summary is not None and summary.statistics is not None, f"{path}: no summary"
        schemas = {c.topic: summary.schemas[c.schema_id].name for c in summary.channels.values()}
        out = McapContents(schemas, summary_messages=summary.statistics.message_count)
        for _, channel, message in reader.iter_messages(log_time_order=False):
            _add(out, channel.topic, message.log_time, channel.message_encoding, message.data)
    return out


def read_mcap_front_to_back(path: Path) -> McapContents:
    """Any file, finished or cut short, read record by record up to where it ends."""
    out = McapContents({})
    with path.open("rb") as f:
        try:
            for schema, channel, message in NonSeekingReader(f).iter_messages(log_time_order=False):
                if schema is not None:
                    out.schemas[channel.topic] = schema.name
                _add(out, channel.topic, message.log_time, channel.message_encoding, message.data)
        # A file cut short ends in a record cut short, or in the chunk being written, whose length the
        # writer had not yet patched in (it is all ones until then).
        except (EndOfFile, RecordLengthLimitExceeded):
            out.cut_short = True
    return out


def _add(out: McapContents, topic: str, log_time: int, encoding: str, data: bytes) -> None:
    out.times.setdefault(topic, []).append(log_time)
    if encoding == "json":
        out.json.setdefault(topic, []).append(json.loads(data))
