"""Faults of the CMM sources end in named, bounded, truthful outcomes (issue 9, classes
4, 8 and 11): a line cut by a disconnect is never joined to the next one, live or in
replay; implausible values are refused naming the line; noise floods cost bounded
output and sockets are read in blocks; degenerate control sets are reported. Every
link test runs over a real pty or a real TCP socket."""

from __future__ import annotations

import json
import math
import re
import socket
import threading
import time

import numpy as np
import pytest
from cmm_plan import LABELS, Sink, make_plan, make_probes, replay
from crossfield.cmm.formats import IppDmeDecoder, PcDmisDecoder
from crossfield.cmm.plausible import DEFAULT_VOLUME_MM
from crossfield.cmm.protocol import SENTENCE, CfpDecoder, Frame, ProbeRecord, Rejection, crc16, encode_point
from crossfield.errors import ConfigError, PluginError, ReferenceImportError
from crossfield.plugins.reference_csv import CsvReference
from crossfield.plugins.reference_pcdmis_xyz import PcDmisXyzReference
from crossfield.plugins.reference_romer_serial import LISTED_PROBLEMS, RomerSerialReference
from crossfield.plugins.reference_spatialanalyzer import SpatialAnalyzerReference
from crossfield.chain.registry import get_implementation, make_plugin_manager
from crossfield.simulator.arm import SimulatedArm, probes_from_points
from crossfield.simulator.ippdme_server import SimulatedIppDmeServer


@pytest.fixture(scope="module")
def plan():
    return make_plan("faults.toml")


def over_pty(arm, plan, log=None, **options):
    sink = Sink()
    with arm.serve_pty() as port:
        reader = RomerSerialReference(port=port, **{"timeout_s": 3.0, **options})
        if log is not None:
            reader.log = lambda level, message, timestamp_ns: log.append((level, message))
        result = reader.acquire(plan, sink)
    return reader, result, sink


def assert_truth(result, probes, atol_mm):
    assert [p.label for p in result.points] == LABELS
    for point, probe in zip(result.points, probes):
        assert np.allclose(point.xyz, probe.xyz, atol=atol_mm, rtol=0), point.label


# ---- class 4: a line cut by a disconnect ------------------------------------------------


def cut_probes():
    """Probes whose plain PC-DMIS lines, cut after the '-' of probe 4 and followed by
    the resend of probe 0 ('1206.941,...'), would read as X = -1206.941."""
    probes = make_probes(11)
    truth = np.array([p.xyz for p in probes])
    truth[0] = (1206.941, 150.0, -20.0)
    truth[4, 0] = -321.5
    return probes_from_points(LABELS, truth, np.random.default_rng(2), sigma_mm=0.0)


def test_pcdmis_line_cut_by_unplug_is_not_joined_to_the_resend(plan):
    probes = cut_probes()
    arm = SimulatedArm(probes, format="pcdmis-plain", unplug_after={3: 0.2}, cut_after={3: 1})
    reader, result, sink = over_pty(arm, plan, format="pcdmis")
    assert arm.connections == 2
    assert_truth(result, probes, 0.5e-3)
    raw = sink.recorded()
    # the sink got the disconnect and the reconnect between the bytes, where they happened
    kinds = [item.kind for item in sink if not isinstance(item, bytes)]
    assert kinds == ["down", "up"]
    (down_at, down), (up_at, _) = raw.link_events
    assert raw[:down_at] == b"".join(arm.sentence(k) for k in range(4)) + b"-"
    assert down_at == up_at and down.detail
    cut_line = raw[:down_at].count(b"\n") + 1
    assert result.problems[0] == f"line {cut_line}: line cut short by a disconnect, ignored: '-'"
    assert all("resent point(s) already received" in p for p in result.problems[1:])
    # replay with the link events splits the same way ...
    again = replay(reader, raw, plan)
    assert again.problems == result.problems
    assert [p.xyz.tolist() for p in again.points] == [p.xyz.tolist() for p in result.points]
    # ... while the bytes alone join the '-' to the resent line: the silent wrong point
    joined = reader.decode(raw, plan)
    assert joined.points[4].xyz[0] == -1206.941 and not any("cut short" in p for p in joined.problems)


def test_ippdme_event_cut_by_a_dropped_connection(plan):
    probes = make_probes(12)
    server = SimulatedIppDmeServer(probes, cut_after={2: 25})
    sink = Sink()
    with server.serve() as url:
        reader = RomerSerialReference(port=url, format="ippdme", timeout_s=3.0)
        result = reader.acquire(plan, sink)
    assert server.connections == 2
    assert_truth(result, probes, 0.5e-4)
    raw = sink.recorded()
    head = server.event(3)[:25]
    line = raw[: raw.index(head)].count(b"\n") + 1
    assert result.problems == (f"line {line}: line cut short by a disconnect, ignored: '{head.decode()}'",)
    assert [e.kind for _, e in raw.link_events] == ["down", "up"]
    assert replay(reader, raw, plan).problems == result.problems
    # without the split, the cut event swallows the next session's first answer
    assert reader.decode(raw, plan).problems[0].startswith(f"line {line}: malformed PtMeas event")


def test_recorded_session_keeps_the_link_events_and_replay_splits_as_live(tmp_path, monkeypatch):
    """A whole session (simulator + romer-serial over a pty) whose arm is unplugged in the
    middle of a line: /cmm/raw holds the link events on their own channel in order with
    the bytes, and the replayed reference equals the live one."""
    import crossfield.simulator.arm as arm_module
    from crossfield.recording.reader import open_recording
    from crossfield.chain.registry import make_plugin_manager as pm
    from crossfield.replay import replay_session
    from session_tools import record_session

    class CutArm(arm_module.SimulatedArm):
        def __init__(self, probes, **kwargs):
            super().__init__(probes, unplug_after={1: 0.2}, cut_after={1: 30}, **kwargs)

    import crossfield.plugins.acquire_simulator as simulator_plugin

    monkeypatch.setattr(simulator_plugin, "SimulatedArm", CutArm)
    live = record_session(tmp_path, "live", frames=1)
    assert live.reference.points and len(live.frames) == 1
    path = tmp_path / "live" / "session.mcap"
    with open_recording(path) as rec:
        raw = [(m.channel_metadata.get("content"), m.data) for m in rec.messages("/cmm/raw", file_order=True)]
        (reference,) = [m.data for m in rec.messages("/reference", decode=False)]
    events = [json.loads(data)["event"] for content, data in raw if content == "link-events"]
    assert events == ["down", "up"]
    down = next(k for k, (content, _) in enumerate(raw) if content == "link-events")
    before = b"".join(data for content, data in raw[:down] if content != "link-events")
    assert re.search(rb"\n\$CFP,3,[^\n]*\Z", before), before[-60:]  # cut in the middle of seq 3
    problems = json.loads(reference)["problems"]
    assert any("line cut short by a disconnect" in p for p in problems)
    replayed = replay_session(path, pm(), output_dir=tmp_path / "replay")
    with open_recording(replayed.info.out_dir / "session.mcap") as rec:
        (again,) = [m.data for m in rec.messages("/reference", decode=False)]
        raw_again = [(m.channel_metadata.get("content"), m.data) for m in rec.messages("/cmm/raw", file_order=True)]
    assert raw_again == raw
    a, b = json.loads(reference), json.loads(again)
    a.pop("source"), b.pop("source")
    assert a == b
    # a reference plugin that cannot take the link events is refused, not fed joined lines
    with pytest.raises(PluginError, match=r"holds 2 link event\(s\) .* reference plugin 'csv' cannot take them"):
        replay_session(path, pm(), plugins={"reference": "csv"}, options=["reference.path=p.csv"],
                       output_dir=tmp_path / "other")


# ---- class 4: implausible values --------------------------------------------------------


def cfp(body: str) -> bytes:
    return b"$" + body.encode() + b"*" + f"{crc16(body.encode()):04X}".encode()


@pytest.mark.parametrize(
    "decode, line, reason",
    [
        (CfpDecoder().decode, Frame(SENTENCE, 4, 0, cfp("CFP,1,0.0,1000000000000.0,2,3,0,0,1,6")),
         "X = 1e+12 mm is outside the measuring volume (|X| <= 5000 mm, option measuring_volume_mm)"),
        (CfpDecoder().decode, Frame(SENTENCE, 4, 0, cfp("CFP,1,0.0,1,2,-5000.1,0,0,1,6")),
         "Z = -5000.1 mm is outside the measuring volume"),
        (PcDmisDecoder().decode, Frame(SENTENCE, 4, 0, b"X1000000000000.0,Y2,Z3"),
         "X = 1e+12 mm is outside the measuring volume"),
        (PcDmisDecoder("inch").decode, Frame(SENTENCE, 4, 0, b"1,200,3"),
         "Y = 5080 mm is outside the measuring volume"),
        (PcDmisDecoder().decode, Frame(SENTENCE, 4, 0, b"1," + b"9" * 190 + b".0,3"),
         "Y = 1e+190 mm is outside the measuring volume"),
        (IppDmeDecoder().decode, Frame(SENTENCE, 4, 0, b"E0000 # PtMeas(X(1e999), Y(2), Z(3))"),
         "X is not finite (inf)"),
        (IppDmeDecoder().decode, Frame(SENTENCE, 4, 0, b"E0000 # PtMeas(X(1e12), Y(2), Z(3))"),
         "X = 1e+12 mm is outside the measuring volume"),
        (IppDmeDecoder().decode, Frame(SENTENCE, 4, 0, b"E0000 # PtMeas(X(1), Y(2), Z(3), R(-1.5))"),
         "probe radius R must be >= 0 mm, got -1.5"),
        (IppDmeDecoder().decode, Frame(SENTENCE, 4, 0, b"E0000 # PtMeas(X(1), Y(2), Z(3), IJK(1e999, 0, 0))"),
         "IJK is not finite"),
    ],
)
def test_decoders_refuse_implausible_values_naming_the_line(decode, line, reason):
    result = decode(line)
    assert isinstance(result, Rejection) and result.kind == "implausible"
    assert str(result).startswith(f"line 4: {reason}"), str(result)


def test_measuring_volume_is_an_option(plan):
    big = cfp("CFP,1,0.0,6000.0,2,3,0,0,1,6")
    assert isinstance(CfpDecoder(volume_mm=7000).decode(Frame(SENTENCE, 1, 0, big)), ProbeRecord)
    assert isinstance(CfpDecoder().decode(Frame(SENTENCE, 1, 0, big)), Rejection)
    assert DEFAULT_VOLUME_MM == 5000.0
    pm = make_plugin_manager()
    for name, base in [("romer-serial", {"port": "x"}), ("csv", {"path": "p"}),
                       ("spatialanalyzer", {"path": "p"}), ("pcdmis-xyz", {"path": "p"})]:
        impl = get_implementation(pm, "reference", name)
        assert impl.options()["measuring_volume_mm"] == DEFAULT_VOLUME_MM
        assert impl.create({**base, "measuring_volume_mm": 8000}).measuring_volume_mm == 8000.0
        for bad in (-1, 0, "eight", float("inf"), True):
            with pytest.raises(ConfigError, match="option 'measuring_volume_mm' must be a positive number of mm"):
                impl.create({**base, "measuring_volume_mm": bad})


@pytest.mark.parametrize(
    "plugin, text, message",
    [
        (CsvReference, "C1,8_98.4,0,0\n", "line 1: field x is not a finite number: '8_98.4'"),
        (CsvReference, "C1,0,0,0\nC2,1e12,0,0\n", "line 2: X = 1e+12 mm is outside the measuring volume"),
        (CsvReference, "C1,0,0,nan\n", "line 1: field z is not a finite number: 'nan'"),
        (CsvReference, "C1,0,0,1e999\n", "line 1: field z is not a finite number: '1e999'"),
        (SpatialAnalyzerReference, "// AXES = CARTESIAN: X, Y, Z (mm)\nC1 1 2 3\nC2 1 -1e12 3\n",
         "line 3: Y = -1e+12 mm is outside the measuring volume"),
        (SpatialAnalyzerReference, "// AXES = CARTESIAN: X, Y, Z (in)\nC1 1 200 3\n",
         "line 2: Y = 5080 mm is outside the measuring volume"),
        (SpatialAnalyzerReference, "// AXES = CARTESIAN: X, Y, Z (mm)\nC1 1 2 1_0\n",
         "line 2: field Z is not a finite number: '1_0'"),
        (PcDmisXyzReference, "XYZIJK METRIC\n1,2,3\n1e12,2,3\n", "line 3: X = 1e+12 mm is outside the measuring volume"),
        (PcDmisXyzReference, "XYZIJK METRIC\n1,2,3,-6\n", "line 2: field 4 (diameter) must be >= 0, got -6"),
        (PcDmisXyzReference, "XYZIJK METRIC\n1,2,inf\n", "line 2: field Z is not a finite number: 'inf'"),
    ],
)
def test_point_files_refuse_implausible_values_naming_file_and_line(tmp_path, plan, plugin, text, message):
    path = tmp_path / "points.txt"
    path.write_text(text)
    with pytest.raises(ReferenceImportError) as info:
        plugin(path=str(path)).acquire(plan, lambda data: None)
    assert str(info.value).startswith(f"{path}, {message}"), str(info.value)


# ---- class 8: floods -------------------------------------------------------------------------


def test_dollar_flood_over_a_pty_costs_bounded_output(plan):
    probes = make_probes(13)
    flood = b"$" * 1_000_000
    arm = SimulatedArm(probes, faults={2: lambda s: flood + s})
    reader, result, sink = over_pty(arm, plan)
    assert_truth(result, probes, 0.5e-4)
    raw = sink.recorded()
    assert raw == arm.expected_bytes()
    # every '$' of the flood is cut short by the next one (the last by seq 3's own '$'):
    # one problem for the whole run, not one per byte
    assert result.problems == (f"line 3: {len(flood)} partial sentences (bare '$' bytes), ignored: '$'",)
    assert replay(reader, raw, plan).problems == result.problems


def test_noise_flood_problems_are_aggregated_with_counts_and_byte_ranges(plan):
    probes = make_probes(14)
    rng = np.random.default_rng(0)
    garbage = [
        bytes(rng.integers(33, 256, 200, dtype=np.uint8)).replace(b"$", b"#") + b"\r\n" for _ in range(2000)
    ]
    dollars = [b"$x" + g for g in garbage[:1000]]
    noise = b"".join(dollars + garbage[1000:])
    arm = SimulatedArm(probes, faults={5: lambda s: noise + s})
    log: list = []
    reader, result, sink = over_pty(arm, plan, log=log)
    # the live log says each problem once, as it is found: as bounded as the problems
    assert [m for level, m in log if level == "warning"] == [f"romer-serial {reader.port}: {p}" for p in result.problems]
    assert len(log) == len(result.problems) + 2  # + "reading cfp from ..." and the final summary
    assert_truth(result, probes, 0.5e-4)
    raw = sink.recorded()
    start, end = raw.index(noise), raw.index(noise) + len(noise)
    assert len(result.problems) == LISTED_PROBLEMS + 1
    summary = result.problems[-1]
    first_line = raw[:start].count(b"\n") + 1
    lines = re.match(r"lines (\d+)-(\d+), bytes (\d+)-(\d+): (\d+) more problem\(s\), not listed one by one: (.*)", summary)
    assert lines, summary
    assert all(p.startswith(f"line {first_line + k}: line longer than 200 bytes, ignored: '$x")
               for k, p in enumerate(result.problems[:-1]))
    counted = {kind: int(n) for n, kind in (item.split(" ", 1) for item in lines[6].split(", "))}
    total = 2000
    assert sum(counted.values()) + LISTED_PROBLEMS == total == int(lines[5]) + LISTED_PROBLEMS
    assert counted == {"noise": 1000, "overlong": 1000 - LISTED_PROBLEMS}
    assert int(lines[1]) == first_line + LISTED_PROBLEMS and int(lines[2]) == first_line + total - 1
    assert int(lines[4]) == end - 3  # the last noise line ends before its "\r\n"
    assert start < int(lines[3]) < end
    assert replay(reader, raw, plan).problems == result.problems


def test_socket_reads_come_in_blocks(plan):
    """A 2 MB burst over real TCP arrives in a few large reads, not one byte per read."""
    probes = make_probes(15)
    arm = SimulatedArm(probes)
    payload = b" " * 2_000_000 + arm.expected_bytes()
    server = socket.create_server(("127.0.0.1", 0))
    port = server.getsockname()[1]

    def serve():
        connection, _ = server.accept()
        with connection:
            time.sleep(0.2)  # pyserial flushes its input right after connecting
            connection.sendall(payload)
            connection.recv(1)

    thread = threading.Thread(target=serve, daemon=True)
    thread.start()
    sink = Sink()
    result = RomerSerialReference(port=f"socket://127.0.0.1:{port}", timeout_s=3.0).acquire(plan, sink)
    thread.join(3.0)
    server.close()
    assert_truth(result, probes, 0.5e-4) and result.problems == ()
    assert sink.recorded() == payload
    assert len(sink) < len(payload) / 1000  # one byte per read was 2e6 reads


# ---- class 11: degenerate control sets, option errors ------------------------------------


def write_csv(tmp_path, rows):
    path = tmp_path / "points.csv"
    path.write_text("id,x,y,z\n" + "".join(f"{label},{x},{y},{z}\n" for label, (x, y, z) in rows.items()))
    return path


FOUR_CONTROLS = """
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
"""


def test_duplicated_and_collinear_controls_are_problems(tmp_path, plan):
    truth = {label: (10.0 * k, -3.0 * k * k, 7.0 + k) for k, label in enumerate(LABELS)}
    clean = CsvReference(path=str(write_csv(tmp_path, truth))).acquire(plan, lambda data: None)
    assert clean.problems == ()
    duplicated = dict(truth, C2=truth["C1"])
    result = CsvReference(path=str(write_csv(tmp_path, duplicated))).acquire(plan, lambda data: None)
    assert result.problems[0] == (
        f"{tmp_path / 'points.csv'}: controls C1 and C2 have the same CMM coordinates (0.0000 mm apart): "
        f"one target probed twice? The registration cannot tell them apart"
    )
    assert len(result.points) == len(LABELS)  # reported, not dropped: the points are what the file says
    collinear = dict(truth, C3=(20.0, -6.0, 9.0))  # on the line through C1 and C2
    result = CsvReference(path=str(write_csv(tmp_path, collinear))).acquire(plan, lambda data: None)
    assert len(result.problems) == 1 and "the controls C1, C2, C3 are collinear" in result.problems[0]


def test_coplanar_controls_are_a_problem_over_the_serial_line(tmp_path):
    from crossfield.plan import parse_plan

    four = parse_plan(FOUR_CONTROLS, "four.toml")
    rng = np.random.default_rng(3)
    flat = np.array([[0, 0, 50.0], [100, 0, 50.0], [0, 80, 50.0], [120, 90, 50.0], [10, 10, 10.0]])
    probes = probes_from_points(four.probing_order(), flat, rng, sigma_mm=0.0)
    reader, result, sink = over_pty(SimulatedArm(probes), four)
    assert result.problems == (
        (
            "the 4 controls C1, C2, C3, C4 are coplanar (RMS 0.0000 mm from their plane, <= 3 x sigma 0.01 mm): "
            "a mirrored registration fits them as well and cannot be detected"
        ),
    )
    assert replay(reader, sink.recorded(), four).problems == result.problems
    spatial = flat.copy()
    spatial[3, 2] = 20.0  # 30 mm out of the plane: a 3-D control set
    probes = probes_from_points(four.probing_order(), spatial, rng, sigma_mm=0.0)
    assert over_pty(SimulatedArm(probes), four)[1].problems == ()


def test_a_far_outlier_is_refused_as_out_of_the_volume_not_as_collinear(tmp_path, plan):
    probes = make_probes(16)
    outlier = encode_point(2, 12.0, (1e12, 5.0, 5.0), (0, 0, 1), 6.0)
    arm = SimulatedArm(probes, faults={1: lambda s: outlier})
    _, result, _ = over_pty(arm, plan)
    assert result.problems[0] == (
        f"line 2: X = 1e+12 mm is outside the measuring volume (|X| <= 5000 mm, option measuring_volume_mm): "
        f"'{outlier[:-2].decode()}'"
    )
    assert "C2" not in [p.label for p in result.points]
    assert not any("collinear" in p for p in result.problems)


@pytest.mark.parametrize("name, base", [("romer-serial", {"port": "x"}), ("csv", {"path": "p"}),
                                        ("spatialanalyzer", {"path": "p"}), ("pcdmis-xyz", {"path": "p"})])
def test_every_bad_option_value_is_refused_naming_its_key(name, base):
    impl = get_implementation(make_plugin_manager(), "reference", name)
    free_text = {"port", "path", "group"}  # any string is a valid name
    for key in impl.options():
        for bad in ("eight", -1, True, float("nan"), [1], 1e400, {"a": 1}):
            if key in free_text and isinstance(bad, str):
                continue
            with pytest.raises(ConfigError) as info:
                impl.create({**base, key: bad})
            assert f"option {key!r}" in str(info.value), (key, bad, str(info.value))


def test_a_noise_flood_does_not_hold_the_import_open(plan):
    """Bytes keep arriving (a stray line every 20 ms) but no new point: the idle timeout
    still ends the import, naming the bytes that came meanwhile."""
    probes = make_probes(17)
    noisy = probes[:3] + [probes[3]] * 200  # after 3 points: 200 lines of noise, 4 s in all
    arm = SimulatedArm(noisy, line_delay_s=0.02, faults={k: (lambda s: b"noise\r\n") for k in range(3, 203)})
    sink = Sink()
    start = time.monotonic()
    with arm.serve_pty() as port:
        reader = RomerSerialReference(port=port, timeout_s=0.4)
        with pytest.raises(ReferenceImportError) as info:
            reader.acquire(plan, sink)
    elapsed = time.monotonic() - start
    message = str(info.value)
    match = re.search(r"no new point for 0.4 s \((\d+) bytes arrived meanwhile, none a new point\): 3 of 9", message)
    assert match, message
    assert int(match[1]) == len(sink.recorded()) - len(b"".join(arm.sentence(k) for k in range(3)))
    assert elapsed < 2.5  # the arm would have sent noise for 4 s
    assert "more problem(s), not listed one by one" in message or "ignored 5 bytes of noise" in message


def test_the_arms_sigma_comes_from_the_configuration_and_the_warning_names_it(plan):
    """Issue 26 item 7: romer-serial states the configured sigma_mm (default: the arm
    model's specification, ARM_MODELS), every point carries it, an unknown arm model is a
    one-line error; when the residuals contradict it the consistency warning names the
    reference source and where its sigma came from."""
    from crossfield.plugins.reference_romer_serial import ARM_MODELS
    from crossfield.uncertainty.consistency import check_means, describe_reference

    probes = make_probes(len(plan.probing_order()))
    arm = SimulatedArm(probes)
    raw = b"".join(arm.sentence(k) for k in range(len(probes)))
    default = RomerSerialReference(port="recorded").decode(raw, plan)
    configured = RomerSerialReference(port="recorded", sigma_mm=0.003).decode(raw, plan)
    assert {p.sigma_mm for p in default.points} == {ARM_MODELS["simulated"]}
    assert {p.sigma_mm for p in configured.points} == {0.003}
    assert RomerSerialReference(port="x").sigma_origin == "the simulated arm model's specification (option arm_model)"
    with pytest.raises(ValueError, match="option 'arm_model' must be one of simulated"):
        RomerSerialReference(port="x", arm_model="unknown")
    named = describe_reference("romer-serial", (p.sigma_mm for p in configured.points), {"sigma_mm": 0.003})
    assert named == "the reference source 'romer-serial' (0.003 mm per coordinate, option sigma_mm)"
    # 8 residual dof, the observed sum of squares 9x the expected CMM part: chi2 = 72; the
    # budget's shrunk variance ratio (nu0 + chi2) / (nu0 + dof), nu0 = 4 (docs/uncertainty.md)
    check = check_means(1, 9 * 3 * 0.003**2, 0.0, 3 * 0.003**2, 8, reference=named)
    f = math.sqrt((4 + 72) / (4 + 8))
    assert not check.consistent and check.cmm_inflation == pytest.approx(f)
    assert f"the CMM standard deviation stated by {named} is inflated by {f:.2f}" in check.warning


def test_an_understated_arm_sigma_is_named_in_the_sessions_warning(tmp_path):
    """The simulated arm scatters 0.01 mm per coordinate; stating 0.001 mm (option sigma_mm)
    makes the registration residuals contradict it: the session's warning names romer-serial,
    its stated sigma and its origin, and the inflation is of the order of the true ratio 10."""
    from crossfield.api import run

    summary = run(scenario="table3", frames=2, seed=1, output_dir=tmp_path, name="s", record=False,
                  rerun=False, options={"reference": {"sigma_mm": 0.001}})
    check = summary.aggregate.consistency
    assert not check.consistent and 5.0 < check.cmm_inflation < 20.0
    assert ("the CMM standard deviation stated by the reference source 'romer-serial' "
            "(0.001 mm per coordinate, option sigma_mm) is inflated by") in check.warning
