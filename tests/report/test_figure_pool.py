"""The report's figures are kept per thread and drawn again (crossfield.report.figure_pool):
a figure drawn into the figure of an earlier, different report is byte for byte the SVG
of one drawn into a new figure, for every chart of report.html."""

from __future__ import annotations

import copy
import threading

import pytest

from crossfield.api import run
from crossfield.plugin_api import document_of
from crossfield.plugins.report_html import camera_figures, report_figures
from crossfield.report.figure_pool import clear_pool


@pytest.fixture(scope="module")
def session(tmp_path_factory):
    out = tmp_path_factory.mktemp("pool")
    return run(scenario="table3", frames=3, seed=5, output_dir=out, name="s", record=False, rerun=False)


def _other(report: dict) -> dict:
    """Another report: one characteristic fewer, the deviations and residuals changed,
    one frame fewer (fewer ticks, other limits, a shorter colour cycle)."""
    other = copy.deepcopy(report)
    other["characteristics"] = other["characteristics"][1:]
    for c in other["characteristics"]:
        c["deviation_mm"] = -3.0 * c["deviation_mm"] + 0.01
    for c in other["registration"]["control_points"]:
        c["residual_mm"] = [2.0 * v for v in c["residual_mm"]][::-1]
    other["frames"] = other["frames"][:-1]
    return other


def _all(report, positions, thumbnails) -> list[str]:
    figures = report_figures(report, positions)
    return [*figures.values(), *(c["svg"] for c in camera_figures(thumbnails))]


def test_a_reused_figure_draws_the_svg_of_a_new_one(session):
    report = document_of(session)
    positions = {p.label: tuple(float(v) for v in p.xyz) for p in session.reference.points}
    other = _other(report)
    thumbs = list(session.thumbnails)
    assert len(thumbs) == 2 and all(_all(report, positions, thumbs))
    clear_pool()
    new = _all(report, positions, thumbs[::-1])
    clear_pool()
    _all(other, positions, thumbs)  # the pool now holds the other report's figures
    again = _all(report, positions, thumbs[::-1])
    assert len(new) == 5 and again == new
    assert _all(other, positions, thumbs) != new  # the other report draws other pictures


def test_each_thread_draws_into_its_own_figures(session):
    report = document_of(session)
    positions = {p.label: tuple(float(v) for v in p.xyz) for p in session.reference.points}
    mine = report_figures(report, positions)
    theirs: list[dict] = []
    worker = threading.Thread(target=lambda: theirs.append(report_figures(report, positions)))
    worker.start()
    worker.join()
    assert theirs == [mine]
