"""Stage `score`: scores.parquet recomputed independently from the upstream tables (errors, 1-sigma,
NEES, the CRLB of the craters used, true positions under false matches), the window summary,
report.md and its figures, scoring.rrd, the layout blueprint, the cache and the headline.

Runs: the default descent from 1,400 s to impact (3,000 s) every 50 s (32 frames), over a 5 km
synthetic catalogue: 100-170 craters used per frame up to ~2,400 s, a handful near 2,750 s (where
some frames fail) and none in the last 150 s. So every scoring window holds frames, one of them a
mix of frames with and without an estimate, and one has no estimate at all.
"""

from __future__ import annotations

import struct
from pathlib import Path

import duckdb
import numpy as np
import polars as pl
import pytest
import rerun as rr
from conftest import run_stages, small_config
from scipy.spatial.transform import Rotation

from pipeline.config import RunConfig
from pipeline.core.estimation import estimators
from pipeline.core.math import frames
from pipeline.io.store import RunStore
from pipeline.io.tables import quats, xyz
from pipeline.ops import detection_columns
from pipeline.ops.score import true_used_positions
from pipeline.stages import score
from pipeline.viz.rerun import base as rerun_base
from pipeline.vocab.tables import SCORES, SUMMARY

WINDOW = {"start_s": 1400.0, "end_s": "none", "frame_rate_hz": 0.02}
N_FRAMES = 32
METHODS = ("paper", "joint")
FALSE_MATCHES = {"false_match_share": 0.2}
WINDOWS = {"0-1500 s": (0.0, 1500.0), "1500-2850 s": (1500.0, 2850.0),
           "1800-2400 s": (1800.0, 2400.0)}  # and "last 150 s", from the impact time
# An extra window from the crater-rich 2,400 s to the craterless end: estimates in some frames only.
EXTRA_WINDOW = {"name": "2400-3000 s", "start_s": 2400.0, "end_s": 3000.0}

POSITION = ("x_m", "y_m", "z_m")
ATTITUDE = ("phi_deg", "theta_deg", "psi_deg")
ATTITUDE_MCI = ("phi_mci_deg", "theta_mci_deg", "psi_mci_deg")
# Tolerances. A DCM entry after a quaternion round trip and a product is exact to a few ulp; 1e-14
# bounds it, and the tiny error angles read off it inherit that absolutely (~6e-13 deg).
DCM_ROUNDING = 1e-14
ANGLE_ATOL_DEG = np.degrees(DCM_ROUNDING)
# Statistics recomputed in another order of summation: a few ulp relative.
STAT_RTOL = 1e-12
PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


def config(run_id: str, db: Path, **sections) -> RunConfig:
    return small_config(run_id, db, WINDOW, **sections)


class Run:
    def __init__(self, cfg: RunConfig, store: RunStore):
        self.cfg, self.store = cfg, store

    def read(self, name: str) -> pl.DataFrame:
        return pl.read_parquet(self.store.path(f"{name}.parquet"))


def run(run_id: str, db: Path, root: Path = Path("runs"), **sections) -> Run:
    cfg = config(run_id, db, **sections)
    store = RunStore(run_id, root)
    run_stages(cfg, store.root)
    return Run(cfg, store)


class _Runs(dict):
    """The read-only runs, each made the first time a test asks for it."""

    def __init__(self, make: dict[str, object]) -> None:
        super().__init__()
        self._make = make

    def __missing__(self, name: str) -> Run:
        self[name] = self._make[name]()  # type: ignore[operator]
        return self[name]


@pytest.fixture(scope="module")
def runs(tmp_path_factory, catalogue_db) -> dict[str, Run]:
    """Read-only runs: clean; 20 % false matches (robust estimators: plain ones flag such frames
    `inconsistent`) with an extra scoring window; a cap of 2 craters (no estimate anywhere).
    Made when first asked for: the last two only by the slow tests."""
    root = tmp_path_factory.mktemp("runs")
    windows = [{"name": k, "start_s": a, "end_s": b} for k, (a, b) in WINDOWS.items()]
    return _Runs({
        "clean": lambda: run("clean", catalogue_db, root),
        "false": lambda: run("false", catalogue_db, root, detection=FALSE_MATCHES,
                             estimation={"robust": True},
                             scoring={"windows": [*windows, EXTRA_WINDOW]}),
        "cap2": lambda: run("cap2", catalogue_db, root, detection={"max_craters": 2})})


def truth_of(r: Run, table: pl.DataFrame) -> pl.DataFrame:
    """The trajectory row of each row of `table` (by frame), in the same order."""
    t = r.read("trajectory")
    return table.select("frame").join(t, on="frame", how="left", maintain_order="left")


def dcms(q: np.ndarray) -> np.ndarray:
    return Rotation.from_quat(q).as_matrix()


def angles_321_deg(dcm: np.ndarray) -> np.ndarray:
    """(phi, theta, psi) (deg) of R = Rz(psi) Ry(theta) Rx(phi), read off the matrices."""
    return np.degrees(np.stack([np.arctan2(dcm[:, 2, 1], dcm[:, 2, 2]),
                                -np.arcsin(np.clip(dcm[:, 2, 0], -1, 1)),
                                np.arctan2(dcm[:, 1, 0], dcm[:, 0, 0])], axis=1))


def columns(table: pl.DataFrame, names) -> np.ndarray:
    return np.stack([table[n].to_numpy() for n in names], axis=1)


# --- scores.parquet -------------------------------------------------------------------------------


def test_scores_have_one_row_per_method_and_frame(runs):
    r = runs["clean"]
    scores, est, traj = r.read("scores"), r.read("estimates"), r.read("trajectory")
    assert dict(scores.schema) == SCORES.columns()
    assert scores.height == N_FRAMES * len(METHODS) == traj.height * len(METHODS)
    for method in METHODS:
        m = scores.filter(pl.col("method") == method)
        assert m.select("frame", "t_s").equals(traj.select("frame", "t_s"))
    # status, n_used and cap come from the estimates, row for row
    assert scores.select("method", "frame", "status", "n_used", "cap").equals(
        est.select("method", "frame", "status", "n_used", "cap"))
    statuses = set(scores["status"])
    assert "ok" in statuses and len(statuses) > 1  # the run has frames without an estimate
    con = duckdb.connect(str(r.store.duckdb_path), read_only=True)
    try:
        assert con.sql("SELECT * FROM scores").pl().equals(scores)
        assert con.sql("SELECT * FROM summary").pl().equals(r.read("summary"))
    finally:
        con.close()
    entry = r.store.entry("score")
    assert set(entry["outputs"]) >= {"scores.parquet", "summary.parquet",
                                     "by_craters_used.parquet"}
    assert set(entry["visuals"]) >= {"scoring.rrd", "layout.rbl", "report.md"}
    assert set(entry["tables"]) == {"scores", "summary", "by_craters_used", "navigation_summary",
                                    "identification"}


@pytest.mark.parametrize("name", ["clean", pytest.param("false", marks=pytest.mark.slow)])
def test_errors_are_the_estimates_minus_the_truth(runs, name):
    """From estimates.parquet and trajectory.parquet: position errors (m, MCI), the 3-2-1 angles of
    R_true^T R_est and of R_est R_true^T (deg, read off the matrices), the methods' 1-sigma and
    NEES; NaN where a frame has no estimate."""
    r = runs[name]
    est, scores = r.read("estimates"), r.read("scores")
    truth = truth_of(r, est)
    ok = (est["status"] == "ok").to_numpy()
    assert ok.sum() > 0.8 * est.height and not ok.all()

    dr = xyz(est, "r_mci", "_m") - xyz(truth, "r_mci", "_m")
    np.testing.assert_array_equal(columns(scores, [f"err_{q}" for q in POSITION]), dr)
    assert np.isnan(dr[~ok]).all() and np.isfinite(dr[ok]).all()

    dcm_true, dcm_est = dcms(quats(truth, "q_mci_from_body")[ok]), dcms(
        quats(est, "q_mci_from_body")[ok])
    body = angles_321_deg(np.swapaxes(dcm_true, 1, 2) @ dcm_est)
    mci = angles_321_deg(dcm_est @ np.swapaxes(dcm_true, 1, 2))
    np.testing.assert_allclose(columns(scores, [f"err_{q}" for q in ATTITUDE])[ok], body,
                               rtol=0, atol=ANGLE_ATOL_DEG)
    np.testing.assert_allclose(columns(scores, [f"err_{q}" for q in ATTITUDE_MCI])[ok], mci,
                               rtol=0, atol=ANGLE_ATOL_DEG)
    assert np.isnan(columns(scores, [f"err_{q}" for q in ATTITUDE + ATTITUDE_MCI])[~ok]).all()

    cov = est["cov"].to_numpy().reshape(-1, 6, 6)
    sigma = np.sqrt(np.diagonal(cov, axis1=1, axis2=2)) * [1, 1, 1, *[np.degrees(1.0)] * 3]
    np.testing.assert_array_equal(columns(scores, [f"sigma_{q}" for q in POSITION + ATTITUDE]),
                                  sigma)

    # NEES of the 6x6 covariance with the body rotation vector, solved on the correlation matrix
    # (the covariance mixes m^2 and rad^2): solve and inverse agree to ~cond(C) ulp
    dtheta = (Rotation.from_quat(quats(truth, "q_mci_from_body")[ok]).inv()
              * Rotation.from_quat(quats(est, "q_mci_from_body")[ok])).as_rotvec()
    e = np.hstack([dr[ok], dtheta])
    d = np.sqrt(np.diagonal(cov[ok], axis1=1, axis2=2))
    corr = cov[ok] / d[:, :, None] / d[:, None, :]
    z = e / d
    nees = np.einsum("ni,nij,nj->n", z, np.linalg.inv(corr), z)
    rtol = 10 * np.finfo(float).eps * np.linalg.cond(corr).max()
    np.testing.assert_allclose(scores["nees"].to_numpy()[ok], nees, rtol=rtol)
    nees_pos = np.einsum("ni,nij,nj->n", dr[ok], np.linalg.inv(cov[ok, :3, :3]), dr[ok])
    np.testing.assert_allclose(scores["nees_position"].to_numpy()[ok], nees_pos,
                               rtol=10 * np.finfo(float).eps * np.linalg.cond(
                                   cov[ok, :3, :3]).max())
    assert scores.filter(~pl.Series(ok))["nees"].is_nan().all()


def crlb_sigmas(r_mci: np.ndarray, q: np.ndarray, c: np.ndarray, cfg: RunConfig) -> np.ndarray:
    """sqrt(diag(CRLB)) in the scores' units, then the attitude about MCI axes (deg)."""
    bound = estimators.crlb(r_mci, q, c, sigma_bearing=cfg.detection.sigma_bearing,
                            sigma_range_m=cfg.detection.sigma_range_m)
    sigma = np.sqrt(np.diag(bound))
    dcm = dcms(q)
    att_mci = dcm @ bound[3:, 3:] @ dcm.T
    return np.r_[sigma[:3], np.degrees(sigma[3:]), np.degrees(np.sqrt(np.diag(att_mci)))]


CRLB_COLUMNS = [f"crlb_{q}" for q in POSITION + ATTITUDE + ATTITUDE_MCI]


def test_crlb_is_that_of_the_used_craters_at_the_true_pose(runs):
    r = runs["clean"]
    scores, traj = r.read("scores"), r.read("trajectory")
    used = detection_columns.with_derived(r.read("detections"), traj).filter("used")
    n_used = used.group_by("frame").len()
    few = n_used.filter(pl.col("len") >= 3).sort("len")["frame"][0]  # the least information
    frames = [traj["frame"][0], traj["frame"][N_FRAMES // 2], few, traj["frame"][-1]]
    for frame in frames:
        t = traj.filter(pl.col("frame") == frame)
        c = xyz(used.filter(pl.col("frame") == frame), "c_mci", "_m")
        rows = scores.filter(pl.col("frame") == frame)
        got = columns(rows, CRLB_COLUMNS)
        if c.shape[0] < 3:
            assert np.isnan(got).all()
            continue
        expected = crlb_sigmas(xyz(t, "r_mci", "_m")[0], quats(t, "q_mci_from_body")[0], c, r.cfg)
        for row in got:  # the bound depends on the craters, not on the method
            np.testing.assert_allclose(row, expected, rtol=STAT_RTOL)
    assert traj["frame"][-1] not in n_used["frame"]  # the last frame has no used crater


@pytest.mark.slow  # the false-match run
def test_false_matches_get_the_bound_of_the_craters_actually_seen(runs, catalogue_db):
    """With false matches, c_mci is the wrong crater's position; the CRLB must use the crater
    actually seen: its catalogue position (by crater_id, MCMF) turned into MCI by Rz(theta_m),
    which is also where the true bearing and range point from the true pose."""
    r = runs["false"]
    traj = r.read("trajectory")
    detections = r.read("detections").join(traj.select("frame", "theta_m_rad"), on="frame")
    used = detections.filter("used")
    false = used["false_match"].to_numpy()
    assert false.sum() > 0.1 * used.height

    con = duckdb.connect(str(catalogue_db), read_only=True)
    try:
        cat = con.sql("SELECT crater_id, x_m, y_m, z_m FROM craters").pl()
    finally:
        con.close()
    seen = used.select("crater_id").join(cat, on="crater_id", how="left", maintain_order="left")
    theta = used["theta_m_rad"].to_numpy()
    cos, sin = np.cos(theta), np.sin(theta)
    x, y, z = (seen[c].to_numpy() for c in ("x_m", "y_m", "z_m"))
    c_true = np.stack([cos * x - sin * y, sin * x + cos * y, z], axis=1)

    got = true_used_positions(detections, score.catalogue_lookup(catalogue_db), physical=False)
    # float64 rotations of ~1.7e6 m vectors: a few ulp (2.3e-10 m each)
    np.testing.assert_allclose(got, c_true, rtol=0, atol=1e-8)
    c_mci = detection_columns.matched_positions_mci(used, traj)
    np.testing.assert_array_equal(got[~false], c_mci[~false])
    assert np.linalg.norm(got[false] - c_mci[false], axis=1).min() > 1.0
    pose = truth_of(r, used)
    # the stored truth's point is the crater seen (false matches included), and so is where the
    # true bearing and range derived from it point from the true pose
    np.testing.assert_allclose(
        frames.mci_from_mcmf(xyz(used, "c_true_mcmf", "_m"), theta), c_true, rtol=0, atol=1e-8)
    seen = detection_columns.with_derived(used, traj)
    los = dcms(quats(pose, "q_mci_from_body")) @ xyz(seen, "u_true_body", "")[:, :, None]
    np.testing.assert_allclose(
        xyz(pose, "r_mci", "_m") + los[:, :, 0] * seen["rho_true_m"].to_numpy()[:, None], c_true,
        rtol=0, atol=1e-6)

    scores = r.read("scores").filter(pl.col("method") == "paper")
    frames_with_false = used.filter("false_match")["frame"].unique().sort()[:3]
    for frame in frames_with_false:
        in_frame = (used["frame"] == frame).to_numpy()
        t = traj.filter(pl.col("frame") == frame)
        r_true, q_true = xyz(t, "r_mci", "_m")[0], quats(t, "q_mci_from_body")[0]
        got_row = columns(scores.filter(pl.col("frame") == frame), CRLB_COLUMNS)[0]
        np.testing.assert_allclose(got_row, crlb_sigmas(r_true, q_true, c_true[in_frame], r.cfg),
                                   rtol=STAT_RTOL)
        wrong = crlb_sigmas(r_true, q_true, c_mci[in_frame], r.cfg)
        assert not np.allclose(got_row, wrong, rtol=1e-6, atol=0)


# --- summary.parquet ------------------------------------------------------------------------------


def expected_summary(scores: pl.DataFrame, windows: dict[str, tuple[float, float]]
                     ) -> dict[tuple[str, str, str], dict]:
    """Per (method, window, quantity), the window statistics computed here from the scores."""
    out = {}
    for method in METHODS:
        m = scores.filter(pl.col("method") == method)
        t = m["t_s"].to_numpy()
        for name, (a, b) in windows.items():
            inside = (t >= a) & (t < b)
            sel = inside & (m["status"] == "ok").to_numpy()
            nees = m["nees"].to_numpy()[sel]
            for q in POSITION + ATTITUDE:
                err = m[f"err_{q}"].to_numpy()[sel]
                crlb = m[f"crlb_{q}"].to_numpy()[sel]
                rmse = np.sqrt(np.mean(err**2)) if sel.any() else np.nan
                crlb_rms = np.sqrt(np.mean(crlb**2)) if sel.any() else np.nan
                out[method, name, q] = {
                    "start_s": a, "end_s": b, "rmse": rmse,
                    "max_abs": np.abs(err).max() if sel.any() else np.nan,
                    "p95_abs": np.percentile(np.abs(err), 95) if sel.any() else np.nan,
                    "crlb_rms": crlb_rms, "ratio_to_crlb": rmse / crlb_rms,
                    "share_estimated": sel.sum() / inside.sum(),
                    "mean_nees": nees.mean() if sel.any() else np.nan,
                    "frames": int(inside.sum())}
    return out


@pytest.mark.parametrize("name", ["clean", pytest.param("false", marks=pytest.mark.slow),
                                  pytest.param("cap2", marks=pytest.mark.slow)])
def test_summary_windows_and_statistics(runs, name):
    r = runs[name]
    scores, summary = r.read("scores"), r.read("summary")
    assert summary.columns == list(SUMMARY.columns())
    t_impact = r.store.entry("trajectory")["info"]["t_impact_s"]
    assert abs(t_impact - 3000.0) < 1e-3  # the default descent's solved impact time
    windows = {w.name: (w.start_s, w.end_s) for w in r.cfg.scoring.windows}
    assert windows.items() >= WINDOWS.items()
    windows["last 150 s"] = (t_impact - 150.0, t_impact)
    expected = expected_summary(scores, windows)
    assert summary.height == len(expected)
    for row in summary.iter_rows(named=True):
        want = expected[row["method"], row["window"], row["quantity"]]
        for key, value in want.items():
            np.testing.assert_allclose(row[key], value, rtol=STAT_RTOL, atol=0,
                                       err_msg=f"{row['method']} {row['window']} {key}")
    assert all(v["frames"] > 0 for v in expected.values())
    share = {(m, w): v["share_estimated"] for (m, w, _), v in expected.items()}
    if name != "cap2":
        assert share["paper", "1800-2400 s"] == share["joint", "1800-2400 s"] == 1.0
        assert share["paper", "last 150 s"] == share["joint", "last 150 s"] == 0.0
    if name == "false":  # frames without an estimate count in the share, not in the RMSE
        assert 0 < share["paper", "2400-3000 s"] < 1 and 0 < share["joint", "2400-3000 s"] < 1
    if name == "cap2":  # no estimate anywhere
        assert set(share.values()) == {0.0}
        stats = summary.select("rmse", "max_abs", "p95_abs", "crlb_rms", "mean_nees")
        assert np.isnan(stats.to_numpy()).all()
        assert (r.read("scores")["status"] == "too_few_craters").all()


def test_the_last_window_is_the_last_150_s_before_impact(runs):
    """[t_impact - 150, t_impact): with frames every 50 s and impact at ~3,000 s the window holds
    the frames from ~2,850 s on; the 1500-2850 s window stops before 2,850 s."""
    r = runs["clean"]
    summary, t_s = r.read("summary"), r.read("trajectory")["t_s"].to_numpy()
    t_impact = r.store.entry("trajectory")["info"]["t_impact_s"]
    for method in METHODS:
        row = summary.filter(pl.col("window") == "last 150 s",
                             pl.col("method") == method).row(0, named=True)
        assert (row["start_s"], row["end_s"]) == (t_impact - 150.0, t_impact)
        assert row["frames"] == np.sum(t_s >= t_impact - 150.0) >= 2
        mid = summary.filter(pl.col("window") == "1500-2850 s",
                             pl.col("method") == method).row(0, named=True)
        assert mid["frames"] == 27  # 1,500 ... 2,800 s


# --- report.md ------------------------------------------------------------------------------------


def png_size(path: Path) -> tuple[int, int]:
    data = path.read_bytes()
    assert data[:8] == PNG_MAGIC and data[12:16] == b"IHDR"
    return struct.unpack(">II", data[16:24])


def fmt(x: float) -> str:
    """report._fmt's format, restated."""
    if not np.isfinite(x):
        return "-"
    return f"{x:.3g}" if abs(x) >= 1e-3 else f"{x:.2e}"


def test_report_lists_the_figures_and_tables(runs):
    r = runs["clean"]
    text = r.store.path("report.md").read_text()
    # figsize (9, 4.2) and (9, 7.5) inches at 110 dpi
    for name, size in (("fig4_craters.png", (990, 462)), ("fig5_position_errors.png", (990, 825)),
                       ("fig6_attitude_errors.png", (990, 825))):
        assert f"]({name})" in text
        assert png_size(r.store.path(name)) == size
    summary = r.read("summary")
    for (method, window), g in summary.group_by("method", "window", maintain_order=True):
        first = g.row(0, named=True)
        rmse = dict(zip(g["quantity"], g["rmse"], strict=True))
        line = (f"| {method} | {window} | {first['frames']} | {first['share_estimated']:.1%} | "
                + " | ".join(fmt(rmse[q]) for q in POSITION + ATTITUDE)
                + f" | {fmt(first['mean_nees'])} |")
        assert line in text, line
    window = r.cfg.scoring.table_window
    assert f"## Against the Cramér-Rao bound ({window})" in text
    for row in summary.filter(pl.col("window") == window).iter_rows(named=True):
        assert (f"| {row['method']} | {row['quantity']} | {fmt(row['rmse'])} | "
                f"{fmt(row['crlb_rms'])} | {row['ratio_to_crlb']:.3f} |") in text
    assert "no limit" in text and "false matches\n0%" in text


# --- scoring.rrd and layout.rbl -------------------------------------------------------------------


def scalars(chunks, entity: str, index: str = "frame") -> pl.DataFrame:
    """The time index and one float per row of a scalar series."""
    df = chunks.reader(index=index, contents=entity).to_polars()
    cells = df[f"{entity}:Scalars:scalars"].to_list()
    assert all(cell is not None and len(cell) == 1 for cell in cells), entity
    return pl.DataFrame({index: df[index], "value": [cell[0] for cell in cells]})


def test_scoring_recording_holds_errors_bounds_and_nees_per_frame(runs):
    r = runs["clean"]
    scores = r.read("scores")
    path = r.store.path("scoring.rrd")
    [entry] = rr.chunk.RrdReader(path).recordings()
    assert (entry.application_id, entry.recording_id) == (rerun_base.APP_ID,
                                                          rerun_base.recording_id("clean"))
    chunks = rr.chunk.RrdReader(path).stream().collect()
    crlb_source = scores.filter(pl.col("method") == METHODS[0])
    for method in METHODS:
        m = scores.filter(pl.col("method") == method)
        frame = m["frame"].cast(pl.Int64).to_numpy()
        series = {"/consistency/{m}/nees": m["nees"]}
        for kind, qs in (("position", POSITION), ("attitude", ATTITUDE)):
            for q in qs:
                base = f"/errors/{kind}/{q.split('_')[0]}"
                series[f"{base}/{{m}}"] = m[f"err_{q}"]
                series[f"{base}/{{m}}_3sigma_upper"] = 3 * m[f"sigma_{q}"]
                series[f"{base}/{{m}}_3sigma_lower"] = -3 * m[f"sigma_{q}"]
                series[f"{base}/crlb_3sigma_upper"] = 3 * crlb_source[f"crlb_{q}"]
                series[f"{base}/crlb_3sigma_lower"] = -3 * crlb_source[f"crlb_{q}"]
        for template, values in series.items():
            entity = template.format(m=method)
            logged = scalars(chunks, entity)
            np.testing.assert_array_equal(logged["frame"].to_numpy(), frame, err_msg=entity)
            np.testing.assert_array_equal(logged["value"].to_numpy(), values.to_numpy(),
                                          err_msg=entity)  # float64 scalars, NaN where undefined
    nees_t = scalars(chunks, "/consistency/joint/nees", index="sim_time")["sim_time"]
    np.testing.assert_array_equal(nees_t.dt.total_nanoseconds().to_numpy() / 1e9,
                                  scores.filter(pl.col("method") == "joint")["t_s"].to_numpy())


def test_layout_is_a_blueprint_with_the_error_and_consistency_views(runs):
    reader = rr.chunk.RrdReader(runs["clean"].store.path("layout.rbl"))
    assert reader.recordings() == []
    [blueprint] = reader.blueprints()
    assert blueprint.application_id == rerun_base.APP_ID
    df = reader.stream(store=blueprint).collect().reader(index="blueprint",
                                                         contents="/**").to_polars()
    origins = {cell[0] for c in df.columns if c.endswith("ViewBlueprint:space_origin")
               for cell in df[c].drop_nulls().to_list()}
    expected = {f"/errors/position/{a}" for a in "xyz"} | {
        f"/errors/attitude/{a}" for a in ("phi", "theta", "psi")} | {
        "/consistency", "/world", "/world/spacecraft/camera", "/world/spacecraft/chase",
        "/counts", "/trajectory", "/estimation", "/navigation/nees", "/navigation/nis_per_dof",
        "/navigation/nees_total", "/navigation/position_error_norm_m",
        "/navigation/bias/gyro_deg_h", "/navigation/bias/accel_milli_g", "/imu/body_rate_deg_s",
        "/altimeter/slant_range_km", "/imu/true_bias/gyro_deg_h", "/imu/true_bias/accel_milli_g",
        "/navigation/updates/craters", "/navigation/updates", "/navigation/status",
        "/identification", "/camera_image"} | {
        f"/navigation/errors/{q}/{a}" for q in ("position_m", "velocity_m_s", "attitude_deg")
        for a in "xyz"}
    assert origins == expected


# --- cache and headline ---------------------------------------------------------------------------


@pytest.mark.slow
def test_score_reruns_when_scoring_changes_and_is_skipped_otherwise(workdir, catalogue_db):
    def ran(**sections) -> list[str]:
        return run_stages(config("r", catalogue_db, **sections), RunStore("r").root)

    assert ran() == ["ingest", "trajectory", "imu", "detect", "estimate", "navigate", "score"]
    scores = Path("runs/r/score/scores.parquet")
    inode = scores.stat().st_ino
    assert ran() == []
    assert scores.stat().st_ino == inode
    changed = {"final_window_s": 60.0, "table_window": "0-1500 s"}
    assert ran(scoring=changed) == ["score"]
    summary = pl.read_parquet("runs/r/score/summary.parquet")
    assert set(summary["window"]) == {*WINDOWS, "last 60 s"}
    assert ran(scoring=changed) == []
    assert ran(scoring=changed, estimation={"max_iterations": 30}) == ["estimate", "navigate",
                                                                       "score"]
    assert run_stages(config("r", catalogue_db, scoring=changed,
                             estimation={"max_iterations": 30}), RunStore("r").root,
                      force=["score"]) == ["score"]


def test_headline_names_the_run_its_numbers_and_how_to_look(runs):
    r = runs["clean"]
    text = score.headline(r.cfg, r.store)
    lines = text.splitlines()
    assert str(r.store.run_dir) in lines[0]
    assert lines[-1].startswith("look at it: just view clean")
    summary = r.read("summary").filter(pl.col("window") == "1800-2400 s")
    for method in METHODS:
        rmse = dict(summary.filter(pl.col("method") == method).select("quantity", "rmse")
                    .iter_rows())
        [line] = [ln for ln in lines if ln.strip().startswith(f"{method} RMSE 1800-2400 s")]
        for label, q, digits in (("X", "x_m", 3), ("Y", "y_m", 3), ("Z", "z_m", 3),
                                 ("phi", "phi_deg", 5), ("theta", "theta_deg", 5),
                                 ("psi", "psi_deg", 5)):
            assert f"{label} {rmse[q]:.{digits}f}" in line, (line, q)
