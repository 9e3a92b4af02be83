"""``crossfield catalog report`` / ``check`` on a catalog whose L01 shifts by 2.5 sigma after
30 in-control sessions: the limits are the baseline's, the tests fire where the shift
completes their patterns (and nowhere in the baseline), Cp/Cpk are the baseline's."""

from __future__ import annotations

import json

import numpy as np
import pytest

import crossfield.catalog
from crossfield.catalog import spc
from crossfield.catalog.commands import main as catalog_main
from crossfield.catalog.synthetic import write_session

T0 = 1_796_298_450_000_000_000
HOUR = 3600 * 10**9
#: in control (no Nelson test fires on it: tests/catalog/test_catalog_spc.py), in units of 2 um
BACKGROUND = [0.5, 1.5, -0.5, -1.5, 0.2, -0.2] * 5
SHIFT = [2.5, 2.6, 2.4, 2.5, 2.7, 2.3, 2.5, 2.6, 2.4, 2.5]
SCALE, NOMINAL = 0.002, 300.0


@pytest.fixture(scope="module")
def url(tmp_path_factory):
    out = tmp_path_factory.mktemp("trends")
    for i, z in enumerate(BACKGROUND + SHIFT):
        write_session(out / "s", f"s{i:03d}", T0 + i * HOUR, {"L01": NOMINAL + SCALE * z, "L02": 200.0 + 0.001 * BACKGROUND[i % 6]},
                      nominal_mm={"L01": NOMINAL, "L02": 200.0}, tolerance_mm=0.02,
                      registration_rms_mm=0.018 + 0.0001 * i)
    url = f"sqlite:///{out / 'c.sqlite'}"
    with crossfield.catalog.open(url) as cat:
        cat.add(out / "s")
    return url


def test_check_fires_where_the_shift_completes_each_test(url, capsys):
    assert catalog_main(["check", "--catalog", url, "--name", "L01", "--baseline-n", "30", "--json"]) == 1
    firings = json.loads(capsys.readouterr().out)
    first = {}
    for f in firings:
        first.setdefault(f["rule"], int(f["session_id"][1:]))
    n = len(BACKGROUND)
    # 2 of 3 beyond 2 sigma at the 2nd shifted point, 4 of 5 beyond 1 sigma at the 4th,
    # eight beyond 1 sigma at the 8th, nine on one side at the 9th; no point beyond 3 sigma,
    # nothing in the baseline
    assert first == {5: n + 1, 6: n + 3, 8: n + 7, 2: n + 8}, first
    assert all(int(f["session_id"][1:]) >= n for f in firings)


def test_check_is_quiet_on_the_baseline_period(url, capsys):
    until = "2026-12-04T17:00:00Z"  # T0 (11:47) + 29 h: the 30 background sessions
    assert catalog_main(["check", "--catalog", url, "--until", until, "--baseline-n", "30"]) == 0
    assert "in control" in capsys.readouterr().out


def test_report_page_has_the_charts_the_limits_and_the_capability(url, tmp_path, capsys):
    page = tmp_path / "trends.html"
    assert catalog_main(["report", "--catalog", url, "-o", str(page), "--baseline-since", "2026-12-03",
                         "--baseline-until", "2026-12-04T17:00:00Z"]) == 0
    assert "2 characteristic(s)" in capsys.readouterr().out
    text = page.read_text(encoding="utf-8")
    base = NOMINAL + SCALE * np.array(BACKGROUND)
    lim = spc.individuals_limits(base)
    cap = spc.capability(base, NOMINAL - 0.02, NOMINAL + 0.02)
    assert f"{lim.lcl:.4f} – {lim.ucl:.4f}" in text
    assert f"{cap.cpk:.2f} (95 %: {cap.cpk_low:.2f} – {cap.cpk_high:.2f})" in text
    assert 'id="figure-spc-L01"' in text and 'id="figure-health-registration_rms_mm"' in text
    assert text.count("<svg") >= 3 and "Nelson test 2 (nine points in a row" in text
    assert "<script" not in text
