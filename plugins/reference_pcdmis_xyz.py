"""Reference stage "pcdmis-xyz": points from a PC-DMIS ``.xyz`` file.

PC-DMIS (Hexagon) reads and writes ``.xyz`` point files: one point per
line, three to eight numbers separated by commas. PC-DMIS interprets a
line by its count of numbers (help topic "Importing an XYZ File as CAD
Data"):

====== ================================================
count  meaning
====== ================================================
3      X, Y, Z
4      X, Y, Z, diameter (a circle)
5      X, Y, Z, two unused numbers
6      X, Y, Z, I, J, K (a point with its vector)
7      X, Y, Z, I, J, K, diameter (a circle)
8      X, Y, Z, I, J, K, two unused numbers
====== ================================================

An optional first line ``XYZIJK`` (columns 1-6) marks the file as such
and states its unit: ``METRIC`` in columns 11-16 means mm, no ``METRIC``
means inch (help topic "Notes on XYZ Files")::

    XYZIJK    METRIC
    102.5310,-40.1120,12.0040,0,0,1
    140.0020,-38.9910,11.9870,0,0,1

Read here (``docs/serial-protocol.md``, "PC-DMIS .xyz files"): the
coordinates are the probe-ball centres in the global (CMM) frame; I, J, K
is the surface normal, so a point's probe vector (approach direction) is
-IJK; diameters and unused numbers are ignored. Also accepted: blanks or
tabs instead of commas, a point name before the numbers (as other tools
write: ``C1 102.531 -40.112 12.004``), and whole-line comments starting
with ``#`` or ``//``. Named points are labelled by name (which must be a
label of the plan's probing order); unnamed points by the plan's probing
order, and a point count that differs from the plan's is reported.
"""

from __future__ import annotations

from crossfield.plugin_api import (
    DEFAULT_VOLUME_MM,
    LENGTH_UNITS,
    FilePoint,
    MeasurementPlan,
    PointFileReference,
    ReferenceData,
    ReferenceImportError,
    approach_direction,
    by_name,
    by_probing_order,
    check_units,
    finite,
    hookimpl,
    in_volume,
    parse_float,
    quoted,
    resolve_units,
    text_lines,
)

#: The keyword that starts the optional first line.
HEADER = "XYZIJK"
#: Unit keywords after it (none: inch, as in PC-DMIS).
HEADER_UNITS = {"METRIC": "mm", "INCH": "inch", "ENGLISH": "inch"}
COMMENTS = ("#", "//")
#: Field names by count of numbers on a line (PC-DMIS's interpretation).
FIELDS: dict[int, tuple[str, ...]] = {
    3: ("X", "Y", "Z"),
    4: ("X", "Y", "Z", "4 (diameter)"),
    5: ("X", "Y", "Z", "4 (unused)", "5 (unused)"),
    6: ("X", "Y", "Z", "I", "J", "K"),
    7: ("X", "Y", "Z", "I", "J", "K", "7 (diameter)"),
    8: ("X", "Y", "Z", "I", "J", "K", "7 (unused)", "8 (unused)"),
}


def _split(line: str) -> list[str]:
    if "," in line:
        return [field.strip() for field in line.split(",")]
    return line.split()


class PcDmisXyzReference(PointFileReference):
    """CMM points from a PC-DMIS ``.xyz`` file (``X,Y,Z[,I,J,K]`` per line).

    path: the ``.xyz`` file. units: ``"auto"`` (from the ``XYZIJK`` first
    line: ``METRIC`` = mm, else inch; an error if the file has no such
    line), ``"mm"`` or ``"inch"`` (must agree with the first line if there
    is one). sigma_mm: standard uncertainty per coordinate (mm) given to
    every point. measuring_volume_mm: a point with |X|, |Y| or |Z| above it
    (mm, after the unit conversion) is an error naming its line; so is a
    negative diameter column.
    """

    def __init__(
        self,
        *,
        path: str,
        units: str = "auto",
        sigma_mm: float = 0.01,
        measuring_volume_mm: float = DEFAULT_VOLUME_MM,
    ):
        super().__init__(path=path, sigma_mm=sigma_mm, measuring_volume_mm=measuring_volume_mm)
        self.units = check_units(units)

    def decode(self, raw: bytes, plan: MeasurementPlan) -> ReferenceData:
        """Parse the file's bytes (as recorded) into labelled points (mm)."""
        where = self.path
        stated: str | None = None
        stated_at = where
        rows: list[tuple[int, list[str], str]] = []
        for number, line in enumerate(text_lines(raw, where, fallback="cp1252"), start=1):
            content = line.strip()
            if not content or content.startswith(COMMENTS):
                continue
            at = f"{where}, line {number}"
            if content[:6].upper() == HEADER and not rows and stated is None:
                words = content[6:].split()
                if len(words) > 1 or (words and words[0].upper() not in HEADER_UNITS):
                    raise ReferenceImportError(
                        f"{at}: expected 'XYZIJK', 'XYZIJK METRIC' or 'XYZIJK INCH', got {quoted(line)}"
                    )
                stated, stated_at = (HEADER_UNITS[words[0].upper()] if words else "inch"), at
                continue
            rows.append((number, _split(content), line))
        if not rows:
            raise ReferenceImportError(f"{where}: no point lines")
        scale = LENGTH_UNITS[resolve_units(self.units, stated, stated_at, where)]
        points = [self._point(number, fields, line, scale) for number, fields, line in rows]
        named = [p.name is not None for p in points]
        if any(named) and not all(named):
            odd = next(p for p in points if (p.name is None) == named[0])
            raise ReferenceImportError(
                f"{where}, line {odd.line}: {'no' if named[0] else 'a'} point name, unlike line "
                f"{points[0].line}: either every line or none starts with a name"
            )
        if all(named):
            return by_name(points, plan, where, self.sigma_mm)
        return by_probing_order(points, plan, where, self.sigma_mm)

    def _point(self, number: int, fields: list[str], line: str, scale: float) -> FilePoint:
        at = f"{self.path}, line {number}"
        name = None
        if fields and parse_float(fields[0]) is None:
            name, fields = fields[0], fields[1:]
            if not name:
                raise ReferenceImportError(f"{at}: empty point name: {quoted(line)}")
        if not 3 <= len(fields) <= 8:
            raise ReferenceImportError(
                f"{at}: expected 3 to 8 numbers (X,Y,Z[,I,J,K]...){' after the name' if name else ''}, "
                f"got {len(fields)}: {quoted(line)}"
            )
        titles = FIELDS[len(fields)]
        values = [finite(field, at, title) for field, title in zip(fields, titles)]
        xyz = in_volume([v * scale for v in values[:3]], at, self.measuring_volume_mm, line)
        for value, title in zip(values, titles):
            if title.endswith("(diameter)") and value < 0:
                raise ReferenceImportError(f"{at}: field {title} must be >= 0, got {value:g}: {quoted(line)}")
        vector = approach_direction(values[3:6], at) if len(values) >= 6 else None
        return FilePoint(number, name, xyz, probe_vector=vector)


@hookimpl
def register_references(register):
    register(
        "pcdmis-xyz",
        PcDmisXyzReference,
        "CMM points from a PC-DMIS .xyz file (X,Y,Z[,I,J,K] per line; XYZIJK METRIC header)",
    )
