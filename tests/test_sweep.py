"""The crater-cap sweep (the paper's Table 1, Figs. 7-8) as a campaign: a small sweep (caps 10 and
none, both methods, seeds 1 and 2, 1,800-2,000 s every 10 s, a 3 km synthetic catalogue) in this
process. table1.csv is recomputed from sweep_scores.parquet and the paper; the sweep's scores are
those of ordinary runs of the same config and seed (each sweep run is one); outputs, recording,
resume, a changed sweep, and (slow) the same Table 1 on two Ray workers.
"""

from __future__ import annotations

import re
import shutil
from pathlib import Path

import numpy as np
import polars as pl
import pytest
import rerun as rr
from conftest import REPO, run_stages
from polars.testing import assert_frame_equal

from pipeline.campaign.execute import run_campaign
from pipeline.campaign.results import TIMING_COLUMNS
from pipeline.campaign.sweep import sweep_spec, write_sweep
from pipeline.config import RunConfig, load_config
from pipeline.io.store import RunStore
from pipeline.studies import suslu2025
from pipeline.viz.rerun import base
from pipeline.workspace import workspace

PAPER = REPO.parent / "shared" / "paper" / "visual-pose-estimation-moon-landing.md"
SWEEP_ID = "sw"
CAPS = (10, None)
SEEDS = (1, 2)
METHODS = ("paper", "joint")
N_FRAMES = 21  # 1,800 ... 2,000 s
QUANTITIES = ("x_m", "y_m", "z_m", "phi_deg", "theta_deg", "psi_deg", "phi_mci_deg",
              "theta_mci_deg", "psi_mci_deg")
TABLE1_SCHEMA = {"method": pl.String, "cap": pl.String, "quantity": pl.String, "rmse": pl.Float64,
                 "paper_rmse": pl.Float64, "ratio_to_paper": pl.Float64,
                 "crlb_rms": pl.Float64, "ratio_to_crlb": pl.Float64, "frames": pl.Int64,
                 "estimated": pl.Int64, "mean_used": pl.Float64}
STAT_RTOL = 1e-12  # the same sums in another order: a few ulp
SCENARIO = """extends = "default"

[catalogue]
synthetic_min_diam_km = 3.0
db_path = "catalogue/craters.duckdb"

[trajectory]
start_s = 1800.0
end_s = 2000.0
frame_rate_hz = 0.1

[sweep]
caps = {caps}
seeds = {seeds}
workers = 2
"""


def label(cap: int | None) -> str:
    return "none" if cap is None else str(cap)


def write_scenario(root: Path, name: str = SWEEP_ID, caps=CAPS, seeds=SEEDS) -> Path:
    path = root / "runs" / "scenarios" / f"{name}.toml"
    path.write_text(SCENARIO.format(caps=[label(c) if c is None else c for c in caps],
                                    seeds=list(seeds)).replace("'", '"'))
    return path


def run_sweep(scenario: Path, run_id: str = SWEEP_ID, **kwargs) -> tuple[dict, RunConfig]:
    """`just sweep`: the sweep's campaign (in this process unless `workers` is given), then
    Table 1 and its report."""
    cfg = load_config(str(scenario), run_id)
    spec = sweep_spec(str(scenario), cfg)
    facts = run_campaign(spec, **({"local": True} if not kwargs else kwargs))
    facts["written"] = write_sweep(spec, cfg, facts["tables"])
    return facts, cfg


class Sweep:
    """The module's sweep (under root/runs/sw) and ordinary runs of the same config on demand."""

    def __init__(self, root: Path):
        self.root = root
        self.scenario = write_scenario(root)
        self.dir = root / "runs" / SWEEP_ID  # the campaign folder: the sweep's outputs
        self.out = self.dir
        self._runs: dict[tuple[int, int | None], RunStore] = {}

    @property
    def cfg(self) -> RunConfig:
        return load_config(str(self.scenario), SWEEP_ID)

    def read(self, name: str) -> pl.DataFrame:
        return pl.read_parquet(self.out / f"{name}.parquet")

    def table1(self) -> pl.DataFrame:
        return pl.read_csv(self.out / "table1.csv", schema=TABLE1_SCHEMA)

    def ordinary_run(self, seed: int, cap: int | None) -> RunStore:
        """Every stage of `just run` with detection.max_craters = cap and root seed = seed."""
        if (seed, cap) not in self._runs:
            run_id = f"seed{seed}-cap{label(cap)}"
            cfg = load_config(str(self.scenario), run_id, {
                "seed": seed, "detection": {"max_craters": label(cap) if cap is None else cap},
                "estimation": {"methods": list(METHODS)}})
            store = RunStore(run_id, self.root / "runs")
            run_stages(cfg, store.root)
            self._runs[seed, cap] = store
        return self._runs[seed, cap]


@pytest.fixture(scope="module")
def sweep(tmp_path_factory) -> Sweep:
    root = tmp_path_factory.mktemp("sweep")
    shutil.copytree(REPO / "runs" / "scenarios", root / "runs" / "scenarios")
    (root / "catalogue").mkdir()
    mp = pytest.MonkeyPatch()
    mp.chdir(root)
    mp.setenv("CRATER_NAV_ROOT", str(root))
    workspace.cache_clear()
    s = Sweep(root)
    facts, _ = run_sweep(s.scenario)
    assert (facts["ran"], facts["ok"]) == (len(CAPS) * len(SEEDS), len(CAPS) * len(SEEDS))
    yield s
    mp.undo()
    workspace.cache_clear()


@pytest.fixture
def in_sweep_root(sweep, monkeypatch):
    monkeypatch.chdir(sweep.root)
    monkeypatch.setenv("CRATER_NAV_ROOT", str(sweep.root))
    workspace.cache_clear()
    yield sweep
    workspace.cache_clear()


# --- table1.csv -----------------------------------------------------------------------------------


def test_table1_has_a_row_per_method_cap_and_quantity(sweep):
    t1 = sweep.table1()
    assert t1.height == len(METHODS) * len(CAPS) * len(QUANTITIES)
    assert t1.select("method", "cap", "quantity").rows() == [
        (m, label(c), q) for m in METHODS for c in CAPS for q in QUANTITIES]
    assert_frame_equal(sweep.read("table1"), t1, check_dtypes=False, check_exact=False,
                       rel_tol=1e-15)  # CSV round trip of floats


def paper_table1() -> dict[int | None, dict[str, float]]:
    """Table 1 as printed in the paper (rows X, Y, Z, phi, theta, psi; caps 10 ... no limit)."""
    if not PAPER.is_file():
        pytest.skip(f"{PAPER} not present")
    text = PAPER.read_text().split("Table 1.")[-1]
    rows = re.findall(r"^\|[^|]*\| *(X|Y|Z|\$\\(?:phi|theta|psi)\$) *\|(.*)\|$", text, re.M)
    names = {"X": "x_m", "Y": "y_m", "Z": "z_m", "$\\phi$": "phi_deg",
             "$\\theta$": "theta_deg", "$\\psi$": "psi_deg"}
    assert [names[r[0]] for r in rows] == ["x_m", "y_m", "z_m", "phi_deg", "theta_deg",
                                           "psi_deg"]
    values = {names[r[0]]: [float(v) for v in r[1].split("|")] for r in rows}
    caps = (10, 20, 50, 100, 200, None)
    return {cap: {q: values[q][i] for q in values} for i, cap in enumerate(caps)}


def test_paper_values_are_the_papers_table1(sweep):
    assert suslu2025.TABLE1 == paper_table1()
    t1 = sweep.table1()
    for row in t1.iter_rows(named=True):
        cap = None if row["cap"] == "none" else int(row["cap"])
        # rows about MCI axes reuse the paper's phi, theta, psi
        assert row["paper_rmse"] == suslu2025.TABLE1[cap][row["quantity"].replace("_mci", "")]


def test_rmse_is_pooled_over_seeds_in_the_table_window(sweep):
    scores, t1 = sweep.read("sweep_scores"), sweep.table1()
    assert sweep.cfg.scoring.table_window == "1800-2400 s"
    inside = scores.filter((pl.col("t_s") >= 1800.0) & (pl.col("t_s") < 2400.0))
    assert inside.height == scores.height == len(METHODS) * len(CAPS) * len(SEEDS) * N_FRAMES
    for row in t1.iter_rows(named=True):
        g = inside.filter(pl.col("method") == row["method"], pl.col("cap_label") == row["cap"])
        ok = g.filter(pl.col("status") == "ok")
        q = row["quantity"]
        err, crlb = ok[f"err_{q}"].to_numpy(), ok[f"crlb_{q}"].to_numpy()
        assert set(g["seed"]) == set(SEEDS) and g.height == len(SEEDS) * N_FRAMES
        assert (row["frames"], row["estimated"]) == (g.height, ok.height)
        assert ok.height > 0.9 * g.height
        rmse, crlb_rms = np.sqrt(np.mean(err**2)), np.sqrt(np.mean(crlb**2))
        np.testing.assert_allclose(row["rmse"], rmse, rtol=STAT_RTOL)
        np.testing.assert_allclose(row["crlb_rms"], crlb_rms, rtol=STAT_RTOL)
        np.testing.assert_allclose(row["ratio_to_paper"], rmse / row["paper_rmse"], rtol=STAT_RTOL)
        np.testing.assert_allclose(row["ratio_to_crlb"], rmse / crlb_rms, rtol=STAT_RTOL)
        np.testing.assert_allclose(row["mean_used"], g["n_used"].mean(), rtol=STAT_RTOL)


def test_caps_bound_the_craters_used(sweep):
    scores = sweep.read("sweep_scores")
    capped = scores.filter(pl.col("cap_label") == "10")
    assert (capped["cap"] == 10).all() and capped["n_used"].max() == 10
    free = scores.filter(pl.col("cap_label") == "none")
    assert free["cap"].is_null().all() and free["n_used"].min() > 10
    t1 = sweep.table1().filter(pl.col("quantity") == "x_m")
    used = dict(zip(t1["cap"], t1["mean_used"], strict=False))
    assert used["10"] <= 10 < used["none"]


# --- the same numbers as ordinary runs ------------------------------------------------------------


@pytest.mark.parametrize(("seed", "cap"), [pytest.param(1, None, marks=pytest.mark.slow),
                                           pytest.param(2, None, marks=pytest.mark.slow),
                                           (1, 10)])
def test_sweep_scores_are_those_of_an_ordinary_run(sweep, seed, cap):
    """A run with detection.max_craters = cap and seed = seed gives, frame for frame and method for
    method, exactly the sweep's scores (same estimates, errors, bounds and NEES)."""
    store = sweep.ordinary_run(seed, cap)
    ordinary = pl.read_parquet(store.path("scores.parquet"))
    swept = sweep.read("sweep_scores").filter(
        (pl.col("seed") == seed) & (pl.col("cap_label") == label(cap))).drop("seed", "cap_label")
    assert ordinary.height == len(METHODS) * N_FRAMES
    assert_frame_equal(swept, ordinary, check_exact=True)
    est = pl.read_parquet(store.path("estimates.parquet"))
    assert (est["n_used"] <= (cap or np.inf)).all()


# --- outputs --------------------------------------------------------------------------------------


def test_table1_markdown_sets_the_papers_table_beside_ours(sweep):
    md = (sweep.out / "table1.md").read_text()
    t1 = sweep.table1()
    assert md.startswith("# Table 1: RMSE over 1800-2400 s")
    assert "| | 10 | none |" in md
    assert "### The paper's Table 1" in md and "| X (m) | 4.923 | 0.6111 |" in md
    # row labels are the vocabulary's (pipeline.vocab.QUANTITIES, ATTITUDE_MCI)
    assert "| yaw psi, MCI axes (deg) | 0.0066 | 0.00076 |" in md
    for method in METHODS:
        assert f"### `{method}`: RMSE (ours / paper)" in md
        assert f"### `{method}`: RMSE / sqrt(CRLB)" in md
        for q, name in (("y_m", "Y (m)"), ("theta_deg", "pitch theta (deg)")):
            r = {c: t1.filter(pl.col("method") == method, pl.col("cap") == c,
                              pl.col("quantity") == q).row(0, named=True) for c in ("10", "none")}
            assert (f"| {name} | {r['10']['rmse']:.4g} ({r['10']['ratio_to_paper']:.2f}) | "
                    f"{r['none']['rmse']:.4g} ({r['none']['ratio_to_paper']:.2f}) |") in md
            assert (f"| {name} | {r['10']['ratio_to_crlb']:.3f} | "
                    f"{r['none']['ratio_to_crlb']:.3f} |") in md


def test_table1_markdown_quotes_the_papers_values_as_printed(sweep):
    md = (sweep.out / "table1.md").read_text()
    block = md.split("### The paper's Table 1")[1].split("###")[0]
    for q, name in (("x_m", "X (m)"), ("y_m", "Y (m)"), ("z_m", "Z (m)")):
        cells = " | ".join(str(suslu2025.TABLE1[cap][q]) for cap in CAPS)
        assert f"| {name} | {cells} |" in block


def test_report_and_figures_7_8(sweep):
    """Fig. 8 (1,800-2,400 s) is drawn; Fig. 7 (0-1,500 s) is left out: no frame of this
    sweep falls in its window."""
    text = (sweep.out / "sweep_report.md").read_text()
    assert (sweep.out / "table1.md").read_text().split("\n\n", 1)[1] in text
    for method in METHODS:
        fig = f"fig8_{method}_caps_1800-2400s.png"
        assert f"]({fig})" in text
        assert (sweep.out / fig).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
        assert f"fig7_{method}" not in text
        assert not (sweep.out / f"fig7_{method}_caps_0-1500s.png").exists()


def test_sweep_recording_holds_a_series_per_method_and_cap(sweep):
    path = sweep.out / "sweep.rrd"
    [entry] = rr.chunk.RrdReader(path).recordings()
    assert (entry.application_id, entry.recording_id) == (base.APP_ID,
                                                          base.recording_id(SWEEP_ID))
    chunks = rr.chunk.RrdReader(path).stream().collect()
    first = sweep.read("sweep_scores").filter(pl.col("seed") == SEEDS[0])
    for method in METHODS:
        for cap in CAPS:
            g = first.filter((pl.col("method") == method) & (pl.col("cap_label") == label(cap)))
            norm = np.sqrt(sum(g[f"err_{a}"].to_numpy() ** 2 for a in ("x_m", "y_m", "z_m")))
            entity = f"/sweep/{method}/position_m/cap_{label(cap)}"
            df = chunks.reader(index="frame", contents=entity).to_polars()
            np.testing.assert_array_equal(df["frame"].to_numpy(), g["frame"].to_numpy())
            logged = np.array([cell[0] for cell in df[f"{entity}:Scalars:scalars"].to_list()])
            np.testing.assert_allclose(logged, norm, rtol=STAT_RTOL)
            attitude = f"/sweep/{method}/attitude_deg/cap_{label(cap)}"
            assert chunks.reader(index="frame", contents=attitude).to_polars().height == N_FRAMES


def test_outputs_beside_the_campaigns_and_no_leftovers(sweep):
    figures = {f"fig8_{m}_caps_1800-2400s.png" for m in METHODS}  # no frame in Fig. 7's window
    sweep_outputs = {"table1.csv", "table1.md", "sweep_scores.parquet", "table1.parquet",
                     "sweep_report.md", "sweep.rrd", *figures}
    campaign = {"campaign.parquet", "campaign.duckdb", "campaign.rrd", "campaign.json",
                "report.md", "spec.toml", "envelope_time.png", "envelope_altitude.png",
                "nees.png", "runs", "results", ".lock"}
    names = {p.name for p in sweep.dir.iterdir()}
    assert names == sweep_outputs | campaign, names
    assert not [p for p in sweep.dir.rglob("*") if ".tmp" in p.name]
    # each ok run's folder is gone once its rows are collected; its scenario file stays
    runs = {p.name for p in (sweep.dir / "runs").iterdir()}
    ids = [f"{SWEEP_ID}-r{i:04d}" for i in range(len(CAPS) * len(SEEDS))]
    assert {f"{i}.toml" for i in ids} | {f"{i}.log" for i in ids} <= runs
    assert not runs & set(ids)
    # the grid: caps in the order given, each with every seed
    table = pl.read_parquet(sweep.dir / "campaign.parquet").unique("run", maintain_order=True)
    assert table.select("seed", "detection.max_craters").rows() == [
        (seed, str(label(cap) if cap is None else cap)) for cap in CAPS for seed in SEEDS]


# --- resume ---------------------------------------------------------------------------------------


@pytest.mark.slow
def test_a_second_sweep_runs_nothing_and_writes_the_same_table(in_sweep_root):
    sweep = in_sweep_root
    before = (sweep.out / "table1.csv").read_bytes()
    facts, _ = run_sweep(sweep.scenario)
    assert facts["ran"] == 0 and facts["skipped"] == len(CAPS) * len(SEEDS)
    assert (sweep.out / "table1.csv").read_bytes() == before


@pytest.mark.slow
def test_a_changed_sweep_reruns_only_its_changed_runs(sweep, tmp_path, monkeypatch):
    """A copy of the sweep folder, swept again with seeds (1, 3): the runs of seed 1 are found
    done, those of seed 3 run; Table 1 pools seeds 1 and 3."""
    shutil.copytree(sweep.root / "runs", tmp_path / "runs", symlinks=True)
    (tmp_path / "catalogue").mkdir()
    shutil.copy(sweep.root / "catalogue" / "craters.duckdb", tmp_path / "catalogue")
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("CRATER_NAV_ROOT", str(tmp_path))
    workspace.cache_clear()
    try:
        scenario = write_scenario(tmp_path, seeds=(1, 3))
        facts, _ = run_sweep(scenario)
    finally:
        workspace.cache_clear()
    assert facts["ran"] == len(CAPS) and facts["skipped"] == len(CAPS)
    scores = pl.read_parquet(tmp_path / "runs" / SWEEP_ID / "sweep_scores.parquet")
    assert set(scores["seed"]) == {1, 3}
    before = sweep.read("sweep_scores").filter(pl.col("seed") == 1)
    assert_frame_equal(scores.filter(pl.col("seed") == 1), before)


@pytest.mark.slow
def test_the_same_table1_on_two_ray_workers(in_sweep_root):
    sweep = in_sweep_root
    scenario = write_scenario(sweep.root, "sw_ray")
    run_sweep(scenario, "sw-ray", workers=2)
    ray_dir = sweep.root / "runs" / "sw-ray"
    assert (ray_dir / "table1.csv").read_bytes() == (sweep.out / "table1.csv").read_bytes()
    assert_frame_equal(pl.read_parquet(ray_dir / "sweep_scores.parquet"),
                       sweep.read("sweep_scores"))
    a = pl.read_parquet(ray_dir / "campaign.parquet").drop(*TIMING_COLUMNS, "run_id")
    b = pl.read_parquet(sweep.dir / "campaign.parquet").drop(*TIMING_COLUMNS, "run_id")
    assert a.equals(b)
