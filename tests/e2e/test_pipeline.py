"""End to end: the `short` scenario (1,800-2,400 s of the paper's case, one frame every 5 s, the
default 1.3 M-crater synthetic catalogue) through every stage with the CLI, then the scores
against tolerances derived from the estimators' own covariances and the Cramér-Rao bound, and
every recording read back.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import duckdb
import numpy as np
import polars as pl
import pytest
import rerun as rr
from conftest import REPO
from scipy import stats
from typer.testing import CliRunner

from pipeline.cli import app
from pipeline.viz.rerun.base import APP_ID, catalogue_recording_id, recording_id
from pipeline.workspace import workspace

# Two-sided 99.9 % bounds: the tests fail by chance about once in a thousand runs each.
ALPHA = 1e-3


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory) -> Path:
    """The short scenario run once through `python -m pipeline run short` in a scratch folder."""
    root = tmp_path_factory.mktemp("e2e")
    shutil.copytree(REPO / "runs" / "scenarios", root / "runs" / "scenarios")
    mp = pytest.MonkeyPatch()
    mp.chdir(root)
    mp.setenv("CRATER_NAV_ROOT", str(root))
    workspace.cache_clear()
    try:
        result = CliRunner().invoke(app, ["run", "short"], catch_exceptions=False)
        assert result.exit_code == 0, result.output
        (root / "headline.txt").write_text(result.output)
    finally:
        mp.undo()
        workspace.cache_clear()
    return root / "runs" / "short"


@pytest.fixture
def in_project(run_dir, monkeypatch) -> Path:
    """The e2e scratch project as the workspace and working directory (for a second command)."""
    root = run_dir.parent.parent
    monkeypatch.chdir(root)
    monkeypatch.setenv("CRATER_NAV_ROOT", str(root))
    workspace.cache_clear()
    yield root
    workspace.cache_clear()


def stage_file(run_dir: Path, name: str) -> Path:
    """A committed output of the run by file name (runs/<run>/<stage>/<name>), from the entries."""
    manifest = json.loads((run_dir / "manifest.json").read_text())
    [path] = [run_dir / stage / name for stage, entry in manifest["stages"].items()
              if name in entry["outputs"] or name in entry["visuals"]]
    return path


def chi2_mean_bounds(dof: int) -> tuple[float, float]:
    """Bounds on the mean of chi-square variables with `dof` degrees of freedom in all."""
    return stats.chi2.ppf(ALPHA / 2, dof), stats.chi2.ppf(1 - ALPHA / 2, dof)


def test_every_stage_ran_and_the_run_says_where_it_wrote(run_dir):
    manifest = json.loads((run_dir / "manifest.json").read_text())
    assert set(manifest["stages"]) == {"ingest", "trajectory", "imu", "detect", "estimate",
                                       "navigate", "score"}
    for name, entry in manifest["stages"].items():
        assert (run_dir / name).is_symlink() and entry["stage"] == name
        assert json.loads((run_dir / name / "stage.json").read_text()) == entry
        for output in (*entry["outputs"], *entry["visuals"]):
            assert (run_dir / name / output).is_file(), (name, output)
    config = json.loads((run_dir / "config.json").read_text())
    assert config["run_id"] == "short"
    text = (run_dir.parent.parent / "headline.txt").read_text()
    assert "runs/short" in text and "just view short" in text
    assert "paper RMSE 1800-2400 s" in text and "joint RMSE 1800-2400 s" in text


def test_every_frame_has_an_estimate_in_the_crater_rich_window(run_dir):
    est = pl.read_parquet(stage_file(run_dir, "estimates.parquet"))
    assert est.height == 2 * 121
    assert (est["status"] == "ok").all()
    assert est["n_used"].min() >= 100  # hundreds of craters in view at 70-150 km


def test_errors_are_consistent_with_each_methods_covariance(run_dir):
    """The mean NEES of each method's 6x6 covariance lies in its chi-square bounds."""
    scores = pl.read_parquet(stage_file(run_dir, "scores.parquet"))
    for method in ("paper", "joint"):
        nees = scores.filter(pl.col("method") == method)["nees"].to_numpy()
        lo, hi = chi2_mean_bounds(6 * nees.size)
        assert lo <= nees.sum() <= hi, (method, nees.mean())


def test_joint_errors_reach_the_cramer_rao_bound(run_dir):
    """Normalised by the per-frame CRLB, the joint's squared errors are chi-square with one
    degree of freedom per frame and axis: an efficient estimator, no better, no worse."""
    scores = pl.read_parquet(stage_file(run_dir, "scores.parquet")).filter(
        pl.col("method") == "joint")
    for q in ("x_m", "y_m", "z_m", "phi_deg", "theta_deg", "psi_deg"):
        z2 = (scores[f"err_{q}"].to_numpy() / scores[f"crlb_{q}"].to_numpy()) ** 2
        lo, hi = chi2_mean_bounds(z2.size)
        assert lo <= z2.sum() <= hi, (q, z2.mean())


def test_summary_window_statistics_match_the_scores(run_dir):
    scores = pl.read_parquet(stage_file(run_dir, "scores.parquet"))
    summary = pl.read_parquet(stage_file(run_dir, "summary.parquet"))
    row = summary.filter((pl.col("method") == "paper") & (pl.col("window") == "1800-2400 s")
                         & (pl.col("quantity") == "y_m")).row(0, named=True)
    err = scores.filter((pl.col("method") == "paper") & (pl.col("t_s") < 2400))["err_y_m"]
    err = err.to_numpy()
    assert row["rmse"] == pytest.approx(np.sqrt(np.mean(err**2)), rel=1e-12)
    assert row["share_estimated"] == 1.0 and row["frames"] == 120  # 2400 s is outside [a, b)
    assert set(summary["window"]) == {"0-1500 s", "1500-2850 s", "1800-2400 s", "last 150 s"}


def test_run_database_answers_questions_across_stages(run_dir):
    con = duckdb.connect(str(run_dir / "run.duckdb"), read_only=True)
    try:
        tables = {r[0] for r in con.sql("SHOW TABLES").fetchall()}
        assert {"trajectory", "detections", "frames", "estimates", "scores",
                "summary"} <= tables
        seen = con.execute("SELECT count(*) FROM detections WHERE t_s = 2000").fetchone()[0]
        frames_n = con.execute("SELECT n_visible FROM frames WHERE t_s = 2000").fetchone()[0]
        assert seen == frames_n > 0
        joined = con.execute("""SELECT count(*) FROM estimates e JOIN trajectory t USING (frame)
                                WHERE e.status = 'ok'""").fetchone()[0]
        assert joined == 2 * 121
    finally:
        con.close()


def test_report_has_the_papers_figures_and_tables(run_dir):
    text = stage_file(run_dir, "report.md").read_text()
    for fig in ("fig4_craters.png", "fig5_position_errors.png", "fig6_attitude_errors.png"):
        assert f"({fig})" in text
        # beside report.md, so that its relative links resolve
        assert stage_file(run_dir, fig).parent == stage_file(run_dir, "report.md").parent
        assert stage_file(run_dir, fig).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert "RMSE / sqrt(CRLB)" in text and "| joint | 1800-2400 s |" in text


ENTITIES = {
    # the catalogue's recording, beside its database (catalogue/craters.rrd)
    "catalogue": ["/world/moon/surface", "/world/moon/craters"],
    "trajectory.rrd": ["/world/moon", "/world/path", "/world/spacecraft",
                       "/world/spacecraft/axes", "/trajectory/altitude_km"],
    "detection.rrd": ["/world/frustum", "/world/footprint", "/world/moon/unused",
                      "/world/moon/used", "/world/spacecraft/camera",
                      "/world/spacecraft/camera/used", "/counts/visible"],
    "estimation.rrd": ["/world/estimate/paper", "/world/estimate/joint",
                       "/world/estimate_path/joint", "/world/estimate_cov/joint",
                       "/estimation/paper/status", "/estimation/joint/iterations"],
    "scoring.rrd": ["/errors/position/x/paper", "/errors/position/x/crlb_3sigma_upper",
                    "/errors/attitude/psi/joint", "/consistency/joint/nees"],
}


@pytest.mark.parametrize("name", sorted(ENTITIES))
def test_recordings_are_complete_and_share_the_runs_recording(run_dir, name):
    if name == "catalogue":
        facts = json.loads(stage_file(run_dir, "catalogue.json").read_text())
        path = Path(facts["recording"])
        assert path == Path(facts["db_path"]).with_suffix(".rrd")
        assert path.parent == run_dir.parent.parent / "catalogue"
    else:
        path = stage_file(run_dir, name)
    reader = rr.chunk.RrdReader(path)
    (entry,) = [r for r in reader.recordings() if r.kind == "recording"]
    # the catalogue's recording is shared by every run of it (attached as an asset)
    expected = catalogue_recording_id("craters") if name == "catalogue" else recording_id("short")
    assert (entry.application_id, entry.recording_id) == (APP_ID, expected)
    store = reader.stream().collect()
    columns = set()
    for index in (None, "frame") if name != "catalogue" else (None,):  # the catalogue: static
        columns |= set(store.reader(index=index, contents="/**").to_polars().columns)
    entities = {c.split(":")[0] for c in columns if ":" in c}
    missing = [e for e in ENTITIES[name] if e not in entities]
    assert not missing, (name, missing)


def test_scores_recording_matches_the_table(run_dir):
    store = rr.chunk.RrdReader(stage_file(run_dir, "scoring.rrd")).stream().collect()
    df = store.reader(index="frame", contents="/errors/position/y/joint").to_polars()
    scores = pl.read_parquet(stage_file(run_dir, "scores.parquet")).filter(
        pl.col("method") == "joint")
    logged = np.array([v[0] for v in df["/errors/position/y/joint:Scalars:scalars"].to_list()])
    np.testing.assert_array_equal(df["frame"].to_numpy(), scores["frame"].to_numpy())
    np.testing.assert_allclose(logged, scores["err_y_m"].to_numpy(), rtol=0, atol=0)


def test_a_second_run_skips_every_stage(run_dir, in_project):
    def stamps() -> dict[str, str]:
        manifest = json.loads((run_dir / "manifest.json").read_text())
        return {k: v["finished_at"] for k, v in manifest["stages"].items()}

    before = stamps()
    result = CliRunner().invoke(app, ["run", "short"], catch_exceptions=False)
    assert result.exit_code == 0
    assert "just view short" in result.output
    assert stamps() == before
