"""Reference stage "csv": CMM points from a CSV file exported by the arm's software.

Format (``docs/serial-protocol.md``, section "CSV import")::

    # comment lines and trailing comments start with '#'
    id,x,y,z,sigma          <- optional header (sigma column optional)
    C1,102.5310,-40.1120,12.0040,0.012
    C2,140.0020,-38.9910,11.9870

x, y, z: probe-ball centre in mm, global (CMM) frame. sigma: standard
uncertainty per coordinate in mm (default: the ``sigma_mm`` option).
Points are labelled by their id, which must be a label of the plan's
probing order (``C1``, ``R1``, ``L3.4``...).
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from pipeline.errors import ReferenceImportError
from pipeline.hookspecs import hookimpl
from pipeline.plan import MeasurementPlan
from pipeline.romer_protocol import show
from pipeline.stages import BytesSink
from pipeline.types import ProbedPoint, ReferenceData

HEADERS = (("id", "x", "y", "z"), ("id", "x", "y", "z", "sigma"))


def _float(text: str) -> float | None:
    try:
        value = float(text)
    except ValueError:
        return None
    return value if math.isfinite(value) else None


class CsvReference:
    """CMM points from a CSV file ``id,x,y,z[,sigma]`` (mm).

    path: the CSV file. sigma_mm: standard uncertainty per coordinate (mm)
    for rows without a sigma column.
    Malformed rows and duplicate ids are errors naming the file and line;
    ids that are not in the plan and plan labels without a row are reported
    as problems, and the other points are kept.
    """

    def __init__(self, *, path: str, sigma_mm: float = 0.01):
        if not isinstance(path, (str, Path)) or not str(path):
            raise ValueError(f"option 'path' must be a file path, got {path!r}")
        if not (isinstance(sigma_mm, (int, float)) and math.isfinite(sigma_mm) and sigma_mm > 0):
            raise ValueError(f"option 'sigma_mm' must be a positive number of mm, got {sigma_mm!r}")
        self.path = str(path)
        self.sigma_mm = float(sigma_mm)

    def acquire(self, plan: MeasurementPlan, sink: BytesSink) -> ReferenceData:
        """Read the file, hand its bytes to ``sink``, then parse them."""
        try:
            raw = Path(self.path).read_bytes()
        except OSError as exc:
            raise ReferenceImportError(f"{self.path}: cannot read CMM points: {exc.strerror}") from None
        sink(raw)
        return self.decode(raw, plan)

    def decode(self, raw: bytes, plan: MeasurementPlan) -> ReferenceData:
        """Parse the file's bytes (as recorded) into labelled points."""
        where = self.path
        try:
            text = bytes(raw).decode("utf-8-sig")
        except UnicodeDecodeError as exc:
            line = bytes(raw).count(b"\n", 0, exc.start) + 1
            raise ReferenceImportError(f"{where}, line {line}: not UTF-8 text (byte {exc.start})") from None
        labels = plan.probing_order()
        known = set(labels)
        points: list[ProbedPoint] = []
        problems: list[str] = []
        seen: dict[str, int] = {}
        first_row = True
        for number, line in enumerate(text.split("\n"), start=1):
            content = line.split("#", 1)[0].strip()
            if not content:
                continue
            fields = [f.strip() for f in content.split(",")]
            at = f"{where}, line {number}"
            if first_row:
                first_row = False
                if len(fields) >= 4 and all(_float(f) is None for f in fields[1:4]):
                    if tuple(f.lower() for f in fields) not in HEADERS:
                        raise ReferenceImportError(
                            f"{at}: expected the header 'id,x,y,z' or 'id,x,y,z,sigma' or a data row, "
                            f"got {show(line.encode())}"
                        )
                    continue
            if len(fields) not in (4, 5):
                raise ReferenceImportError(
                    f"{at}: expected 4 or 5 fields (id,x,y,z[,sigma]), got {len(fields)}: "
                    f"{show(line.encode())}"
                )
            ident = fields[0]
            if not ident:
                raise ReferenceImportError(f"{at}: empty id: {show(line.encode())}")
            values = []
            for name, field in zip(("x", "y", "z", "sigma"), fields[1:]):
                value = _float(field)
                if value is None:
                    raise ReferenceImportError(f"{at}: field {name} is not a finite number: {field!r}")
                values.append(value)
            sigma = values[3] if len(values) == 4 else self.sigma_mm
            if not sigma > 0:
                raise ReferenceImportError(f"{at}: sigma must be > 0 mm, got {sigma}")
            if ident in seen:
                raise ReferenceImportError(f"{at}: duplicate id {ident!r} (first on line {seen[ident]})")
            seen[ident] = number
            if ident not in known:
                problems.append(f"{at}: id {ident!r} is not a label of the plan's probing order, ignored")
                continue
            points.append(ProbedPoint(label=ident, xyz=np.array(values[:3]), sigma_mm=sigma))
        missing = [label for label in labels if label not in seen]
        if not points:
            raise ReferenceImportError(
                f"{where}: no point of the plan found (expected ids {', '.join(labels[:12])}"
                f"{' ...' if len(labels) > 12 else ''})"
            )
        if missing:
            problems.append(f"{where}: no point for {len(missing)} label(s): {', '.join(missing)}")
        return ReferenceData(points=tuple(points), problems=tuple(problems), source=self.path)


@hookimpl
def register_references(register):
    register("csv", CsvReference, "CMM points from a CSV file id,x,y,z[,sigma] (mm)")
