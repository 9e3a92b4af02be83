"""report.html with pictures, rendered by a real browser (headless Chromium, the Debian
``chromium`` package the Makefile installs), and the lab's template override.
The screenshot in docs/report.md (docs/img/report-html.png) is this test's command
on a ``crossfield run --scenario table3 --frames 6 --name demo`` session."""

from __future__ import annotations

import shutil
import subprocess

import cv2
import numpy as np
import pytest

from crossfield.api import run
from crossfield.plugins.report_html import TEMPLATE_DIR, HtmlReport


@pytest.fixture(scope="module")
def session(tmp_path_factory):
    out = tmp_path_factory.mktemp("pictures")
    return run(scenario="table3", frames=3, seed=2, output_dir=out, name="s", record=False, rerun=False)


def test_chromium_renders_the_report_with_its_pictures(session, tmp_path):
    chromium = shutil.which("chromium") or shutil.which("chromium-browser")
    assert chromium, "the Debian package 'chromium' is needed (make apt-packages)"
    page = session.info.out_dir / "report.html"
    text = page.read_text(encoding="utf-8")
    for figure in ("figure-deviations", "figure-residuals", "figure-trends", "figure-camera-upper",
                   "figure-camera-lower"):
        assert f'id="{figure}"' in text
    png = tmp_path / "report.png"
    result = subprocess.run(
        [chromium, "--headless", "--no-sandbox", "--disable-gpu", "--hide-scrollbars",
         "--window-size=1200,2400", f"--screenshot={png}", page.as_uri()],
        capture_output=True, text=True, timeout=120,
    )
    assert result.returncode == 0, result.stderr[-2000:]
    image = cv2.imread(str(png))
    assert image is not None and image.shape[:2] == (2400, 1200)
    # the page is drawn: dark text, the green tolerance bands of Figure 1, not a blank page
    dark = np.mean(image.max(axis=2) < 100)
    green = np.mean((image[:, :, 1] > 200) & (image[:, :, 2] < 235) & (image[:, :, 0] < 235))
    assert dark > 0.005 and green > 0.002, (dark, green)
    # the camera thumbnails (Cameras section, near the top): two large near-black images
    # with the bright target discs in them
    top = image[: image.shape[0] // 2]
    black = np.mean(top.max(axis=2) < 40)
    assert black > 0.05, black


def test_a_lab_template_folder_replaces_the_page(session, tmp_path):
    lab = tmp_path / "lab"
    lab.mkdir()
    (lab / "report.html.j2").write_text(
        '<!DOCTYPE html><html><head><style>{% include "report.css" %}</style></head><body>'
        "<h1>ACME Lab {{ report.plan.name }}</h1>{{ table3 }}{{ figures.deviations }}</body></html>\n",
        encoding="utf-8",
    )
    out = tmp_path / "out"
    HtmlReport(templates=str(lab)).write(session, out)
    page = (out / "report.html").read_text(encoding="utf-8")
    assert "<h1>ACME Lab simulator table3</h1>" in page and 'id="table3-lengths"' in page
    assert (TEMPLATE_DIR / "report.css").read_text(encoding="utf-8")[:200] in page  # crossfield's CSS
    assert "<svg" in page
    with pytest.raises(ValueError, match="templates"):
        HtmlReport(templates=str(tmp_path / "missing"))


def test_print_css_is_present(session):
    page = (session.info.out_dir / "report.html").read_text(encoding="utf-8")
    assert "@media print" in page and "@page" in page


def test_ids_are_unique_and_every_reference_resolves_within_its_figure(session):
    """Several matplotlib SVGs inlined in one page: each numbers its ids from 1 (figure_1,
    patch_1, ...) and names its markers by a hash, so without figures.svg's prefix the page
    repeated ~180 ids and a <use> could draw another figure's marker. Every id is now unique in
    the page, and every #reference of a figure points at an id of that same figure."""
    import re
    from collections import Counter

    text = (session.info.out_dir / "report.html").read_text(encoding="utf-8")
    ids = Counter(re.findall(r'\bid="([^"]+)"', text))
    assert ids and not [i for i, n in ids.items() if n > 1]
    figures = re.findall(r"<svg\b.*?</svg>", text, flags=re.S)
    assert len(figures) >= 5
    for figure in figures:
        own = set(re.findall(r'\bid="([^"]+)"', figure))
        refs = set(re.findall(r'(?:href="|url\()#([^")]+)', figure))
        assert refs and refs <= own, sorted(refs - own)[:5]
