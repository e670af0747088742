"""A recording's MCAP channels: each registered with its schema on first use, then written.

A record becomes JSON (``common.recording.mcap_json``) on a channel of its name, its
schema inferred from the first record, or one of Foxglove's own
(``common.recording.foxglove``: the camera's pictures and the log lines in place, and
the views derived from records on channels of their own, marked
``deepxpalm.view_of``). Used by the recorder's writer thread only.
"""

from __future__ import annotations

import dataclasses
import json
from typing import Any

from mcap.writer import Writer

from common.recording import foxglove
from common.recording.channels import CHANNELS
from common.recording.mcap_json import (
    ENC_KEY,
    MESSAGE_ENCODING,
    NONFINITE_KEY,
    SCHEMA_ENCODING,
    SCHEMA_PREFIX,
    VIEW_OF_KEY,
    decoded_fields,
    encodings_in_schema,
    schema_of,
    to_json,
)


@dataclasses.dataclass
class ChannelState:
    id: int
    encs: dict[str, str]
    seq: int = 0


class McapChannels:
    """The channels of one MCAP writer, and how a record is written to its channel."""

    def __init__(
        self, writer: Writer, wall_offset_ns: int, *, decode_wire: bool, foxglove_views: bool
    ) -> None:
        self._writer = writer
        self.wall_offset_ns = wall_offset_ns
        self._decode_wire = decode_wire
        self._foxglove = foxglove_views
        self._channels: dict[str, ChannelState] = {}

    def add_record(self, channel: str, t_ns: int, record: dict[str, Any]) -> bool:
        """Write ``record`` on ``channel`` (its wire bytes decoded, a camera picture as
        Foxglove's own type); True when it held NaN or inf, written as null."""
        if self._decode_wire and isinstance(record.get("wire"), (bytes, bytearray)):
            record["decoded"] = decoded_fields(bytes(record["wire"]))
        if channel in foxglove.IN_PLACE:
            record.update(foxglove.camera_fields(record, t_ns + self.wall_offset_ns))
        return self._add_json(channel, t_ns, record)

    def add_views(self, channel: str, t_ns: int, record: dict[str, Any]) -> None:
        """The Foxglove views derived from a record written on ``channel`` (if asked for)."""
        if self._foxglove:
            for topic, message in foxglove.views(channel, record, t_ns + self.wall_offset_ns):
                self._add_view(topic, channel, t_ns, message)

    def _add_view(self, topic: str, source: str, t_ns: int, message: dict[str, Any]) -> None:
        """A Foxglove message derived from a record, on a channel of its own."""
        state = self._channels.get(topic)
        if state is None:
            state = self._register_typed(topic, foxglove.VIEW_TOPICS[topic], {VIEW_OF_KEY: source})
        self._write_message(state, t_ns, json.dumps(message, separators=(",", ":")).encode())

    def _add_json(self, channel: str, t_ns: int, record: dict[str, Any]) -> bool:
        encs: dict[str, str] = {}
        nonfinite: list[str] = []
        body = to_json(record, "", encs, nonfinite)
        state = self._channels.get(channel)
        if state is None:
            state = self._register(channel, body, encs)
        if encs != state.encs:
            body[ENC_KEY] = encs
        if nonfinite:
            body[NONFINITE_KEY] = nonfinite
        self._write_message(
            state, t_ns, json.dumps(body, separators=(",", ":"), allow_nan=False).encode()
        )
        return bool(nonfinite)

    def _write_message(self, state: ChannelState, t_ns: int, data: bytes) -> None:
        state.seq += 1
        self._writer.add_message(
            state.id,
            log_time=max(0, t_ns + self.wall_offset_ns),
            data=data,
            publish_time=max(0, t_ns),
            sequence=state.seq & 0xFFFFFFFF,
        )

    def _register_typed(
        self, channel: str, type_name: str, metadata: dict[str, str] | None = None
    ) -> ChannelState:
        """A channel whose schema is one of Foxglove's (docs/recording.md, "Foxglove")."""
        schema = foxglove.SCHEMAS[type_name]
        schema_id = self._writer.register_schema(
            type_name, SCHEMA_ENCODING, json.dumps(schema).encode()
        )
        cid = self._writer.register_channel(channel, MESSAGE_ENCODING, schema_id, metadata or {})
        state = ChannelState(cid, encodings_in_schema(schema))
        self._channels[channel] = state
        return state

    def _register(self, channel: str, body: dict[str, Any], encs: dict[str, str]) -> ChannelState:
        if channel in foxglove.IN_PLACE:
            return self._register_typed(channel, foxglove.IN_PLACE[channel])
        if channel == foxglove.LOG_CHANNEL:
            return self._register_typed(channel, "foxglove.Log")
        schema = schema_of(body, "", encs) or {"type": "object", "properties": {}}
        schema["title"] = channel
        if channel in CHANNELS:
            schema["description"] = CHANNELS[channel]
        schema_id = self._writer.register_schema(
            SCHEMA_PREFIX + channel, SCHEMA_ENCODING, json.dumps(schema).encode()
        )
        cid = self._writer.register_channel(channel, MESSAGE_ENCODING, schema_id)
        state = ChannelState(cid, encodings_in_schema(schema))
        self._channels[channel] = state
        return state
