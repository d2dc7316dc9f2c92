"""A campaign's outputs never depend on one run being valid; a dispersion that changes nothing is
refused at load naming it; the runs' results carry their digest (resume reruns a damaged or
deleted one, saying so); a Ray address that does not answer is one line within seconds; the
workers are clamped to the cores; the preparation of many runs shows its progress."""

from __future__ import annotations

import json
import socket
import time
from pathlib import Path

import polars as pl
import pytest
from test_campaign import write_spec
from test_cli import assert_clear_error, main

from pipeline.campaign import execute
from pipeline.campaign.execute import clamp_workers, prepare, run_campaign
from pipeline.campaign.paths import campaign_paths
from pipeline.campaign.spec import load_spec
from pipeline.errors import ConfigError, PipelineError

PHYSICAL = ', epoch_utc = "2026-01-30T08:40:00Z"'


@pytest.mark.slow
def test_an_invalid_first_run_is_a_status_and_the_outputs_are_written(workdir: Path,
                                                                      catalogue_db: Path,
                                                                      capsys):
    """Run 0 draws p_identify = 1.5 (outside [0, 1]), run 1 a valid 0.9: campaign.parquet, the
    database and the report are written (the report read the first run's config and failed,
    on every rerun). Then a deleted part and an altered one: resume says so and reruns the run."""
    spec = load_spec(write_spec(workdir, catalogue_db, "first", runs=2, body=(
        '[dispersions]\n"detection.p_identify" = { values = [1.5, 0.9] }\n')))
    facts = run_campaign(spec, local=True)
    assert (facts["invalid"], facts["ran"], facts["ok"]) == (1, 1, 1)
    paths = campaign_paths(spec)
    for name in ("campaign.parquet", "campaign.duckdb", "report.md", "campaign.json"):
        assert (paths.root / name).is_file(), name
    per_run = pl.read_parquet(paths.root / "campaign.parquet").unique("run", maintain_order=True)
    assert per_run["status"].to_list() == ["invalid_config", "ok"]
    assert "detection.p_identify" in per_run["error"][0]
    report = (paths.root / "report.md").read_text()
    assert "Success rate: 1/2" in report and "invalid_config" in report
    assert run_campaign(spec, local=True)["ran"] == 0  # resume: nothing missing
    capsys.readouterr()
    rid = spec.run_id(1)
    paths.part(rid, "windows").unlink()
    assert run_campaign(spec, local=True)["ran"] == 1
    err = " ".join(capsys.readouterr().err.split())
    assert f"{paths.part(rid, 'windows')}: missing; rerunning run {rid}" in err
    scores = paths.part(rid, "scores")
    data = bytearray(scores.read_bytes())
    data[len(data) // 2] ^= 0x01
    scores.write_bytes(bytes(data))
    assert run_campaign(spec, local=True)["ran"] == 1
    assert "not the file saved with the run" in " ".join(capsys.readouterr().err.split())
    # an edited record (a draw off the spec's grid) is no record: the run reruns
    record = json.loads(paths.done(rid).read_text())
    record["draws"]["detection.p_identify"] = 0.123
    paths.done(rid).write_text(json.dumps(record))
    assert run_campaign(spec, local=True)["ran"] == 1
    assert "not the record saved with the run (edited)" in " ".join(
        capsys.readouterr().err.split())
    assert pl.read_parquet(paths.root / "campaign.parquet")["status"].unique().sort() \
        .to_list() == ["invalid_config", "ok"]
    assert 0.123 not in pl.read_parquet(paths.root / "campaign.parquet")[
        "detection.p_identify"].to_list()
    # the readers of the campaign's own outputs check them against campaign.json
    from pipeline.io.sqlshell import SqlSessionError, open_session
    from pipeline.viz.viewer import run_recordings

    _, shown, _ = run_recordings("first")
    (paths.root / "evil.rrd").symlink_to(paths.root / "campaign.parquet")
    assert run_recordings("first")[1] == shown  # a stray recording is not opened
    db = paths.root / "campaign.duckdb"
    data = bytearray(db.read_bytes())
    data[-100] ^= 0x01
    db.write_bytes(bytes(data))
    with pytest.raises(SqlSessionError, match=r"campaign.duckdb: not the file .*campaign.json"):
        open_session(campaign="first")
    if shown:  # a damaged recording is refused, not opened
        shown[0].write_bytes(shown[0].read_bytes()[:-10])
        with pytest.raises(PipelineError, match=r"not the file .*campaign.json records"):
            run_recordings("first")


def test_a_damaged_part_is_left_out_of_the_outputs_not_read(workdir: Path, catalogue_db: Path,
                                                            capsys):
    """The outputs written from the results as they are (the report command's way): a run whose
    part was altered is left out, in one line, rather than read."""
    from pipeline.campaign.results import write_outputs

    spec = load_spec(write_spec(workdir, catalogue_db, "left", runs=1, body=(
        '[dispersions]\n"detection.p_identify" = { kind = "uniform", low = 1.5, high = 1.6 }\n')))
    run_campaign(spec, local=True)
    paths = campaign_paths(spec)
    part = paths.part(spec.run_id(0), "windows")
    part.write_bytes(part.read_bytes() + b"x")
    facts = write_outputs(spec, paths)
    assert facts["done"] == 0
    assert f"{part}: not the file saved with the run" in " ".join(capsys.readouterr().err.split())


def test_a_campaign_with_no_valid_run_writes_its_outputs_and_fails(workdir: Path,
                                                                  catalogue_db: Path,
                                                                  monkeypatch, capsys):
    """Every run draws an invalid config: the tables and the report say so, the command exits
    non-zero in one line, and SQL reads the campaign's database (no run built a catalogue)."""
    write_spec(workdir, catalogue_db, "none-valid", runs=2, body=(
        '[dispersions]\n"detection.p_identify" = { values = [1.5, 1.6] }\n'))
    code, out, err = main(monkeypatch, capsys, "campaign", "none-valid", "--local")
    assert_clear_error(code, err[err.index("error: "):], "none-valid", "none of its 2 runs",
                       "2 invalid configs")
    root = workdir / "runs" / "none-valid"
    for name in ("campaign.parquet", "campaign.duckdb", "report.md"):
        assert (root / name).is_file(), name
    assert "invalid_config" in (root / "report.md").read_text()
    code, out, err = main(monkeypatch, capsys, "sql", "--campaign", "none-valid", "--format",
                          "csv", "SELECT count(DISTINCT run) AS n FROM campaign.campaign")
    assert code == 0, err
    assert out.split() == ["n", "2"]


@pytest.mark.parametrize(("body", "head", "trajectory", "named", "why"), [
    ('"detection.pixel_sigma_px" = { kind = "uniform", low = 0.1, high = 1.0 }', "", "",
     "detection.pixel_sigma_px", "paper's sensor"),
    ('"detection.world_seed" = { values = [1, 2] }', "", "", "detection.world_seed",
     "paper's sensor"),
    ('"detection.world_seed" = { values = [1, 2] }\n[overrides.detection]\nsensor = "physical"',
     "", PHYSICAL, "detection.world_seed", "no errors to draw"),
    ('"trajectory.jitter_seed" = { values = [1, 2] }', "", "", "trajectory.jitter_seed",
     "jitter_rate_sigma_rad_s = 0"),
    ('seed = { values = [5, 5] }', "", "", "values[1]", "repeats"),
    ('"detection.p_identify" = { values = [0.5, 0.5] }', "", "", "values[1]", "repeats"),
    ('"detection.sigma_range_m" = { kind = "normal", mean = 10.0, sigma = 2.0 }',
     'target = "trajectory"\n', "", "detection.sigma_range_m", "no stage up to target"),
    ('"detection.p_identify" = { kind = "normal", mean = 0.9, sigma = 0.0 }', "", "",
     "detection.p_identify", "sigma = 0"),
    ('"detection.p_identify" = { kind = "uniform", low = 0.9, high = 0.9 }', "", "",
     "detection.p_identify", "must be > low"),
    ('"render.albedo" = { kind = "uniform", low = 0.1, high = 0.2 }', "", "", "render.albedo",
     "no frame is rendered"),
    ('"identification.star_tracker_sigma_arcsec" = { kind = "uniform", low = 1.0, high = 9.0 }',
     "", "", "identification.star_tracker_sigma_arcsec", "identification is simulated"),
    ('"detection.selection" = { values = ["random", "largest"] }', "", "",
     "detection.selection", "with no cap"),
    ('"estimation.gate_probability" = { kind = "uniform", low = 0.9, high = 0.99 }', "", "",
     "estimation.gate_probability", "robust = false"),
    ('"navigation.loose_method" = { values = ["paper", "joint"] }', "", "",
     "navigation.loose_method", "no fix is taken"),
    ('"trajectory.jitter_knot_s" = { kind = "uniform", low = 0.5, high = 2.0 }', "", "",
     "trajectory.jitter_knot_s", "jitter's seed and knots change nothing"),
    ('"detection.p_identify" = { values = [0.5] }', "", "", "detection.p_identify",
     "one value is an override"),
    ('"detection.sigma_range_m" = { kind = "normal", mean = 10.0, sigma = 1e-300 }', "", "",
     "detection.sigma_range_m", "more than 1e-9 of the mean"),
])
def test_a_dispersion_that_changes_nothing_is_refused_naming_it(workdir: Path, catalogue_db: Path,
                                                                body, head, trajectory, named,
                                                                why):
    path = write_spec(workdir, catalogue_db, "nothing", runs=2, head=head, trajectory=trajectory,
                      body=f"[dispersions]\n{body}\n")
    with pytest.raises(ConfigError) as err:
        load_spec(path)
    msg = str(err.value)
    assert "\n" not in msg and path in msg and named in msg and why in msg, msg


@pytest.mark.parametrize("body", [
    # the physical sensor reads its pixel noise; a dispersed sensor makes its fields count
    '"detection.pixel_sigma_px" = { kind = "uniform", low = 0.1, high = 1.0 }\n'
    '[overrides.detection]\nsensor = "physical"',
    '"detection.pixel_sigma_px" = { kind = "uniform", low = 0.1, high = 1.0 }\n'
    '"detection.sensor" = { values = ["paper", "physical"] }',
    '"detection.world_seed" = { values = [1, 2] }\n[overrides.detection]\nsensor = "physical"\n'
    'catalogue_sigma_height_m = 20.0',
    'seed = { values = [5, 6] }',
    # a window makes the renderer's options count, an algorithm identification's
    '"render.albedo" = { kind = "uniform", low = 0.1, high = 0.2 }\n'
    '[overrides.render]\nstart_s = 1900.0\nend_s = 1910.0\n'
    '[overrides.detection]\nsensor = "physical"',
    '"identification.star_tracker_sigma_arcsec" = { kind = "uniform", low = 1.0, high = 9.0 }\n'
    '"identification.mode" = { values = ["simulated", "lost_in_space"] }\n'
    '[overrides.detection]\nsensor = "physical"',
    # a cap, or a dispersed cap, makes the selection count; a dispersed switch its options
    '"detection.selection" = { values = ["random", "largest"] }\n[overrides.detection]\n'
    'max_craters = 10',
    '"detection.selection" = { kind = "choice", values = ["random", "largest"] }\n'
    '"detection.max_craters" = { values = [10, "none"] }',
    '"estimation.gate_probability" = { kind = "uniform", low = 0.9, high = 0.99 }\n'
    '"estimation.robust" = { values = [false, true] }',
])
def test_a_dispersion_that_reaches_its_runs_is_accepted(workdir: Path, catalogue_db: Path, body):
    load_spec(write_spec(workdir, catalogue_db, "reach", runs=2, trajectory=PHYSICAL,
                         body=f"[dispersions]\n{body}\n"))


@pytest.mark.slow
def test_a_ray_address_that_does_not_answer_is_one_line_within_seconds(workdir: Path,
                                                                       catalogue_db: Path,
                                                                       monkeypatch, capsys):
    spec = write_spec(workdir, catalogue_db, "addr", runs=2)
    t0 = time.monotonic()
    with pytest.raises(PipelineError, match=r"nothing answers at 127\.0\.0\.1:9"):
        run_campaign(load_spec(spec), address="127.0.0.1:9")
    assert time.monotonic() - t0 < 10
    code, _, err = main(monkeypatch, capsys, "campaign", spec, "--address", "127.0.0.1:9")
    assert_clear_error(code, err, "--address", "127.0.0.1:9", "nothing answers")
    # a port that answers (here a proxy, or any service) with no Ray cluster behind it
    with socket.create_server(("127.0.0.1", 0)) as server:
        port = server.getsockname()[1]
        monkeypatch.setattr(execute, "RAY_PROBE_TIMEOUT_S", 8.0)
        t0 = time.monotonic()
        with pytest.raises(PipelineError, match=f"--address '127.0.0.1:{port}': .*no Ray"):
            run_campaign(load_spec(spec), address=f"127.0.0.1:{port}")
        assert time.monotonic() - t0 < 12
    monkeypatch.setenv("RAY_ADDRESS", "nohost")
    with pytest.raises(PipelineError, match="RAY_ADDRESS 'nohost': expected host:port"):
        run_campaign(load_spec(spec))


def test_workers_above_the_cores_are_clamped_saying_so(capsys):
    assert clamp_workers(1000, 2) == 2
    assert "--workers 1000: this machine has 2 cores" in " ".join(capsys.readouterr().err.split())
    assert clamp_workers(2, 2) == 2 and clamp_workers(None, 2) is None
    assert capsys.readouterr().err == ""


def test_preparing_many_runs_shows_its_progress(workdir: Path, catalogue_db: Path, monkeypatch,
                                                capsys):
    spec = load_spec(write_spec(workdir, catalogue_db, "many", runs=3))
    monkeypatch.setattr(execute, "PROGRESS_EVERY_S", -1.0)
    tasks, invalid, _ = prepare(spec, campaign_paths(spec))
    assert (len(tasks), len(invalid)) == (3, 0)
    err = " ".join(capsys.readouterr().err.split())
    assert "campaign many: prepared 2 of 3 runs' configs" in err


@pytest.mark.parametrize(("overrides", "key", "why"), [
    ({"hazard": {"enabled": False}}, "hazard.grid_step_m", "hazard.enabled = false"),
    ({"velocimeter": {"enabled": False}}, "velocimeter.sigma_m_s", "velocimeter.enabled = false"),
    ({"map": {"kind": "sphere"}}, "map.resolution_m", "map.kind = 'sphere'"),
    ({"terrain": {"kind": "sphere"}, "map": {"kind": "truth"}}, "terrain.seed",
     "terrain.kind = 'sphere'"),
    ({}, "altimeter.fault_bias_m", "altimeter.fault = 'none'"),
    ({"altimeter": {"fault": "dropout"}}, "altimeter.fault_bias_m", "fault = 'dropout'"),
])
def test_an_option_of_what_the_flight_does_not_carry_changes_nothing(overrides, key, why):
    """The fly stage reads the whole section, but an instrument that is off, a map that is no
    terrain, a sphere for a world, or a fault of another kind leave the option unread; with
    it on, the option reaches the runs."""
    from pipeline.campaign.reach import why_ignored
    from pipeline.config import load_config

    cfg = load_config("landing", "reach", overrides)
    assert why in (why_ignored(cfg, key, "fly", set()) or "")
    on = {"hazard": {"enabled": True}, "velocimeter": {"enabled": True},
          "map": {"kind": "terrain"}, "terrain": {"kind": "terrain"},
          "altimeter": {"fault": "bias"}}[key.split(".")[0]]
    assert why_ignored(load_config("landing", "reach", {key.split(".")[0]: on}), key, "fly",
                       set()) is None
