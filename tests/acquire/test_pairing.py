"""The pairing checks of the camera sources, with synthetic frame events (no SDK)."""

import numpy as np
import pytest

from crossfield.camera.pairing import ArrivalPairer, BlockCounter, GrabbedFrame, IncidentLog, pair_skew_ns

MS = 1_000_000


def frame(camera, index, host_ms, block=None, camera_ms=0.0, ok=True):
    return GrabbedFrame(
        camera=camera, ok=ok, index=index, block_id=index if block is None else block,
        camera_ns=round(camera_ms * MS), host_ns=round(host_ms * MS),
        image=np.full((2, 2), index, np.uint16) if ok else None, error="" if ok else "incomplete",
    )


# ---- BlockCounter (software trigger) ------------------------------------------------------------


def test_counter_accepts_consecutive_frames_from_any_start():
    counter = BlockCounter()
    for block in (7, 8, 9):
        counter.trigger_sent()
        assert counter.classify(block) == BlockCounter.OK


def test_late_frame_after_a_timeout_is_stale_and_the_next_one_is_ok():
    counter = BlockCounter()
    counter.trigger_sent()
    assert counter.classify(0) == BlockCounter.OK
    counter.trigger_sent()  # trigger 1: frame 1 does not come in time (timeout)
    counter.trigger_sent()  # trigger 2: the late frame 1 arrives first, then frame 2
    assert counter.expected == 2
    assert counter.classify(1) == BlockCounter.STALE
    assert counter.classify(2) == BlockCounter.OK


def test_first_frame_answers_the_first_trigger_even_when_it_comes_late():
    counter = BlockCounter()
    counter.trigger_sent()  # trigger 0 times out
    counter.trigger_sent()  # trigger 1: frame 0 arrives late, then frame 1
    assert counter.classify(0) == BlockCounter.STALE
    assert counter.classify(1) == BlockCounter.OK
    other = BlockCounter()
    other.trigger_sent()  # trigger 0 times out; its frame arrives before trigger 1 is sent
    assert other.unsolicited(0) is False
    other.trigger_sent()
    assert other.classify(1) == BlockCounter.OK
    idle = BlockCounter()
    assert idle.unsolicited(3) is True  # a frame before any trigger: free-running camera


def test_skipped_ids_are_reported_and_the_counter_resynchronises():
    counter = BlockCounter()
    counter.trigger_sent()
    counter.classify(10)
    counter.trigger_sent()
    assert counter.classify(12) == BlockCounter.AHEAD  # block 11 was lost in transport
    counter.trigger_sent()
    assert counter.classify(13) == BlockCounter.OK


def test_gige_block_ids_wrap_from_65535_to_1():
    counter = BlockCounter(modulus=65535)
    counter.trigger_sent()
    counter.classify(65534)
    for block in (65535, 1, 2):
        counter.trigger_sent()
        assert counter.classify(block) == BlockCounter.OK, block
    counter.trigger_sent()
    assert counter.classify(65535) == BlockCounter.STALE  # an old frame from before the wrap


def test_drained_frames_are_late_unless_past_the_next_expected_id():
    counter = BlockCounter()
    counter.trigger_sent()
    counter.classify(4)
    counter.trigger_sent()  # trigger for block 5 timed out
    assert counter.unsolicited(5) is False  # late frame of that trigger
    assert counter.unsolicited(6) is True  # the camera exposed without a trigger of ours
    counter.trigger_sent()
    assert counter.classify(7) == BlockCounter.OK


# ---- skew and ArrivalPairer (external trigger) ------------------------------------------------------


def test_skew_uses_camera_clock_intervals_when_available():
    prev = (frame("upper", 0, 100.0, camera_ms=5000.0), frame("lower", 0, 101.0, camera_ms=9000.0))
    u, l = frame("upper", 1, 171.0, camera_ms=5071.4), frame("lower", 1, 190.0, camera_ms=9071.5)
    skew, basis = pair_skew_ns(u, l, prev)
    assert basis == "camera clock"
    assert skew == pytest.approx(-0.1 * MS, abs=1)
    skew, basis = pair_skew_ns(u, l, None)
    assert basis == "host arrival" and skew == -19 * MS


def test_pairer_drops_the_frame_whose_partner_missed_the_trigger():
    incidents = IncidentLog("test")
    pairer = ArrivalPairer(max_skew_ns=20 * MS, timeout_ns=500 * MS, incidents=incidents)
    pairs = []
    # pulses every 100 ms; the lower camera misses pulse 2
    lower_index = 0
    for pulse in range(5):
        t = 100.0 * pulse
        pairs += pairer.push(frame("upper", pulse, t + 10), round((t + 10) * MS))
        if pulse != 2:
            pairs += pairer.push(frame("lower", lower_index, t + 12), round((t + 12) * MS))
            lower_index += 1
    assert [(u.index, l.index) for u, l in pairs] == [(0, 0), (1, 1), (3, 2), (4, 3)]
    assert [(i.kind, i.camera, i.sequence) for i in incidents] == [("no_partner", "upper", 2)]


def test_pairer_times_out_a_lonely_frame_and_drops_failed_buffers():
    incidents = IncidentLog("test")
    pairer = ArrivalPairer(max_skew_ns=20 * MS, timeout_ns=200 * MS, incidents=incidents)
    assert pairer.push(frame("upper", 0, 0.0), 0) == []
    assert pairer.push(frame("lower", 0, 1.0, ok=False), 1 * MS) == []
    assert pairer.poll(150 * MS) == []
    assert pairer.poll(250 * MS) == []
    assert [(i.kind, i.camera) for i in incidents] == [("grab_failed", "lower"), ("timeout", "upper")]
    assert not pairer.pending["upper"] and not pairer.pending["lower"]


def test_pairer_reports_lost_frames_between_good_pairs():
    incidents = IncidentLog("test")
    pairer = ArrivalPairer(max_skew_ns=20 * MS, timeout_ns=500 * MS, incidents=incidents)
    pairer.push(frame("upper", 0, 0.0, block=1), 0)
    assert len(pairer.push(frame("lower", 0, 1.0, block=1), MS)) == 1
    pairer.push(frame("upper", 1, 100.0, block=3), 100 * MS)  # upper block 2 lost in transport
    assert len(pairer.push(frame("lower", 1, 101.0, block=2), 101 * MS)) == 1
    assert [(i.kind, i.camera) for i in incidents] == [("counter_mismatch", "upper")]


def test_incident_log_calls_the_log_callable_with_on_log_keywords():
    calls = []
    log = IncidentLog("test", log=lambda **kw: calls.append(kw))
    log.add("timeout", "lower", 3, "no frame")
    assert calls[0]["level"] == "warning" and "timeout: no frame" in calls[0]["message"]
    assert calls[0]["timestamp_ns"] == log.items[0].host_ns
    assert log.counts() == {"timeout": 1}
    with pytest.raises(ValueError):
        log.add("bogus", "upper", 0, "x")
