"""`just compare`: runs side by side (counts and errors against time and altitude, windows, the
ellipse-centre bias of physical runs), and a clear error for a run that is not there."""

from __future__ import annotations

import polars as pl
import pytest
from conftest import run_stages, small_config
from test_cli import assert_clear_error, main

from pipeline.ops import compare

WINDOW = {"start_s": 1900.0, "end_s": 1920.0, "frame_rate_hz": 1.0}
PHYSICAL = {"sensor": "physical", "range_source": "apparent_size", "bearing": "corrected",
            "detect_min_diameter_px": 5.0}
RUN = ("ingest", "trajectory", "imu", "detect", "estimate", "navigate", "score")


@pytest.mark.slow
def test_compare_writes_the_report_of_a_paper_and_a_physical_run(workdir, catalogue_db,
                                                                 monkeypatch, capsys):
    run_stages(small_config("paper", catalogue_db, WINDOW), workdir / "runs", RUN)
    run_stages(small_config("phys", catalogue_db, WINDOW,
                            trajectory={"epoch_utc": "2026-01-30T08:40:00Z"},
                            detection=PHYSICAL), workdir / "runs", RUN)
    code, out, _ = main(monkeypatch, capsys, "compare", "paper", "phys", "--name", "two")
    assert code in (0, None)
    folder = workdir / "runs" / "compare-two"
    assert f"wrote {folder / 'report.md'}" in " ".join(out.split())
    text = (folder / "report.md").read_text()
    for fig in ("fig_visible.png", "fig_used.png", "fig_errors.png", "fig_centre_bias.png"):
        assert (folder / fig).stat().st_size > 10_000 and fig in text
    rows = [line for line in text.splitlines() if line.startswith("| paper |")
            or line.startswith("| phys |")]
    assert sum(r.startswith("| paper | 1800-2400 s") for r in rows) == 1
    assert sum(r.startswith("| phys | 1800-2400 s") for r in rows) == 1
    assert "## Ellipse-centre bias" in text  # only the physical run has ellipses


def test_centre_bias_is_none_without_ellipses_and_binned_with_them():
    assert compare.centre_bias("x", pl.DataFrame({"c_true_mcmf_x_m": [0.0]}), None, None) is None


@pytest.mark.parametrize("args", [("compare", "nowhere"), ("compare", "../escape")])
def test_compare_of_a_missing_or_bad_run_is_one_clear_line(workdir, monkeypatch, capsys, args):
    code, _, err = main(monkeypatch, capsys, *args)
    assert_clear_error(code, err, args[1])
