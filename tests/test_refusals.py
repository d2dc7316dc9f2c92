"""Input the machine cannot honour is one line naming the file or key, never a traceback: a disk
full in a stage's write (polars' ComputeError, a write's ENOSPC naming no file), non-UTF-8 bytes
in a query or a spec, `--timeout-s inf`, a NUL byte or a path leaving the project in a path the
pipeline writes (identification.index_dir, catalogue.db_path), a render larger than the machine's
memory, a run's stages into a campaign's or a comparison's folder and a comparison into a
run's."""

from __future__ import annotations

import io
import os
import sys
from pathlib import Path

import pytest
from test_cli import TINY, assert_clear_error, main

from pipeline.config import load_config
from pipeline.errors import ConfigError, PipelineError
from pipeline.io import files

PHYSICAL_RENDER = {"trajectory": {"epoch_utc": "2026-01-30T08:40:00Z", "start_s": 1800.0,
                                  "end_s": 1810.0},
                   "detection": {"sensor": "physical", "range_source": "apparent_size"},
                   "render": {"start_s": 1800.0, "end_s": 1810.0}}


@pytest.fixture
def tiny_scenario(workdir: Path) -> Path:
    (workdir / "runs" / "scenarios" / "tiny.toml").write_text(TINY)
    return workdir


def test_a_full_disk_in_a_stage_table_is_one_line_naming_the_file(tiny_scenario, monkeypatch,
                                                                  capsys):
    import pyarrow.parquet as pq

    real = pq.write_table

    def full(table, where, *args, **kwargs):  # as Arrow raises ENOSPC: no file name
        if Path(where).name == "imu.parquet":
            raise OSError("IOError: No space left on device (os error 28)")
        return real(table, where, *args, **kwargs)

    monkeypatch.setattr(pq, "write_table", full)
    code, _, err = main(monkeypatch, capsys, "run", "tiny")
    assert "Traceback" not in err
    assert_clear_error(code, err[err.index("error: "):], "imu.parquet", "No space left on device")


def test_a_write_that_fails_without_a_file_name_is_named(tmp_path, monkeypatch):
    def full(fd):
        raise OSError(28, "No space left on device")  # as write()/fsync() raise it: no name

    monkeypatch.setattr(os, "fsync", full)
    target = tmp_path / "frames.json"
    with pytest.raises(OSError) as err:
        files.atomic_write_bytes(target, b"{}")
    assert err.value.errno == 28 and err.value.filename == str(target)
    assert not list(tmp_path.iterdir())  # no temporary left
    assert files.write_failure(ValueError("x (os error 28)"), target).errno == 28


def test_non_utf8_queries_and_an_infinite_timeout_are_one_line(workdir, monkeypatch, capsys):
    code, _, err = main(monkeypatch, capsys, "sql", "SELECT 'a\udcff'")
    assert_clear_error(code, err, "not UTF-8")
    monkeypatch.setattr(sys, "stdin", io.TextIOWrapper(io.BytesIO(b"SELECT '\xff'")))
    code, _, err = main(monkeypatch, capsys, "sql", "-")
    assert_clear_error(code, err, "standard input", "0xff")
    code, _, err = main(monkeypatch, capsys, "sql", "--timeout-s", "inf", "SELECT 1")
    assert_clear_error(code, err, "--timeout-s inf", "finite")


@pytest.mark.parametrize("kind", ["folder", "fifo", "missing"])
def test_a_source_that_is_no_file_says_what_it_is_and_leaves_no_run(workdir, monkeypatch,
                                                                    capsys, kind):
    source = workdir / f"src_{kind}.csv"
    if kind == "folder":
        source.mkdir()
    elif kind == "fifo":
        os.mkfifo(source)
    code, _, err = main(monkeypatch, capsys, "ingest", "--source", str(source))
    said = {"folder": "a folder, not a catalogue file", "fifo": "not a regular file",
            "missing": "catalogue file not found"}[kind]
    assert_clear_error(code, err, str(source), said)
    assert not (workdir / "runs" / source.stem).exists()  # no empty run folder left


@pytest.mark.parametrize(("args", "said"), [
    (["--db", "../elsewhere.duckdb"], "--db '../elsewhere.duckdb': a relative path"),
    (["--max-reject-share", "2"], "--max-reject-share 2: must be a finite number in [0, 1]")])
def test_an_ingest_flag_out_of_range_is_named_as_the_flag(workdir, monkeypatch, capsys, args,
                                                          said):
    code, _, err = main(monkeypatch, capsys, "ingest", *args)
    message = assert_clear_error(code, err, said)
    assert "default.toml" not in message  # the value came from the command line, not the file


def test_a_file_name_that_is_not_utf8_is_one_line(workdir, monkeypatch, capsys):
    name = os.fsdecode(b"g\xffx.csv")  # a surrogate: the bytes of a Latin-1 file name
    source = workdir / name
    source.write_text("lat,lon,diam\n1.0,2.0,3.0\n")
    code, _, err = main(monkeypatch, capsys, "ingest", "--source", str(source))
    err = err.split("ingest: running (run g_x)\n")[-1]  # the stage's start, then the one line
    assert_clear_error(code, err, "g\\udcffx.csv", "not UTF-8")


def test_a_non_utf8_spec_is_one_line_naming_it(workdir, monkeypatch, capsys):
    path = workdir / "runs" / "campaigns" / "bytes.toml"
    path.parent.mkdir(parents=True)
    path.write_bytes(b'base = "default"\nruns = 2\n# \xff\xfe\n')
    code, _, err = main(monkeypatch, capsys, "campaign", str(path), "--local")
    assert_clear_error(code, err, str(path), "not UTF-8", "0xff")


def test_a_non_utf8_scenario_is_one_line_naming_it(workdir, monkeypatch, capsys):
    path = workdir / "runs" / "scenarios" / "bytes.toml"
    path.write_bytes(b'extends = "default"\n# caf\xe9\n')
    code, _, err = main(monkeypatch, capsys, "run", "bytes")
    assert_clear_error(code, err, str(path), "not UTF-8", "0xe9", "offset 25")


@pytest.mark.parametrize("section", ["identification.index_dir", "catalogue.db_path"])
@pytest.mark.parametrize(("path", "why"), [
    ("catalogue/ix\0", "NUL"), ("../../elsewhere", "leaves it"), ("a/../../b", "leaves it"),
    ("", "empty")])
def test_a_written_path_the_project_cannot_hold_is_refused(workdir, section, path, why):
    table, key = section.split(".")
    with pytest.raises(ConfigError) as err:
        load_config("default", "x", {table: {key: path}})
    assert section in str(err.value) and why in str(err.value)


@pytest.mark.parametrize("path", ["..name/ix", "catalogue/./ix", "/abs/elsewhere", "~/ix"])
def test_written_paths_inside_the_project_or_absolute_are_taken(workdir, path):
    cfg = load_config("default", "x", {"identification": {"index_dir": path},
                                       "catalogue": {"db_path": path + ".duckdb"}})
    assert cfg.identification.index_dir == path and cfg.catalogue.db_path == path + ".duckdb"


def test_a_render_the_memory_cannot_hold_is_refused_at_load(workdir):
    load_config("default", "x", PHYSICAL_RENDER)  # the default size renders
    big = {**PHYSICAL_RENDER, "detection": {**PHYSICAL_RENDER["detection"],
                                            "image_size_px": 100_000}}
    with pytest.raises(ConfigError) as err:
        load_config("default", "x", big)
    msg = str(err.value)
    assert "detection.image_size_px = 100,000" in msg and "GiB of memory" in msg, msg


def test_a_run_into_a_campaigns_folder_is_refused(tiny_scenario, monkeypatch, capsys):
    folder = tiny_scenario / "runs" / "mc"
    folder.mkdir()
    (folder / "spec.toml").write_text('base = "default"\nruns = 2\n')
    code, _, err = main(monkeypatch, capsys, "run", "tiny", "--run-id", "mc")
    assert "Traceback" not in err
    assert_clear_error(code, err[err.index("error: "):], str(folder), "campaign", "--run-id")
    assert sorted(p.name for p in folder.iterdir()) == ["spec.toml"]


def test_runs_and_comparisons_keep_out_of_each_others_folders(tiny_scenario, monkeypatch,
                                                             capsys):
    code, _, err = main(monkeypatch, capsys, "run", "tiny", "--run-id", "compare-x")
    assert code == 0, err  # a run may be named so while no comparison holds the folder...
    code, _, err = main(monkeypatch, capsys, "compare", "compare-x", "--name", "x")
    assert "Traceback" not in err  # ...and then no comparison is written into it
    assert_clear_error(code, err[err.index("error: "):], "compare-x", "a run",
                       "not a comparison's")
    code, _, err = main(monkeypatch, capsys, "compare", "compare-x", "--name", "y")
    assert code == 0, err
    folder = tiny_scenario / "runs" / "compare-y"
    assert (folder / "compare.json").is_file() and (folder / "report.md").is_file()
    code, _, err = main(monkeypatch, capsys, "run", "tiny", "--run-id", "compare-y")
    assert_clear_error(code, err[err.index("error: "):], str(folder), "comparison", "--run-id")
    assert not (folder / "manifest.json").exists()


@pytest.mark.parametrize(("overrides", "key", "words"), [
    ({"trajectory": {"start_s": 300.0}}, "trajectory.start_s", "reads no frame window"),
    ({"trajectory": {"end_s": 340.0}}, "trajectory.end_s", "reads no frame window"),
    ({"flight": {"coast_s": 800.0, "max_duration_s": 500.0}}, "flight.coast_s",
     "before powered descent"),
    ({"hazard": {"grid_step_m": 0.05}, "flight": {"slope_baseline_m": 100.0}},
     "hazard.grid_step_m", "slope map"),
    ({"hazard": {"grid_step_m": 0.05, "divert_m": 200.0}}, "hazard.grid_step_m", "slope map"),
])
def test_what_the_closed_loop_cannot_honour_is_refused_at_load(overrides, key, words):
    """A frame window the closed loop does not read, a coast past the flight's end, a hazard
    map beyond the machine (a MemoryError an hour into the flight): one line at load."""
    with pytest.raises(ConfigError) as err:
        load_config("landing", "refusal", overrides)
    msg = str(err.value)
    assert "\n" not in msg and key in msg and words in msg, msg


def test_environment_values_that_mean_nothing_are_one_line(monkeypatch, capsys) -> None:
    """CRATER_NAV_VISUALS neither on nor off, CRATER_NAV_ROOT at no project: one line naming
    the variable (the first was taken as on, the second gave an empty list of scenarios)."""
    from pipeline.io.rrd import visuals_enabled
    from pipeline.workspace import workspace

    monkeypatch.setenv("CRATER_NAV_VISUALS", "maybe")
    with pytest.raises(PipelineError, match=r"CRATER_NAV_VISUALS='maybe' in the environment"):
        visuals_enabled()
    monkeypatch.setenv("CRATER_NAV_VISUALS", "off")
    assert not visuals_enabled()
    monkeypatch.setenv("CRATER_NAV_ROOT", "/nonexistent")
    workspace.cache_clear()
    try:
        with pytest.raises(PipelineError, match=r"CRATER_NAV_ROOT='/nonexistent' in the env"):
            workspace()
    finally:
        workspace.cache_clear()


@pytest.mark.parametrize(("section", "key", "value"), [
    ("catalogue", "db_path", "runs/r1/cat.duckdb"), ("catalogue", "db_path", "pipeline/x.duckdb"),
    ("identification", "index_dir", "runs/r1"), ("identification", "index_dir", "./runs/c/x")])
def test_a_written_path_inside_the_runs_or_the_code_is_refused(section, key, value):
    """The catalogue's database and the indexes wrote into another run's or a campaign's folder,
    or the source tree: one line at load."""
    with pytest.raises(ConfigError) as err:
        load_config("default", "paths", {section: {key: value}})
    msg = str(err.value)
    assert "\n" not in msg and f"{section}.{key}" in msg and "inside the project's" in msg, msg


def test_a_frame_rate_too_low_for_the_window_gives_no_frame_outside_it():
    """1e-300 Hz over 1,900-1,930 s: the frame of slack at the window's edge took a frame at
    t = 0 s, outside the window, and the run went on with it; no frame in the window is
    refused, as at 0.001 Hz."""
    from pipeline.ops.trajectory import simulate

    cfg = load_config("default", "rate", {"trajectory": {"start_s": 1900.0, "end_s": 1930.0,
                                                         "frame_rate_hz": 1e-300}})
    with pytest.raises(ConfigError, match="no frame between start_s"):
        simulate(cfg.trajectory)


def test_a_scenario_saved_with_a_byte_order_mark_loads(tmp_path):
    """Some editors start UTF-8 files with a BOM: it is no content (TOML's parser had said
    `Invalid statement (line 1, col 1)`)."""
    path = tmp_path / "bom.toml"
    path.write_bytes(b"\xef\xbb\xbf" + b'extends = "default"\n[trajectory]\nend_s = 30.0\n')
    assert load_config(str(path), "bom").trajectory.end_s == 30.0
