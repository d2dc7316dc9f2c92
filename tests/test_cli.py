"""Command line: every command is listed; a small run prints where it wrote, its headline numbers
and how to look; `sql` and `view` on that run; and bad input gives one clear `error: ...` line,
exit code 1 and no traceback (the console entry point `pipeline.cli.main`, in process and as
`python -m pipeline`), before anything is computed or written.
"""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import polars as pl
import pytest
import typer
from conftest import REPO
from typer.testing import CliRunner

from pipeline import bench, cli
from pipeline.cli import app
from pipeline.errors import PipelineError
from pipeline.io.store import RunStore
from pipeline.workspace import workspace

COMMANDS = {"run", "ingest", "trajectory", "imu", "render", "detect", "estimate", "fly",
            "navigate", "score", "sweep", "campaign", "compare", "sql", "view", "stages", "bench",
            "detect-image"}
RECORDINGS = ["detect/detection.rrd", "estimate/estimation.rrd", "imu/imu.rrd",
              "navigate/navigation.rrd", "score/scoring.rrd", "trajectory/trajectory.rrd"]
# Six frames (1,900-1,950 s) over a 10 km synthetic catalogue: ~20 craters used per frame.
TINY = """extends = "default"

[catalogue]
synthetic_min_diam_km = 10.0
db_path = "catalogue/tiny.duckdb"

[trajectory]
start_s = 1900.0
end_s = 1950.0
frame_rate_hz = 0.1
"""


def main(monkeypatch, capsys, *args: str) -> tuple[int, str, str]:
    """`crater-nav ARGS` through the console entry point: (exit code, stdout, stderr)."""
    monkeypatch.setattr(sys, "argv", ["crater-nav", *args])
    with pytest.raises(SystemExit) as exit_:
        cli.main()
    out = capsys.readouterr()
    return exit_.value.code, out.out, out.err


def assert_clear_error(code: int, err: str, *fragments: str) -> str:
    """Exit code 1 and one `error: ...` message (no traceback) holding every fragment."""
    assert code == 1
    assert "Traceback" not in err
    message = " ".join(err.split())  # rich and typer may wrap long lines
    assert message.startswith("error: ") and message.count("error: ") == 1, err
    for fragment in fragments:
        assert fragment in message, (fragment, message)
    return message


@pytest.fixture(scope="module")
def tiny(tmp_path_factory) -> Path:
    """A project folder with the scenarios and `tiny`, run once through `run tiny` (CliRunner);
    the output is kept in headline.txt."""
    root = tmp_path_factory.mktemp("cli")
    shutil.copytree(REPO / "runs" / "scenarios", root / "runs" / "scenarios")
    (root / "runs" / "scenarios" / "tiny.toml").write_text(TINY)
    (root / "catalogue").mkdir()
    mp = pytest.MonkeyPatch()
    mp.chdir(root)
    mp.setenv("CRATER_NAV_ROOT", str(root))
    workspace.cache_clear()
    try:
        result = CliRunner().invoke(app, ["run", "tiny"], catch_exceptions=False)
    finally:
        mp.undo()
        workspace.cache_clear()
    assert result.exit_code == 0, result.output
    (root / "headline.txt").write_text(result.output)
    return root


# --- commands that work ---------------------------------------------------------------------------


def test_help_lists_every_command():
    result = CliRunner().invoke(app, ["--help"], terminal_width=120)
    assert result.exit_code == 0
    assert set(typer.main.get_command(app).commands) == COMMANDS
    listed = {line.split()[1] for line in result.output.splitlines()
              if line.startswith("│ ") and len(line.split()) > 2}
    assert COMMANDS <= listed, listed


def test_stages_lists_each_declaration_in_order():
    from pipeline.stages import DAG

    result = CliRunner().invoke(app, ["stages"])
    assert result.exit_code == 0, result.output
    heads = [line.split(":")[0] for line in result.output.splitlines()
             if line and not line.startswith(" ")]
    assert heads == list(DAG.order)
    block = result.output.split("detect: ")[1].split("\nestimate: ")[0]
    # trajectory.parquet has two producers: the open loop's trajectory, the closed loop's fly
    assert "inputs:  catalogue.json, trajectory.parquet (from ingest, trajectory, fly)" in block
    assert "outputs: detections.parquet, frames.parquet\n" in block
    assert "visuals: detection.rrd (drawn by pipeline.viz.draw.detect)" in block
    code = block.split("code:")[1]
    assert "pipeline.ops.detect" in code and "pipeline.io.store" not in code
    assert "pipeline.viz" not in code  # the computation is keyed without the visual layer


def test_run_prints_the_folder_the_headline_and_how_to_look(tiny):
    text = (tiny / "headline.txt").read_text()
    run_dir = tiny.resolve() / "runs" / "tiny"
    summary = pl.read_parquet(run_dir / "score" / "summary.parquet")
    assert f"run tiny: {run_dir}/ (report: {run_dir / 'score' / 'report.md'}; " in text
    for method in ("paper", "joint"):
        x = summary.filter(pl.col("method") == method, pl.col("window") == "1800-2400 s",
                           pl.col("quantity") == "x_m")["rmse"][0]
        assert f"{method} RMSE 1800-2400 s: X {x:.3f} Y" in text
    assert text.rstrip().splitlines()[-1].startswith("look at it: just view tiny")


def test_sql_prints_a_table_of_a_runs_scores(tiny, monkeypatch):
    monkeypatch.chdir(tiny)
    monkeypatch.setenv("CRATER_NAV_ROOT", str(tiny))
    workspace.cache_clear()
    result = CliRunner().invoke(app, [
        "sql", "--run", "tiny", "--format", "csv",
        "SELECT method, count(*) AS n_frames FROM scores GROUP BY method ORDER BY method"])
    workspace.cache_clear()
    assert result.exit_code == 0, result.output
    assert result.output.splitlines() == ["method,n_frames", "joint,6", "paper,6"]


@pytest.mark.parametrize("display", [None, ":0"])
def test_view_opens_every_recording_of_the_run_with_the_catalogue(tiny, monkeypatch, display):
    """With a display: the viewer opens the run's committed recordings with the catalogue's
    recording attached as an asset. Without one: one line saying to use --screenshot."""
    calls = []
    monkeypatch.setattr(cli.os, "execv", lambda exe, args: calls.append((exe, args)))
    monkeypatch.setenv("CRATER_NAV_ROOT", str(tiny))
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    if display is None:
        monkeypatch.delenv("DISPLAY", raising=False)
    else:
        monkeypatch.setenv("DISPLAY", display)
    workspace.cache_clear()
    result = CliRunner().invoke(app, ["view", "tiny"])
    workspace.cache_clear()
    if display is None:
        assert isinstance(result.exception, PipelineError) and not calls
        assert "--screenshot out.png" in str(result.exception)
        return
    assert result.exit_code == 0, result.output
    [(exe, args)] = calls
    assert Path(exe).name == "rerun" and args[0] == exe
    files = [str(tiny / "runs" / "tiny" / name) for name in RECORDINGS]
    assert sorted(args[-len(files):]) == sorted(files)
    assert args[1:-len(files)] == ["--asset", str(tiny / "catalogue" / "tiny.rrd")]
    assert result.output.strip() == " ".join(args)


# --- clear errors ---------------------------------------------------------------------------------


@pytest.mark.parametrize(("stage", "missing"), [("detect", "ingest"), ("estimate", "detect"),
                                                ("score", "trajectory")])
def test_a_stage_without_its_upstream_names_it_and_the_just_command(workdir, monkeypatch, capsys,
                                                                    stage, missing):
    code, _, err = main(monkeypatch, capsys, stage, "short")
    assert_clear_error(code, err, f"stage '{stage}' of run 'short' needs stage '{missing}'",
                       f"`just {missing} short`", "`just run short`")
    assert not (workdir / "runs" / "short" / "manifest.json").exists()
    store = RunStore("short")
    assert store.committed_stages() == []  # nothing committed, no stage folder left behind
    assert not store.stages_dir.exists() or not list(store.stages_dir.iterdir())


def test_python_m_pipeline_prints_one_error_line_and_exits_1(workdir):
    result = subprocess.run([sys.executable, "-m", "pipeline", "detect", "short"],
                            capture_output=True, text=True, cwd=workdir)
    assert_clear_error(result.returncode, result.stderr, "needs stage 'ingest'",
                       "`just ingest short`")


@pytest.mark.parametrize("command", ["run", "trajectory", "sweep"])
def test_unknown_scenario_lists_the_known_ones(workdir, monkeypatch, capsys, command):
    code, _, err = main(monkeypatch, capsys, command, "nosuch")
    known = sorted(p.stem for p in (REPO / "runs" / "scenarios").glob("*.toml"))
    assert_clear_error(code, err, "runs/scenarios/nosuch.toml: scenario not found",
                       f"known scenarios: {known}")
    assert not [p for p in (workdir / "runs").iterdir() if p.name != "scenarios"]


def test_unknown_config_key_names_the_file_and_the_key(workdir, monkeypatch, capsys):
    path = workdir / "runs" / "scenarios" / "typo.toml"
    path.write_text('extends = "default"\n\n[detection]\nfov_degrees = 40.0\n')
    code, _, err = main(monkeypatch, capsys, "detect", "typo")
    assert_clear_error(code, err, "runs/scenarios/typo.toml",
                       "detection: unknown key(s) ['fov_degrees']")


def test_run_force_of_an_unknown_stage_lists_the_stages(workdir, monkeypatch, capsys):
    code, _, err = main(monkeypatch, capsys, "run", "short", "--force", "bogus")
    assert_clear_error(code, err, "--force 'bogus': not a stage",
                       "['ingest', 'trajectory', 'imu', 'detect', 'estimate', 'navigate', "
                       "'score']")
    assert not (workdir / "runs" / "short").exists()  # checked before anything ran


@pytest.mark.parametrize("run_dir", ["never-ran", "empty"])
def test_view_without_recordings_is_a_clear_error(workdir, monkeypatch, capsys, run_dir):
    (workdir / "runs" / "empty").mkdir()
    (workdir / "runs" / "empty" / "config.json").write_text("{}")
    monkeypatch.setattr(cli.os, "execv", lambda *a: pytest.fail("the viewer was started"))
    code, _, err = main(monkeypatch, capsys, "view", run_dir)
    assert_clear_error(code, err, f"runs/{run_dir}: no .rrd recordings", "`just run`")


@pytest.mark.parametrize("only", [["bogus"], ["ingest", "bogus", "nope"]])
def test_bench_with_an_unknown_group_runs_nothing(workdir, monkeypatch, capsys, only):
    def must_not_run(*_args):
        pytest.fail("a benchmark ran")

    for name in bench.GROUPS:
        monkeypatch.setitem(bench.GROUPS, name, must_not_run)
    monkeypatch.setattr(bench, "Scratch", must_not_run)
    args = [a for name in only for a in ("--only", name)]
    code, _, err = main(monkeypatch, capsys, "bench", *args)
    unknown = sorted(set(only) - set(bench.GROUPS))
    assert_clear_error(code, err, f"unknown benchmark group(s) {unknown}",
                       f"groups: {list(bench.GROUPS)}")
    assert not (workdir / "runs" / "bench").exists()


@pytest.mark.parametrize("key", ["sigma_bearing", "sigma_range_m"])
def test_zero_measurement_noise_is_refused_clearly(workdir, monkeypatch, capsys, key):
    """Zero measurement noise is refused by the config with one error line naming the key,
    before anything is computed or written."""
    (workdir / "runs" / "scenarios" / "tiny.toml").write_text(TINY)
    (workdir / "runs" / "scenarios" / "noiseless.toml").write_text(
        f'extends = "tiny"\n\n[detection]\n{key} = 0.0\n')
    code, out, err = main(monkeypatch, capsys, "run", "noiseless")
    assert_clear_error(code, err, f"detection.{key}")
    assert out == ""
    assert not (workdir / "runs" / "noiseless").exists()
    assert list((workdir / "catalogue").iterdir()) == []


def test_ingest_of_a_missing_file_names_it(workdir, monkeypatch, capsys):
    code, _, err = main(monkeypatch, capsys, "ingest", "--source", "no/such/craters.csv")
    assert_clear_error(code, err, "no/such/craters.csv: catalogue file not found")
    assert list((workdir / "catalogue").iterdir()) == []


def test_sql_reads_a_query_from_standard_input(tiny, monkeypatch):
    """`just sql -` takes the query from standard input: a query file may start with a -- comment,
    which the command line would take for an option."""
    monkeypatch.setenv("CRATER_NAV_ROOT", str(tiny))
    workspace.cache_clear()
    result = CliRunner().invoke(app, ["sql", "--run", "tiny", "--format", "csv", "-"],
                                input="-- frames per method\nSELECT method, count(*) AS n "
                                      "FROM scores GROUP BY method ORDER BY method\n")
    workspace.cache_clear()
    assert result.exit_code == 0, result.output
    assert result.output.splitlines() == ["method,n", "joint,6", "paper,6"]


def test_a_screenshot_that_is_not_a_png_is_refused(tiny, monkeypatch, capsys):
    monkeypatch.setenv("CRATER_NAV_ROOT", str(tiny))
    workspace.cache_clear()
    code, _, err = main(monkeypatch, capsys, "view", "tiny", "--screenshot", "shot.jpg")
    workspace.cache_clear()
    assert_clear_error(code, err, "shot.jpg", "PNG")
