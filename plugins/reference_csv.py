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

from crossfield.plugin_api import (
    DEFAULT_VOLUME_MM,
    FilePoint,
    MeasurementPlan,
    PointFileReference,
    ReferenceData,
    ReferenceImportError,
    by_name,
    finite,
    hookimpl,
    in_volume,
    parse_float,
    quoted,
    text_lines,
)

HEADERS = (("id", "x", "y", "z"), ("id", "x", "y", "z", "sigma"))


class CsvReference(PointFileReference):
    """CMM points from a CSV file ``id,x,y,z[,sigma]`` (mm).

    path: the CSV file. sigma_mm: standard uncertainty per coordinate (mm)
    for rows without a sigma column. measuring_volume_mm: a row with
    |x|, |y| or |z| above it (mm) is an error naming its line.
    Malformed rows and duplicate ids are errors naming the file and line;
    ids that are not in the plan and plan labels without a row are reported
    as problems, and the other points are kept.
    """

    def __init__(self, *, path: str, sigma_mm: float = 0.01, measuring_volume_mm: float = DEFAULT_VOLUME_MM):
        super().__init__(path=path, sigma_mm=sigma_mm, measuring_volume_mm=measuring_volume_mm)

    def decode(self, raw: bytes, plan: MeasurementPlan) -> ReferenceData:
        """Parse the file's bytes (as recorded) into labelled points."""
        return by_name(self.parse(raw), plan, self.path, self.sigma_mm, noun="id")

    def parse(self, raw: bytes) -> list[FilePoint]:
        """The file's rows as points (mm), in file order."""
        where = self.path
        points: list[FilePoint] = []
        first_row = True
        for number, line in enumerate(text_lines(raw, where), start=1):
            content = line.split("#", 1)[0].strip()
            if not content:
                continue
            fields = [f.strip() for f in content.split(",")]
            at = f"{where}, line {number}"
            if first_row:
                first_row = False
                if len(fields) >= 4 and all(parse_float(f) is None for f in fields[1:4]):
                    if tuple(f.lower() for f in fields) not in HEADERS:
                        raise ReferenceImportError(
                            f"{at}: expected the header 'id,x,y,z' or 'id,x,y,z,sigma' or a data row, "
                            f"got {quoted(line)}"
                        )
                    continue
            if len(fields) not in (4, 5):
                raise ReferenceImportError(
                    f"{at}: expected 4 or 5 fields (id,x,y,z[,sigma]), got {len(fields)}: {quoted(line)}"
                )
            ident = fields[0]
            if not ident:
                raise ReferenceImportError(f"{at}: empty id: {quoted(line)}")
            values = [finite(field, at, name) for name, field in zip(("x", "y", "z", "sigma"), fields[1:])]
            sigma = values[3] if len(values) == 4 else None
            if sigma is not None and not sigma > 0:
                raise ReferenceImportError(f"{at}: sigma must be > 0 mm, got {sigma}")
            xyz = in_volume(values[:3], at, self.measuring_volume_mm, line)
            points.append(FilePoint(number, ident, xyz, sigma))
        return points


@hookimpl
def register_references(register):
    register("csv", CsvReference, "CMM points from a CSV file id,x,y,z[,sigma] (mm)")
