"""Shared parts of the reference-point file imports (``csv``, ``spatialanalyzer``, ``pcdmis-xyz``).

Every file import does the same things around its own line grammar:
read the file and hand its bytes to the recorder's sink before parsing;
turn the bytes into numbered text lines; parse numbers and units with
errors naming the file and line; and label the parsed points, either by
their names (which must be labels of the plan's probing order) or, for
files without names, by the plan's probing order itself. Those parts live
here; each plugin module only adds its grammar (``parse``).

Errors that stop the import are :class:`ReferenceImportError` s naming the
file and line (``points.txt, line 7: ...``). Points whose name is not in
the plan, and plan labels without a point, are *problems*
(``ReferenceData.problems``): the other points are kept.
"""

from __future__ import annotations

import math
import re
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from crossfield.cmm.controls import control_problems
from crossfield.cmm.plausible import DEFAULT_VOLUME_MM, check_volume, coordinate_problem
from crossfield.cmm.protocol import show
from crossfield.errors import ReferenceImportError
from crossfield.plan import MeasurementPlan
from crossfield.stages import BytesSink
from crossfield.types import ProbedPoint, ReferenceData

__all__ = [
    "LENGTH_UNITS",
    "MM_PER_INCH",
    "UNIT_OPTIONS",
    "UNIT_SPELLINGS",
    "UNIT_VECTOR_TOLERANCE",
    "FilePoint",
    "PointFileReference",
    "approach_direction",
    "by_name",
    "by_probing_order",
    "check_path",
    "check_sigma",
    "check_units",
    "finite",
    "in_volume",
    "parse_float",
    "quoted",
    "read_point_file",
    "resolve_units",
    "text_lines",
    "unit_name",
]

MM_PER_INCH = 25.4

#: Length units a file may be in: name -> mm per unit.
LENGTH_UNITS: dict[str, float] = {"mm": 1.0, "inch": MM_PER_INCH}

#: How files spell those units (lower case) -> the name in :data:`LENGTH_UNITS`.
UNIT_SPELLINGS: dict[str, str] = {
    "mm": "mm",
    "millimeter": "mm",
    "millimeters": "mm",
    "millimetre": "mm",
    "millimetres": "mm",
    "in": "inch",
    "inch": "inch",
    "inches": "inch",
    '"': "inch",
}

#: Values of the ``units`` option of the file imports.
UNIT_OPTIONS = ("auto", "mm", "inch")

#: How far |(I, J, K)| may be from 1 before a vector is rejected.
UNIT_VECTOR_TOLERANCE = 1e-3


# ---- options --------------------------------------------------------------------------


def check_path(path: object) -> str:
    if not isinstance(path, (str, Path)) or not str(path):
        raise ValueError(f"option 'path' must be a file path, got {path!r}")
    return str(path)


def check_sigma(sigma_mm: object) -> float:
    number = isinstance(sigma_mm, (int, float)) and not isinstance(sigma_mm, bool)
    if not (number and math.isfinite(sigma_mm) and sigma_mm > 0):  # type: ignore[arg-type]
        raise ValueError(f"option 'sigma_mm' must be a positive number of mm, got {sigma_mm!r}")
    return float(sigma_mm)  # type: ignore[arg-type]


def check_units(units: object) -> str:
    if units not in UNIT_OPTIONS:
        raise ValueError(f"option 'units' must be one of {', '.join(UNIT_OPTIONS)}, got {units!r}")
    return str(units)


# ---- bytes -> lines -> values ------------------------------------------------------------


def read_point_file(path: str, sink: BytesSink) -> bytes:
    """The file's bytes, handed to ``sink`` before anything parses them."""
    try:
        raw = Path(path).read_bytes()
    except OSError as exc:
        raise ReferenceImportError(f"{path}: cannot read CMM points: {exc.strerror}") from None
    sink(raw)
    return raw


def text_lines(raw: bytes, where: str, fallback: str | None = None) -> list[str]:
    """The file's lines (line k+1 is item k; a line is the text after the
    k-th ``\\n``, a trailing ``\\r`` removed). UTF-8, a BOM accepted; if
    that fails and ``fallback`` names an encoding (``"cp1252"`` for files
    written by Windows programs), that one; else an error naming the line."""
    data = bytes(raw)
    try:
        text = data.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        text = None
        if fallback:
            try:
                text = data.decode(fallback)
            except UnicodeDecodeError:
                pass
        if text is None:
            line = data.count(b"\n", 0, exc.start) + 1
            encodings = "UTF-8" + (f" nor {fallback}" if fallback else "")
            neither = "neither " if fallback else "not "
            raise ReferenceImportError(
                f"{where}, line {line}: {neither}{encodings} text (byte {exc.start})"
            ) from None
    return [line.removesuffix("\r") for line in text.split("\n")]


def quoted(line: str) -> str:
    """A line as shown in messages ('...', escaped, cut after 100 bytes)."""
    return show(line.encode("utf-8", "backslashreplace"))


#: A number as point files write it: optional sign, digits with an optional
#: decimal point, optional exponent. Not Python's float() syntax, which also
#: takes ``8_98.4`` (= 898.4), ``nan``, ``inf`` and surrounding blanks.
_DECIMAL = re.compile(r"[+-]?(?:[0-9]+(?:\.[0-9]*)?|\.[0-9]+)(?:[eE][+-]?[0-9]+)?")


def parse_float(text: str) -> float | None:
    """``text`` as a finite float if it is a plain decimal number
    (``-12.5``, ``1.25e3``), else None."""
    if not _DECIMAL.fullmatch(text):
        return None
    value = float(text)
    return value if math.isfinite(value) else None


def finite(text: str, at: str, name: str) -> float:
    """``text`` as a finite float, or an error naming ``at`` and the field."""
    value = parse_float(text)
    if value is None:
        raise ReferenceImportError(f"{at}: field {name} is not a finite number: {text!r}")
    return value


def in_volume(xyz: Sequence[float], at: str, volume_mm: float, line: str) -> tuple[float, float, float]:
    """``xyz`` (3,) mm if it is finite and inside the measuring volume, else
    an error naming ``at`` (:mod:`crossfield.cmm.plausible`)."""
    problem = coordinate_problem(xyz, volume_mm)
    if problem:
        raise ReferenceImportError(f"{at}: {problem}: {quoted(line)}")
    x, y, z = (float(v) for v in xyz)
    return (x, y, z)


def unit_name(spelling: str, at: str) -> str:
    """The unit named by ``spelling`` (``mm``, ``inch``...), or an error
    listing the known spellings."""
    unit = UNIT_SPELLINGS.get(spelling.strip().lower())
    if unit is None:
        known = ", ".join(UNIT_SPELLINGS)
        raise ReferenceImportError(
            f"{at}: unknown length unit {spelling.strip()!r} (known: {known}); "
            f"export the points in mm or inch"
        )
    return unit


def resolve_units(option: str, stated: str | None, stated_at: str, where: str) -> str:
    """The unit the coordinates are in.

    option: the plugin's ``units`` option (``auto``, ``mm``, ``inch``).
    stated: the unit the file states (None: it states none), at ``stated_at``.
    ``auto`` takes the file's; a file that states none needs the option;
    an option that contradicts the file is an error.
    """
    if option == "auto":
        if stated is None:
            raise ReferenceImportError(
                f'{where}: the file does not state its length unit; set the option units ("mm" or "inch")'
            )
        return stated
    if stated is not None and stated != option:
        raise ReferenceImportError(
            f"{stated_at}: the file states {stated} but the option units is {option!r}; "
            f'remove the option or set it to "{stated}"'
        )
    return option


def approach_direction(normal: Sequence[float], at: str) -> tuple[float, float, float]:
    """The probe's approach direction from a surface normal ``I, J, K``
    (unitless): minus the normal, normalised. An error if |IJK| is not 1
    within :data:`UNIT_VECTOR_TOLERANCE`."""
    i, j, k = (float(v) for v in normal)
    norm = math.sqrt(i * i + j * j + k * k)
    if abs(norm - 1.0) > UNIT_VECTOR_TOLERANCE:
        raise ReferenceImportError(
            f"{at}: I, J, K ({i:g}, {j:g}, {k:g}) is not a unit vector (norm {norm:.6f})"
        )
    return (-i / norm, -j / norm, -k / norm)


# ---- points -> labelled reference data ---------------------------------------------------


@dataclass(frozen=True)
class FilePoint:
    """One point read from a file.

    line: its line number. name: its name in the file (None: the format
    has none). xyz: (3,) probe-ball centre in mm, global (CMM) frame.
    sigma_mm: its own standard uncertainty per coordinate (mm), or None
    for the plugin's default. probe_vector: unit approach direction, or None.
    """

    line: int
    name: str | None
    xyz: tuple[float, float, float]
    sigma_mm: float | None = None
    probe_vector: tuple[float, float, float] | None = None

    def probed(self, label: str, sigma_mm: float) -> ProbedPoint:
        return ProbedPoint(
            label=label,
            xyz=np.array(self.xyz, dtype=np.float64),
            sigma_mm=sigma_mm if self.sigma_mm is None else self.sigma_mm,
            probe_vector=np.zeros(3) if self.probe_vector is None else np.array(self.probe_vector),
        )


def _first(labels: Sequence[str], count: int = 12) -> str:
    return ", ".join(labels[:count]) + (" ..." if len(labels) > count else "")


def by_name(
    points: Sequence[FilePoint],
    plan: MeasurementPlan,
    where: str,
    sigma_mm: float,
    noun: str = "point name",
    hint: str = "",
) -> ReferenceData:
    """Label each point by its name, which must be a label of the plan's
    probing order; points keep the file's order.

    A duplicate name is an error naming both lines (``hint`` is appended:
    how to select one); a name outside the plan is a problem (the point is
    ignored); labels without a point are one problem; no point of the plan
    at all is an error. ``noun`` names the column in messages (``id``).
    """
    labels = plan.probing_order()
    known = set(labels)
    seen: dict[str, int] = {}
    kept: list[ProbedPoint] = []
    problems: list[str] = []
    for point in points:
        assert point.name is not None
        at = f"{where}, line {point.line}"
        if point.name in seen:
            raise ReferenceImportError(
                f"{at}: duplicate {noun} {point.name!r} (first on line {seen[point.name]}){hint}"
            )
        seen[point.name] = point.line
        if point.name not in known:
            problems.append(
                f"{at}: {noun} {point.name!r} is not a label of the plan's probing order, ignored"
            )
            continue
        kept.append(point.probed(point.name, sigma_mm))
    if not kept:
        raise ReferenceImportError(f"{where}: no point of the plan found (expected {noun}s {_first(labels)})")
    missing = [label for label in labels if label not in seen]
    if missing:
        problems.append(f"{where}: no point for {len(missing)} label(s): {', '.join(missing)}")
    problems += control_problems(kept, plan, where)
    return ReferenceData(points=tuple(kept), problems=tuple(problems), source=where)


def by_probing_order(
    points: Sequence[FilePoint], plan: MeasurementPlan, where: str, sigma_mm: float
) -> ReferenceData:
    """Label unnamed points by the plan's probing order: the k-th point of
    the file is ``plan.probing_order()[k]`` (as the arm's stream without
    sequence numbers). A count that differs from the plan's is a problem:
    extra points are ignored, missing labels are named (if a point is
    missing in the middle of the file, every later label is wrong: the
    problem says so). No point at all is an error."""
    labels = plan.probing_order()
    if not points:
        raise ReferenceImportError(f"{where}: no point found (expected {len(labels)}: {_first(labels)})")
    kept = [point.probed(label, sigma_mm) for point, label in zip(points, labels)]
    problems: list[str] = []
    if len(points) > len(labels):
        extra = points[len(labels) :]
        lines = f"line {extra[0].line}" if len(extra) == 1 else f"lines {extra[0].line}-{extra[-1].line}"
        problems.append(
            f"{where}: {len(points)} points for the plan's {len(labels)} labels (labelled in probing "
            f"order, last {labels[-1]} on line {points[len(labels) - 1].line}): {len(extra)} point(s) "
            f"beyond the plan ignored ({lines})"
        )
    elif len(points) < len(labels):
        missing = labels[len(points) :]
        problems.append(
            f"{where}: {len(points)} points for the plan's {len(labels)} labels (labelled in probing "
            f"order): no point for {len(missing)} label(s): {', '.join(missing)}; if a point is missing "
            f"before the end of the file, every later label is wrong"
        )
    problems += control_problems(kept, plan, where)
    return ReferenceData(points=tuple(kept), problems=tuple(problems), source=where)


# ---- the common plugin shape -----------------------------------------------------------


class PointFileReference:
    """Base of the file imports: ``acquire`` reads the file, hands its bytes
    to the sink, then :meth:`decode` s them; subclasses implement
    :meth:`decode`. ``path``, ``sigma_mm`` and ``measuring_volume_mm``
    (half-width of the measuring volume, mm) as in the plugins' options."""

    def __init__(self, *, path: str, sigma_mm: float = 0.01, measuring_volume_mm: float = DEFAULT_VOLUME_MM):
        self.path = check_path(path)
        self.sigma_mm = check_sigma(sigma_mm)
        self.measuring_volume_mm = check_volume(measuring_volume_mm)

    def acquire(self, plan: MeasurementPlan, sink: BytesSink) -> ReferenceData:
        """Read the file, hand its bytes to ``sink``, then parse them."""
        return self.decode(read_point_file(self.path, sink), plan)

    def decode(self, raw: bytes, plan: MeasurementPlan) -> ReferenceData:  # pragma: no cover
        raise NotImplementedError
