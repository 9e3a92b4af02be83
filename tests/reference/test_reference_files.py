"""Reference-point file imports: SpatialAnalyzer ASCII exports and PC-DMIS .xyz files."""

from __future__ import annotations

import numpy as np
import pytest
from cmm_plan import LABELS, make_plan

from crossfield.errors import ConfigError, ReferenceImportError
from crossfield.chain.registry import get_implementation, make_plugin_manager
from crossfield.plugins.reference_csv import CsvReference
from crossfield.plugins.reference_pcdmis_xyz import PcDmisXyzReference
from crossfield.plugins.reference_spatialanalyzer import SpatialAnalyzerReference


@pytest.fixture(scope="module")
def plan():
    return make_plan("file-test.toml")


@pytest.fixture(scope="module")
def truth():
    """label -> (xyz mm as written with 6 decimals, surface normal IJK)."""
    rng = np.random.default_rng(11)
    out = {}
    for label in LABELS:
        xyz = np.round(rng.uniform(-2000.0, 2000.0, 3), 6)
        normal = rng.normal(size=3)
        out[label] = (xyz, np.round(normal / np.linalg.norm(normal), 6))
    return out


def write(tmp_path, name: str, text: str, encoding: str = "utf-8"):
    path = tmp_path / name
    path.write_bytes(text.encode(encoding))
    return path


def acquire(reader, plan):
    """acquire() with a sink; checks the sink got the file's bytes and that
    decode() of them gives the same result."""
    chunks: list[bytes] = []
    result = reader.acquire(plan, chunks.append)
    raw = b"".join(chunks)
    with open(reader.path, "rb") as handle:
        assert raw == handle.read()
    again = reader.decode(raw, plan)
    assert again.problems == result.problems and again.source == result.source == reader.path
    assert [p.label for p in again.points] == [p.label for p in result.points]
    for p, q in zip(again.points, result.points):
        assert np.array_equal(p.xyz, q.xyz) and np.array_equal(p.probe_vector, q.probe_vector)
        assert p.sigma_mm == q.sigma_mm
    return result


def sa_line(collection, group, label, xyz, sep=",  "):
    return sep.join([collection, group, label] + [f"{v:.6f}" for v in xyz])


SA_HEADER = (
    "// SpatialAnalyzer SA 2022.2.0624.7 ( x64 )  \n"
    "// Points Relative to Coordinate Frame 'Frames::Station World'\n"
    "// AXES = CARTESIAN: X,  Y,  Z ({unit})\n"
    "// Collection,  Group,  Point,  X,  Y,  Z\n"
    "\n"
)


# ---- SpatialAnalyzer ----------------------------------------------------------------


def test_spatialanalyzer_export_with_comments_mm(tmp_path, plan, truth):
    # the layout of a real SA export: comma + two blanks, names with blanks
    lines = [sa_line("Station A", "CMM points (arm)", label, truth[label][0]) for label in LABELS]
    path = write(tmp_path, "points.txt", SA_HEADER.format(unit="mm") + "\n".join(lines) + "\n")
    result = acquire(SpatialAnalyzerReference(path=str(path), sigma_mm=0.02), plan)
    assert result.problems == ()
    assert [p.label for p in result.points] == LABELS
    for point in result.points:
        assert np.array_equal(point.xyz, truth[point.label][0])
        assert point.sigma_mm == 0.02 and not point.probe_vector.any()
    # the same points through the csv import give the same reference data
    rows = [",".join([label] + [repr(float(v)) for v in truth[label][0]]) for label in LABELS]
    csv = write(tmp_path, "points.csv", "\n".join(rows))
    expected = CsvReference(path=str(csv), sigma_mm=0.02).acquire(plan, lambda raw: None)
    assert [p.label for p in expected.points] == [p.label for p in result.points]
    assert all(np.array_equal(p.xyz, q.xyz) for p, q in zip(expected.points, result.points))


def test_spatialanalyzer_inch_space_separated_scientific(tmp_path, plan, truth):
    inch = {label: truth[label][0] / 25.4 for label in LABELS}
    head = SA_HEADER.format(unit="in").replace(",  ", " ")  # the comments of a blank-separated export
    lines = [" ".join(["Arm", label] + [f"{v:.15E}" for v in inch[label]]) for label in LABELS]
    head = head.replace("Collection Group Point", "Group Point")
    path = write(tmp_path, "inch.txt", head + "\n".join(lines) + "\r\n")
    result = acquire(SpatialAnalyzerReference(path=str(path)), plan)
    assert result.problems == ()
    for point in result.points:
        written = [float(f"{v:.15E}") for v in inch[point.label]]
        assert np.array_equal(point.xyz, np.array(written) * 25.4)  # converted exactly as stated
        assert np.allclose(point.xyz, truth[point.label][0], atol=1e-9, rtol=0)
    # the unit can also come from the option when the file has no axis comment
    bare = write(tmp_path, "bare.txt", "\n".join(lines) + "\n")
    same = acquire(SpatialAnalyzerReference(path=str(bare), units="inch"), plan)
    assert all(np.array_equal(p.xyz, q.xyz) for p, q in zip(same.points, result.points))


def test_spatialanalyzer_layout_from_field_count_comments_and_problems(tmp_path, plan, truth):
    rows = [
        "// exported by hand, no column comment",
        "// AXES = CARTESIAN: X, Y, Z (mm)",
        *(f"{label}, {x}, {y}, {z}" for label, (x, y, z) in ((k, truth[k][0]) for k in LABELS[:7])),
        "",
        "// a comment between points",
        "TOOL-1, 1.0, 2.0, 3.0",
    ]
    path = write(tmp_path, "point-names.txt", "\n".join(rows) + "\n")
    result = acquire(SpatialAnalyzerReference(path=str(path)), plan)
    assert [p.label for p in result.points] == LABELS[:7]
    assert result.problems == (
        f"{path}, line 12: point name 'TOOL-1' is not a label of the plan's probing order, ignored",
        f"{path}: no point for 2 label(s): L3.4, L3.5",
    )


def test_spatialanalyzer_without_names_is_labelled_in_probing_order(tmp_path, plan, truth):
    rows = ["// AXES = CARTESIAN: X, Y, Z (mm)"] + [" ".join(f"{v:.6f}" for v in truth[k][0]) for k in LABELS]
    result = acquire(SpatialAnalyzerReference(path=str(write(tmp_path, "xyz.txt", "\n".join(rows)))), plan)
    assert [p.label for p in result.points] == LABELS and result.problems == ()
    assert all(np.array_equal(p.xyz, truth[p.label][0]) for p in result.points)


def test_spatialanalyzer_group_option_picks_one_of_two_groups(tmp_path, plan, truth):
    nominal = [sa_line("Job", "Nominal", label, truth[label][0] + 1.0) for label in LABELS]
    measured = [sa_line("Job", "Measured", label, truth[label][0]) for label in LABELS]
    path = write(tmp_path, "two-groups.txt", SA_HEADER.format(unit="mm") + "\n".join(nominal + measured))
    first_measured = 6 + len(LABELS)
    with pytest.raises(ReferenceImportError) as info:
        SpatialAnalyzerReference(path=str(path)).acquire(plan, lambda raw: None)
    assert str(info.value) == (
        f"{path}, line {first_measured}: duplicate point name 'C1' (first on line 6); "
        f"keep one group with the option group"
    )
    result = acquire(SpatialAnalyzerReference(path=str(path), group="Measured"), plan)
    assert [p.label for p in result.points] == LABELS
    assert all(np.array_equal(p.xyz, truth[p.label][0]) for p in result.points)
    with pytest.raises(
        ReferenceImportError, match=r"no point in group 'Build' \(groups in the file: Measured, Nominal\)"
    ):
        SpatialAnalyzerReference(path=str(path), group="Build").acquire(plan, lambda raw: None)


def test_spatialanalyzer_windows_text(tmp_path, plan, truth):
    lines = [sa_line("Hall 3", "Arm 20°C", label, truth[label][0]) for label in LABELS]
    path = write(tmp_path, "cp1252.txt", SA_HEADER.format(unit="mm") + "\r\n".join(lines), encoding="cp1252")
    result = acquire(SpatialAnalyzerReference(path=str(path)), plan)
    assert [p.label for p in result.points] == LABELS


@pytest.mark.parametrize(
    "body, options, message",
    [
        (
            "A, B, C, C1, 1, 2, 3\n",
            {"units": "mm"},
            "line 1: cannot tell the columns of a line with 7 fields",
        ),
        ("C1, 1, 2\n", {"units": "mm"}, "line 1: field X is not a finite number: 'C1'"),
        (
            "// Collection, Group, Point, X, Y, Z\nA, B, C1, 1, 2, 3\nA, B, C2, 1, 2\n",
            {"units": "mm"},
            "line 3: expected 6 fields (Collection, Group, Point, X, Y, Z, from ",
        ),
        (
            "// Collection Group Point X Y Z\nA B C1 1 2 3\nMy Job B C2 1 2 3\n",
            {"units": "mm"},
            (
                "line 3: expected 6 fields (Collection, Group, Point, X, Y, Z, from file-error.txt, line 1), "
                "got 7 (a name with blanks in a blank-separated export? export with commas): 'My Job B C2 1 2 3'"
            ),
        ),
        ("C1, 1, 2, 3\nC2, 1, two, 3\n", {"units": "mm"}, "line 2: field Y is not a finite number: 'two'"),
        ("C1, 1, 2, nan\n", {"units": "mm"}, "line 1: field Z is not a finite number: 'nan'"),
        (
            "// AXES = CARTESIAN: X, Y, Z (furlong)\nC1, 1, 2, 3\n",
            {},
            "line 1: unknown length unit 'furlong'",
        ),
        (
            "// AXES = CYLINDRICAL: R, Theta, Z (mm)\nC1, 1, 2, 3\n",
            {},
            "line 1: points exported in CYLINDRICAL coordinates; export them in Cartesian",
        ),
        ("C1, 1, 2, 3\n", {}, "the file does not state its length unit; set the option units"),
        (
            "// AXES = CARTESIAN: X, Y, Z (in)\nC1, 1, 2, 3\n",
            {"units": "mm"},
            "line 1: the file states inch but the option units is 'mm'",
        ),
        ("// AXES = CARTESIAN: X, Y, Z (mm)\n, 1, 2, 3\n", {}, "line 2: empty point name"),
        ("// only comments\n\n", {"units": "mm"}, "no point lines (only comments and blank lines)"),
        ("X9, 1, 2, 3\n", {"units": "mm"}, "no point of the plan found (expected point names C1, C2"),
        (
            "C1, 1, 2, 3\n",
            {"units": "mm", "group": "Arm"},
            "option group is 'Arm' but the file has no group column",
        ),
    ],
)
def test_spatialanalyzer_errors_name_file_and_line(tmp_path, plan, body, options, message):
    path = write(tmp_path, "file-error.txt", body)
    with pytest.raises(ReferenceImportError) as info:
        SpatialAnalyzerReference(path=str(path), **options).acquire(plan, lambda raw: None)
    text = str(info.value).replace(str(tmp_path) + "/", "")
    assert text.startswith(f"file-error.txt{',' if message.startswith('line ') else ':'} {message}"), text


# ---- PC-DMIS .xyz ---------------------------------------------------------------------


def xyz_line(xyz, ijk=None, sep=","):
    values = list(xyz) + ([] if ijk is None else list(ijk))
    return sep.join(f"{v:.6f}" for v in values)


def test_pcdmis_xyzijk_metric_labelled_in_probing_order(tmp_path, plan, truth):
    rows = ["XYZIJK    METRIC"] + [xyz_line(*truth[label]) for label in LABELS]
    path = write(tmp_path, "points.xyz", "\r\n".join(rows) + "\r\n")
    result = acquire(PcDmisXyzReference(path=str(path), sigma_mm=0.005), plan)
    assert result.problems == ()
    assert [p.label for p in result.points] == LABELS
    for point in result.points:
        xyz, normal = truth[point.label]
        assert np.array_equal(point.xyz, xyz) and point.sigma_mm == 0.005
        # IJK is the surface normal: the probe approaches against it
        assert np.allclose(point.probe_vector, -normal / np.linalg.norm(normal), atol=1e-15, rtol=0)
        assert point.device_sequence == -1 and np.isnan(point.probe_diameter_mm)


def test_pcdmis_header_without_metric_is_inch(tmp_path, plan, truth):
    rows = ["XYZIJK"] + [xyz_line(truth[label][0] / 25.4) for label in LABELS]
    result = acquire(PcDmisXyzReference(path=str(write(tmp_path, "inch.xyz", "\n".join(rows)))), plan)
    for point in result.points:
        written = [float(f"{v:.6f}") for v in truth[point.label][0] / 25.4]
        assert np.array_equal(point.xyz, np.array(written) * 25.4)
        assert not point.probe_vector.any()
    # without the header the unit must come from the option
    bare = write(tmp_path, "bare.xyz", "\n".join(rows[1:]))
    with pytest.raises(ReferenceImportError, match="does not state its length unit; set the option units"):
        PcDmisXyzReference(path=str(bare)).acquire(plan, lambda raw: None)
    same = acquire(PcDmisXyzReference(path=str(bare), units="inch"), plan)
    assert all(np.array_equal(p.xyz, q.xyz) for p, q in zip(same.points, result.points))
    with pytest.raises(
        ReferenceImportError, match="line 1: the file states inch but the option units is 'mm'"
    ):
        PcDmisXyzReference(path=str(write(tmp_path, "i.xyz", "\n".join(rows))), units="mm").acquire(
            plan, lambda raw: None
        )


def test_pcdmis_counts_of_numbers_per_line(tmp_path, plan, truth):
    # 3..8 numbers, read as PC-DMIS reads them; comments; blank or tab separators
    forms = [
        lambda xyz, n: xyz_line(xyz),
        lambda xyz, n: xyz_line(xyz) + ",12.7",  # circle diameter
        lambda xyz, n: xyz_line(xyz) + ",0,0",  # unused
        lambda xyz, n: xyz_line(xyz, n),
        lambda xyz, n: xyz_line(xyz, n) + ",6.0",  # circle diameter
        lambda xyz, n: xyz_line(xyz, n) + ",1,2",  # unused
        lambda xyz, n: xyz_line(xyz, n, sep=" "),
        lambda xyz, n: xyz_line(xyz, n, sep="\t"),
        lambda xyz, n: xyz_line(xyz, sep="  "),
    ]
    rows = ["# from the arm PC", "XYZIJK METRIC", "// probing order of plan file-test"]
    rows += [form(*truth[label]) for form, label in zip(forms, LABELS)]
    result = acquire(PcDmisXyzReference(path=str(write(tmp_path, "forms.xyz", "\n".join(rows)))), plan)
    assert [p.label for p in result.points] == LABELS and result.problems == ()
    for k, point in enumerate(result.points):
        assert np.array_equal(point.xyz, truth[point.label][0])
        assert point.probe_vector.any() == (k in (3, 4, 5, 6, 7))


def test_pcdmis_named_points(tmp_path, plan, truth):
    rows = ["XYZIJK METRIC"] + [
        f"{label}\t{xyz_line(truth[label][0], sep=chr(9))}" for label in reversed(LABELS)
    ]
    rows.append("TOOL\t1\t2\t3")
    path = write(tmp_path, "named.xyz", "\n".join(rows))
    result = acquire(PcDmisXyzReference(path=str(path)), plan)
    assert [p.label for p in result.points] == LABELS[::-1]  # by name, not by position
    assert all(np.array_equal(p.xyz, truth[p.label][0]) for p in result.points)
    assert result.problems == (
        f"{path}, line {len(rows)}: point name 'TOOL' is not a label of the plan's probing order, ignored",
    )


def test_pcdmis_count_mismatch_is_reported(tmp_path, plan, truth):
    few = write(tmp_path, "few.xyz", "XYZIJK METRIC\n" + "\n".join(xyz_line(truth[k][0]) for k in LABELS[:7]))
    result = acquire(PcDmisXyzReference(path=str(few)), plan)
    assert [p.label for p in result.points] == LABELS[:7]
    assert result.problems == (
        (
            f"{few}: 7 points for the plan's 9 labels (labelled in probing order): no point for 2 label(s): "
            "L3.4, L3.5; if a point is missing before the end of the file, every later label is wrong"
        ),
    )
    many = write(
        tmp_path,
        "many.xyz",
        "XYZIJK METRIC\n" + "\n".join(xyz_line(truth[k][0]) for k in LABELS + ["C1", "C2"]),
    )
    result = acquire(PcDmisXyzReference(path=str(many)), plan)
    assert [p.label for p in result.points] == LABELS
    assert result.problems == (
        (
            f"{many}: 11 points for the plan's 9 labels (labelled in probing order, last L3.5 on line 10): "
            "2 point(s) beyond the plan ignored (lines 11-12)"
        ),
    )


@pytest.mark.parametrize(
    "body, message",
    [
        ("XYZIJK METRIC\n1,2\n", "line 2: expected 3 to 8 numbers (X,Y,Z[,I,J,K]...), got 2: '1,2'"),
        ("XYZIJK METRIC\n1,2,3,4,5,6,7,8,9\n", "line 2: expected 3 to 8 numbers"),
        ("XYZIJK METRIC\n1,2,3\n1,2,x3\n", "line 3: field Z is not a finite number: 'x3'"),
        ("XYZIJK METRIC\n1,2,3,d\n", "line 2: field 4 (diameter) is not a finite number: 'd'"),
        ("XYZIJK METRIC\n1,2,3,0,0.5,0.5\n", "line 2: I, J, K (0, 0.5, 0.5) is not a unit vector"),
        ("XYZIJK METRIC\nC1,1,2,3\n4,5,6\n", "line 3: no point name, unlike line 2"),
        ("XYZIJK METRIC\n1,2,3\nC2,4,5,6\n", "line 3: a point name, unlike line 2"),
        ("XYZIJK MILLIMETRE\n1,2,3\n", "line 1: expected 'XYZIJK', 'XYZIJK METRIC' or 'XYZIJK INCH'"),
        ("XYZIJK METRIC\n# nothing\n", "no point lines"),
        ("XYZIJK METRIC\n,1,2,3\n", "line 2: empty point name"),
        (b"XYZIJK METRIC\n1,2,3\n\x81\n", "line 3: neither UTF-8 nor cp1252 text"),
    ],
)
def test_pcdmis_errors_name_file_and_line(tmp_path, plan, body, message):
    path = tmp_path / "bad.xyz"
    path.write_bytes(body if isinstance(body, bytes) else body.encode())
    with pytest.raises(ReferenceImportError) as info:
        PcDmisXyzReference(path=str(path)).acquire(plan, lambda raw: None)
    text = str(info.value)
    sep = "," if message.startswith("line") else ":"
    assert text.startswith(f"{path}{sep} {message}"), text


# ---- registry --------------------------------------------------------------------------


def test_file_imports_are_registered_with_their_options(tmp_path):
    pm = make_plugin_manager()
    sa = get_implementation(pm, "reference", "spatialanalyzer")
    options = sa.options()
    assert set(options) == {"path", "units", "group", "sigma_mm", "measuring_volume_mm"}
    assert (options["units"], options["group"], options["sigma_mm"]) == ("auto", "", 0.01)
    reader = sa.create({"path": "points.txt", "units": "inch", "group": "Arm"})
    assert (reader.path, reader.units, reader.group) == ("points.txt", "inch", "Arm")
    xyz = get_implementation(pm, "reference", "pcdmis-xyz")
    assert set(xyz.options()) == {"path", "units", "sigma_mm", "measuring_volume_mm"}
    with pytest.raises(ConfigError, match="option 'units' must be one of auto, mm, inch, got 'cm'"):
        xyz.create({"path": "p.xyz", "units": "cm"})
    with pytest.raises(ConfigError, match="needs option 'path'"):
        xyz.create({})
    with pytest.raises(ConfigError, match="option 'sigma_mm' must be a positive number of mm"):
        sa.create({"path": "p.txt", "sigma_mm": -1})
    missing = PcDmisXyzReference(path=str(tmp_path / "missing.xyz"))
    with pytest.raises(ReferenceImportError, match="missing.xyz: cannot read CMM points: No such file"):
        missing.acquire(make_plan("p.toml"), lambda raw: None)
