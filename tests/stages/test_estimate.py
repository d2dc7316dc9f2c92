"""Stage `estimate`: estimates.parquet and its table, covariances honest against the truth, the
joint method against the paper's, no truth reaching an estimator, too few craters, warm starts and
restarts, false matches with and without the robust front end, estimation.rrd and the cache.

All runs share one window of the default descent, 1900-2000 s at 1 Hz (altitude 138-124 km, where
the Eq. 9 threshold is ~1.7 km), over a 5 km synthetic catalogue: 60-83 used craters per frame.
The estimator cores are unit-tested in tests/core/test_estimators.py; these tests check the stage.
"""

from __future__ import annotations

import shutil
from collections import Counter
from pathlib import Path

import duckdb
import numpy as np
import polars as pl
import pytest
import rerun as rr
from conftest import run_stages, small_config
from scipy.spatial.transform import Rotation
from scipy.stats import chi2, poisson

from pipeline.config import RunConfig
from pipeline.core.estimation import estimators
from pipeline.core.math.constants import MOON_RADIUS_M
from pipeline.io.store import RunStore
from pipeline.io.tables import quats, xyz
from pipeline.ops import detection_columns, estimate
from pipeline.stages import DAG
from pipeline.viz.rerun import base, estimation
from pipeline.vocab.tables import ESTIMATES

WINDOW = {"start_s": 1900.0, "end_s": 2000.0, "frame_rate_hz": 1.0}
N_FRAMES = 101
METHODS = ("paper", "joint")
PIPELINE = ("ingest", "trajectory", "detect", "estimate")
FALSE_MATCHES = {"false_match_share": 0.1}

# Truth that the detection and trajectory stages write beside the measurements.
TRUE_DETECTION_COLUMNS = ("crater_id", "diam_km", "c_true_mcmf_x_m", "c_true_mcmf_y_m",
                          "c_true_mcmf_z_m", "false_match")
NOT_TRUTH_TRAJECTORY_COLUMNS = ("frame", "t_s", "theta_m_rad")  # time and the Moon's rotation

F32_REL = 2.0**-24  # float32 rounding in the recordings
# Two estimates from different starting points stop within a few step_tol_m (1e-9 m) of the same
# Gauss-Newton fixed point: 10 x step_tol_m in position, and that over the shortest range in the
# window (~1.24e5 m) in attitude.
SAME_FIXED_POINT_M = 1e-8
SAME_FIXED_POINT_RAD = 1e-13


def config(run_id: str, db: Path, **sections) -> RunConfig:
    return small_config(run_id, db, WINDOW, **sections)


def run(run_id: str, db: Path, root: Path = Path("runs"), **sections) -> RunStore:
    store = RunStore(run_id, root)
    run_stages(config(run_id, db, **sections), store.root, PIPELINE)
    return store


@pytest.fixture(scope="module")
def runs(tmp_path_factory, catalogue_db) -> dict[str, RunStore]:
    """Read-only runs: clean measurements; 10 % false matches with the plain and the robust
    estimators. Detection streams are per purpose, so all three see the same identified craters
    with the same noise: only the matches differ."""
    root = tmp_path_factory.mktemp("runs")
    return {"clean": run("clean", catalogue_db, root),
            "plain": run("plain", catalogue_db, root, detection=FALSE_MATCHES),
            "robust": run("robust", catalogue_db, root, detection=FALSE_MATCHES,
                          estimation={"robust": True})}


def read(store: RunStore, name: str) -> pl.DataFrame:
    return pl.read_parquet(store.path(f"{name}.parquet"))


def errors(store: RunStore, method: str) -> tuple[np.ndarray, np.ndarray]:
    """Errors (N, 6) [position MCI (m), attitude dtheta body (rad)] of a method's frames against
    the truth, with R_est = R_true Exp(dtheta) as the estimators define it, and covariances."""
    est = read(store, "estimates").filter(pl.col("method") == method).sort("frame")
    truth = read(store, "trajectory").join(est.select("frame"), on="frame").sort("frame")
    assert (est["status"] == "ok").all()
    d_pos = xyz(est, "r_mci", "_m") - xyz(truth, "r_mci", "_m")
    d_att = (Rotation.from_quat(quats(truth, "q_mci_from_body")).inv()
             * Rotation.from_quat(quats(est, "q_mci_from_body"))).as_rotvec()
    return np.hstack([d_pos, d_att]), est["cov"].to_numpy().reshape(-1, 6, 6)


def nees(x: np.ndarray, cov: np.ndarray) -> np.ndarray:
    return np.einsum("ni,nij,nj->n", x, np.linalg.inv(cov), x)


def chi2_mean_bounds(dof: int, n: int, p: float = 1e-3) -> tuple[float, float]:
    """Two-sided bounds (probability 1 - p) of the mean of n independent chi-square(dof)."""
    return tuple(chi2.ppf([p / 2, 1 - p / 2], dof * n) / n)


def rms(x: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.sum(x**2, axis=1))))


# --- the table ------------------------------------------------------------------------------------


def test_estimates_table_rows_columns_and_database(runs):
    store = runs["clean"]
    est, frames = read(store, "estimates"), read(store, "frames")
    assert est.schema == pl.Schema(ESTIMATES.columns())
    assert est.height == N_FRAMES * len(METHODS)
    for method in METHODS:  # one row per frame and method, in frame order
        m = est.filter(pl.col("method") == method)
        assert m.select("frame", "t_s").equals(frames.select("frame", "t_s"))
        np.testing.assert_array_equal(m["n_used"].to_numpy(), frames["n_used"].to_numpy())
    assert est["cap"].is_null().all()  # detection.max_craters = "none"
    assert est["n_used"].min() >= 10
    assert ((est["status"] == "ok") == (est["n_used"] >= 3)).all()
    assert (est["iterations"] >= 1).all() and (est["solve_ms"] > 0).all()
    assert (est["n_rejected"] == 0).all() and (est["rejected_ids"].list.len() == 0).all()

    cov = est["cov"].to_numpy().reshape(-1, 6, 6)
    np.testing.assert_allclose(cov, np.swapaxes(cov, 1, 2), rtol=1e-10, atol=0)
    assert np.linalg.eigvalsh(cov).min() > 0
    sigma = np.sqrt(np.diagonal(cov, axis1=1, axis2=2))
    np.testing.assert_array_equal(xyz(est, "sigma_pos", "_m"), sigma[:, :3])
    np.testing.assert_array_equal(xyz(est, "sigma_att", "_rad"), sigma[:, 3:])
    q = quats(est, "q_mci_from_body")
    np.testing.assert_allclose(np.linalg.norm(q, axis=1), 1.0, rtol=0, atol=1e-15)
    assert (q[:, 3] >= 0).all()
    quest_cov = est["att_cov_quest"].to_numpy()  # QUEST's own covariance: the paper method only
    paper = (est["method"] == "paper").to_numpy()
    assert np.isfinite(quest_cov[paper]).all() and np.isnan(quest_cov[~paper]).all()

    con = duckdb.connect(str(store.duckdb_path), read_only=True)
    try:
        assert con.sql("SELECT * FROM estimates").pl().equals(est)
    finally:
        con.close()
    entry = store.entry("estimate")
    assert entry["info"]["status_counts"] == {"joint/ok": N_FRAMES, "paper/ok": N_FRAMES}
    assert entry["info"]["robust"] is False
    assert set(entry["outputs"]) == {"estimates.parquet"}
    assert set(entry["visuals"]) == {"estimation.rrd"}


# --- honesty: errors against the truth ------------------------------------------------------------


@pytest.mark.parametrize("method", METHODS)
@pytest.mark.parametrize("name", ["clean", "robust"])
def test_errors_are_consistent_with_the_covariances(runs, name, method):
    """Mean NEES over the frames within chi-square bounds (frames are independent: each has its
    own measurement noise, and the synthetic catalogue is exact), for the whole pose and for each
    block. The robust run, after removing the false matches, must be as honest."""
    x, cov = errors(runs[name], method)
    for block, dof in ((slice(0, 6), 6), (slice(0, 3), 3), (slice(3, 6), 3)):
        mean = nees(x[:, block], cov[:, block, block]).mean()
        lo, hi = chi2_mean_bounds(dof, N_FRAMES)
        assert lo < mean < hi, (block, mean, (lo, hi))


def test_joint_is_not_worse_than_paper(runs):
    """The joint ML adds the bearings to the ranges, so its position covariance is below the
    paper's (Loewner order), and as the efficient estimator its error is uncorrelated with the
    difference d = e_paper - e_joint (Hausman), whose covariance is then P_paper - P_joint. So
    d must pass its own NEES test, and the squared-error gain sum(|e_p|^2 - |e_j|^2), expected
    tr(P_paper - P_joint) >= 0, must not be negative beyond 3 of its predicted standard deviations
    (var = 2 tr(P_d^2) + 4 tr(P_joint P_d) per frame). A joint method that returned the paper's
    pose (d = 0) or added noise fails."""
    x_p, cov_p = errors(runs["clean"], "paper")
    x_j, cov_j = errors(runs["clean"], "joint")
    e_p, e_j = x_p[:, :3], x_j[:, :3]
    p_j = cov_j[:, :3, :3]
    p_d = cov_p[:, :3, :3] - p_j
    assert np.linalg.eigvalsh(p_d).min() > 0

    d = e_p - e_j
    lo, hi = chi2_mean_bounds(3, N_FRAMES)
    assert lo < nees(d, p_d).mean() < hi

    gain = np.sum(e_p**2 - e_j**2)
    var = np.sum(2 * np.einsum("nij,nji->n", p_d, p_d) + 4 * np.einsum("nij,nji->n", p_j, p_d))
    assert gain > -3 * np.sqrt(var)


# --- what an estimator sees -----------------------------------------------------------------------


def scramble(table: pl.DataFrame, columns, rng: np.random.Generator) -> pl.DataFrame:
    """Columns replaced by garbage of the same dtype."""
    out = []
    for name in columns:
        s = table[name]
        if s.dtype == pl.Boolean:
            out.append(~s)
        elif s.dtype.is_integer():
            out.append(pl.Series(name, rng.permutation(s.to_numpy())))
        else:
            out.append(pl.Series(name, rng.normal(0.0, 1e6, s.len())).cast(s.dtype))
    return table.with_columns(out)


def replace_outputs(store: RunStore, tables: dict[str, pl.DataFrame]) -> None:
    """Replace stage tables (Parquet, hence run.duckdb's views) keeping the stages fresh: an
    output overwritten in place makes its stage stale, so each stage owning a replaced table is
    recommitted through the store with its key and entry, and the stages downstream of it with
    the new upstream digests."""
    recommitted: set[str] = set()
    for stage in DAG.order:
        entry = store.entry(stage)
        if entry is None or not (set(entry["tables"]) & set(tables)
                                 or set(entry["inputs"]) & recommitted):
            continue
        inputs = {u: {**i, "digest": store.digest(u)} for u, i in entry["inputs"].items()}
        with store.lock():
            tx = store.begin(stage, entry["key"], inputs, entry["config_hash"],
                             entry["code_hash"], visuals=tuple(entry["visuals"]))
            for name in (*entry["outputs"], *entry["visuals"]):
                table = name.removesuffix(".parquet")
                if table in entry["tables"]:
                    tx.table(table, tables.get(table, pl.read_parquet(store.path(name))))
                else:
                    shutil.copyfile(store.path(name), tx.output(name))
            tx.commit(entry["info"], visuals_key=entry["visuals_key"])
        recommitted.add(stage)
    for name, table in tables.items():
        assert read(store, name).equals(table), name


class EstimatorSpy:
    """Wraps estimate_pose and records each call's inputs and result."""

    def __init__(self) -> None:
        self.calls: list[tuple[tuple, dict, estimators.PoseEstimate]] = []

    def __call__(self, *args, **kwargs) -> estimators.PoseEstimate:
        result = estimators.estimate_pose(*args, **kwargs)
        self.calls.append((args, kwargs, result))
        return result

    def of(self, method: str) -> list[tuple[tuple, dict, estimators.PoseEstimate]]:
        return [c for c in self.calls if c[0][0] == method]


def forbid(*_args, **_kwargs):
    raise AssertionError("the estimate stage recomputed the truth")


def test_estimator_never_sees_the_truth(workdir, catalogue_db, monkeypatch):
    """The truth is scrambled in every upstream output (Parquet and run.duckdb) after detection,
    and every way to recompute it (propagation, detection) raises: the forced estimate stage must
    give identical estimates. Robust mode with false matches, so that the `false_match` column
    would help a cheat. And each estimator call gets exactly the frame's used measurements."""
    sections = {"detection": FALSE_MATCHES, "estimation": {"robust": True}}
    cfg = config("r", catalogue_db, **sections)
    store = run("r", catalogue_db, **sections)
    before = read(store, "estimates")

    rng = np.random.default_rng(0)
    trajectory, detections, frames = (read(store, n) for n in ("trajectory", "detections",
                                                                "frames"))
    replace_outputs(store, {
        "trajectory": scramble(trajectory, [c for c in trajectory.columns
                                            if c not in NOT_TRUTH_TRAJECTORY_COLUMNS], rng),
        "detections": scramble(detections, TRUE_DETECTION_COLUMNS, rng),
        "frames": scramble(frames, ["altitude_km", "n_false_match",
                                    *[c for c in frames.columns if c.startswith("corner")]], rng),
    })
    for module, name in (("pipeline.stages.trajectory", "simulate"),
                         ("pipeline.ops.trajectory", "simulate"),
                         ("pipeline.core.dynamics.orbit", "propagate_descent"),
                         ("pipeline.core.dynamics.orbit", "apoapsis_state"),
                         ("pipeline.stages.detect", "detect_all"),
                         ("pipeline.ops.detect", "detect_all"),
                         ("pipeline.core.sensors.detection", "detect_frame")):
        monkeypatch.setattr(f"{module}.{name}", forbid)
    spy = EstimatorSpy()
    monkeypatch.setattr(estimate, "estimate_pose", spy)
    assert run_stages(cfg, store.root, ["estimate"], force=["estimate"]) == ["estimate"]

    after = read(store, "estimates")
    assert after.drop("solve_ms").equals(before.drop("solve_ms"))

    used = detections.filter("used")
    assert len(spy.calls) == N_FRAMES * len(METHODS)
    allowed = {"sigma_bearing", "sigma_range_m", "r_prior_mci_m", "step_tol_m", "max_iterations",
               "robust", "rng", "checks"}  # checks: thresholds and the Moon radius, no truth
    for (method, *_), kwargs, _ in spy.calls:
        assert method in METHODS and set(kwargs) <= allowed
    for i, frame in enumerate(frames["frame"]):
        rows = used.filter(pl.col("frame") == frame)
        (_, c, u, rho), _, _ = spy.of("paper")[i]
        np.testing.assert_array_equal(c, detection_columns.matched_positions_mci(rows, frames))
        np.testing.assert_array_equal(u, xyz(rows, "u_meas_body", ""))
        np.testing.assert_array_equal(rho, rows["rho_meas_m"].to_numpy())


# --- failures, warm starts and restarts -----------------------------------------------------------


def test_cap_of_two_gives_too_few_craters_everywhere(workdir, catalogue_db):
    store = run("r", catalogue_db, detection={"max_craters": 2})
    est = read(store, "estimates")
    assert est.height == N_FRAMES * len(METHODS)
    assert (est["status"] == "too_few_craters").all()
    assert (est["n_used"] == 2).all() and (est["cap"] == 2).all()
    assert (est["iterations"] == 0).all() and (est["n_rejected"] == 0).all()
    values = est.select(pl.exclude("frame", "t_s", "method", "cap", "status", "n_used",
                                   "n_rejected", "rejected_ids", "rejected_det_index", "iterations",
                                   "solve_ms"))
    for name in values.columns:  # pose, sigmas and covariances all NaN
        v = values[name]
        flat = v.to_numpy() if v.dtype == pl.Float64 else np.stack(v.to_numpy())
        assert np.isnan(flat).all(), name
    assert store.entry("estimate")["info"]["status_counts"] == {
        "joint/too_few_craters": N_FRAMES, "paper/too_few_craters": N_FRAMES}

    chunks = rr.chunk.RrdReader(store.path("estimation.rrd")).stream().collect()
    series = chunks.reader(index="frame", contents="/estimation/**").to_polars()
    assert series.height == N_FRAMES
    for method in METHODS:  # STATUS_CODES["too_few_craters"]; no pose to draw
        np.testing.assert_array_equal(
            frame_values(series, f"/estimation/{method}/status:Scalars:scalars"), 1.0)
        assert f"/world/estimate/{method}:Transform3D:translation" not in series.columns


def test_warm_start_and_restart_after_failures(workdir, catalogue_db, runs, monkeypatch):
    """Odd frames keep only 2 used craters, so every valid frame follows a failure. Each method
    starts from the closed form (no prior) on the first frame and after every failure, and from
    its own previous estimate otherwise; the valid frames converge to what the clean run (warm
    started from the previous frame every time) found, so the result does not depend on it."""
    cfg = config("r", catalogue_db)
    store = RunStore("r")
    run_stages(cfg, store.root, ["ingest", "trajectory", "detect"])
    detections = read(store, "detections")
    rank = pl.col("used").cast(pl.Int32).cum_sum().over("frame")
    odd = (pl.col("frame") % 2) == 1
    detections = detections.with_columns(used=pl.when(odd).then(pl.col("used") & (rank <= 2))
                                         .otherwise(pl.col("used")))
    replace_outputs(store, {"detections": detections})
    spy = EstimatorSpy()
    monkeypatch.setattr(estimate, "estimate_pose", spy)
    assert run_stages(cfg, store.root, ["estimate"], force=["estimate"]) == ["estimate"]

    est = read(store, "estimates")
    odd_rows = (est["frame"] % 2 == 1).to_numpy()
    assert (est.filter(odd_rows)["status"] == "too_few_craters").all()
    assert (est.filter(odd_rows)["n_used"] == 2).all()
    assert (est.filter(~odd_rows)["status"] == "ok").all()

    for method in METHODS:
        calls = spy.of(method)
        assert len(calls) == N_FRAMES
        previous = None
        for _, kwargs, result in calls:
            prior = kwargs["r_prior_mci_m"]
            if previous is None or previous.status != "ok":
                assert prior is None  # the closed form, never a stale or NaN prior
            else:
                np.testing.assert_array_equal(prior, previous.r_mci_m)
            previous = result

    clean = read(runs["clean"], "estimates")
    both = est.filter(~odd_rows).join(clean, on=["frame", "method"], suffix="_clean")
    assert both.height == (N_FRAMES + 1) // 2 * len(METHODS)
    assert (both["n_used"] == both["n_used_clean"]).all()  # the same craters
    r = xyz(both, "r_mci", "_m")
    r_clean = np.stack([both[f"r_mci_{c}_m_clean"].to_numpy() for c in "xyz"], axis=1)
    assert np.abs(r - r_clean).max() < SAME_FIXED_POINT_M
    q = Rotation.from_quat(quats(both, "q_mci_from_body"))
    q_clean = Rotation.from_quat(np.stack([both[f"q_mci_from_body_{c}_clean"].to_numpy()
                                           for c in "xyzw"], axis=1))
    assert (q.inv() * q_clean).magnitude().max() < SAME_FIXED_POINT_RAD


# --- false matches and the robust front end -------------------------------------------------------


def test_false_matches_make_plain_fixes_say_so_and_robust_recovers(runs):
    """False matches are to the nearest other visible crater, kilometres away, so a plain fit
    through them is off by far more than its metres of noise: its own residual test must say so
    (status `inconsistent`, no pose) instead of returning a wrong `ok`. Robust estimation, having
    dropped them, is within 20 % of the clean run (it fits ~10 % fewer craters: ~5 % larger
    errors expected)."""
    used = read(runs["plain"], "detections").filter("used")
    with_false = set(used.filter("false_match")["frame"].to_list())
    assert len(with_false) > 0.8 * N_FRAMES
    plain = read(runs["plain"], "estimates")
    for method in METHODS:
        m = plain.filter(pl.col("method") == method)
        flagged = m.filter(pl.col("frame").is_in(list(with_false)))
        assert (flagged["status"] == "inconsistent").all(), flagged["status"].value_counts()
        assert flagged["r_mci_x_m"].is_nan().all()
        x = {name: errors(runs[name], method)[0] for name in ("clean", "robust")}
        pos = {name: rms(v[:, :3]) for name, v in x.items()}
        att = {name: rms(v[:, 3:]) for name, v in x.items()}
        assert pos["robust"] < 1.2 * pos["clean"], (method, pos)
        assert att["robust"] < 1.2 * att["clean"], (method, att)


def test_robust_rejects_the_false_matches_and_records_them(runs, catalogue_db):
    """rejected_ids are matched catalogue ids. A false match whose wrong crater lies farther than
    10 x the gate radius (sqrt(chi2 gate) x the larger of sigma_range and range x sigma_bearing)
    from the crater actually seen must be rejected. Good craters are rejected only by the gate's
    own false alarms: Poisson with mean (1 - gate_probability) x their count, bounded here at its
    99.99 % quantile. An id used twice in a frame (a false match onto another used crater) is
    counted with its multiplicity."""
    cfg = config("robust", catalogue_db, detection=FALSE_MATCHES, estimation={"robust": True})
    store = runs["robust"]
    est, truth = read(store, "estimates"), read(store, "trajectory")
    used = detection_columns.with_derived(read(store, "detections"), truth).filter("used").join(
        truth.select("frame", *[c for c in truth.columns if c.startswith(("r_mci", "q_mci"))]),
        on="frame")
    p_body = xyz(used, "u_true_body", "") * used["rho_true_m"].to_numpy()[:, None]
    seen = xyz(used, "r_mci", "_m") + Rotation.from_quat(quats(used, "q_mci_from_body")).apply(
        p_body)  # the crater actually seen, MCI
    offset = np.linalg.norm(xyz(used, "c_mci", "_m") - seen, axis=1)
    gate_m = np.sqrt(chi2.ppf(cfg.estimation.gate_probability, 3)) * max(
        cfg.detection.sigma_range_m, used["rho_true_m"].max() * cfg.detection.sigma_bearing)
    false = used["false_match"].to_numpy()
    # right matches sit on the crater seen (to the rounding of the rotations, ~1e-9 m)
    assert np.all(offset[~false] < 1e-6)
    must_reject = used.filter(pl.Series(false & (offset > 10 * gate_m)))
    assert must_reject.height > 0.99 * false.sum()

    assert (read(runs["plain"], "estimates")["n_rejected"] == 0).all()
    assert (est["status"] == "ok").all()
    for method in METHODS:
        m = est.filter(pl.col("method") == method)
        assert (m["n_rejected"] == m["rejected_ids"].list.len()).all()
        tp = rejected_good = 0
        for frame, ids in m.select("frame", "rejected_ids").iter_rows():
            rejected = Counter(ids)
            frame_used = used.filter(pl.col("frame") == frame)
            assert not rejected - Counter(frame_used["matched_id"].to_list())  # used ids only
            wrong = Counter(frame_used.filter("false_match")["matched_id"].to_list())
            needed = Counter(must_reject.filter(pl.col("frame") == frame)["matched_id"].to_list())
            assert not needed - rejected, (method, frame)  # every far false match rejected
            tp += sum((rejected & wrong).values())
            rejected_good += sum((rejected - wrong).values())
        n_good = int((~false).sum())
        bound = poisson.ppf(0.9999, (1 - cfg.estimation.gate_probability) * n_good)
        assert rejected_good <= bound, (method, rejected_good, bound)
        assert tp + rejected_good == m["n_rejected"].sum()


# --- recording and cache --------------------------------------------------------------------------


def frame_values(df: pl.DataFrame, column: str) -> np.ndarray:
    """One value per row of a reader column (asserting it), stacked."""
    cells = df[column].to_list()
    assert all(cell is not None and len(cell) == 1 for cell in cells), column
    return np.array([cell[0] for cell in cells])


def test_estimation_recording_holds_the_promised_entities(runs):
    store = runs["robust"]
    est = read(store, "estimates")
    path = store.path("estimation.rrd")
    [entry] = rr.chunk.RrdReader(path).recordings()
    assert entry.recording_id == base.recording_id("robust")
    chunks = rr.chunk.RrdReader(path).stream().collect()
    f32_atol_m = (MOON_RADIUS_M + 300e3) * F32_REL
    for method in METHODS:
        m = est.filter(pl.col("method") == method)
        r, q = xyz(m, "r_mci", "_m"), quats(m, "q_mci_from_body")

        pose = chunks.reader(index="frame", contents=f"/world/estimate/{method}").to_polars()
        np.testing.assert_array_equal(pose["frame"].to_numpy(), m["frame"].to_numpy())
        tf = f"/world/estimate/{method}:Transform3D"
        np.testing.assert_allclose(frame_values(pose, f"{tf}:translation"), r, rtol=0,
                                   atol=f32_atol_m)
        np.testing.assert_allclose(frame_values(pose, f"{tf}:quaternion"), q, rtol=0,
                                   atol=2 * F32_REL)

        static = chunks.reader(index=None, contents=f"/world/estimate_path/{method}").to_polars()
        [strip] = static[f"/world/estimate_path/{method}:LineStrips3D:strips"][0].to_list()
        np.testing.assert_allclose(np.array(strip), r, rtol=0, atol=f32_atol_m)

        ell = chunks.reader(index="frame", contents=f"/world/estimate_cov/{method}").to_polars()
        e = f"/world/estimate_cov/{method}:Ellipsoids3D"
        np.testing.assert_allclose(frame_values(ell, f"{e}:centers"), r, rtol=0, atol=f32_atol_m)
        cov = m["cov"].to_numpy().reshape(-1, 6, 6)[:, :3, :3]
        expected = 3 * np.sqrt(np.linalg.eigvalsh(cov)) * estimation.COVARIANCE_SCALE
        np.testing.assert_allclose(np.sort(frame_values(ell, f"{e}:half_sizes"), axis=1),
                                   expected, rtol=1e-6)

        series = chunks.reader(index="frame", contents=f"/estimation/{method}/**").to_polars()
        np.testing.assert_array_equal(series["frame"].to_numpy(), m["frame"].to_numpy())
        for name, column in (("iterations", "iterations"), ("solve_ms", "solve_ms"),
                             ("rejected", "n_rejected")):
            np.testing.assert_array_equal(
                frame_values(series, f"/estimation/{method}/{name}:Scalars:scalars"),
                m[column].cast(pl.Float64).to_numpy())
        status = frame_values(series, f"/estimation/{method}/status:Scalars:scalars")
        np.testing.assert_array_equal(status, 0.0)  # STATUS_CODES["ok"]

        rejected = chunks.reader(index="frame",
                                 contents=f"/world/moon/rejected/{method}").to_polars()
        assert set(rejected["frame"]) == set(m.filter(pl.col("n_rejected") > 0)["frame"])


def test_rejected_markers_are_the_rejected_craters(runs):
    """One marker per rejected crater, at its catalogue (MCMF) position."""
    store = runs["robust"]
    est = read(store, "estimates")
    con = duckdb.connect(store.entry("ingest")["info"]["db_path"], read_only=True)
    try:
        catalogue = con.sql("SELECT crater_id, x_m, y_m, z_m FROM craters").fetchall()
    finally:
        con.close()
    position_of = {cid: np.array(r_mcmf) for cid, *r_mcmf in catalogue}
    chunks = rr.chunk.RrdReader(store.path("estimation.rrd")).stream().collect()
    for method in METHODS:
        m = est.filter(pl.col("method") == method, pl.col("n_rejected") > 0)
        markers = chunks.reader(index="frame",
                                contents=f"/world/moon/rejected/{method}").to_polars()
        assert markers["frame"].to_list() == m["frame"].to_list()
        points = markers[f"/world/moon/rejected/{method}:Points3D:positions"].to_list()
        for (frame, ids), marked in zip(m.select("frame", "rejected_ids").iter_rows(), points,
                                        strict=True):
            assert len(marked) == len(ids), (method, frame, len(marked), len(ids))
            expected = np.array([position_of[i] for i in ids])
            np.testing.assert_allclose(np.sort(np.array(marked), axis=0),
                                       np.sort(expected, axis=0), rtol=0,
                                       atol=MOON_RADIUS_M * F32_REL)


def test_stage_cache_follows_estimation_config_only(workdir, catalogue_db):
    def ran(**sections) -> list[str]:
        return run_stages(config("r", catalogue_db, **sections), RunStore("r").root, PIPELINE)

    assert ran() == list(PIPELINE)
    estimates = Path("runs/r/estimate/estimates.parquet")
    inode = estimates.stat().st_ino
    assert ran() == []  # fresh: skipped
    assert ran(scoring={"final_window_s": 60.0, "table_window": "0-1500 s"}) == []
    assert estimates.stat().st_ino == inode
    assert ran(estimation={"max_iterations": 30}) == ["estimate"]
    assert ran(estimation={"max_iterations": 30, "methods": ["joint"]}) == ["estimate"]
    assert set(read(RunStore("r"), "estimates")["method"]) == {"joint"}
    # the measurement sigmas are the estimators' too: detection and estimation rerun
    assert ran(estimation={"max_iterations": 30, "methods": ["joint"]},
               detection={"sigma_range_m": 5.0}) == ["detect", "estimate"]
