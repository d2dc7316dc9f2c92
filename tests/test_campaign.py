"""Campaigns: the spec and its errors, the draws, that each dispersion reaches its run, failed runs
recorded, resume, and (slow) Ray: the same table on 1 and 2 workers, a two-node cluster."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import polars as pl
import pytest

from pipeline.campaign import execute
from pipeline.campaign.execute import campaign_paths, run_campaign
from pipeline.campaign.results import TIMING_COLUMNS
from pipeline.campaign.spec import load_spec
from pipeline.errors import ConfigError

DISPERSIONS = """
[dispersions]
"detection.sigma_range_m" = { kind = "normal", mean = 10.0, sigma = 2.0 }
"detection.sigma_bearing" = { kind = "uniform", low = 5e-5, high = 2e-4 }
"imu.grade" = { kind = "choice", values = ["tactical", "navigation"] }
"navigation.gate_probability" = { values = [0.999, 0.9999] }
"""


def write_spec(workdir: Path, db: Path, name: str = "t", runs: int = 2, body: str = DISPERSIONS,
               head: str = "catalogue_errors = true\n", trajectory: str = "") -> str:
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
])
def test_spec_errors_are_one_line_naming_file_and_key(workdir: Path, text: str, named: str):
    path = workdir / "runs" / "campaigns" / "bad.toml"
    path.parent.mkdir(parents=True)
    path.write_text('base = "default"\nruns = 2\n' + text)
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
    assert [a.draws(i)["navigation.gate_probability"] for i in range(4)] == [0.999, 0.9999] * 2
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


def test_each_dispersion_reaches_its_run(spec_file: str):
    spec = load_spec(spec_file)
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
        assert (paths.runs / rid / "navigate" / "navigation.rrd").stat().st_size == 0
    b0 = pl.read_parquet(paths.runs / spec.run_id(0) / "navigate" / "navigation.parquet")
    b1 = pl.read_parquet(paths.runs / spec.run_id(1) / "navigate" / "navigation.parquet")
    assert b0["true_b_gyro_x_rad_s"][0] != b1["true_b_gyro_x_rad_s"][0]
    report = (paths.root / "report.md").read_text()
    assert "Success rate: 2/2" in report and f"just run {paths.scenario(spec.run_id(0))}" in \
        report


def test_failed_runs_are_recorded_and_a_campaign_resumes(spec_file: str,
                                                         monkeypatch: pytest.MonkeyPatch):
    spec = load_spec(spec_file)
    calls: list[str] = []
    real = execute.execute_stages

    def flaky(cfg, store, target):
        calls.append(store.run_id)
        if store.run_id.endswith("r0001") and len(calls) < 3:
            raise RuntimeError("boom in the filter")
        real(cfg, store, target)

    monkeypatch.setattr(execute, "execute_stages", flaky)
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
