"""Property-based tests (hypothesis) of every CMM framer, decoder and point-file loader:
for arbitrary bytes, arbitrary chunking and arbitrary disconnects, no traceback; every
valid point imported exactly once, with its exact coordinates; every rejected byte range
accounted for; problems bounded by the plan's size, not by the input's."""

from __future__ import annotations

import math
import re
from collections import Counter

import numpy as np
from cmm_plan import LABELS, make_plan
from crossfield.cmm.formats import (
    IppDmeDecoder,
    PcDmisDecoder,
    PlainLineFramer,
    encode_ippdme_event,
    encode_pcdmis,
)
from crossfield.cmm.plausible import DEFAULT_VOLUME_MM
from crossfield.cmm.protocol import (
    CUT,
    NOISE,
    OVERLONG,
    PARTIAL,
    SENTENCE,
    CfpDecoder,
    Frame,
    LineDecoder,
    LineFramer,
    ProbeRecord,
    Rejection,
    encode_point,
)
from crossfield.errors import ReferenceImportError
from crossfield.plugins.reference_csv import CsvReference
from crossfield.plugins.reference_pcdmis_xyz import PcDmisXyzReference
from crossfield.plugins.reference_romer_serial import LISTED_PROBLEMS, RomerSerialReference
from crossfield.plugins.reference_spatialanalyzer import SpatialAnalyzerReference
from crossfield.stages import LinkEvent
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st

PLAN = make_plan("properties.toml")
PROPERTY = settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
BLANK = b" \t\r\n"
#: What the plain line framer drops around a line: ``bytes.strip()``'s ASCII whitespace
#: (vertical tab and form feed included; formats.PlainLineFramer).
PLAIN_BLANK = b" \t\n\r\x0b\x0c"

#: Bytes that exercise the framers' and decoders' branches more often than uniform bytes.
interesting = st.binary(max_size=60) | st.lists(
    st.sampled_from([b"$", b"\n", b"\r\n", b"*", b",", b"CFP", b"X1", b"-", b"9" * 120, b"\xff", b" ", b"E0000 # "]),
    max_size=30,
).map(b"".join)
streams = st.lists(interesting, max_size=8).map(b"".join)


def chunked(data: bytes, cuts: list[int]) -> list[bytes]:
    points = sorted({min(c, len(data)) for c in cuts})
    return [data[a:b] for a, b in zip([0, *points], [*points, len(data)]) if b > a]


def run_framer(framer, data: bytes, cuts: list[int], breaks: set[int]):
    """Feed ``data`` in the pieces ``cuts`` makes; call ``cut()`` at each offset in ``breaks``."""
    frames = []
    pos = 0
    for piece in chunked(data, sorted(set(cuts) | breaks)):
        frames += framer.feed(piece)
        pos += len(piece)
        if pos in breaks:
            frames += framer.cut()
    return frames + framer.finish()


# ---- framers -----------------------------------------------------------------------------


@PROPERTY
@given(data=streams, cuts=st.lists(st.integers(0, 400), max_size=10), breaks=st.sets(st.integers(1, 400), max_size=3))
def test_cfp_framer_accounts_for_every_byte(data, cuts, breaks):
    breaks = {b for b in breaks if b < len(data)}
    frames = run_framer(LineFramer(), data, cuts, breaks)
    # the result does not depend on how the stream is chunked (only on where the link broke)
    assert frames == run_framer(LineFramer(), data, sorted(breaks), breaks)
    covered = bytearray(len(data))
    end = 0
    for f in frames:
        assert f.offset >= end, "frames overlap or are out of order"
        assert f.line == data.count(b"\n", 0, f.offset) + 1
        span = data[f.offset : f.offset + f.size]
        assert f.size > 0 and len(span) == f.size and b"\n" not in span
        if f.kind == PARTIAL and f.count > 1:
            assert span == b"$" * f.count and f.data == b"$"
        elif f.kind in (SENTENCE, PARTIAL, CUT, OVERLONG):
            assert span.startswith(f.data) and f.data.startswith(b"$")
            if f.kind == SENTENCE:
                assert span in (f.data, f.data + b"\r")
        else:
            assert f.kind == NOISE and span.startswith(f.data) and span.strip(BLANK)
        stop = f.offset + f.size
        if f.kind == OVERLONG:  # skipped with it: up to the next "$", line end or link break
            stop = min([i for i in (data.find(b"$", stop), data.find(b"\n", stop)) if i != -1] + [len(data)])
            stop = min([b for b in breaks if b >= f.offset + f.size] + [stop])
        covered[f.offset : stop] = b"\x01" * (stop - f.offset)
        end = stop
    # every byte outside the frames is blank (line ends, spaces)
    assert all(covered[k] or data[k] in BLANK for k in range(len(data)))


@PROPERTY
@given(data=streams, cuts=st.lists(st.integers(0, 400), max_size=10), breaks=st.sets(st.integers(1, 400), max_size=3))
def test_plain_framer_accounts_for_every_byte(data, cuts, breaks):
    breaks = {b for b in breaks if b < len(data)}
    frames = run_framer(PlainLineFramer(), data, cuts, breaks)
    assert frames == run_framer(PlainLineFramer(), data, sorted(breaks), breaks)
    covered = bytearray(len(data))
    end = 0
    for f in frames:
        assert f.offset >= end and f.line == data.count(b"\n", 0, f.offset) + 1
        span = data[f.offset : f.offset + f.size]
        assert len(span) == f.size and b"\n" not in span
        if f.kind == OVERLONG:
            assert span.startswith(f.data) and len(f.data) == 200
            stop = data.find(b"\n", f.offset)
            stop = min([b for b in breaks if b > f.offset] + [len(data) if stop == -1 else stop])
        else:
            assert f.kind in (SENTENCE, PARTIAL, CUT) and f.data == span.strip() and f.data
            stop = f.offset + f.size
        covered[f.offset : stop] = b"\x01" * (stop - f.offset)
        end = stop
    assert all(covered[k] or data[k] in PLAIN_BLANK for k in range(len(data)))


# ---- decoders ------------------------------------------------------------------------------

ipp_text = st.text(alphabet="EX YZIJKR()PtMeas#&%!,.-+e0123456789", max_size=80).map(str.encode)
pc_text = st.text(alphabet="XYZIJKxyz,.-+ 0123456789e", max_size=60).map(str.encode)
numbers = st.floats(allow_nan=True, allow_infinity=True) | st.floats(-1e4, 1e4)


def check_decoded(result, line: int) -> None:
    assert result is None or isinstance(result, (ProbeRecord, Rejection))
    if isinstance(result, Rejection):
        assert str(result).startswith(f"line {line}: ")
    if isinstance(result, ProbeRecord):
        assert all(math.isfinite(v) and abs(v) <= DEFAULT_VOLUME_MM for v in result.xyz)
        if result.probe_vector is not None:
            assert abs(np.linalg.norm(result.probe_vector) - 1) < 1e-9
        assert math.isnan(result.probe_diameter_mm) or 0 <= result.probe_diameter_mm <= 2 * DEFAULT_VOLUME_MM


@PROPERTY
@given(text=interesting | ipp_text | pc_text, kind=st.sampled_from([SENTENCE, NOISE, PARTIAL, OVERLONG, CUT]),
       line=st.integers(1, 10**6))
def test_decoders_never_raise_and_only_return_plausible_points(text, kind, line):
    frame = Frame(kind, line, 0, text, len(text))
    for decoder in (CfpDecoder(), PcDmisDecoder(), PcDmisDecoder("inch"), IppDmeDecoder()):
        check_decoded(decoder.decode(frame), line)


@PROPERTY
@given(xyz=st.tuples(numbers, numbers, numbers), radius=numbers)
def test_ippdme_points_are_read_exactly_or_refused(xyz, radius):
    text = f"E0000 # PtMeas(X({xyz[0]!r}), Y({xyz[1]!r}), Z({xyz[2]!r}), R({radius!r}))".encode()
    result = IppDmeDecoder().decode(Frame(SENTENCE, 3, 0, text))
    plausible = all(math.isfinite(v) and abs(v) <= DEFAULT_VOLUME_MM for v in xyz) and (
        math.isfinite(radius) and 0 <= radius <= DEFAULT_VOLUME_MM
    )
    if plausible:
        assert isinstance(result, ProbeRecord) and result.xyz == xyz and result.probe_diameter_mm == 2 * radius
    else:
        assert isinstance(result, Rejection) and result.line == 3


# ---- a stream of valid points in arbitrary noise, through the whole reader ----------------

coords = st.tuples(*[st.floats(-2000, 2000, allow_nan=False)] * 3)


def cfp_points(xyzs):
    return [encode_point(k + 1, 10.0 + k, xyz, (0.0, 0.0, 1.0), 6.0) for k, xyz in enumerate(xyzs)]


@PROPERTY
@given(
    xyzs=st.lists(coords, min_size=len(LABELS), max_size=len(LABELS)),
    noise=st.lists(streams, min_size=len(LABELS) + 1, max_size=len(LABELS) + 1),
    cuts=st.lists(st.integers(0, 4000), max_size=8),
    breaks=st.lists(st.booleans(), min_size=len(LABELS) + 1, max_size=len(LABELS) + 1),
)
def test_cfp_reader_imports_every_valid_point_once_among_noise(xyzs, noise, cuts, breaks):
    """Noise between the sentences (any bytes, after the sentence's line end), link breaks
    inside the noise: each planned point exactly once, exactly as sent."""
    sentences = cfp_points(xyzs)
    stream, events = b"", []
    for k, junk in enumerate(noise):
        head, tail = junk[: len(junk) // 2], junk[len(junk) // 2 :]
        stream += head
        if breaks[k]:
            events.append((len(stream), LinkEvent("down", "test")))
        stream += tail
        if k < len(sentences):
            stream += sentences[k]
    reader = RomerSerialReference(port="test", timeout_s=1.0)
    try:
        result = reader.decode(stream, PLAN, link_events=events)
    except ReferenceImportError as exc:
        # only if noise made a sentence look like seq < first_seq... never for valid seqs
        raise AssertionError(f"valid points were not imported: {exc}") from None
    assert [p.label for p in result.points] == LABELS
    expected = [CfpDecoder().decode_sentence(s.rstrip(b"\r\n"), 1).xyz for s in sentences]
    assert [tuple(p.xyz) for p in result.points] == expected
    assert len(result.problems) <= (len(LABELS) + 1) * (LISTED_PROBLEMS + 2)
    assert_problems_account_for_rejections(reader, stream, events, result)


def assert_problems_account_for_rejections(reader, stream, events, result):
    """Every rejection of the stream is in the problems: listed, or counted in a flood summary."""
    decoder = LineDecoder(reader.make_decoder(), reader.format.framer())
    results, pos = [], 0
    for offset, event in events:
        results += decoder.feed(stream[pos:offset])
        pos = offset
        results += decoder.cut()
    results += decoder.feed(stream[pos:]) + decoder.finish()
    rejections = [r for r in results if isinstance(r, Rejection)]
    pending = Counter(result.problems)
    unlisted = 0
    for r in rejections:
        if pending[str(r)]:
            pending[str(r)] -= 1
        else:
            unlisted += r.count
    counted = 0
    for p in result.problems:
        match = re.search(r": (\d+) more problem\(s\), not listed one by one: (.*)$", p)
        if match:
            counted += sum(int(item.split(" ", 1)[0]) for item in match[2].split(", "))
            assert int(match[1]) == sum(int(item.split(" ", 1)[0]) for item in match[2].split(", "))
    assert unlisted == counted
    # every rejected byte range lies in the stream and they do not overlap
    end = 0
    for r in rejections:
        assert 0 <= r.offset and r.offset >= end and r.offset + r.size <= len(stream)
        end = r.offset + r.size


@PROPERTY
@given(
    xyzs=st.lists(st.tuples(*[st.integers(-2_000_000, 2_000_000).map(lambda v: v / 1000)] * 3), min_size=len(LABELS),
                  max_size=len(LABELS), unique=True),
    noise=st.lists(streams, min_size=len(LABELS) + 1, max_size=len(LABELS) + 1),
    fmt=st.sampled_from(["pcdmis", "ippdme"]),
)
def test_line_formats_import_every_valid_point_once_among_noise_lines(xyzs, noise, fmt):
    """Noise lines (any bytes, ended by a line end) between valid PC-DMIS / I++ DME lines."""
    assume(all(math.dist(a, b) > 0.5 for k, a in enumerate(xyzs) for b in xyzs[k + 1 :]))  # no "held button"
    if fmt == "pcdmis":
        lines = [encode_pcdmis(xyz) for xyz in xyzs]
    else:
        lines = [encode_ippdme_event(xyz, (0.0, 0.0, -1.0), 6.0) for xyz in xyzs]
    reader = RomerSerialReference(port="test", format=fmt)
    decoder = reader.make_decoder()
    junk = [n + b"\n" for n in noise]
    # a noise line that is itself a valid point line is a valid point: not noise
    for n in junk:
        for line in n.split(b"\n"):
            assume(not isinstance(decoder.decode(Frame(SENTENCE, 1, 0, line.strip())), ProbeRecord))
    stream = b"".join(j + (lines[k] if k < len(lines) else b"") for k, j in enumerate(junk))
    result = reader.decode(stream, PLAN)
    assert [p.label for p in result.points] == LABELS
    assert np.allclose([p.xyz for p in result.points], xyzs, atol=0.5e-3, rtol=0)
    assert len(result.problems) <= (len(LABELS) + 1) * (LISTED_PROBLEMS + 2)


@PROPERTY
@given(data=streams, fmt=st.sampled_from(["cfp", "pcdmis", "ippdme"]), first_seq=st.sampled_from([1, "auto"]))
def test_reader_on_arbitrary_bytes_ends_in_a_result_or_a_named_error(data, fmt, first_seq):
    reader = RomerSerialReference(port="test", format=fmt, first_seq=first_seq if fmt == "cfp" else 1)
    try:
        result = reader.decode(data, PLAN)
    except ReferenceImportError as exc:
        assert str(exc).startswith("romer-serial: test: ") or str(exc).startswith("line ")
        return
    assert len(result.points) <= len(LABELS)
    assert len(result.problems) <= (len(LABELS) + 1) * (LISTED_PROBLEMS + 2) + 2


# ---- point files ------------------------------------------------------------------------------

files = streams | st.text(alphabet="C1R3L.,_ \t\n#/XYZIJKMETRICAXES=():mmin0123456789e+-", max_size=300).map(str.encode)


@PROPERTY
@given(data=files, plugin=st.sampled_from([CsvReference, SpatialAnalyzerReference, PcDmisXyzReference]),
       units=st.sampled_from(["auto", "mm", "inch"]))
def test_point_files_on_arbitrary_bytes_end_in_a_result_or_a_named_error(data, plugin, units):
    options = {} if plugin is CsvReference else {"units": units}
    reader = plugin(path="points.txt", **options)
    try:
        result = reader.decode(data, PLAN)
    except ReferenceImportError as exc:
        assert str(exc).startswith("points.txt")
        return
    for p in result.points:
        assert np.isfinite(p.xyz).all() and np.abs(p.xyz).max() <= DEFAULT_VOLUME_MM
    assert len({p.label for p in result.points}) == len(result.points)


@PROPERTY
@given(
    xyzs=st.lists(st.tuples(*[st.floats(-4000, 4000, allow_nan=False)] * 3), min_size=len(LABELS), max_size=len(LABELS)),
    extra=st.lists(st.sampled_from(["", "   ", "# a comment", "#", "\t"]), min_size=len(LABELS), max_size=len(LABELS)),
    crlf=st.booleans(),
)
def test_csv_imports_every_row_once_with_exact_values(xyzs, extra, crlf):
    rows = ["id,x,y,z"]
    for label, xyz, junk in zip(LABELS, xyzs, extra):
        rows += [junk, f"{label},{xyz[0]!r},{xyz[1]!r},{xyz[2]!r}"]
    text = ("\r\n" if crlf else "\n").join(rows)
    result = CsvReference(path="p.csv").decode(text.encode(), PLAN)
    assert [p.label for p in result.points] == LABELS
    assert [tuple(p.xyz) for p in result.points] == [tuple(x) for x in xyzs]  # repr round-trips exactly


@PROPERTY
@given(
    xyzs=st.lists(st.tuples(*[st.integers(-4_000_000, 4_000_000).map(lambda v: v / 1000)] * 3),
                  min_size=len(LABELS), max_size=len(LABELS)),
    comments=st.lists(st.sampled_from(["", "  ", "// a comment", "//"]), min_size=len(LABELS), max_size=len(LABELS)),
    named=st.booleans(),
    sep=st.sampled_from([",", " ", ",  ", "\t"]),
)
def test_spatialanalyzer_imports_every_point_once_with_exact_values(xyzs, comments, named, sep):
    rows = ["// AXES = CARTESIAN: X,  Y,  Z (mm)"]
    for label, xyz, comment in zip(LABELS, xyzs, comments):
        fields = ([label] if named else []) + [f"{v:.3f}" for v in xyz]
        rows += [comment, sep.join(fields)]
    result = SpatialAnalyzerReference(path="sa.txt").decode("\n".join(rows).encode(), PLAN)
    assert [p.label for p in result.points] == LABELS
    assert [tuple(p.xyz) for p in result.points] == [tuple(x) for x in xyzs]


@PROPERTY
@given(
    xyzs=st.lists(st.tuples(*[st.integers(-4_000_000, 4_000_000).map(lambda v: v / 1000)] * 3),
                  min_size=len(LABELS), max_size=len(LABELS)),
    comments=st.lists(st.sampled_from(["", "# c", "// c", " "]), min_size=len(LABELS), max_size=len(LABELS)),
    with_normal=st.booleans(),
)
def test_pcdmis_xyz_imports_every_point_once_with_exact_values(xyzs, comments, with_normal):
    rows = ["XYZIJK METRIC"]
    for xyz, comment in zip(xyzs, comments):
        rows += [comment, ",".join([f"{v:.3f}" for v in xyz] + (["0", "0", "1"] if with_normal else []))]
    result = PcDmisXyzReference(path="p.xyz").decode("\r\n".join(rows).encode(), PLAN)
    assert [p.label for p in result.points] == LABELS  # unnamed: in probing order
    assert [tuple(p.xyz) for p in result.points] == [tuple(x) for x in xyzs]
    if with_normal:
        assert all(tuple(p.probe_vector) == (-0.0, -0.0, -1.0) for p in result.points)
