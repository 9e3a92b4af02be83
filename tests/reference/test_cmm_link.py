"""Production CMM link: PC-DMIS lines, I++ DME over TCP, held buttons, unplug/replug,
the romer-sim command. Every link test runs over a real pty or real TCP."""

from __future__ import annotations

import os
import random
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from cmm_plan import LABELS, PLAN_TOML, Sink, make_plan, make_probes, replay

from crossfield.cmm.formats import (
    IppDmeDecoder,
    PcDmisDecoder,
    PlainLineFramer,
    encode_ippdme_event,
    encode_pcdmis,
)
from crossfield.errors import ReferenceImportError
from crossfield.cmm.protocol import OVERLONG, PARTIAL, SENTENCE, Frame, LineDecoder, ProbeRecord, Rejection
from crossfield.simulator.arm import SimulatedArm, bad_checksum
from crossfield.simulator.ippdme_server import SimulatedIppDmeServer
from crossfield.plugins.reference_romer_serial import RomerSerialReference

ROOT = Path(__file__).resolve().parents[2]
ROMER_SIM = (
    "import sys; from crossfield.simulator.romer_sim import main_romer_sim; "
    "sys.exit(main_romer_sim(sys.argv[1:]))"
)


@pytest.fixture(scope="module")
def plan():
    return make_plan("link-test.toml")


@pytest.fixture
def probes():
    return make_probes(7)


def assert_points(result, probes, atol_mm):
    assert [p.label for p in result.points] == LABELS
    for point, probe in zip(result.points, probes):
        assert np.allclose(point.xyz, probe.xyz, atol=atol_mm, rtol=0), point.label


def assert_same_reference(a, b):
    assert a.problems == b.problems and a.source == b.source
    assert [p.label for p in a.points] == [p.label for p in b.points]
    for p, q in zip(a.points, b.points):
        assert np.array_equal(p.xyz, q.xyz) and np.array_equal(p.probe_vector, q.probe_vector)
        assert p.device_sequence == q.device_sequence


def over_pty(arm, plan, wait_for_arm=True, **options):
    sink = Sink()
    with arm.serve_pty() as port:
        reader = RomerSerialReference(port=port, **{"timeout_s": 3.0, **options})
        result = reader.acquire(plan, sink)
        if wait_for_arm:
            assert arm.wait_done(5.0)
    return reader, result, sink.recorded()


# ---- PC-DMIS generic lines ------------------------------------------------------------


def test_pcdmis_encoding():
    assert encode_pcdmis([100.0, -200.0004, 300.0]) == b"X100.000,Y-200.000,Z300.000\r\n"
    assert encode_pcdmis([25.4, 0.0, -50.8], units="inch", prefixed=False) == b"1.0000,0.0000,-2.0000\r\n"


@pytest.mark.parametrize(
    "line, expected",
    [
        (b"X100.000,Y200.000,Z300.000", (100.0, 200.0, 300.0)),
        (b"x1.5, y-2, z+3.25", (1.5, -2.0, 3.25)),
        (b"100.000,200.000,300.000", (100.0, 200.0, 300.0)),
        (b"X1,Y2,Z3,I0,J0.6,K-0.8", (1.0, 2.0, 3.0)),
    ],
)
def test_pcdmis_decoder_accepts(line, expected):
    record = PcDmisDecoder().decode(Frame(SENTENCE, 4, 0, line))
    assert isinstance(record, ProbeRecord) and record.xyz == expected and record.seq is None
    inch = PcDmisDecoder("inch", volume_mm=10_000).decode(Frame(SENTENCE, 4, 0, line))  # 300 in = 7.6 m
    assert np.allclose(inch.xyz, np.array(expected) * 25.4, rtol=1e-15)


@pytest.mark.parametrize(
    "line, reason",
    [
        (b"X100.000,Y200.000", "not a point line"),
        (b"X1,Y2,Z3,junk", "not a point line"),
        (b"100.053.000,2.000,3.000", "not a point line"),  # two lines run together
        (b"X1,Y2,Z3,I1,J1,K0", "I,J,K (1, 1, 0) is not a unit vector"),
        (b"X1,Y2,Z\xb03", "not ASCII"),
    ],
)
def test_pcdmis_decoder_rejects(line, reason):
    result = PcDmisDecoder().decode(Frame(SENTENCE, 9, 0, line))
    assert isinstance(result, Rejection) and str(result).startswith(f"line 9: {reason}")


def test_plain_line_framer_is_chunking_invariant():
    stream = b"X1,Y2,Z3\r\n\r\n  \n100,200,300\n" + b"9" * 300 + b"\nX4,Y5,Z6\r\nX7,Y8"
    whole = PlainLineFramer()
    expected = whole.feed(stream) + whole.finish()
    assert [(f.kind, f.line, f.data) for f in expected] == [
        (SENTENCE, 1, b"X1,Y2,Z3"),
        (SENTENCE, 4, b"100,200,300"),
        (OVERLONG, 5, b"9" * 200),
        (SENTENCE, 6, b"X4,Y5,Z6"),
        (PARTIAL, 7, b"X7,Y8"),
    ]
    rng = random.Random(3)
    for _ in range(50):
        framer, frames, pos = PlainLineFramer(), [], 0
        while pos < len(stream):
            step = rng.randint(1, 30)
            frames += framer.feed(stream[pos : pos + step])
            pos += step
        assert frames + framer.finish() == expected


@pytest.mark.parametrize(
    "fmt, units, atol", [("pcdmis", "mm", 0.5e-3), ("pcdmis-plain", "inch", 25.4 * 0.5e-4)]
)
def test_pcdmis_over_pty(plan, probes, fmt, units, atol):
    arm = SimulatedArm(probes, format=fmt, units=units)
    reader, result, raw = over_pty(arm, plan, format="pcdmis", units=units)
    assert result.problems == ()
    assert_points(result, probes, atol)
    assert all(p.device_sequence == -1 and np.isnan(p.probe_diameter_mm) for p in result.points)
    assert raw == bytes(arm.written) == arm.expected_bytes()
    assert_same_reference(replay(reader, raw, plan), result)


def test_pcdmis_damaged_line_is_reported_and_the_reprobe_takes_its_place(plan, probes):
    # without sequence numbers a lost line cannot be placed: the import reports
    # it and waits for the missing count (the operator probes the point again)
    arm = SimulatedArm(list(probes[:4]) + [probes[3]] + list(probes[4:]), format="pcdmis")
    arm.faults = {3: lambda line: line.replace(b",Y", b";Y")}
    reader, result, raw = over_pty(arm, plan, format="pcdmis")
    line = raw[: raw.index(b";Y")].count(b"\n") + 1
    assert result.problems[0].startswith(f"line {line}: not a point line")
    assert_points(result, probes, 0.5e-3)


# ---- held button ---------------------------------------------------------------------------


def test_held_button_gives_one_point_cfp(plan, probes):
    arm = SimulatedArm(probes, bursts={2: 4, 8: 3})
    reader, result, raw = over_pty(arm, plan, wait_for_arm=False)
    assert_points(result, probes, 0.5e-4)  # the first press, not a jittered repeat
    first = raw[: raw.index(arm.sentence(2, 1))].count(b"\n") + 1
    assert result.problems[0] == (
        f"lines {first}-{first + 3}: held button: 4 repeat(s) of C3 ignored, first point kept"
    )
    # the import stopped at the plan's last point: the repeats of L3.5 are only
    # reported if they arrived in the same read
    assert all("L3.5" in p for p in result.problems[1:])
    assert_same_reference(replay(reader, raw, plan), result)


def test_held_button_gives_one_point_pcdmis(plan, probes):
    arm = SimulatedArm(probes, format="pcdmis", bursts={0: 2, 5: 5})
    reader, result, raw = over_pty(arm, plan, format="pcdmis")
    assert_points(result, probes, 0.5e-3)
    assert result.problems == (
        "lines 2-3: held button: 2 repeat(s) of C1 ignored, first point kept",
        "lines 9-13: held button: 5 repeat(s) of L3.2 ignored, first point kept",
    )


def test_repeat_far_from_its_press_is_not_a_burst(plan, probes):
    far = SimulatedArm(probes, bursts={1: 1}, burst_jitter_mm=5.0)
    reader, result, raw = over_pty(far, plan, wait_for_arm=True, burst_radius_mm=0.5)
    assert_points(result, probes, 0.5e-4)
    assert result.problems[0].startswith("line 3: seq 2 repeated ")
    assert "mm away from its first point (line 2, kept as C2), ignored" in result.problems[0]


# ---- unplug / replug -------------------------------------------------------------------


@pytest.mark.parametrize("fmt, atol", [("cfp", 0.5e-4), ("pcdmis", 0.5e-3)])
def test_unplug_and_replug_loses_and_duplicates_nothing(plan, probes, fmt, atol):
    arm = SimulatedArm(probes, format=fmt, unplug_after={2: 0.3, 5: 0.15}, line_delay_s=0.01)
    reader, result, raw = over_pty(arm, plan, format="cfp" if fmt == "cfp" else "pcdmis")
    assert arm.connections == 3
    assert_points(result, probes, atol)  # each label once, in order
    assert len(result.points) == len(LABELS)
    # the resent lines are recognised; nothing else is a problem
    assert all("resent point(s) already received" in p for p in result.problems)
    # lines still in the pty when the cable was pulled are lost on the wire (the
    # arm's resend recovers them): every line read is one the arm wrote
    written_lines = set(bytes(arm.written).splitlines())
    assert set(raw.splitlines()) <= written_lines
    assert_same_reference(replay(reader, raw, plan), result)


def test_unplug_fills_a_hole_left_by_a_damaged_line(plan, probes):
    # line 3 arrives damaged; after the replug the arm resends it intact
    # (line delay: the damaged line is read before the cable is pulled)
    arm = SimulatedArm(probes, faults={2: bad_checksum}, unplug_after={4: 0.1}, line_delay_s=0.05)
    reader, result, raw = over_pty(arm, plan)
    assert sorted(p.label for p in result.points) == sorted(LABELS)
    for probe in probes:
        assert np.allclose(result.by_label()[probe.label].xyz, probe.xyz, atol=0.5e-4)
    assert result.problems[0].startswith("line 3: bad checksum")
    assert any("seq 3 arrived out of order" in p for p in result.problems)
    assert not any(p.startswith("no valid point") for p in result.problems)


def test_link_that_never_returns_fails_after_timeout(plan, probes):
    arm = SimulatedArm(probes, unplug_after={3: 30.0})
    with arm.serve_pty() as port:
        reader = RomerSerialReference(port=port, timeout_s=0.4)
        with pytest.raises(ReferenceImportError) as info:
            reader.acquire(plan, lambda data: None)
    message = str(info.value)
    assert "lost the connection (" in message and "did not come back within 0.4 s" in message
    # the lines still in the pty when the cable was pulled may be lost with it
    assert " of 9 points arrived (missing " in message and "L3.1 (seq 5), L3.2 (seq 6)" in message


# ---- I++ DME over TCP ------------------------------------------------------------------


def test_ippdme_event_round_trip():
    event = encode_ippdme_event([1.0, -2.5, 3.0], [0.0, 0.6, -0.8], 4.0)
    assert event == (
        b"E0000 # PtMeas(X(1.0000), Y(-2.5000), Z(3.0000), "
        b"IJK(-0.000000, -0.600000, 0.800000), R(2.0000))\r\n"
    )
    record = IppDmeDecoder().decode(Frame(SENTENCE, 1, 0, event.strip()))
    assert record.xyz == (1.0, -2.5, 3.0) and record.probe_diameter_mm == 4.0
    assert np.allclose(record.probe_vector, (0.0, 0.6, -0.8))


@pytest.mark.parametrize(
    "line, result",
    [
        (b"00001 &", None),
        (b"00001 %", None),
        (b'E0000 # KeyPress("Done")', None),
        (b"E0000 # GoTo(X(1), Y(2), Z(3))", None),
        (b"E0000 # PtMeas(X(1e2), Y(.5), Z(-3))", (100.0, 0.5, -3.0)),
        (b'00001 ! Error(3, 0509, "StartSession", "Already started")', "server error for command 00001"),
        (b"E0000 # PtMeas(X(1), Y(2))", "PtMeas event without X, Y and Z"),
        (b"E0000 # PtMeas(X(1), Y(2), Z(abc))", "malformed PtMeas event: Z(abc) is not 1 number(s)"),
        (b"E0000 # PtMeas(X(1), Y(2), Z(3), IJK(0, 0, 0))", "IJK is a zero vector"),
        (b"hello", "not an I++ DME response"),
    ],
)
def test_ippdme_decoder(line, result):
    decoded = IppDmeDecoder().decode(Frame(SENTENCE, 5, 0, line))
    if result is None:
        assert decoded is None
    elif isinstance(result, tuple):
        assert decoded.xyz == result and decoded.probe_vector is None and np.isnan(decoded.probe_diameter_mm)
    else:
        assert isinstance(decoded, Rejection) and str(decoded).startswith(f"line 5: {result}")


def ippdme_session(server, plan, **options):
    sink = Sink()
    with server.serve() as url:
        reader = RomerSerialReference(port=url, format="ippdme", **{"timeout_s": 3.0, **options})
        result = reader.acquire(plan, sink)
    return reader, result, sink.recorded()


def test_ippdme_over_tcp(plan, probes):
    server = SimulatedIppDmeServer(probes, bursts={4: 2})
    reader, result, raw = ippdme_session(server, plan)
    assert_points(result, probes, 0.5e-4)
    for point, probe in zip(result.points, probes):
        assert np.allclose(point.probe_vector, probe.probe_vector, atol=2e-6)
        assert point.probe_diameter_mm == 6.0
    assert result.problems == ("lines 12-13: held button: 2 repeat(s) of L3.1 ignored, first point kept",)
    assert server.commands[:3] == ["00001 StartSession()", "00002 EnableUser()",
                                   "00003 OnPtMeasReport(X(), Y(), Z(), IJK(), R())"]
    assert bytes(server.written).startswith(raw) and raw.startswith(b"00001 &\r\n00001 %\r\n")
    assert_same_reference(replay(reader, raw, plan), result)


def test_ippdme_reconnects_after_a_drop(plan, probes):
    server = SimulatedIppDmeServer(probes, drop_after={1, 5})
    reader, result, raw = ippdme_session(server, plan)
    assert server.connections == 3
    assert [c for c in server.commands if c.endswith("StartSession()")] == ["00001 StartSession()"] * 3
    assert_points(result, probes, 0.5e-4)
    assert result.problems == ()
    assert_same_reference(replay(reader, raw, plan), result)


def test_ippdme_server_error_is_a_problem(plan, probes):
    decoder = LineDecoder(IppDmeDecoder(), PlainLineFramer())
    stream = b'00001 &\r\n00001 ! Error(3, 0509, "StartSession", "busy")\r\n' + b"".join(
        encode_ippdme_event(p.xyz, p.probe_vector, p.probe_diameter_mm) for p in probes
    )
    reader = RomerSerialReference(port="socket://localhost:1294", format="ippdme")
    result = reader.decode(stream, plan)
    assert result.problems == (
        "line 2: server error for command 00001: "
        "'00001 ! Error(3, 0509, \"StartSession\", \"busy\")'",
    )
    assert len(decoder.feed(stream)) == 1 + len(probes)


def test_format_options_are_checked():
    with pytest.raises(ValueError, match="option 'format' must be one of cfp, pcdmis, ippdme"):
        RomerSerialReference(port="x", format="nmea")
    with pytest.raises(ValueError, match="format 'cfp' is defined in mm"):
        RomerSerialReference(port="x", units="inch")
    with pytest.raises(ValueError, match="option 'burst_radius_mm' must be a positive number of mm"):
        RomerSerialReference(port="x", burst_radius_mm=0)


# ---- crossfield romer-sim --------------------------------------------------------------------


def test_romer_sim_command_serves_a_real_reader(tmp_path, plan):
    points = tmp_path / "points.csv"
    truth = {label: [10.0 * k, -5.0 * k * k, 2.5 * k + 0.1234] for k, label in enumerate(LABELS)}
    points.write_text("id,x,y,z\n" + "".join(f"{k},{x},{y},{z}\n" for k, (x, y, z) in truth.items()))
    process = subprocess.Popen(
        [sys.executable, "-c", ROMER_SIM, "--csv", str(points), "--sigma", "0", "--exit-when-done",
         "--burst", "1:2"],
        cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
        env={**os.environ, "PYTHONPATH": str(ROOT)},
    )
    try:
        port = process.stdout.readline().strip()
        assert port.endswith("romer-arm"), process.stderr.read()
        result = RomerSerialReference(port=port, timeout_s=5.0).acquire(plan, lambda data: None)
        assert process.wait(10) == 0
    finally:
        process.kill()
    assert [p.label for p in result.points] == LABELS
    for point in result.points:
        assert np.allclose(point.xyz, truth[point.label], atol=1e-9, rtol=0)
    assert result.problems == ("lines 3-4: held button: 2 repeat(s) of C2 ignored, first point kept",)
    assert "all probes sent, reader gone" in process.stderr.read()


def test_romer_sim_ippdme(tmp_path, plan):
    plan_file = tmp_path / "plan.toml"
    plan_file.write_text(PLAN_TOML)
    process = subprocess.Popen(
        [sys.executable, "-c", ROMER_SIM, "--plan", str(plan_file), "--format", "ippdme",
         "--tcp", "127.0.0.1:0", "--exit-when-done", "--seed", "4"],
        cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
        env={**os.environ, "PYTHONPATH": str(ROOT)},
    )
    try:
        url = process.stdout.readline().strip()
        assert url.startswith("socket://127.0.0.1:"), process.stderr.read()
        result = RomerSerialReference(port=url, format="ippdme", timeout_s=5.0).acquire(plan, lambda d: None)
        assert process.wait(10) == 0
    finally:
        process.kill()
    assert [p.label for p in result.points] == LABELS and result.problems == ()
