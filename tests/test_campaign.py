"""Campaigns: the spec and its errors, the draws, that each dispersion reaches its run (its config
and its outputs), failed runs recorded, resume (and a changed spec reruns), the shared catalogue,
the envelopes against an analytic case, the campaign's SQL and recording, and (slow) Ray: the same
table on 1 and 2 workers, a two-node cluster."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import polars as pl
import pytest

from pipeline.campaign import execute, one_run
from pipeline.campaign.execute import run_campaign
from pipeline.campaign.paths import campaign_paths
from pipeline.campaign.results import TIMING_COLUMNS, read_table
from pipeline.campaign.spec import load_spec
from pipeline.core.sensors.imu import GRADES
from pipeline.errors import ConfigError, PipelineError
from pipeline.ops import detection_columns

DISPERSIONS = """
[dispersions]
"detection.sigma_range_m" = { kind = "normal", mean = 10.0, sigma = 2.0 }
"detection.sigma_bearing" = { kind = "uniform", low = 5e-5, high = 2e-4 }
"imu.grade" = { kind = "choice", values = ["tactical", "navigation"] }
"detection.p_identify" = { values = [0.6, 0.95] }
"""


def write_spec(workdir: Path, db: Path, name: str = "t", runs: int = 2, body: str = DISPERSIONS,
               head: str = "", trajectory: str = "") -> str:
    folder = workdir / "runs" / "campaigns"
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / f"{name}.toml"
    path.write_text(f'base = "default"\nruns = {runs}\nseed = 7\n{head}\n[overrides]\n'
                    f'catalogue = {{ synthetic_min_diam_km = 5.0, db_path = "{db}" }}\n'
                    f'trajectory = {{ start_s = 1800.0, end_s = 1808.0{trajectory} }}\n' + body)
    return str(path)


@pytest.fixture
def spec_file(workdir: Path, catalogue_db: Path) -> str:
    return write_spec(workdir, catalogue_db)


@pytest.mark.parametrize(("text", "named"), [
    ("bogus = 1\n", "bogus"),
    ('[dispersions]\n"detection.nope" = { kind = "normal", mean = 1.0, sigma = 1.0 }\n',
     "detection.nope"),
    ('[dispersions]\n"imu.grade" = { kind = "normal", mean = 1.0, sigma = 1.0 }\n', "imu.grade"),
    ('[dispersions]\n"detection.sigma_range_m" = { kind = "beta", a = 1.0 }\n',
     "detection.sigma_range_m"),
    ('[dispersions]\n"detection.sigma_range_m" = { kind = "normal", mean = 1.0 }\n', "sigma"),
    ('[dispersions]\n"catalogue.seed" = { values = [1, 2] }\n', "catalogue.seed"),
    ('[dispersions]\n"detection.max_craters" = { values = [1.5] }\n', "detection.max_craters"),
    ('[overrides]\ndetection = { sigma_rnage_m = 1.0 }\n', "detection.sigma_rnage_m"),
    ("mounting_sigma_deg = 0.1\n", "mounting_sigma_deg"),
    ("catalogue_errors = true\n", "catalogue_errors"),  # the paper's sensor has none
    ("jitter = true\n", "jitter"),  # the default's jitter rate is 0: the seed changes nothing
    ('[dispersions]\nseed = { kind = "uniform", low = 1.0, high = 2.0 }\n', "seed"),
    ('base = "../nowhere.toml"\n', "nowhere.toml"),
    ('[overrides]\nestimation = { methods = ["nope"] }\n', "estimation.methods"),  # at load
    ('[dispersions]\nseed = { values = [1] }\n', "one value is an override"),  # no grid
])
def test_spec_errors_are_one_line_naming_file_and_key(workdir: Path, text: str, named: str):
    path = workdir / "runs" / "campaigns" / "bad.toml"
    path.parent.mkdir(parents=True)
    path.write_text(('' if text.startswith("base") else 'base = "default"\n') + "runs = 2\n"
                    + text)
    with pytest.raises(ConfigError) as err:
        load_spec(str(path))
    msg = str(err.value)
    assert "\n" not in msg and str(path) in msg and named in msg


def test_draws_come_from_the_root_seed_and_the_index_alone(workdir: Path, catalogue_db: Path):
    a = load_spec(write_spec(workdir, catalogue_db, "a", runs=4))
    b = load_spec(write_spec(workdir, catalogue_db, "b", runs=8))
    for i in range(4):
        assert a.draws(i) == b.draws(i)
    assert len({a.draws(i)["seed"] for i in range(4)}) == 4
    assert [a.draws(i)["detection.p_identify"] for i in range(4)] == [0.6, 0.95] * 2
    # adding a dispersion leaves the others' draws as they were
    c = load_spec(write_spec(workdir, catalogue_db, "c", runs=4, body=DISPERSIONS + (
        '"altimeter.sigma_m" = { kind = "uniform", low = 0.5, high = 2.0 }\n')))
    assert all({k: v for k, v in c.draws(i).items() if k != "altimeter.sigma_m"} == a.draws(i)
               for i in range(4))
    assert np.std([c.draws(i)["altimeter.sigma_m"] for i in range(4)]) > 0


def test_camera_mounting_is_drawn_per_run(workdir: Path, catalogue_db: Path):
    spec = load_spec(write_spec(workdir, catalogue_db, "m", runs=3, head=(
        "mounting_sigma_deg = 0.1\n"), body='detection = { sensor = "physical" }\n',
        trajectory=', epoch_utc = "2026-01-30T08:40:00"'))
    angles = np.array([spec.draws(i)["detection.camera_mounting_deg"] for i in range(3)])
    assert angles.shape == (3, 3) and 0 < np.std(angles) < 0.5
    over = spec.overrides_for(1)
    assert over["detection"]["camera_mounting_deg"] == list(angles[1])
    assert over["detection"]["sensor"] == "physical"


@pytest.mark.slow
def test_each_dispersion_reaches_its_run(workdir: Path, catalogue_db: Path):
    spec = load_spec(write_spec(workdir, catalogue_db, "kept", head="keep_runs = true\n"))
    facts = run_campaign(spec, local=True)
    assert facts["ok"] == 2
    paths = campaign_paths(spec)
    table = pl.read_parquet(paths.root / "campaign.parquet")
    for i in range(spec.runs):
        drawn = spec.draws(i)
        rid = spec.run_id(i)
        config = json.loads((paths.runs / rid / "config.json").read_text())
        for key, value in drawn.items():
            got = config
            for part in key.split("."):
                got = got[part]
            assert got == (list(value) if isinstance(value, list) else value), key
        rows = table.filter(pl.col("run") == i)
        assert rows["status"].to_list() == ["ok"] * rows.height
        assert rows["detection.sigma_range_m"][0] == drawn["detection.sigma_range_m"]
        assert rows.filter(pl.col("window") == "1800-2400 s")["filter_rmse_x_m"][0] > 0
        # the run's outputs were made with the drawn truth: the IMU's turn-on biases differ by
        # seed and grade; the recorded config is what reruns the run alone
        nav = pl.read_parquet(paths.runs / rid / "navigate" / "navigation.parquet")
        assert nav.height and np.isfinite(nav["err_pos_x_m"].to_numpy()).any()
        # the measurements carry the drawn noise: range and bearing errors' spread
        det = detection_columns.with_derived(
            pl.read_parquet(paths.runs / rid / "detect" / "detections.parquet"),
            pl.read_parquet(paths.runs / rid / "trajectory" / "trajectory.parquet")).filter(
            pl.col("identified"))
        range_err = (det["rho_meas_m"] - det["rho_true_m"]).to_numpy()
        assert abs(np.std(range_err) / drawn["detection.sigma_range_m"] - 1) < 0.1, rid
        cos = sum(det[f"u_meas_body_{c}"] * det[f"u_true_body_{c}"] for c in "xyz").to_numpy()
        angle = np.arccos(np.clip(cos, -1, 1))  # 2-D error: Rayleigh, RMS sqrt(2) sigma
        assert abs(np.sqrt(np.mean(angle**2) / 2) / drawn["detection.sigma_bearing"] - 1) < 0.1
        # the share of visible craters identified is the drawn p_identify (binomial, n > 1,000)
        visible = pl.read_parquet(paths.runs / rid / "detect" / "detections.parquet")
        share = visible["identified"].mean()
        assert visible.height > 1000 and abs(share - drawn["detection.p_identify"]) < 0.05
        # the IMU's turn-on gyro bias is of the drawn grade's size (the grades differ 300x)
        nav0 = nav.row(0, named=True)
        bias = np.linalg.norm([nav0[f"true_b_gyro_{c}_rad_s"] for c in "xyz"])
        sigma = GRADES[drawn["imu.grade"]].gyro.bias_sigma
        assert 0.02 < bias / sigma < 5, (rid, drawn["imu.grade"], bias / sigma)
        assert (paths.runs / rid / "navigate" / "navigation.rrd").stat().st_size == 0
    b0 = pl.read_parquet(paths.runs / spec.run_id(0) / "navigate" / "navigation.parquet")
    b1 = pl.read_parquet(paths.runs / spec.run_id(1) / "navigate" / "navigation.parquet")
    assert b0["true_b_gyro_x_rad_s"][0] != b1["true_b_gyro_x_rad_s"][0]
    report = (paths.root / "report.md").read_text()
    assert "Success rate: 2/2" in report and f"just run {paths.scenario(spec.run_id(0))}" in \
        report


@pytest.mark.slow
def test_failed_runs_are_recorded_and_a_campaign_resumes(spec_file: str,
                                                         monkeypatch: pytest.MonkeyPatch):
    spec = load_spec(spec_file)
    calls: list[str] = []
    real = one_run.execute_stages

    def flaky(cfg, store, target):
        calls.append(store.run_id)
        if store.run_id.endswith("r0001") and len(calls) < 3:
            raise RuntimeError("boom in the filter")
        real(cfg, store, target)

    monkeypatch.setattr(one_run, "execute_stages", flaky)
    facts = run_campaign(spec, local=True)
    assert (facts["done"], facts["ok"]) == (2, 1)
    table = pl.read_parquet(campaign_paths(spec).root / "campaign.parquet")
    failed = table.filter(pl.col("run") == 1)
    assert failed["status"].to_list() == ["failed"]
    assert failed["error"][0] == "RuntimeError: boom in the filter"
    assert run_campaign(spec, local=True)["ran"] == 0  # resume: nothing missing
    assert calls == [spec.run_id(0), spec.run_id(1)]
    again = run_campaign(spec, local=True, retry_failed=True)
    assert again["ran"] == 1 and again["ok"] == 2
    assert calls[-1] == spec.run_id(1)


def test_a_draw_outside_its_range_is_a_recorded_invalid_run(workdir: Path, catalogue_db: Path):
    spec = load_spec(write_spec(workdir, catalogue_db, "neg", runs=2, body=(
        '[dispersions]\n"detection.sigma_range_m" = { kind = "uniform", low = -2.0, '
        'high = -1.0 }\n')))
    facts = run_campaign(spec, local=True)
    assert facts["ran"] == 0 and facts["ok"] == 0 and facts["invalid"] == 2
    table = pl.read_parquet(campaign_paths(spec).root / "campaign.parquet")
    assert table["status"].to_list() == ["invalid_config"] * 2
    assert "detection.sigma_range_m" in table["error"][0]


def _comparable(path: Path) -> pl.DataFrame:
    return pl.read_parquet(path).drop(*TIMING_COLUMNS)


@pytest.mark.slow
def test_same_table_on_one_and_two_ray_workers(workdir: Path, catalogue_db: Path):
    tables = []
    for workers in (1, 2):
        spec = load_spec(write_spec(workdir, catalogue_db, f"w{workers}", runs=4))
        # the same spec under another name: compare everything but the names
        facts = run_campaign(spec, workers=workers)
        assert facts["ok"] == 4 and facts["workers"] == workers
        t = _comparable(campaign_paths(spec).root / "campaign.parquet")
        tables.append(t.drop("run_id"))
    assert tables[0].equals(tables[1])


@pytest.mark.slow
def test_a_campaign_across_a_two_node_cluster(workdir: Path, catalogue_db: Path):
    import ray
    from ray.cluster_utils import Cluster

    cluster = Cluster(initialize_head=True, head_node_args={"num_cpus": 1})
    try:
        cluster.add_node(num_cpus=1)
        cluster.wait_for_nodes()
        ray.init(address=cluster.address, log_to_driver=False)
        spec = load_spec(write_spec(workdir, catalogue_db, "cluster", runs=4))
        facts = run_campaign(spec, workers=2)
        assert facts["ok"] == 4
        table = pl.read_parquet(campaign_paths(spec).root / "campaign.parquet")
        assert table["node"].n_unique() == 2
    finally:
        ray.shutdown()
        cluster.shutdown()


@pytest.mark.slow
def test_a_seed_grid_and_a_base_given_as_a_path(workdir: Path, catalogue_db: Path):
    """The sweep's way: the seeds as a grid, the base a scenario file beside the spec."""
    (workdir / "runs" / "campaigns").mkdir(parents=True)
    base = workdir / "runs" / "campaigns" / "mybase.toml"
    base.write_text(f'extends = "default"\n[catalogue]\nsynthetic_min_diam_km = 5.0\n'
                    f'db_path = "{catalogue_db}"\n[trajectory]\nstart_s = 1800.0\n'
                    'end_s = 1804.0\n')
    path = workdir / "runs" / "campaigns" / "seeds.toml"
    path.write_text('base = "mybase.toml"\nruns = 4\n[dispersions]\n'
                    'seed = { values = [5, 6] }\n"detection.max_craters" = { values = [10, '
                    '"none"] }\n')
    spec = load_spec(str(path))
    assert spec.base == str(base)
    assert [(spec.draws(i)["detection.max_craters"], spec.draws(i)["seed"])
            for i in range(4)] == [(10, 5), (10, 6), ("none", 5), ("none", 6)]
    facts = run_campaign(spec, local=True)
    assert facts["ok"] == 4
    table = pl.read_parquet(campaign_paths(spec).root / "campaign.parquet")
    assert table.unique("run", maintain_order=True)["seed"].to_list() == [5, 6, 5, 6]
    scores = read_table(campaign_paths(spec), "scores")
    assert scores.filter(pl.col("run") < 2)["n_used"].max() == 10
    assert scores.filter(pl.col("run") >= 2)["n_used"].max() > 10


@pytest.mark.slow
def test_a_changed_spec_reruns_the_runs_it_changes(spec_file: str):
    spec = load_spec(spec_file)
    assert run_campaign(spec, local=True)["ran"] == 2
    path = Path(spec_file)
    path.write_text(path.read_text().replace("mean = 10.0", "mean = 12.0"))
    changed = load_spec(spec_file)
    facts = run_campaign(changed, local=True)
    assert facts["ran"] == 2 and facts["ok"] == 2  # every run draws the changed dispersion
    table = pl.read_parquet(campaign_paths(changed).root / "campaign.parquet")
    drawn = table.unique("run", maintain_order=True)["detection.sigma_range_m"].to_list()
    assert drawn == [changed.draws(i)["detection.sigma_range_m"] for i in range(2)]
    # the run folders of ok runs are gone (keep_runs = false); scenario files and logs stay
    paths = campaign_paths(changed)
    assert not (paths.runs / changed.run_id(0)).exists()
    assert paths.scenario(changed.run_id(0)).is_file()


@pytest.mark.slow
def test_resume_follows_what_a_run_depends_on(workdir: Path, catalogue_db: Path):
    """More runs keep the finished ones (their draws do not depend on the count); a changed base
    scenario or target reruns them (the executor's key)."""
    spec = load_spec(write_spec(workdir, catalogue_db, "grow", runs=2))
    assert run_campaign(spec, local=True)["ran"] == 2
    more = load_spec(write_spec(workdir, catalogue_db, "grow", runs=3))
    assert run_campaign(more, local=True)["ran"] == 1
    base = workdir / "runs" / "scenarios" / "default.toml"
    base.write_text(base.read_text().replace("visibility_a = 0.1826 ", "visibility_a = 0.2 "))
    assert run_campaign(load_spec(str(more.path)), local=True)["ran"] == 3
    assert run_campaign(load_spec(str(more.path)), local=True)["ran"] == 0
    path = Path(more.path)
    # (a target that still reads the dispersed imu.grade: one that does not is refused at load)
    path.write_text(path.read_text().replace("seed = 7\n", 'seed = 7\ntarget = "navigate"\n'))
    assert run_campaign(load_spec(str(path)), local=True)["ran"] == 3


def test_a_shared_catalogue_is_taken_while_the_database_holds_it(tmp_path: Path,
                                                                 catalogue_db: Path):
    from conftest import run_stages, small_config

    from pipeline.io.catalogue import db as cdb
    from pipeline.io.store import RunStore

    cfg = small_config("ingest-only", catalogue_db, {"start_s": 1800.0, "end_s": 1801.0})
    run_stages(cfg, tmp_path, ["ingest"])
    facts_path = RunStore("ingest-only", tmp_path).path("catalogue.json")
    loaded = cdb.load_recorded_catalogue(facts_path)
    try:
        cdb.share_catalogue(loaded)
        assert cdb.load_recorded_catalogue(facts_path) is loaded
        other = cdb.Catalogue(loaded.crater_id, loaded.diam_km, loaded.r_mcmf_m, loaded.index,
                              {**loaded.meta, "key": "another"})
        cdb.share_catalogue(other)  # not the database's: read again
        again = cdb.load_recorded_catalogue(facts_path)
        assert again is not other and np.array_equal(again.crater_id, loaded.crater_id)
    finally:
        cdb._SHARED.clear()


def test_envelopes_against_numpy_and_the_chi_square_bounds(tmp_path: Path):
    """Known errors in the runs' files: the percentiles are numpy's, 3x RMS and the mean NEES by
    hand, the bounds scipy's chi2(3N)/N; an estimator's failed frames are left out, the filter's
    uninitialised records too."""
    from scipy import stats

    from pipeline.campaign.results import Collected, build_database

    rng = np.random.default_rng(3)
    runs = 50
    err = rng.normal(0, 2.0, (runs, 2, 3))
    files: dict[str, list] = {"navigation": [], "scores": []}
    for r in range(runs):
        nav = pl.DataFrame({
            "t_s": [0.0, 10.0], "altitude_m": [2000.0, 1000.0],
            "status": ["not_initialised" if r == 0 else "ok", "ok"],
            **{f"err_pos_{c}_m": err[r, :, i] for i, c in enumerate("xyz")},
            **{f"err_att_{c}_rad": [1e-3, 1e-3] for c in "xyz"},
            **{f"sigma_pos_{c}_m": [2.0, 2.0] for c in "xyz"},
            "nees_pos": (err[r] ** 2).sum(-1) / 4.0})
        est = pl.DataFrame({
            "method": ["paper"], "t_s": [0.0], "altitude_m": [2000.0],
            "status": ["failed" if r < 10 else "ok"],
            **{f"err_{c}_m": [float(r)] for c in "xyz"},
            **{f"err_{a}_deg": [0.0] for a in ("phi", "theta", "psi")},
            **{f"sigma_{c}_m": [1.0] for c in "xyz"}, "nees_position": [3.0]})
        for part, df in (("navigation", nav), ("scores", est)):
            path = tmp_path / f"r{r}.{part}.parquet"
            df.write_parquet(path)
            files[part].append((r, f"r{r}", str(path)))
    env = build_database(tmp_path / "c.duckdb", Collected(pl.DataFrame(), files))
    f = env.filter((pl.col("source") == "filter") & (pl.col("t_s") == 0.0)).row(0, named=True)
    norms = np.linalg.norm(err[1:, 0], axis=1)  # run 0's first record is not initialised
    assert f["runs"] == runs - 1
    for p in (50, 95, 99.7):
        assert f[f"pos_p{p:g}_m"] == pytest.approx(np.percentile(norms, p), rel=1e-12)
    assert f["pos_rms3_m"] == pytest.approx(3 * np.sqrt(np.mean(norms**2)), rel=1e-12)
    assert f["pos_sigma3_m"] == pytest.approx(3 * np.sqrt(12.0), rel=1e-12)
    assert f["att_p50_deg"] == pytest.approx(np.degrees(np.sqrt(3) * 1e-3), rel=1e-12)
    assert f["mean_nees_pos"] == pytest.approx(np.mean(norms**2 / 4.0), rel=1e-12)
    n = runs - 1
    assert f["nees_lo"] == pytest.approx(stats.chi2.ppf(0.025, 3 * n) / n, rel=1e-12)
    assert f["nees_hi"] == pytest.approx(stats.chi2.ppf(0.975, 3 * n) / n, rel=1e-12)
    paper = env.filter(pl.col("source") == "paper").row(0, named=True)
    ok_norms = np.sqrt(3) * np.arange(10, runs)
    assert paper["runs"] == runs - 10
    assert paper["pos_p99.7_m"] == pytest.approx(np.percentile(ok_norms, 99.7), rel=1e-12)
    assert paper["mean_nees_pos"] == 3.0 and paper["altitude_m"] == 2000.0
    # the per-frame tables keep each run's rows in order, runs in order
    nav = duckdb_table(tmp_path / "c.duckdb", "navigation")
    assert nav["run"].to_list() == list(np.repeat(np.arange(runs), 2))
    assert nav["t_s"].to_list() == [0.0, 10.0] * runs


def duckdb_table(path: Path, name: str) -> pl.DataFrame:
    import duckdb

    con = duckdb.connect(str(path), read_only=True)
    try:
        return con.sql(f"SELECT * FROM {name}").pl()
    finally:
        con.close()


@pytest.mark.slow
def test_campaign_sql_and_recording(spec_file: str, capsys: pytest.CaptureFixture):
    import rerun as rr

    from pipeline.io.sqlshell import run_query

    spec = load_spec(spec_file)
    facts = run_campaign(spec, local=True)
    run_query("SELECT source, count(*) AS n FROM campaign.envelopes GROUP BY source "
              "ORDER BY source", campaign=spec.name, fmt="csv")
    out = capsys.readouterr().out
    n = facts["tables"]["envelopes"].filter(pl.col("source") == "filter").height
    assert out.splitlines()[:2] == ["source,n", f"filter,{n}"] and "paper," in out
    run_query("SELECT count(DISTINCT run) AS runs FROM campaign.scores", campaign=spec.name,
              fmt="csv")
    assert capsys.readouterr().out.splitlines()[1] == "2"
    with pytest.raises(Exception, match="refused"):
        run_query("CREATE TABLE campaign.x AS SELECT 1", campaign=spec.name)
    rrd = campaign_paths(spec).root / "campaign.rrd"
    chunks = rr.chunk.RrdReader(rrd).stream().collect()
    env = facts["tables"]["envelopes"].filter(pl.col("source") == "filter")
    entity = "/envelopes/filter/position_m/p99_7"
    df = chunks.reader(index="sim_time", contents=entity).to_polars()
    logged = np.array([cell[0] for cell in df[f"{entity}:Scalars:scalars"].to_list()])
    np.testing.assert_allclose(logged, env["pos_p99.7_m"].to_numpy())


@pytest.mark.slow
def test_the_built_in_world_jitter_and_mounting_reach_their_runs(workdir: Path,
                                                                 catalogue_db: Path,
                                                                 tmp_path: Path):
    """The physical sensor's built-ins: each run its own world (catalogue errors: the true
    ranges to the same craters differ), its own pointing jitter (the same positions, other
    attitudes) and its own camera mounting (pixels are the drawn camera's projection of the
    measured bearings, away from the nominal camera's), the navigator assuming the nominal."""
    from conftest import run_stages

    from pipeline.config import load_config

    spec = load_spec(write_spec(
        workdir, catalogue_db, "physical", head=(
            "catalogue_errors = true\njitter = true\nmounting_sigma_deg = 0.05\n"
            "keep_runs = true\n"),
        trajectory=', epoch_utc = "2026-01-30T08:40:00Z", jitter_rate_sigma_rad_s = 1e-4',
        body=('detection = { sensor = "physical", catalogue_sigma_horizontal_m = 100.0, '
              'catalogue_sigma_height_m = 50.0 }\nestimation = { catalogue_sigmas = "truth" }\n')))
    assert run_campaign(spec, local=True)["ok"] == 2
    paths = campaign_paths(spec)
    runs = []
    for i in range(2):
        rid = spec.run_id(i)
        cfg = load_config(str(paths.scenario(rid)), rid)
        assert cfg.detection.world_seed == spec.draws(i)["detection.world_seed"]
        assert cfg.estimation.assumed_camera_mounting_deg == (0.0, 0.0, 0.0)
        traj = pl.read_parquet(paths.runs / rid / "trajectory" / "trajectory.parquet")
        det = detection_columns.with_derived(
            pl.read_parquet(paths.runs / rid / "detect" / "detections.parquet"), traj)
        runs.append((cfg, det, traj))
    # the worlds: the true range to the same crater in the same frame differs by the errors
    keys = ["frame", "crater_id"]
    both = runs[0][1].select(*keys, "rho_true_m").join(
        runs[1][1].select(*keys, "rho_true_m"), on=keys, suffix="_b")
    assert both.height > 100
    assert np.median(np.abs(both["rho_true_m"] - both["rho_true_m_b"]).to_numpy()) > 10.0
    # the jitter: the same positions, other attitudes
    (a, b) = (runs[0][2], runs[1][2])
    np.testing.assert_allclose(a["r_mci_x_m"].to_numpy(), b["r_mci_x_m"].to_numpy(),
                               rtol=1e-12)  # one integration (the attitude rides along)
    assert np.abs(a["q_mci_from_body_x"] - b["q_mci_from_body_x"]).max() > 1e-7
    # the mounting: pixels project the measured bearings through the drawn camera
    for cfg, det, _ in runs:
        u = np.stack([det[f"u_meas_body_{c}"].to_numpy() for c in "xyz"], 1)
        pixel = np.stack([det["pixel_u"].to_numpy(), det["pixel_v"].to_numpy()], 1)
        own = cfg.detection.pixel_camera().project_body(u)
        nominal = load_config(str(paths.scenario(cfg.run_id)), cfg.run_id, {"detection": {
            "camera_mounting_deg": [0.0, 0.0, 0.0]}}).detection.pixel_camera().project_body(u)
        angle = np.radians(np.linalg.norm(cfg.detection.camera_mounting_deg))
        f_px = cfg.detection.pixel_camera().fx_px
        assert np.all(np.abs(pixel - own) <= 2.0**-24 * np.abs(own) + 1e-9)  # stored in float32
        assert np.median(np.linalg.norm(pixel - nominal, axis=1)) > 0.2 * f_px * angle > 0.1
        # the navigator takes the nominal mounting: a common rotation of every bearing, taken
        # into its attitude; the joint fixes' attitude is off by the drawn angle, where the same
        # run with the true mounting known is not
        def attitude_bias_deg(scores_path: Path) -> float:
            ok = pl.read_parquet(scores_path).filter((pl.col("method") == "joint")
                                                     & (pl.col("status") == "ok"))
            assert ok.height >= 5
            return float(np.linalg.norm([ok[f"err_{a}_deg"].mean()
                                         for a in ("phi", "theta", "psi")]))

        drawn_deg = np.degrees(angle)
        bias = attitude_bias_deg(paths.runs / cfg.run_id / "score" / "scores.parquet")
        assert 0.5 < bias / drawn_deg < 2.0, (bias, drawn_deg)
        known = load_config(str(paths.scenario(cfg.run_id)), f"known{cfg.run_id[-1]}", {
            "estimation": {"assumed_camera_mounting_deg": "truth"}})
        run_stages(known, tmp_path)
        assert attitude_bias_deg(tmp_path / known.run_id / "score" / "scores.parquet") < \
            0.2 * drawn_deg


@pytest.mark.slow
def test_a_dead_worker_is_retried_then_recorded_crashed(workdir: Path, catalogue_db: Path,
                                                        tmp_path: Path,
                                                        monkeypatch: pytest.MonkeyPatch):
    """Run 1's worker process dies once (retried: ok); run 0's dies every time (recorded
    `crashed`, the campaign completes and reports it)."""
    import os

    marker = tmp_path / "run1-died"
    real = execute.run_one

    def dies(task, shared, catalogue=None):
        if task.index == 0 or (task.index == 1 and not marker.exists()):
            marker.touch() if task.index == 1 else None
            os._exit(1)
        return real(task, shared, catalogue)

    monkeypatch.setattr(execute, "run_one", dies)
    spec = load_spec(write_spec(workdir, catalogue_db, "dies"))
    facts = run_campaign(spec, workers=2)
    assert marker.exists() and facts["done"] == 2 and facts["ok"] == 1
    table = pl.read_parquet(campaign_paths(spec).root / "campaign.parquet")
    crashed = table.filter(pl.col("run") == 0)
    assert crashed["status"].to_list() == ["crashed"] and crashed["error"][0]
    assert "crashed" in (campaign_paths(spec).root / "report.md").read_text()


def test_an_ordinary_run_folder_is_not_taken_for_a_campaign(spec_file: str):
    spec = load_spec(spec_file)
    root = campaign_paths(spec).root
    root.mkdir(parents=True)
    (root / "manifest.json").write_text("{}")
    with pytest.raises(PipelineError, match="ordinary run") as err:
        run_campaign(spec, local=True)
    assert "\n" not in str(err.value) and not (root / "results").exists()
