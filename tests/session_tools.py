"""Helpers for the replay / compare / audit tests: record a simulator session,
rewrite an MCAP file with edits (as an editing tool would, with valid CRCs)."""

from __future__ import annotations

import copy
import json
from collections.abc import Callable
from dataclasses import dataclass
from html.parser import HTMLParser
from pathlib import Path
from typing import Any

from mcap.records import Attachment, Channel, Header, Message, Metadata, Schema
from mcap.stream_reader import StreamReader
from mcap.writer import Writer

from crossfield.chain.registry import make_plugin_manager
from crossfield.chain.runner import run_session
from crossfield.config import parse_config
from crossfield.session import SessionSummary

#: report.json keys that name the run, not its results (compared separately).
REPORT_IDENTITY = ("session", "config_source", "integrity")


def record_session(
    out: Path,
    name: str,
    *,
    scenario: str = "table3",
    frames: int = 3,
    seed: int = 4,
    **stages: dict[str, Any],
) -> SessionSummary:
    """Run and record a simulator session into ``out/name/session.mcap`` (no .rrd).

    The report is the ``json`` plugin's (report.json only) unless ``report`` says
    otherwise: report.html's figures cost about 1 s of CPU per session, and every
    replay and audit of the recording re-runs its report plugin.
    """
    data: dict[str, Any] = {
        "session": {"output_dir": str(out), "name": name, "rerun": False},
        "acquire": {"plugin": "simulator", "scenario": scenario, "frames": frames, "seed": seed},
        "reference": {"plugin": "romer-serial", "port": "simulator"},
        "report": {"plugin": "json"},
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
    channels: Callable[[Channel], Channel] = lambda c: c,
    schemas: Callable[[Schema], Schema] = lambda s: s,
) -> None:
    """Copy ``src`` to ``dst`` with the real mcap writer through ``messages`` /
    ``metadata`` / ``attachments`` edits (valid CRCs, as an editing tool writes).

    The file order of an unedited copy is the original's: each schema and
    channel is registered just before the first message that uses it (as
    crossfield's writer does), metadata records and attachments are written
    where they were (after as many messages as before them, the open chunk
    finished first); /integrity messages are copied as they are. Message
    order is kept unless the edit changes it. new_channels: topic ->
    (message encoding, crossfield.recording.codec.SchemaSpec or None) for
    topics the edit adds (topics already in the file keep their channel).
    ``channels`` / ``schemas`` edit each channel / schema record.
    """
    edit_channel, edit_schema = channels, schemas
    schemas: dict[int, Schema] = {}
    channels: dict[int, Channel] = {}
    msgs: list[Msg] = []
    meta: list[tuple[str, dict[str, str]]] = []
    meta_at: list[int] = []
    found_attachments: list[Attachment] = []
    attachment_at: list[int] = []
    library = profile = ""
    channel_of: dict[str, Channel] = {}
    with open(src, "rb") as f:
        for record in StreamReader(f).records:
            if isinstance(record, Header):
                library, profile = record.library, record.profile
            elif isinstance(record, Schema):
                schemas.setdefault(record.id, record)
            elif isinstance(record, Channel):
                channels.setdefault(record.id, record)
                channel_of.setdefault(record.topic, record)
            elif isinstance(record, Message):
                topic = channels[record.channel_id].topic
                msgs.append(Msg(topic, record.log_time, record.sequence, bytes(record.data)))
            elif isinstance(record, Metadata):
                meta.append((record.name, dict(record.metadata)))
                meta_at.append(len(msgs))
            elif isinstance(record, Attachment):
                found_attachments.append(record)
                attachment_at.append(len(msgs))
    # Each metadata record / attachment stays before the message that followed it.
    following = {k: msgs[k] for k in set(meta_at + attachment_at) if k < len(msgs)}
    msgs = messages(msgs)
    meta = metadata(meta)
    kept_attachments = attachments(found_attachments)
    position = {id(m): k for k, m in enumerate(msgs)}

    def where(original: int) -> int:
        anchor = following.get(original)
        if anchor is not None and id(anchor) in position:
            return position[id(anchor)]
        return min(original, len(msgs))

    placed: list[tuple[int, int, Any]] = []
    for k, item in enumerate(meta):
        placed.append((where(meta_at[k]) if k < len(meta_at) else len(msgs), 0, ("metadata", item)))
    for k, item in enumerate(kept_attachments):
        at = where(attachment_at[k]) if k < len(attachment_at) else 0
        placed.append((at, 1, ("attachment", item)))
    placed.sort(key=lambda p: (p[0], p[1]))
    with open(dst, "wb") as out:
        writer = Writer(out, chunk_size=1 << 20)
        writer.start(profile=profile, library=library)
        schema_ids: dict[int, int] = {}
        channel_ids: dict[str, int] = {}

        def channel_id(topic: str) -> int:
            if topic not in channel_ids:
                if topic in channel_of:
                    c = edit_channel(channel_of[topic])
                    sid = 0
                    if c.schema_id:
                        if c.schema_id not in schema_ids:
                            s = edit_schema(schemas[c.schema_id])
                            schema_ids[c.schema_id] = writer.register_schema(s.name, s.encoding, s.data)
                        sid = schema_ids[c.schema_id]
                    channel_ids[topic] = writer.register_channel(c.topic, c.message_encoding, sid, c.metadata)
                else:
                    encoding, spec = (new_channels or {})[topic]
                    sid = writer.register_schema(spec.name, spec.encoding, spec.data) if spec else 0
                    channel_ids[topic] = writer.register_channel(topic, encoding, sid)
            return channel_ids[topic]

        def emit(item: Any) -> None:
            kind, value = item
            writer.flush()
            if kind == "metadata":
                writer.add_metadata(*value)
            else:
                a = value
                writer.add_attachment(a.create_time, a.log_time, a.name, a.media_type, a.data)

        p = 0
        for k, m in enumerate(msgs):
            while p < len(placed) and placed[p][0] <= k:
                emit(placed[p][2])
                p += 1
            writer.add_message(channel_id(m.topic), m.log_time, m.data, m.log_time, m.sequence)
        for item in placed[p:]:
            emit(item[2])
        writer.finish()


def edit_json(msg: Msg, change: Callable[[Any], None]) -> Msg:
    """``msg`` with its JSON document changed in place by ``change``."""
    doc = json.loads(msg.data)
    change(doc)
    return Msg(msg.topic, msg.log_time, msg.sequence, json.dumps(doc, separators=(",", ":")).encode())


def shift_cfp_x(raw: bytes, seq: int, delta_mm: float) -> bytes:
    """``raw`` (CFP sentences, docs/serial-protocol.md) with X of every sentence of
    press ``seq`` moved by ``delta_mm``, each with a valid CRC (as a forger would)."""
    import re

    from crossfield.cmm.protocol import crc16

    def edit(match: re.Match) -> bytes:
        fields = match.group(1).split(b",")
        if int(fields[1]) != seq:
            return match.group(0)
        fields[3] = f"{float(fields[3]) + delta_mm:.4f}".encode()
        body = b",".join(fields)
        return b"$" + body + b"*" + f"{crc16(body):04X}".encode()

    return re.sub(rb"\$(CFP,[^*$\r\n]*)\*[0-9A-Fa-f]{4}", edit, raw)


def forge(src: Path, dst: Path, edit_raw: Callable[[bytes], bytes], work: Path, signing_key: Any = None) -> None:
    """A consistent forgery of the recording ``src``: the joined ``/cmm/raw`` bytes
    edited by ``edit_raw`` (same length, split as recorded), every derived message
    re-derived by a replay, and the whole file written again by crossfield's own
    writer (so the integrity chain is recomputed and self-consistent). The session
    facts (metadata, attachments) are the original's."""
    from mcap.stream_reader import StreamReader as _Reader

    from crossfield.recording.codec import SchemaSpec
    from crossfield.recording.layout import RAW_TOPICS, TOPIC_CMM_RAW, TOPIC_INTEGRITY
    from crossfield.recording.recorder import SessionRecorder
    from crossfield.recording.writer import ChannelSpec, McapFileSink, MemorySink
    from crossfield.replay import replay_session

    raw = b""
    with open(src, "rb") as f:
        topics: dict[int, str] = {}
        for r in _Reader(f).records:
            if isinstance(r, Channel):
                topics[r.id] = r.topic
            elif isinstance(r, Message) and topics[r.channel_id] == TOPIC_CMM_RAW:
                raw += bytes(r.data)
    edited_raw = edit_raw(raw)
    assert len(edited_raw) == len(raw) and edited_raw != raw

    def split(ms: list[Msg]) -> list[Msg]:
        out, at = [], 0
        for m in ms:
            if m.topic == TOPIC_CMM_RAW:
                m = Msg(m.topic, m.log_time, m.sequence, edited_raw[at : at + len(m.data)])
                at += len(m.data)
            out.append(m)
        return out

    stage1 = work / "raw-edited.mcap"
    rewrite_mcap(src, stage1, split)
    sink = MemorySink(skip_topics=RAW_TOPICS)
    replay_session(stage1, make_plugin_manager(), output_dir=work, record=False, rerun=False,
                   observers=[SessionRecorder(sink)])
    derived: dict[tuple[str, int, int, int], bytes] = {}
    seen: dict[tuple[str, int, int], int] = {}
    for topic, log_time, sequence, data in sink.messages:
        k = (topic, sequence, log_time)
        derived[k + (seen.get(k, 0),)] = data
        seen[k] = seen.get(k, 0) + 1

    out = McapFileSink(dst, signing_key=signing_key)
    schemas: dict[int, Schema] = {}
    channels: dict[int, Channel] = {}
    occurrence: dict[tuple[str, int, int], int] = {}
    with open(stage1, "rb") as f:
        for r in _Reader(f).records:
            if isinstance(r, Schema):
                schemas.setdefault(r.id, r)
            elif isinstance(r, Channel):
                channels.setdefault(r.id, r)
            elif isinstance(r, Metadata):
                out.metadata(r.name, dict(r.metadata))
            elif isinstance(r, Attachment):
                out.attachment(r.name, r.media_type, bytes(r.data), r.log_time)
            elif isinstance(r, Message):
                c = channels[r.channel_id]
                if c.topic == TOPIC_INTEGRITY:
                    continue  # the forger's writer makes its own chain
                s = schemas.get(c.schema_id)
                spec = ChannelSpec(
                    c.topic,
                    c.message_encoding,
                    SchemaSpec(s.name, s.encoding, bytes(s.data)) if s else None,
                    tuple(c.metadata.items()),
                )
                k = (c.topic, r.sequence, r.log_time)
                n = occurrence.get(k, 0)
                occurrence[k] = n + 1
                out.message(spec, r.log_time, derived.get(k + (n,), bytes(r.data)), r.sequence)
    out.close()


def sigint_default() -> None:
    """``preexec_fn`` of a child the test stops with SIGINT / Ctrl-C: restore the default
    action, so that Python in the child installs its KeyboardInterrupt handler even when the
    test suite itself was started with SIGINT ignored (a background job of a non-interactive
    shell, ``nohup``: children inherit SIG_IGN, and Python then leaves SIGINT ignored)."""
    import signal

    signal.signal(signal.SIGINT, signal.SIG_DFL)


class HtmlCells(HTMLParser):
    """The text of each <td>/<th> of an HTML document, row by row (``rows``)."""

    def __init__(self) -> None:
        super().__init__()
        self.rows: list[list[str]] = []
        self._cell: str | None = None

    def handle_starttag(self, tag, attrs):
        if tag == "tr":
            self.rows.append([])
        elif tag in ("td", "th"):
            self._cell = ""

    def handle_endtag(self, tag):
        if tag in ("td", "th"):
            self.rows[-1].append(self._cell)
            self._cell = None

    def handle_data(self, data):
        if self._cell is not None:
            self._cell += data
