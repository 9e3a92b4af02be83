"""crossfield export SESSION --csv FILE and crossfield.export: one row per characteristic."""

from __future__ import annotations

import csv
import io

import pytest

from crossfield import export
from crossfield.cli import main
from crossfield.plugins.report_html import HtmlReport

from test_report import make_summary


@pytest.fixture()
def session(tmp_path):
    summary = make_summary()
    HtmlReport(figures=False).write(summary, tmp_path)
    return summary, tmp_path


def test_cli_and_api_give_the_same_rows(session, tmp_path, capsys):
    summary, folder = session
    out = tmp_path / "results.csv"
    assert main(["export", str(folder), "--csv", str(out)]) == 0
    assert capsys.readouterr().out == f"wrote {out}\n"
    rows = list(csv.DictReader(io.StringIO(out.read_text(encoding="utf-8"))))
    assert tuple(rows[0]) == export.COLUMNS
    api_rows = export.characteristic_rows(summary)
    assert len(rows) == len(api_rows) == len(summary.characteristics)
    for row, api, c in zip(rows, api_rows, summary.characteristics):
        assert row["name"] == api["name"] == c.name
        for column, value in (("nominal_mm", c.nominal_mm), ("measured_mm", c.measured_mm),
                              ("deviation_mm", c.deviation_mm), ("U_mm", c.expanded_uncertainty_mm),
                              ("u_mm", c.uncertainty_mm), ("upper_tol_mm", c.upper_tol_mm),
                              ("lower_tol_mm", c.lower_tol_mm), ("k", c.coverage_factor)):
            if value is None or value != value:
                assert row[column] == ""
            else:
                assert float(row[column]) == value  # unrounded: reads back bit for bit
        assert row["decision"] == api["decision"] == c.decision
        assert row["accepted"] == str(c.passed)
    assert main(["export", str(folder / "report.json"), "--csv", "-"]) == 0
    assert capsys.readouterr().out.replace("\r\n", "\n") == out.read_text(encoding="utf-8").replace("\r\n", "\n")


def test_bad_input_is_one_clear_error(tmp_path, capsys):
    assert main(["export", str(tmp_path), "--csv", str(tmp_path / "x.csv")]) == 2
    assert "a folder without session.mcap or report.json; export wants a session folder" in capsys.readouterr().err
    (tmp_path / "report.json").write_text("{not json", encoding="utf-8")
    assert main(["export", str(tmp_path), "--csv", str(tmp_path / "x.csv")]) == 2
    assert "not valid JSON: line 1" in capsys.readouterr().err
    (tmp_path / "report.json").write_text('{"format": "crossfield-report/1"}', encoding="utf-8")
    assert main(["export", str(tmp_path), "--csv", str(tmp_path / "x.csv")]) == 2
    assert "has no uncertainty budget" in capsys.readouterr().err
