"""Reference stage "spatialanalyzer": points exported as ASCII by SpatialAnalyzer (SA).

SA's "Export ASCII" of points writes one point per line, in SA's working
coordinate frame, with the columns chosen in its dialog (point name
options "Collection Group Target", "Group Target", "Target" or none;
separator comma or space). With "Include SA Version and Frame Comments"
and "Include Axis Comments" the file starts with ``//`` comment lines
that state the frame, the coordinate system with its unit, and the
columns. A real export (comma separator) looks like::

    // SpatialAnalyzer SA 2022.2.0624.7 ( x64 )
    // Points Relative to Coordinate Frame 'Frames::World'
    // AXES = CARTESIAN: X,  Y,  Z (mm)
    // Collection,  Group,  Point,  X,  Y,  Z

    Station A,  CMM points,  C1,  102.531000,  -40.112000,  12.004000
    Station A,  CMM points,  C2,  140.002000,  -38.991000,  11.987000

Read here (``docs/serial-protocol.md``, "SpatialAnalyzer ASCII export"):

* ``//`` lines are comments; from them the ``AXES = <system>: ... (<unit>)``
  line gives the unit (``mm`` or ``in``; other units are refused) and the
  column line (``Collection, Group, Point, X, Y, Z``) gives the columns.
  Without a column line, the first data line's field count tells the
  layout: 3 ``X Y Z``, 4 ``Point X Y Z``, 5 ``Group Point X Y Z``, 6
  ``Collection Group Point X Y Z``.
* Fields are separated by commas (with any blanks around them) if the
  line has a comma, else by blanks; names may contain blanks only with
  the comma separator.
* The label of a point is its point (target) name, which must be a label
  of the plan's probing order; files without names are labelled by the
  plan's probing order. ``group`` keeps only the points of one group
  (an export of several groups may name a point twice).
"""

from __future__ import annotations

import re

from crossfield.plugin_api import (
    DEFAULT_VOLUME_MM,
    LENGTH_UNITS,
    FilePoint,
    MeasurementPlan,
    PointFileReference,
    ReferenceData,
    ReferenceImportError,
    by_name,
    by_probing_order,
    check_units,
    finite,
    hookimpl,
    in_volume,
    quoted,
    resolve_units,
    text_lines,
    unit_name,
)

#: Columns of each point-name option, by field count (no column comment).
LAYOUTS: dict[int, tuple[str, ...]] = {
    3: ("x", "y", "z"),
    4: ("point", "x", "y", "z"),
    5: ("group", "point", "x", "y", "z"),
    6: ("collection", "group", "point", "x", "y", "z"),
}
#: Column titles that hold the point name.
POINT_COLUMNS = ("point", "target", "point name", "target name")

_AXES = re.compile(
    r"AXES\s*=\s*(?P<system>[A-Za-z]+)\s*:(?P<axes>[^(]*)(?:\((?P<unit>[^)]*)\))?\s*$", re.IGNORECASE
)


def _split(line: str) -> list[str]:
    """Fields of a line: comma separated (blanks around fields dropped) if
    it has a comma, else blank separated."""
    if "," in line:
        return [field.strip() for field in line.split(",")]
    return line.split()


def _columns(comment: str) -> tuple[str, ...] | None:
    """The column titles of a comment line like 'Collection,  Group,
    Point,  X,  Y,  Z' (lower case), or None if it is not one."""
    titles = tuple(" ".join(field.split()).lower() for field in _split(comment))
    for k in range(len(titles) - 2):
        if titles[k : k + 3] == ("x", "y", "z"):
            return titles
    return None


class SpatialAnalyzerReference(PointFileReference):
    """CMM points from a SpatialAnalyzer ASCII point export.

    path: the exported file. units: ``"auto"`` (the unit in the file's
    ``// AXES = ... (mm)`` comment; an error if there is none), ``"mm"`` or
    ``"inch"`` (for files without axis comment; must agree with the file
    if it has one). group: keep only the points of this group (``""``: all).
    sigma_mm: standard uncertainty per coordinate (mm) given to every point.
    measuring_volume_mm: a point with |X|, |Y| or |Z| above it (mm, after
    the unit conversion) is an error naming its line.
    """

    def __init__(
        self,
        *,
        path: str,
        units: str = "auto",
        group: str = "",
        sigma_mm: float = 0.01,
        measuring_volume_mm: float = DEFAULT_VOLUME_MM,
    ):
        super().__init__(path=path, sigma_mm=sigma_mm, measuring_volume_mm=measuring_volume_mm)
        self.units = check_units(units)
        if not isinstance(group, str):
            raise TypeError(f"option 'group' must be a group name (\"\": all groups), got {group!r}")
        self.group = group.strip()

    def decode(self, raw: bytes, plan: MeasurementPlan) -> ReferenceData:
        """Parse the file's bytes (as recorded) into labelled points (mm)."""
        where = self.path
        stated: str | None = None
        stated_at = where
        columns: tuple[str, ...] | None = None
        columns_at = ""
        rows: list[tuple[int, list[str], str]] = []
        for number, line in enumerate(text_lines(raw, where, fallback="cp1252"), start=1):
            content = line.strip()
            at = f"{where}, line {number}"
            if not content:
                continue
            if content.startswith("//"):
                comment = content[2:].strip()
                axes = _AXES.match(comment)
                if axes:
                    if axes["system"].upper() != "CARTESIAN":
                        raise ReferenceImportError(
                            f"{at}: points exported in {axes['system'].upper()} coordinates; export them "
                            f"in Cartesian coordinates (X, Y, Z)"
                        )
                    if axes["unit"] is None:
                        raise ReferenceImportError(f"{at}: the AXES comment names no unit: {quoted(line)}")
                    stated, stated_at = unit_name(axes["unit"], at), at
                elif columns is None and not rows:
                    columns = _columns(comment)
                    columns_at = at
                continue
            rows.append((number, _split(content), line))
        if not rows:
            raise ReferenceImportError(f"{where}: no point lines (only comments and blank lines)")
        units = resolve_units(self.units, stated, stated_at, where)
        if columns is None:
            first_line, first, _ = rows[0]
            columns = LAYOUTS.get(len(first))
            if columns is None:
                raise ReferenceImportError(
                    f"{where}, line {first_line}: cannot tell the columns of a line with {len(first)} "
                    f"fields: without a column comment ('// Collection, Group, Point, X, Y, Z') a line "
                    f"must be X Y Z, Point X Y Z, Group Point X Y Z or Collection Group Point X Y Z"
                )
            columns_at = f"the layout of line {first_line}"
        points = self._points(rows, columns, columns_at, LENGTH_UNITS[units])
        if self.group and not points:
            groups = sorted({fields[columns.index("group")] for _, fields, _ in rows})
            raise ReferenceImportError(
                f"{where}: no point in group {self.group!r} (groups in the file: {', '.join(groups)})"
            )
        if points and points[0].name is None:
            return by_probing_order(points, plan, where, self.sigma_mm)
        hint = "; keep one group with the option group" if "group" in columns and not self.group else ""
        return by_name(points, plan, where, self.sigma_mm, hint=hint)

    def _points(
        self, rows: list[tuple[int, list[str], str]], columns: tuple[str, ...], columns_at: str, scale: float
    ) -> list[FilePoint]:
        where = self.path
        x = columns.index("x")
        names = [k for k, title in enumerate(columns[:x]) if title in POINT_COLUMNS]
        name = names[0] if names else (x - 1 if x > 0 else None)
        group = columns.index("group") if "group" in columns else None
        if self.group and group is None:
            raise ReferenceImportError(
                f"{where}: option group is {self.group!r} but the file has no group column ({columns_at})"
            )
        titles = ", ".join(title.title() for title in columns)
        points = []
        for number, fields, line in rows:
            at = f"{where}, line {number}"
            if len(fields) != len(columns):
                blanks = len(fields) > len(columns) and "," not in line
                raise ReferenceImportError(
                    f"{at}: expected {len(columns)} fields ({titles}, from {columns_at}), got {len(fields)}"
                    f"{' (a name with blanks in a blank-separated export? export with commas)' if blanks else ''}"
                    f": {quoted(line)}"
                )
            if group is not None and self.group and fields[group] != self.group:
                continue
            label = None
            if name is not None:
                label = fields[name]
                if not label:
                    raise ReferenceImportError(f"{at}: empty point name")
            xyz = in_volume(
                [finite(fields[x + k], at, axis) * scale for k, axis in enumerate("XYZ")],
                at,
                self.measuring_volume_mm,
                line,
            )
            points.append(FilePoint(number, label, xyz))
        return points


@hookimpl
def register_references(register):
    register(
        "spatialanalyzer",
        SpatialAnalyzerReference,
        "CMM points from a SpatialAnalyzer ASCII point export (Collection Group Point X Y Z; mm or inch)",
    )
