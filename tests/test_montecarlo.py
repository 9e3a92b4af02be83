"""GUM Supplement 1 Monte Carlo check against the linear budget on the demo (table3)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from crossfield.api import run
from crossfield.report import document
from crossfield.uncertainty.montecarlo import session_monte_carlo

DRAWS = 300  # u_MC to about 1 / sqrt(2 N) = 4 % (relative standard uncertainty)


@pytest.fixture(scope="module")
def demo(tmp_path_factory):
    out = tmp_path_factory.mktemp("mc")
    return run(scenario="table3", frames=1, seed=3, output_dir=out, name="mc", record=False, rerun=False)


def test_monte_carlo_agrees_with_the_linear_budget_on_the_demo(demo):
    results = session_monte_carlo(demo, DRAWS, seed=1)
    by_name = {c.name: c for c in demo.characteristics}
    assert [r.name for r in results] == list(by_name)
    for r in results:
        c = by_name[r.name]
        assert r.n_draws == DRAWS
        assert r.u_mc_mm == pytest.approx(c.uncertainty_mm, rel=0.10), r.name
    # the 95 % interval's half-width beside U (k = 2): within 10 % on average over the ten lengths
    assert abs(np.mean([r.agreement for r in results])) <= 0.10


def test_monte_carlo_section_in_report_json(demo, tmp_path):
    from crossfield.plugins.report_html import HtmlReport

    reporter = HtmlReport(monte_carlo=20)
    reporter.write(demo, tmp_path)
    report = json.loads((tmp_path / "report.json").read_text(encoding="utf-8"))
    document.validate(report)
    mc = report["monte_carlo"]
    assert mc["n_draws"] == 20 and len(mc["characteristics"]) == len(demo.characteristics)
    assert 'id="monte-carlo"' in (tmp_path / "report.html").read_text(encoding="utf-8")
    assert "Monte Carlo (GUM-S1, 20 draws)" in reporter.summary_text(demo)
    with pytest.raises(ValueError, match="monte_carlo"):
        HtmlReport(monte_carlo=1)
