"""The small measurement plan the CMM-link and reference-file tests share.

Three controls, a reference point and a five-probe cylinder: nine probes,
labelled in probing order by :data:`LABELS`.
"""

import numpy as np

from crossfield.plan import MeasurementPlan, parse_plan
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
