"""Helpers for the replay / compare / audit tests: record a simulator session,
rewrite an MCAP file with edits (as an editing tool would, with valid CRCs)."""

from __future__ import annotations

import copy
import json
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from mcap.records import Attachment, Channel, Header, Message, Metadata, Schema
from mcap.stream_reader import StreamReader
from mcap.writer import Writer

from crossfield.config import parse_config
from crossfield.registry import make_plugin_manager
from crossfield.runner import run_session
from crossfield.session import SessionSummary

#: report.json keys that name the run, not its results (compared separately).
REPORT_IDENTITY = ("session", "config_source")


def record_session(
    out: Path,
    name: str,
    *,
    scenario: str = "table3",
    frames: int = 3,
    seed: int = 4,
    **stages: dict[str, Any],
) -> SessionSummary:
    """Run and record a simulator session into ``out/name/session.mcap`` (no .rrd)."""
    data: dict[str, Any] = {
        "session": {"output_dir": str(out), "name": name, "rerun": False},
        "acquire": {"plugin": "simulator", "scenario": scenario, "frames": frames, "seed": seed},
        "reference": {"plugin": "romer-serial", "port": "simulator"},
    }
    for stage, value in stages.items():
        data.setdefault(stage, {}).update(value)
    return run_session(parse_config(data, "<test>"), make_plugin_manager())


def report_numbers(report: dict[str, Any]) -> dict[str, Any]:
    """report.json without the fields that name the run (session id, folder, parent,
    output settings, reference port): what a replay must reproduce exactly."""
    doc = copy.deepcopy(report)
    for key in REPORT_IDENTITY:
        doc.pop(key, None)
    for key in ("name", "output_dir", "record", "rerun"):
        doc["config"]["session"].pop(key, None)
    doc["reference"].pop("source", None)
    return doc


@dataclass
class Msg:
    topic: str
    log_time: int
    sequence: int
    data: bytes


def rewrite_mcap(
    src: Path,
    dst: Path,
    messages: Callable[[list[Msg]], list[Msg]] = lambda m: m,
    metadata: Callable[[list[tuple[str, dict[str, str]]]], list[tuple[str, dict[str, str]]]] = lambda m: m,
    new_channels: dict[str, tuple[str, Any]] | None = None,
    attachments: Callable[[list[Attachment]], list[Attachment]] = lambda a: a,
) -> None:
    """Copy ``src`` to ``dst`` through ``messages`` / ``metadata`` edits (message
    order kept unless the edit changes it; /integrity messages are copied as they are;
    ``attachments`` edits the list of mcap.records.Attachment).
    new_channels: topic -> (message encoding, crossfield.recording.codec.SchemaSpec or None)
    for topics the edit adds."""
    schemas: dict[int, Schema] = {}
    channels: dict[int, Channel] = {}
    msgs: list[Msg] = []
    meta: list[tuple[str, dict[str, str]]] = []
    found_attachments: list[Attachment] = []
    library = profile = ""
    channel_of: dict[str, Channel] = {}
    with open(src, "rb") as f:
        for record in StreamReader(f).records:
            if isinstance(record, Header):
                library, profile = record.library, record.profile
            elif isinstance(record, Schema):
                schemas[record.id] = record
            elif isinstance(record, Channel):
                channels[record.id] = record
                channel_of.setdefault(record.topic, record)
            elif isinstance(record, Message):
                topic = channels[record.channel_id].topic
                msgs.append(Msg(topic, record.log_time, record.sequence, bytes(record.data)))
            elif isinstance(record, Metadata):
                meta.append((record.name, dict(record.metadata)))
            elif isinstance(record, Attachment):
                found_attachments.append(record)
    msgs = messages(msgs)
    meta = metadata(meta)
    kept_attachments = attachments(found_attachments)
    with open(dst, "wb") as out:
        writer = Writer(out, chunk_size=1 << 20)
        writer.start(profile=profile, library=library)
        schema_ids = {sid: writer.register_schema(s.name, s.encoding, s.data) for sid, s in schemas.items()}
        channel_ids = {
            topic: writer.register_channel(
                c.topic, c.message_encoding, schema_ids.get(c.schema_id, 0), c.metadata
            )
            for topic, c in channel_of.items()
        }
        for topic, (encoding, spec) in (new_channels or {}).items():
            schema_id = writer.register_schema(spec.name, spec.encoding, spec.data) if spec else 0
            channel_ids[topic] = writer.register_channel(topic, encoding, schema_id)
        for name, record in meta:
            writer.add_metadata(name, record)
        for a in kept_attachments:
            writer.add_attachment(a.create_time, a.log_time, a.name, a.media_type, a.data)
        for m in msgs:
            writer.add_message(channel_ids[m.topic], m.log_time, m.data, m.log_time, m.sequence)
        writer.finish()


def edit_json(msg: Msg, change: Callable[[Any], None]) -> Msg:
    """``msg`` with its JSON document changed in place by ``change``."""
    doc = json.loads(msg.data)
    change(doc)
    return Msg(msg.topic, msg.log_time, msg.sequence, json.dumps(doc, separators=(",", ":")).encode())
