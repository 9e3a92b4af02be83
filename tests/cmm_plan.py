"""The small measurement plan the CMM-link and reference-file tests share.

Three controls, a reference point and a five-probe cylinder: nine probes,
labelled in probing order by :data:`LABELS`.
"""

import numpy as np

from crossfield.plan import MeasurementPlan, parse_plan
from crossfield.stages import LinkEvent
from crossfield.simulator.arm import probes_from_points

PLAN_TOML = """
[[control]]
id = "C1"
[[control]]
id = "C2"
[[control]]
id = "C3"
[[reference_point]]
id = "R1"
[[reference_line]]
id = "L3"
probes = 5
fit = "cylinder"
"""
LABELS = ["C1", "C2", "C3", "R1", "L3.1", "L3.2", "L3.3", "L3.4", "L3.5"]


def make_plan(source: str) -> MeasurementPlan:
    """The plan, read as if from the file ``source`` (named in error messages)."""
    plan = parse_plan(PLAN_TOML, source)
    assert plan.probing_order() == LABELS
    return plan


def make_probes(seed: int) -> list:
    """Simulated-arm probes for :data:`LABELS` at random positions (mm)."""
    rng = np.random.default_rng(seed)
    return probes_from_points(LABELS, rng.uniform(-400.0, 400.0, (len(LABELS), 3)), rng)


class Recorded(bytes):
    """What a sink received, as replay gets it from a recording: the bytes,
    and ``link_events`` = [(offset in the bytes, LinkEvent)] in order."""

    link_events: list


class Sink(list):
    """A BytesSink that keeps everything handed to it (bytes and LinkEvents), in order."""

    def __call__(self, item) -> None:
        self.append(item)

    def recorded(self) -> Recorded:
        raw, events, size = [], [], 0
        for item in self:
            if isinstance(item, LinkEvent):
                events.append((size, item))
            else:
                raw.append(bytes(item))
                size += len(item)
        out = Recorded(b"".join(raw))
        out.link_events = events
        return out


def replay(reader, raw, plan):
    """``reader.decode`` of what a :class:`Sink` recorded, with its link events (as replay does)."""
    return reader.decode(raw, plan, link_events=getattr(raw, "link_events", []))
