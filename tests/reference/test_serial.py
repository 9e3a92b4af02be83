"""CMM reference stage: CFP line protocol, romer-serial over a real pty, csv import."""

from __future__ import annotations

import random
import socket
import threading
import time

import numpy as np
import pytest

import crossfield.plugins.reference_csv as reference_csv
import crossfield.plugins.reference_romer_serial as reference_romer_serial
from crossfield.errors import ConfigError, ReferenceImportError
from crossfield.plan import parse_plan
from crossfield.chain.registry import get_implementation, make_plugin_manager
from crossfield.cmm.protocol import (
    NOISE,
    OVERLONG,
    PARTIAL,
    SENTENCE,
    CfpDecoder,
    LineDecoder,
    LineFramer,
    ProbeRecord,
    Rejection,
    crc16,
    encode_point,
)
from crossfield.simulator.arm import (
    SimulatedArm,
    bad_checksum,
    dropped,
    probes_from_points,
    repeated,
    truncated,
    with_noise,
)
from crossfield.plugins.reference_csv import CsvReference
from crossfield.plugins.reference_romer_serial import RomerSerialReference
from cmm_plan import Sink

PLAN_TOML = """
[plan]
name = "serial test"

[[control]]
id = "C1"
[[control]]
id = "C2"
[[control]]
id = "C3"
[[control]]
id = "C4"

[[reference_point]]
id = "R1"

[[reference_line]]
id = "L3"
probes = 5
fit = "cylinder"
"""
LABELS = ["C1", "C2", "C3", "C4", "R1", "L3.1", "L3.2", "L3.3", "L3.4", "L3.5"]


@pytest.fixture(scope="module")
def plan():
    plan = parse_plan(PLAN_TOML, "serial-test.toml")
    assert plan.probing_order() == LABELS
    return plan


@pytest.fixture
def probes():
    rng = np.random.default_rng(20240611)
    truth = rng.uniform(-400.0, 400.0, size=(len(LABELS), 3))
    return probes_from_points(LABELS, truth, rng, sigma_mm=0.01)


def acquire_over_pty(arm: SimulatedArm, plan, wait_for_arm: bool = True, **options):
    """Run romer-serial against ``arm`` on a real pty; return (reader, result, raw bytes)."""
    sink = Sink()
    with arm.serve_pty() as port:
        reader = RomerSerialReference(port=port, **{"timeout_s": 3.0, **options})
        result = reader.acquire(plan, sink)
        if wait_for_arm:
            assert arm.wait_done(5.0), "the simulated arm did not finish writing"
    return reader, result, sink.recorded()


def assert_same_reference(a, b):
    assert a.source == b.source
    assert a.problems == b.problems
    assert [p.label for p in a.points] == [p.label for p in b.points]
    for p, q in zip(a.points, b.points):
        assert np.array_equal(p.xyz, q.xyz)
        assert np.array_equal(p.probe_vector, q.probe_vector)
        assert (p.sigma_mm, p.device_sequence, p.device_time_s, p.probe_diameter_mm) == (
            q.sigma_mm,
            q.device_sequence,
            q.device_time_s,
            q.probe_diameter_mm,
        )


def line_of(raw: bytes, needle: bytes) -> int:
    """1-based line number of the first occurrence of ``needle`` in ``raw``."""
    return raw[: raw.index(needle)].count(b"\n") + 1


# ---- protocol layers ---------------------------------------------------------


def crc16_bitwise(data: bytes) -> int:
    """Textbook MSB-first CRC-16 with polynomial 0x1021, init 0xFFFF."""
    crc = 0xFFFF
    for byte in data:
        crc ^= byte << 8
        for _ in range(8):
            crc = ((crc << 1) ^ 0x1021) if crc & 0x8000 else crc << 1
            crc &= 0xFFFF
    return crc


def test_crc16_is_ccitt_false():
    assert crc16(b"123456789") == 0x29B1  # catalogue check value of CRC-16/CCITT-FALSE
    body = b"CFP,12,3.500,1.0000,-2.0000,3.0000,0.000000,0.000000,-1.000000,6.000"
    assert crc16(body) == crc16_bitwise(body)


def test_encode_decode_round_trip():
    sentence = encode_point(42, 12.3456, (101.23456, -0.00004, 3e2), (0.0, 0.6, -0.8), 6.0)
    assert sentence.startswith(b"$CFP,42,12.346,101.2346,-0.0000,300.0000,0.000000,0.600000,-0.800000,6.000*")
    assert sentence.endswith(b"\r\n")
    record = CfpDecoder().decode_sentence(sentence[:-2], line=1)
    assert isinstance(record, ProbeRecord)
    assert record.seq == 42 and record.device_time_s == 12.346
    assert record.xyz == (101.2346, -0.0, 300.0)
    assert np.allclose(record.probe_vector, (0.0, 0.6, -0.8), atol=0, rtol=1e-15)
    assert record.probe_diameter_mm == 6.0


@pytest.mark.parametrize(
    "mutate, reason",
    [
        (lambda s: s.replace(b"*", b"#"), "no checksum ('*' missing)"),
        (lambda s: s[:-4] + b"12G4", "malformed checksum"),
        (bad_checksum, "bad checksum: got "),
        (lambda s: s.replace(b",6.000*", b",6.0O0*"), "bad checksum"),
    ],
)
def test_decoder_rejects_damaged_sentences(mutate, reason):
    good = encode_point(7, 1.0, (1, 2, 3), (0, 0, 1), 6.0)[:-2]
    result = CfpDecoder().decode_sentence(mutate(good), line=7)
    assert isinstance(result, Rejection)
    assert str(result).startswith(f"line 7: {reason}")


def sentence_with(body: str) -> bytes:
    return b"$" + body.encode() + b"*" + f"{crc16(body.encode()):04X}".encode()


@pytest.mark.parametrize(
    "body, reason",
    [
        ("CFX,1,0.0,1,2,3,0,0,1,6", "unknown sentence type 'CFX'"),
        ("CFP,1,0.0,1,2,3,0,0,1", "expected 9 fields after CFP, got 8"),
        ("CFP,x1,0.0,1,2,3,0,0,1,6", "field seq is not an integer"),
        ("CFP,1,0.0,1,2e3,3,0,0,1,6", "field Y is not a decimal number: '2e3'"),
        ("CFP,1,0.0,1,nan,3,0,0,1,6", "field Y is not a decimal number: 'nan'"),
        ("CFP,1,-1.0,1,2,3,0,0,1,6", "device time must be >= 0 s, got -1.0"),
        ("CFP,1,0.0,1,2,3,0,0.5,0.5,6", "probe vector (0.0, 0.5, 0.5) is not a unit vector"),
        ("CFP,1,0.0,1,2,3,0,0,1,0.0", "probe diameter must be > 0 mm"),
    ],
)
def test_decoder_names_the_bad_field(body, reason):
    result = CfpDecoder().decode_sentence(sentence_with(body), line=3)
    assert isinstance(result, Rejection)
    assert str(result).startswith(f"line 3: {reason}"), str(result)
    assert str(result).endswith(f"'{sentence_with(body).decode()}'")


def test_framer_resynchronises_and_numbers_lines():
    s1 = encode_point(1, 0.0, (1, 2, 3), (0, 0, 1), 6.0)
    s2 = encode_point(2, 1.0, (4, 5, 6), (0, 0, 1), 6.0)
    stream = b"\x00\xffnoise\r\n" + b"\r\n" + s1 + b"zz" + s2[:25] + s2 + b"$" + b"9" * 300 + b"\n" + s1[:12]
    frames = LineFramer().feed(stream)
    tail = LineFramer()
    tail.feed(stream)
    frames_end = tail.finish()
    assert [(f.kind, f.line) for f in frames] == [
        (NOISE, 1),
        (SENTENCE, 3),
        (NOISE, 4),
        (PARTIAL, 4),
        (SENTENCE, 4),
        (OVERLONG, 5),
    ]
    assert frames[1].data == s1[:-2] and frames[4].data == s2[:-2]
    assert frames[2].data == b"zz" and frames[3].data == s2[:25]
    assert frames[1].offset == stream.index(s1)
    assert [(f.kind, f.line, f.data) for f in frames_end] == [(PARTIAL, 6, s1[:12])]


def test_framer_result_does_not_depend_on_chunking():
    rng = random.Random(5)
    parts = [encode_point(k, k, (k, -k, 2 * k), (1, 0, 0), 4.0) for k in range(30)]
    parts[3] = b"\x00\x01junk" + parts[3]
    parts[7] = parts[7][:20]
    parts[11] = parts[11] + b"\r\n\n"
    parts[15] = bad_checksum(parts[15])
    parts[20] = b"$" + b"x" * 500
    stream = b"".join(parts) + b"$CFP,99"
    whole = LineDecoder()
    expected = [str(r) for r in whole.feed(stream) + whole.finish()]
    assert len(expected) == 27 + 5  # 27 points; noise, partial, bad crc, overlong, trailing partial
    for _ in range(100):
        decoder, results, pos = LineDecoder(), [], 0
        while pos < len(stream):
            step = rng.randint(1, 40)
            results += decoder.feed(stream[pos : pos + step])
            pos += step
        results += decoder.finish()
        assert [str(r) for r in results] == expected


# ---- romer-serial over a real pseudo-terminal --------------------------------


def test_all_points_imported_and_labelled_in_order(plan, probes):
    arm = SimulatedArm(probes, line_delay_s=0.002)
    reader, result, raw = acquire_over_pty(arm, plan, sigma_mm=0.02)
    assert result.problems == ()
    assert result.source == reader.port and arm.pty_path.startswith("/dev/pts/")
    assert [p.label for p in result.points] == LABELS
    for k, (point, probe) in enumerate(zip(result.points, probes)):
        assert point.device_sequence == k + 1
        assert point.device_time_s == pytest.approx(10.0 + 2.0 * k)
        assert np.allclose(point.xyz, probe.xyz, atol=0.5e-4, rtol=0)  # 4 decimals on the line
        assert np.allclose(point.probe_vector, probe.probe_vector, atol=1e-6)
        assert point.sigma_mm == 0.02 and point.probe_diameter_mm == 6.0
    # the sink received exactly what the arm wrote, and replay decodes it identically
    assert raw == bytes(arm.written) == arm.expected_bytes()
    assert_same_reference(reader.decode(raw, plan), result)


def test_bad_checksum_line_is_named_and_other_points_kept(plan, probes):
    arm = SimulatedArm(probes, faults={2: bad_checksum})
    reader, result, raw = acquire_over_pty(arm, plan)
    corrupted = arm.messages()[2]
    line = line_of(raw, corrupted)
    assert line == 3
    assert [p.label for p in result.points] == [label for label in LABELS if label != "C3"]
    assert result.problems[0].startswith(f"line {line}: bad checksum: got ")
    assert corrupted.rstrip(b"\r\n").decode() in result.problems[0]
    assert "sequence gap: 1 point(s) missing before seq 4: C3 (seq 3)" in result.problems[1]
    assert result.problems[-1] == "no valid point for 1 label(s): C3 (seq 3)"
    # the later points keep their own labels (labelled by seq, not arrival)
    assert np.allclose(result.by_label()["C4"].xyz, probes[3].xyz, atol=1e-4)
    assert raw == bytes(arm.written)
    assert_same_reference(reader.decode(raw, plan), result)


def test_noise_and_partial_line_are_resynchronised(plan, probes):
    faults = {1: with_noise(b"\xff\xfe\x00#!"), 4: truncated(33), 6: with_noise(b"\r\n\x7f\x7f\r\n")}
    arm = SimulatedArm(probes, faults=faults, preamble=b"\x00\x00ATZ\r\n", line_delay_s=0.001)
    reader, result, raw = acquire_over_pty(arm, plan)
    messages = arm.messages()
    seq6 = messages[6][:-2].decode()
    assert [p.label for p in result.points] == [label for label in LABELS if label != "R1"]
    assert result.problems == (
        "line 1: ignored 5 bytes of noise: '\\x00\\x00ATZ'",
        "line 3: ignored 5 bytes of noise: '\\xff\\xfe\\x00#!'",
        f"line 6: partial sentence (cut short), ignored: '{messages[5][:33].decode()}'",
        f"line 6: sequence gap: 1 point(s) missing before seq 6: R1 (seq 5): '{seq6}'",
        "line 8: ignored 2 bytes of noise: '\\x7f\\x7f'",
        "no valid point for 1 label(s): R1 (seq 5)",
    )
    assert raw == bytes(arm.written) == arm.expected_bytes()
    assert_same_reference(reader.decode(raw, plan), result)


def test_duplicate_seq_gives_no_second_point(plan, probes):
    arm = SimulatedArm(probes, faults={3: repeated(2)})
    reader, result, raw = acquire_over_pty(arm, plan)
    assert [p.label for p in result.points] == LABELS
    line = line_of(raw, arm.sentence(3)) + 1
    assert result.problems == (f"line {line}: 1 resent point(s) already received (C4), ignored",)
    assert_same_reference(reader.decode(raw, plan), result)


def test_conflicting_repeat_and_extra_points_are_reported(plan, probes):
    # seq 2 sent again with different coordinates, and one press beyond the plan
    arm = SimulatedArm(list(probes) + [probes[0]])
    clash = encode_point(2, 99.0, (0.0, 0.0, 0.0), (0, 0, 1), 6.0)
    arm.faults = {2: lambda s: clash + s}
    # (the arm may still hold the extra press when the reader closes the port)
    reader, result, raw = acquire_over_pty(arm, plan, wait_for_arm=False)
    assert [p.label for p in result.points] == LABELS
    assert np.allclose(result.by_label()["C2"].xyz, probes[1].xyz, atol=1e-4)
    distance = np.linalg.norm(np.round(probes[1].xyz, 4))
    assert result.problems[0] == (
        f"line 3: seq 2 repeated {distance:.3f} mm away from its first point (line 2, kept as C2), "
        f"ignored: '{clash[:-2].decode()}'"
    )
    # the import stops reading once the plan's last point is in: it may or may not
    # have read the extra press, but it read everything up to the last planned one
    expected = arm.expected_bytes()
    assert expected.startswith(raw) and len(raw) >= len(b"".join(arm.messages()[:10]))
    assert_same_reference(reader.decode(raw, plan), result)
    everything = reader.decode(expected, plan)
    assert [p.label for p in everything.points] == LABELS
    assert everything.problems[-1].startswith(
        "line 12: seq 11 is beyond the plan's 10 points (last is L3.5 = seq 10), ignored: '$CFP,11,"
    )


def test_timeout_names_how_many_points_arrived(plan, probes):
    arm = SimulatedArm(probes[:7], faults={1: dropped})
    chunks: list[bytes] = []
    with arm.serve_pty() as port:
        reader = RomerSerialReference(port=port, timeout_s=0.3)
        with pytest.raises(ReferenceImportError) as info:
            reader.acquire(plan, chunks.append)
    message = str(info.value)
    assert message.startswith(f"romer-serial: {port}: no new point for 0.3 s: 6 of 10 points arrived")
    assert "missing C2 (seq 2), L3.3 (seq 8), L3.4 (seq 9), L3.5 (seq 10)" in message
    assert "sequence gap: 1 point(s) missing before seq 3: C2 (seq 2)" in message
    ends = "recorded data ends before the plan's last point: 6 of 10"
    with pytest.raises(ReferenceImportError, match=ends):
        reader.decode(b"".join(chunks), plan)


def test_lost_link_is_reported(plan, probes):
    arm = SimulatedArm(probes[:3], hang_up_when_done=True)
    sink = Sink()
    with arm.serve_pty() as port:
        reader = RomerSerialReference(port=port, timeout_s=0.5)
        with pytest.raises(ReferenceImportError) as info:
            reader.acquire(plan, sink)
    assert str(info.value).startswith(f"romer-serial: {port}: lost the connection (")
    assert "and it did not come back within 0.5 s: 3 of 10 points arrived" in str(info.value)
    assert "3 of 10 points arrived" in str(info.value)
    assert sink.recorded() == arm.expected_bytes()
    assert sink.recorded().link_events == [(len(arm.expected_bytes()), sink[-1])]
    assert sink[-1].kind == "down" and sink[-1].detail.startswith(port)


def test_unopenable_port_is_named(plan):
    reader = RomerSerialReference(port="/dev/does-not-exist-crossfield", timeout_s=0.1)
    with pytest.raises(ReferenceImportError, match="cannot open port '/dev/does-not-exist-crossfield'"):
        reader.acquire(plan, lambda data: None)


def test_first_seq_from_device_and_ambiguous_start(plan, probes):
    arm = SimulatedArm(probes, first_seq=500)
    reader, result, raw = acquire_over_pty(arm, plan, first_seq="auto")
    assert [p.label for p in result.points] == LABELS and result.points[0].device_sequence == 500
    # a rejected first sentence makes the first label unknowable: refuse to guess
    arm = SimulatedArm(probes, first_seq=500, faults={0: bad_checksum})
    refused = "line 2: cannot label the points: a sentence was rejected"
    with pytest.raises(ReferenceImportError, match=refused):
        acquire_over_pty(arm, plan, first_seq="auto")
    # with the default first_seq=1, seq 500.. are all outside the plan
    with pytest.raises(ReferenceImportError, match="0 of 10 points arrived"):
        acquire_over_pty(SimulatedArm(probes, first_seq=500), plan, timeout_s=0.3)


def test_paced_line_rate(plan, probes):
    # 115200 baud 8N1: a ~95-byte sentence takes ~8 ms; the import still completes
    arm = SimulatedArm(probes, baudrate=115200)
    reader, result, raw = acquire_over_pty(arm, plan)
    assert [p.label for p in result.points] == LABELS and raw == arm.expected_bytes()


def test_socket_url_transport(plan, probes):
    """The transport layer takes any pyserial URL: here socket://."""
    arm = SimulatedArm(probes)
    server = socket.create_server(("127.0.0.1", 0))
    port = server.getsockname()[1]

    def serve():
        connection, _ = server.accept()
        with connection:
            # pyserial's socket:// flushes its input right after connecting (as it does
            # for a UART), so a device talks only once the client is settled
            time.sleep(0.2)
            connection.sendall(arm.expected_bytes())
            connection.recv(1)  # hold the connection until the client closes

    thread = threading.Thread(target=serve, daemon=True)
    thread.start()
    reader = RomerSerialReference(port=f"socket://127.0.0.1:{port}", timeout_s=3.0)
    chunks: list[bytes] = []
    result = reader.acquire(plan, chunks.append)
    thread.join(3.0)
    server.close()
    assert [p.label for p in result.points] == LABELS
    assert b"".join(chunks) == arm.expected_bytes()


def test_registered_with_options():
    pm = make_plugin_manager(builtins=False, extra=[reference_romer_serial, reference_csv])
    serial_impl = get_implementation(pm, "reference", "romer-serial")
    assert set(serial_impl.options()) == {
        "port", "arm_model", "baudrate", "timeout_s", "sigma_mm", "first_seq", "format", "units", "burst_radius_mm",
        "measuring_volume_mm",
    }
    reader = serial_impl.create({"port": "/dev/ttyUSB0", "baudrate": 115200})
    assert (reader.port, reader.baudrate, reader.sigma_mm) == ("/dev/ttyUSB0", 115200, 0.01)
    with pytest.raises(ConfigError, match="needs option 'port'"):
        serial_impl.create({})
    with pytest.raises(ConfigError, match="option 'timeout_s' must be a positive number"):
        serial_impl.create({"port": "x", "timeout_s": 0})
    csv_impl = get_implementation(pm, "reference", "csv")
    assert set(csv_impl.options()) == {"path", "sigma_mm", "measuring_volume_mm"}


# ---- csv ---------------------------------------------------------------------


def test_csv_import(tmp_path, plan, probes):
    path = tmp_path / "points.csv"
    rows = ["# exported by the arm software", "ID, X, Y, Z, Sigma"]
    for probe in probes:
        x, y, z = (float(v) for v in probe.xyz)
        sigma = ",0.015" if probe.label == "C2" else ""
        rows.append(f"{probe.label},{x!r},{y!r},{z!r}{sigma}   # {probe.label}")
    rows.insert(4, "")
    rows.append("X9,1,2,3")
    path.write_text("\r\n".join(rows) + "\r\n", encoding="utf-8")
    chunks: list[bytes] = []
    reader = CsvReference(path=str(path), sigma_mm=0.02)
    result = reader.acquire(plan, chunks.append)
    assert b"".join(chunks) == path.read_bytes()
    assert [p.label for p in result.points] == LABELS
    for point, probe in zip(result.points, probes):
        assert np.array_equal(point.xyz, probe.xyz)
    assert result.by_label()["C2"].sigma_mm == 0.015 and result.by_label()["C1"].sigma_mm == 0.02
    assert result.problems == (
        f"{path}, line {len(rows)}: id 'X9' is not a label of the plan's probing order, ignored",
    )
    assert result.source == str(path)
    assert_same_reference(reader.decode(b"".join(chunks), plan), result)


def test_csv_missing_labels_are_reported(tmp_path, plan):
    path = tmp_path / "few.csv"
    path.write_text("C1,0,0,0\nC2,1,0,0\nC3,0,1,0\n")
    result = CsvReference(path=str(path)).acquire(plan, lambda data: None)
    assert [p.label for p in result.points] == ["C1", "C2", "C3"]
    assert result.problems == (f"{path}: no point for 7 label(s): C4, R1, L3.1, L3.2, L3.3, L3.4, L3.5",)


@pytest.mark.parametrize(
    "text, message",
    [
        ("C1,0,0,0\nC2,1,zero,0\n", "line 2: field y is not a finite number: 'zero'"),
        ("id,x,y,z\nC1,0,0,0\nC2,1,0\n", "line 3: expected 4 or 5 fields (id,x,y,z[,sigma]), got 3"),
        ("# c\nC1,0,0,0\n\nC1,1,1,1\n", "line 4: duplicate id 'C1' (first on line 2)"),
        ("C1,0,0,0,-0.1\n", "line 1: sigma must be > 0 mm, got -0.1"),
        ("name,a,b,c\nC1,0,0,0\n", "line 1: expected the header 'id,x,y,z' or 'id,x,y,z,sigma'"),
        ("C1,0,0,inf\n", "line 1: field z is not a finite number: 'inf'"),
        ("C1,0,0,0\n\xff\n".encode("latin-1"), "line 2: not UTF-8 text"),
        ("Q1,0,0,0\n", "no point of the plan found"),
    ],
)
def test_csv_errors_name_file_and_line(tmp_path, plan, text, message):
    path = tmp_path / "bad.csv"
    path.write_bytes(text if isinstance(text, bytes) else text.encode())
    with pytest.raises(ReferenceImportError) as info:
        CsvReference(path=str(path)).acquire(plan, lambda data: None)
    assert str(info.value).startswith(f"{path}")
    assert message in str(info.value)


def test_csv_unreadable_file(tmp_path, plan):
    with pytest.raises(ReferenceImportError, match="missing.csv: cannot read CMM points"):
        CsvReference(path=str(tmp_path / "missing.csv")).acquire(plan, lambda data: None)
