"""The HTML reports of identify and calibrate (issue 42) in a real headless browser: the page
renders, its images load, nothing overflows at 1280 px; a screenshot of each is written
(into $COMBINED_REALITY_SCREENSHOTS too, where set, to look at). The calibrate report is
checked in test_calibrate.py, beside the calibration it shows."""
from __future__ import annotations

import os
import shutil
from pathlib import Path

import pytest
from browser import NO_BROWSER, browser, check_page, screenshot

from combined_reality.cli import main
from combined_reality.files import cylinder_tag, write_run


def check_report(page: Path, png: Path, sections: list[str]) -> dict:
    """The browser's view of a report: every image loaded, no element beyond 1280 px, the
    sections there; its screenshot written to `png`."""
    seen = check_page(page, width=1280)
    assert seen["images"] >= 4 and seen["broken"] == 0, seen
    assert seen["scrollWidth"] <= seen["clientWidth"] == 1280 and seen["overflow"] == [], seen
    for s in sections:
        assert any(h.startswith(s) for h in seen["h2"]), (s, seen["h2"])
    screenshot(page, png, width=1280, height=seen["height"])
    assert png.stat().st_size > 50_000  # a page with its plots, not a blank one
    keep = os.environ.get("COMBINED_REALITY_SCREENSHOTS")
    if keep:
        Path(keep).mkdir(parents=True, exist_ok=True)
        shutil.copy(png, Path(keep) / png.name)
    return seen


@pytest.mark.skipif(browser() is None, reason=NO_BROWSER)
def test_the_identify_report_renders_in_a_browser(cyl_a, run_a, tmp_path, capsys):
    runs = []
    for k, (a, b) in enumerate(((0, 6000), (8000, 14000))):
        runs.append(tmp_path / f"run{k + 1}.csv")
        write_run(runs[-1], run_a.slice(a, b), comments=[cylinder_tag(cyl_a)])
    page = tmp_path / "identify.html"
    assert main(["identify", "--config", str(cyl_a.source), *map(str, runs), "--report", str(page)]) == 0
    assert f"wrote {page}" in capsys.readouterr().err
    check_report(page, tmp_path / "identify_report.png",
                 ["Estimates", "The fit, run by run", "Measured and simulated: run1.csv",
                  "Measured and simulated: run2.csv", "The errors against time", "The friction law found"])


def test_a_report_must_be_html(cyl_a, run_a, tmp_path, capsys):
    write_run(tmp_path / "r.csv", run_a.slice(0, 3000))
    code = main(["identify", "--config", str(cyl_a.source), str(tmp_path / "r.csv"), "--report",
                 str(tmp_path / "r.png")])
    assert code == 2 and "the report is HTML" in capsys.readouterr().err
