"""romer-serial reports link events (down, up, timeout, rejected lines) through its log
callable as they happen; over a real pty with the simulated arm's unplug fault."""

from __future__ import annotations

import time

import numpy as np
import pytest
from cmm_plan import LABELS, Sink, make_plan, make_probes, replay

from crossfield.errors import ReferenceImportError
from crossfield.simulator.arm import SimulatedArm, bad_checksum
from crossfield.plugins.reference_romer_serial import RomerSerialReference, wall_clock


@pytest.fixture(scope="module")
def plan():
    return make_plan("link-events.toml")


@pytest.fixture
def probes():
    return make_probes(3)


class ClockedArm(SimulatedArm):
    """The simulated arm, noting when it pulls and replugs the cable (host ns)."""

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self.unplugged_ns: list[int] = []
        self.plugged_ns: list[int] = []

    def _hang_up(self) -> None:
        self.unplugged_ns.append(time.time_ns())
        super()._hang_up()

    def _plug_in(self) -> None:
        self.plugged_ns.append(time.time_ns())  # (before: no reader can open the pty earlier)
        super()._plug_in()


def run(arm, plan, **options):
    """acquire() over the arm's pty; returns (reader, result, raw, events) where events
    interleaves ('bytes', data) from the sink and ('log', level, message, ns) from log."""
    events: list[tuple] = []
    with arm.serve_pty() as port:
        reader = RomerSerialReference(port=port, **{"timeout_s": 3.0, **options})
        reader.log = lambda level, message, timestamp_ns: events.append(("log", level, message, timestamp_ns))
        try:
            result = reader.acquire(plan, lambda data: events.append(("bytes", data)))
        except ReferenceImportError as exc:
            result = exc
    sink = Sink(e[1] for e in events if e[0] == "bytes")
    return reader, result, sink.recorded(), events


def logged(events, level=None, containing=""):
    return [e for e in events if e[0] == "log" and (level is None or e[1] == level) and containing in e[2]]


def test_unplug_and_replug_are_logged_with_their_times(plan, probes):
    arm = ClockedArm(probes, unplug_after={2: 0.3, 5: 0.2}, line_delay_s=0.01)
    start_ns = time.time_ns()
    reader, result, raw, events = run(arm, plan)
    end_ns = time.time_ns()
    # no point lost or duplicated
    assert [p.label for p in result.points] == LABELS
    for point, probe in zip(result.points, probes):
        assert np.allclose(point.xyz, probe.xyz, atol=0.5e-4, rtol=0)
    replayed = replay(reader, raw, plan)
    assert [p.label for p in replayed.points] == LABELS and replayed.problems == result.problems

    downs = logged(events, "warning", "link down at ")
    ups = logged(events, "info", "link up again after ")
    assert len(downs) == len(ups) == len(reader.outages) == 2
    link = [e[2] for e in events if e[0] == "log" and ("link down at" in e[2] or "link up again" in e[2])]
    assert [("down" if "link down" in message else "up") for message in link] == ["down", "up", "down", "up"]
    for k, (outage, down, up) in enumerate(zip(reader.outages, downs, ups)):
        # the reader saw the cable go after the arm pulled it, and came back after the arm replugged
        assert arm.unplugged_ns[k] <= outage.down_ns == down[3] < outage.up_ns == up[3] <= end_ns
        assert arm.plugged_ns[k + 1] <= outage.up_ns
        assert start_ns <= down[3]
        assert down[2].startswith(f"romer-serial {reader.port}: link down at {wall_clock(outage.down_ns)}: ")
        assert outage.reason and outage.reason in down[2]
        assert f"{outage.points_before} of 9 points so far" in down[2]
        assert up[2].startswith(
            f"romer-serial {reader.port}: link up again after {outage.duration_s:.2f} s "
            f"(down since {wall_clock(outage.down_ns)}); "
        )
    assert reader.outages[0].points_before <= 3 <= reader.outages[1].points_before <= 6
    # every problem (here: the resends after each replug) was logged once, as it happened
    warnings = [e[2] for e in logged(events, "warning") if "link down" not in e[2]]
    assert warnings == [f"romer-serial {reader.port}: {problem}" for problem in result.problems]
    # (a line cut by the pulled cable is a partial sentence; the arm's resend brings it back whole)
    assert any("resent point(s) already received" in p for p in result.problems)
    assert all("resent point(s)" in p or "partial sentence (cut short)" in p for p in result.problems)
    final = logged(events, "info")[-1][2]
    assert final.startswith(
        f"romer-serial {reader.port}: 9 of 9 points imported, {len(result.problems)} problem(s)"
    )
    assert "; the link was down 2 time(s), " in final


def test_rejected_line_is_logged_before_the_next_points_arrive(plan, probes):
    arm = SimulatedArm(probes, faults={2: bad_checksum}, line_delay_s=0.02)
    reader, result, raw, events = run(arm, plan)
    bad = logged(events, "warning", "line 3: bad checksum")
    assert len(bad) == 1 and bad[0][2] == f"romer-serial {reader.port}: {result.problems[0]}"
    # the chunk holding the last point arrives after the rejection was logged
    last = arm.sentence(len(probes) - 1)
    last_chunk = max(k for k, e in enumerate(events) if e[0] == "bytes" and last[:20] in e[1])
    assert events.index(bad[0]) < last_chunk
    assert not reader.outages and not logged(events, containing="link down")
    assert reader.decode(raw, plan).problems == result.problems  # the log adds nothing to the bytes


def test_timeout_and_lost_link_are_logged_as_errors(plan, probes):
    reader, error, raw, events = run(SimulatedArm(probes[:4]), plan, timeout_s=0.3)
    assert isinstance(error, ReferenceImportError)
    (entry,) = logged(events, "error")
    assert entry[2] == f"romer-serial {reader.port}: no new point for 0.3 s: 4 of 9 points arrived " + (
        "(missing L3.1 (seq 5), L3.2 (seq 6), L3.3 (seq 7), L3.4 (seq 8), L3.5 (seq 9))"
    )
    assert str(error) == f"romer-serial: {reader.port}: " + entry[2].split(": ", 1)[1]

    arm = SimulatedArm(probes[:3], hang_up_when_done=True)
    reader, error, raw, events = run(arm, plan, timeout_s=0.4)
    assert isinstance(error, ReferenceImportError)
    (down,) = logged(events, "warning", "link down at ")
    (entry,) = logged(events, "error")
    assert "lost the connection (" in entry[2] and "did not come back within 0.4 s" in entry[2]
    assert down[3] < entry[3] and not logged(events, containing="link up")
    assert raw == arm.expected_bytes()
    assert (
        len(reader.outages) == 1 and reader.outages[0].up_ns is None and reader.outages[0].duration_s is None
    )
