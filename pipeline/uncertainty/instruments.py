"""Instruments whose calibration fell due before the session (``[[job.instrument]] due``).

A measurement is traceable only through instruments in calibration (ISO/IEC 17025
6.4.7, 6.5; ISO 10012 7.1): an instrument whose due date is before the session's
date makes every ISO 14253-1 decision ``not_proven`` and no characteristic passes,
unless the user states ``[session] allow_overdue_instruments = true`` (kept in the
recorded config). Either way the report lists each overdue instrument as a problem
(:func:`crossfield.report.document.problems`).
"""

from __future__ import annotations

import dataclasses
import datetime as dt
from collections.abc import Iterable

from crossfield.plan import Instrument, JobHeader
from crossfield.session import CharacteristicSummary, SessionInfo

__all__ = ["ALLOW_KEY", "gate_characteristics", "instrument_problems", "overdue", "session_date"]

#: The ``[session]`` key that accepts decisions made with an overdue instrument.
ALLOW_KEY = "allow_overdue_instruments"


def session_date(info: SessionInfo) -> dt.date | None:
    """The session's UTC date (from ``start_time_ns``, ns since the epoch); None if unknown (0)."""
    if not info.start_time_ns:
        return None
    return dt.datetime.fromtimestamp(info.start_time_ns / 1e9, tz=dt.timezone.utc).date()


def _due(instrument: Instrument) -> dt.date | None:
    """The instrument's due date, None when not stated or not a date (YYYY-MM-DD)."""
    try:
        return dt.date.fromisoformat(instrument.due.strip()) if instrument.due.strip() else None
    except ValueError:
        return None


def overdue(job: JobHeader, on: dt.date | None) -> tuple[tuple[Instrument, str], ...]:
    """The instruments of ``job`` not shown in calibration on ``on``, each with why:
    due before that date, or a due date that is not a date."""
    found = []
    for instrument in job.instruments:
        due = _due(instrument)
        if due is None and instrument.due.strip():
            found.append((instrument, f"due date {instrument.due!r} is not a date (YYYY-MM-DD)"))
        elif due is not None and on is not None and due < on:
            found.append((instrument, f"calibration fell due {due.isoformat()}, before the session ({on.isoformat()})"))
    return tuple(found)


def allowed(info: SessionInfo) -> bool:
    """True when the config states ``[session] allow_overdue_instruments = true``."""
    return bool(info.config.session.get(ALLOW_KEY, False))


def gate_characteristics(
    characteristics: Iterable[CharacteristicSummary], info: SessionInfo
) -> tuple[CharacteristicSummary, ...]:
    """``characteristics`` as decided, or, with an overdue instrument and no override,
    each ``not_proven`` and not passed (the measured values and U unchanged)."""
    characteristics = tuple(characteristics)
    if allowed(info) or not overdue(info.plan.job, session_date(info)):
        return characteristics
    return tuple(dataclasses.replace(c, decision="not_proven", passed=False) for c in characteristics)


def instrument_problems(info: SessionInfo) -> list[str]:
    """One report line per overdue instrument, saying what it does to the decisions."""
    effect = (
        f"decisions kept by [session] {ALLOW_KEY} = true"
        if allowed(info)
        else f"every decision not proven ([session] {ALLOW_KEY} = true overrides)"
    )
    return [
        f"instrument {i.id}{f' ({i.kind})' if i.kind else ''}: {why}; {effect}"
        for i, why in overdue(info.plan.job, session_date(info))
    ]
