"""Replay a recorded session from its raw inputs (``crossfield replay``).

Only the raw inputs of the recording are used: both camera images of every
stereo pair, the exact bytes read from the CMM arm (``/cmm/raw``), the
calibration (``calibration.yml``) and the recorded copies of the calibration
files the budget's calibration term reads (``calibration/stereo.yml``; the
recorded path is never opened to read them, :func:`calibration_notes`), the
measurement plan (``plan.toml``), the simulator's ground truth when there is one, and the recorded config
(which plugins ran, with which options). Recorded stage results are never
read. Frames are fed in the order they were recorded, with their recorded
capture times; serial bytes with their recorded read times; the session
start time is the recorded one. The chain is the live one
(:func:`crossfield.chain.runner.run_pipeline`), so with the recorded plugins every
stage output, and every number of the report, is the same float as
recorded, and the replayed session's own recording holds the same
messages. With swapped plugins or options the replay is a new session
whose ``parent`` (metadata and report) names the recording it re-ran
(path and SHA-256) and what was changed.

A recording that was cut short (killed writer, truncated file) is replayed
up to its last complete chunk; the summary's ``incomplete`` says where it ends.
A session that stopped early (Ctrl-C, a source error: ``/session/stop``) is
replayed up to where it stopped and states the same stop and reason.
"""

from __future__ import annotations

import dataclasses
import json
import time
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any

import pluggy

from crossfield.chain.runner import run_session, safe_session_name
from crossfield.config import Config, with_overrides
from crossfield.errors import ConfigError, RecordingError
from crossfield.recording import layout as L
from crossfield.recording.calibration_files import disk_notes, no_copy_note
from crossfield.recording.codec import decode_image, decode_link_event, ground_truth_from_doc, utc_text  # noqa: F401 - public here too
from crossfield.recording.facts import SessionFacts, load_session_facts, require_session  # noqa: F401
from crossfield.recording.integrity import file_sha256
from crossfield.recording.prefetch import ahead
from crossfield.recording.stop import read_stop
from crossfield.session import SessionStop, SessionSummary
from crossfield.stages import STAGES, SerialChunk
from crossfield.types import CAMERAS, StereoFrame

#: The recording layouts this replay reads.
READABLE_FORMATS = L.READABLE_FORMATS

#: Session keys that say where and how a replay is written, not what it computes.
OUTPUT_KEYS = ("name", "output_dir", "record", "rerun", "rerun_image_every", "signing_key", "compression")

#: The facts of a recorded session (:class:`crossfield.recording.facts.SessionFacts`).
RecordedSession = SessionFacts


def load_recorded_session(path: str | Path) -> RecordedSession:
    """Open ``path`` and read its session facts (:func:`crossfield.recording.facts.load_session_facts`).

    :class:`RecordingError` (one line, naming the file) when it is not an
    MCAP file, is MCAP written by another program, or lacks what a replay needs.
    """
    return load_session_facts(path)


class RecordingSource:
    """The acquisition of a replay: the recorded stereo pairs and serial bytes.

    Implements :class:`crossfield.stages.RecordedAcquisition`. Frames come in the order
    they were recorded (file order), each with its recorded capture time
    (the image messages' log time). After :meth:`frames` is exhausted,
    ``incomplete`` says where a cut-short recording ends (None if complete).
    """

    def __init__(self, recorded: RecordedSession) -> None:
        self.recorded = recorded
        self.calibration = recorded.calibration
        self.ground_truth = recorded.ground_truth
        self.default_plan = recorded.plan
        self.recorded_plugins = recorded.plugins
        #: The recorded copies of the calibration files (None: the recording kept none, and
        #: the session reads them from the recorded path as it did then).
        self.recorded_calibration_files = recorded.calibration_files
        self.start_time_ns = int(recorded.session.get("start_time_ns") or 0)
        self.incomplete: str | None = None
        self.frames_read = 0
        #: Why the live run stopped early (``/session/stop``): the replay stops there too.
        self.recorded_stop: SessionStop | None = read_stop(recorded.recording)

    def frames(self) -> Iterator[StereoFrame]:
        """The recorded pairs, read and decoded ahead on a second thread
        (:func:`crossfield.recording.prefetch.ahead`, two pairs ahead): the same pairs in the
        same order, and the same errors at the same point, as :meth:`decoded_frames`."""
        notes: list[str | None] = []
        for frame in ahead(lambda: self._decode(notes.append), depth=2, name="replay-decode"):
            self.frames_read += 1
            yield frame
        self.incomplete = notes[0] if notes else None

    def decoded_frames(self) -> Iterator[StereoFrame]:
        """The recorded pairs, read and decoded on the calling thread; ``incomplete``
        is set once they are exhausted."""
        def finished(notes: str | None) -> None:
            self.incomplete = notes

        for frame in self._decode(finished):
            self.frames_read += 1
            yield frame

    def _decode(self, finished: Callable[[str | None], None]) -> Iterator[StereoFrame]:
        """The pairs in file order; at the end ``finished(notes)`` with what the
        ``incomplete`` note says (None for a complete recording)."""
        rec = self.recorded.recording
        pairs = 0
        pending: dict[int, dict[str, Any]] = {}
        last: tuple[int, int] | None = None
        for m in rec.messages(L.IMAGE_TOPICS, decode=False, file_order=True):
            camera = L.CAMERA_OF_TOPIC[m.topic]
            where = f"{rec.path}: {m.topic} sequence {m.sequence}"
            pixels, _ = decode_image(m.data, where)
            entry = pending.setdefault(m.sequence, {"time": m.log_time_ns, "bit_depth": 0})
            if camera in entry:
                raise RecordingError(f"{where}: a second {camera} image for this stereo pair")
            entry[camera] = pixels
            entry["bit_depth"] = int(m.channel_metadata.get(L.CHANNEL_BIT_DEPTH) or 8 * pixels.itemsize)
            if all(c in entry for c in CAMERAS):
                del pending[m.sequence]
                pairs += 1
                last = (m.sequence, entry["time"])
                yield StereoFrame(
                    m.sequence, entry["time"], entry["upper"], entry["lower"], entry["bit_depth"]
                )
        notes = []
        if not rec.complete:
            ends = (
                f"the last complete stereo pair is sequence {last[0]} at {utc_text(last[1])}"
                if last
                else "no complete stereo pair was recorded"
            )
            notes.append(
                f"the recording {rec.path} is incomplete ({rec.damage}); {pairs} stereo pair(s) "
                f"replayed, {ends}"
            )
        elif self.recorded.result is None:
            notes.append(
                f"the session recorded in {rec.path} did not end normally (no {L.META_RESULT!r} record: "
                f"it was interrupted, e.g. by Ctrl-C, before its results were written); "
                f"{pairs} stereo pair(s) replayed"
            )
        for seq, entry in sorted(pending.items()):
            have = [c for c in CAMERAS if c in entry]
            notes.append(f"stereo pair {seq} has only its {' and '.join(have)} image, not replayed")
        finished("; ".join(notes) or None)

    def serial_chunks(self) -> list[SerialChunk]:
        """Every recorded read from the CMM line, and its link events:
        (bytes or LinkEvent, time ns, source), in the order they happened."""
        rec = self.recorded.recording
        chunks: list[SerialChunk] = []
        for m in rec.messages(L.TOPIC_CMM_RAW, decode=False, file_order=True):
            source = str(m.channel_metadata.get(L.CHANNEL_SOURCE, ""))
            if m.channel_metadata.get(L.CHANNEL_CONTENT) == L.LINK_EVENTS:
                event = decode_link_event(m.data, f"{rec.path}: {L.TOPIC_CMM_RAW} link event {m.sequence}")
                chunks.append(SerialChunk(event, m.log_time_ns, source))
            else:
                chunks.append(SerialChunk(m.data, m.log_time_ns, source))
        return chunks

    def describe(self) -> dict[str, Any]:
        return dict(self.recorded.acquisition)

    def close(self) -> None:
        pass


def changes(recorded: Config, replayed: Config) -> dict[str, Any]:
    """What a replay changes: {"plugins": {stage: {"from", "to"}}, "options": {"stage.key": {"from", "to"}}}.

    Where and how the replay is written (session name, output_dir, record,
    rerun) is not a change of the computation and is left out.
    """
    a, b = recorded.to_dict(), replayed.to_dict()
    plugins: dict[str, Any] = {}
    options: dict[str, Any] = {}
    for table in ("session", *STAGES):
        ta, tb = dict(a.get(table, {})), dict(b.get(table, {}))
        if table != "session" and ta.get("plugin") != tb.get("plugin"):
            plugins[table] = {"from": ta.get("plugin"), "to": tb.get("plugin")}
        for key in sorted(set(ta) | set(tb)):
            if key == "plugin" or (table == "session" and key in OUTPUT_KEYS):
                continue
            if ta.get(key) != tb.get(key):
                options[f"{table}.{key}"] = {"from": ta.get(key), "to": tb.get(key)}
    return {"plugins": plugins, "options": options}


def _default_output(recorded: RecordedSession) -> tuple[Path, str]:
    """(base folder, session id) for a replay written next to the recorded session.

    The recorded session id is data: it names the replay's folder only if it
    is a plain folder name (:func:`crossfield.chain.runner.safe_session_name`);
    otherwise (``../..``, an absolute path, ...) the recording's own folder
    or file name does."""
    path = recorded.path.resolve()
    base = path.parent.parent if path.name == "session.mcap" else path.parent
    own = path.parent.name if path.name == "session.mcap" else path.stem
    for candidate in (recorded.session_id, own, "session"):
        name = safe_session_name(f"{candidate}-replay") if candidate else None
        if name:
            return base, name
    raise AssertionError("unreachable: 'session-replay' is a safe name")  # pragma: no cover


#: Where a replay is written is set by its own arguments, not by ``--option``.
_OUTPUT_ARGUMENTS = {
    "session.name": "-o/--output (output=)",
    "session.output_dir": "-o/--output (output_dir=)",
    "session.record": "--no-record (record=)",
    "session.rerun": "--no-rerun (rerun=)",
}


def _refuse_unreplayable(options: Sequence[str]) -> None:
    """A replay re-reads the recorded frames, CMM bytes and plan, and is written
    where its own arguments say: an option that would change those is refused
    with the reason, never silently ignored."""
    for text in options:
        key = text.split("=", 1)[0].strip()
        if key.startswith("acquire.") or key == "session.plan":
            raise ConfigError(
                f"--option {text!r}: a replay reads the stereo pairs and the measurement plan from the "
                f"recording, so {key} cannot be changed (run a new session instead)"
            )
        if key in _OUTPUT_ARGUMENTS:
            raise ConfigError(
                f"--option {text!r}: where and what a replay writes is set by {_OUTPUT_ARGUMENTS[key]}, "
                f"not by {key}"
            )


#: The replay's note on a recording whose measurements state no budget (recorded before
#: the budget existed): the budget the replay reports is computed now, not recorded.
NO_RECORDED_BUDGET = (
    "the recording states no uncertainty budget (recorded before budgets were recorded): "
    "the budget in this replay is computed now by the replayed measure stage"
)


def recorded_budget_note(path: Path) -> str | None:
    """:data:`NO_RECORDED_BUDGET` when the recording's first ``/measurement`` with
    characteristics has none with a ``budget`` key, else None (also when there is none
    to read: nothing to say about what was not measured)."""
    from crossfield.recording.reader import open_recording

    try:
        with open_recording(path, validate_crcs=False) as rec:
            for message in rec.messages(L.TOPIC_MEASUREMENT):
                characteristics = (message.decoded or {}).get("characteristics") or []
                if characteristics:
                    return None if any("budget" in c for c in characteristics) else NO_RECORDED_BUDGET
    except RecordingError:
        return None
    return None


def calibration_notes(recorded: RecordedSession) -> list[str]:
    """What a replay says about the calibration file(s): one line per recorded copy whose
    file on disk differs or is gone (the replay uses the copy), or that the recording kept
    no copy (the file is read from the recorded path, as before the copies were kept)."""
    if recorded.calibration_files is None:
        note = no_copy_note(recorded.calibration.source)
        return [] if note is None else [note]
    return disk_notes(recorded.calibration_files)


def replay_session(
    path: str | Path,
    pm: pluggy.PluginManager,
    *,
    plugins: Mapping[str, str | None] | None = None,
    options: Sequence[str] = (),
    output: str | Path | None = None,
    output_dir: str | Path | None = None,
    record: bool = True,
    rerun: bool | None = None,
    observers: Iterable[object] = (),
    recorded: RecordedSession | None = None,
    reports: bool = True,
) -> SessionSummary:
    """Re-run the session recorded in ``path`` from its raw inputs.

    plugins: stage -> implementation name to swap in (None keeps the
    recorded one; ``acquire`` cannot be swapped: the frames come from the
    recording). options: ``stage.key=value`` overrides. output: the MCAP
    file to write (its report files go into a new folder named after it);
    by default a new session folder ``<id>-replay`` is made next to the
    recorded one (or in ``output_dir``). record: write the MCAP (audit
    replays without). rerun: write session.rrd (default: as recorded).
    observers: extra observer plugins for this replay. reports: write the report
    files (the audit's reproduction compares the recorded results and writes none:
    :func:`crossfield.chain.runner.run_session`). Returns the summary;
    ``summary.info.parent`` names the recording and the changes.
    """
    recorded = recorded or load_recorded_session(path)
    plugins = dict(plugins or {})
    if plugins.get("acquire") and plugins["acquire"] != recorded.config.stages["acquire"].plugin:
        raise ConfigError(
            f"replay reads the stereo pairs from the recording; the acquire stage cannot be swapped "
            f"(--acquire {plugins['acquire']})"
        )
    plugins.pop("acquire", None)
    _refuse_unreplayable(options)
    config = with_overrides(recorded.config, plugins, list(options))
    changed = changes(recorded.config, config)

    if output is not None:
        mcap_path: Path | None = Path(output)
        base, session_id = mcap_path.parent, mcap_path.stem
        if record and mcap_path.exists():
            raise RecordingError(f"{mcap_path}: a file already exists there (not overwritten)")
    else:
        mcap_path = None
        base, session_id = _default_output(recorded)
        if output_dir is not None:
            base = Path(output_dir)
    session_options = [
        f"session.name={json.dumps(session_id)}",
        f"session.output_dir={json.dumps(str(base))}",
        f"session.record={'true' if record else 'false'}",
    ]
    if rerun is not None:
        session_options.append(f"session.rerun={'true' if rerun else 'false'}")
    overridden = bool(changed["plugins"] or changed["options"])
    source_name = f"{recorded.path} (recorded config" + (", with replay overrides)" if overridden else ")")
    config = dataclasses.replace(with_overrides(config, {}, session_options), source=source_name)

    source = RecordingSource(recorded)
    parent = {
        "path": str(recorded.path.resolve()),
        "sha256": file_sha256(recorded.path),
        "session_id": recorded.session_id,
        "complete": recorded.complete,
        "changed": changed,
        "replayed_at_utc": utc_text(time.time_ns()),
    }
    notes = calibration_notes(recorded)
    budget_note = recorded_budget_note(recorded.path)
    if budget_note is not None:
        notes.append(budget_note)
    if notes:
        parent["notes"] = notes
    return run_session(
        config,
        pm,
        observers=observers,
        source=source,
        cmm_raw=source.serial_chunks(),
        mcap_path=mcap_path,
        parent=parent,
        reports=reports,
    )
