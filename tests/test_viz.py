"""pipeline.viz: recordings written from small synthetic tables (the plots' entities, one unit per
plot, the NEES reference lines, the covariance scale), the layout (the 3D eye on the spacecraft),
the catalogue recording, the errors by number of craters used, the study's numbers, the `view`
command without a display, and a headless screenshot that is not empty (slow)."""

from __future__ import annotations

import json
import subprocess
from pathlib import Path

import numpy as np
import polars as pl
import pytest
import rerun as rr
from scipy.stats import chi2

from pipeline.io.catalogue import build_catalogue
from pipeline.ops.score import by_craters_used
from pipeline.studies import suslu2025
from pipeline.viz import viewer
from pipeline.viz.report import figures, md_tables, run_report
from pipeline.viz.rerun import base, estimation, layout, rendered, trajectory, world
from pipeline.vocab import METHODS, QUANTITIES, STATE_DIM, STATUS_CODES

R_MOON = 1_737_400.0
N = 12  # frames


# --- synthetic tables -------------------------------------------------------------------------


def trajectory_table(n: int = N) -> pl.DataFrame:
    """A straight descent over the north pole: altitude 120 km down to 10 km."""
    t = np.arange(n) * 10.0
    alt = np.linspace(120e3, 10e3, n)
    r = np.stack([np.linspace(0, 50e3, n), np.zeros(n), R_MOON + alt], 1)
    return pl.DataFrame({
        "frame": np.arange(n, dtype=np.int32), "t_s": t,
        **{f"r_mci_{c}_m": r[:, i] for i, c in enumerate("xyz")},
        "v_mci_x_m_s": np.full(n, 1600.0), "v_mci_y_m_s": np.zeros(n),
        "v_mci_z_m_s": np.full(n, -50.0),
        "q_mci_from_body_x": np.zeros(n), "q_mci_from_body_y": np.ones(n),
        "q_mci_from_body_z": np.zeros(n), "q_mci_from_body_w": np.zeros(n),  # z down (nadir)
        "altitude_m": alt, "theta_m_rad": t * 2.66e-6})


def estimates_table(traj: pl.DataFrame) -> pl.DataFrame:
    """Both methods; frame 3 has too few craters, the joint method's frame 7 did not converge."""
    rows = []
    for method in ("paper", "joint"):
        for row in traj.iter_rows(named=True):
            f = row["frame"]
            status = "too_few_craters" if f == 3 else (
                "not_converged" if (method, f) == ("joint", 7) else "ok")
            ok = status == "ok"
            cov = np.diag([4.0, 9.0, 16.0, 1e-10, 1e-10, 1e-10]) * (1 + f)
            rows.append({
                "frame": f, "t_s": row["t_s"], "method": method, "status": status,
                **{f"r_mci_{c}_m": row[f"r_mci_{c}_m"] + (1.0 if ok else np.nan) for c in "xyz"},
                **{f"q_mci_from_body_{c}": row[f"q_mci_from_body_{c}"] for c in "xyzw"},
                "cov": (cov if ok else np.full((6, 6), np.nan)).ravel().tolist(),
                "n_used": 0 if f == 3 else 3 + 20 * f, "n_rejected": f % 2,
                "rejected_det_index": [], "iterations": 3 + f % 4, "solve_ms": 0.2 + 0.01 * f})
    return pl.DataFrame(rows).with_columns(
        pl.col("cov").cast(pl.Array(pl.Float64, 36)),
        pl.col("rejected_det_index").cast(pl.List(pl.Int32)))


def scores_table(est: pl.DataFrame) -> pl.DataFrame:
    rng = np.random.default_rng(1)
    ok = (est["status"] == "ok").to_numpy()
    cols = {}
    for q in QUANTITIES:
        scale = 2.0 if q.unit == "m" else 1e-3
        cols[f"err_{q.name}"] = np.where(ok, rng.normal(0, scale, est.height), np.nan)
        cols[f"sigma_{q.name}"] = np.where(ok, scale, np.nan)
        cols[f"crlb_{q.name}"] = np.full(est.height, scale)
    return est.select("method", "frame", "t_s", "status", "n_used").with_columns(
        **cols, nees=np.where(ok, rng.chisquare(STATE_DIM, est.height), np.nan))


@pytest.fixture(scope="module")
def tables():
    traj = trajectory_table()
    est = estimates_table(traj)
    return traj, est, scores_table(est)


def log_trajectory(rec, traj) -> None:
    trajectory.log_trajectory(
        rec, traj["frame"].to_numpy(), traj["t_s"].to_numpy(),
        np.stack([traj[f"r_mci_{c}_m"].to_numpy() for c in "xyz"], 1),
        np.stack([traj[f"v_mci_{c}_m_s"].to_numpy() for c in "xyz"], 1),
        np.stack([traj[f"q_mci_from_body_{c}"].to_numpy() for c in "xyzw"], 1),
        traj["theta_m_rad"].to_numpy(), traj["altitude_m"].to_numpy())


def columns(path: Path, contents: str, index: str | None = "frame") -> dict[str, list]:
    """Arrow columns of `contents` (the blueprint-free recording store) as Python lists."""
    table = rr.chunk.RrdReader(path).stream().collect().reader(
        index=index, contents=contents).to_arrow_table()
    return {name: table.column(name).to_pylist() for name in table.column_names}


def series(cols: dict[str, list], entity: str) -> np.ndarray:
    return np.array([np.nan if v is None else v[0] for v in cols[f"{entity}:Scalars:scalars"]])


# --- recordings ---------------------------------------------------------------------------------


def test_trajectory_plots_altitude_and_speed_apart(tmp_path, tables):
    traj = tables[0]
    path = tmp_path / "trajectory.rrd"
    with layout.recording("r", path) as rec:
        log_trajectory(rec, traj)
    cols = columns(path, "/trajectory/**")
    np.testing.assert_allclose(series(cols, "/trajectory/altitude_km"),
                               traj["altitude_m"].to_numpy() / 1e3)
    np.testing.assert_allclose(series(cols, "/trajectory/speed_m_s"),
                               np.hypot(1600.0, 50.0) * np.ones(N))
    labels = columns(path, "/world/spacecraft/axes", index=None)
    assert all(len(s) <= 3 for s in labels["/world/spacecraft/axes:Arrows3D:labels"][0])
    # the 3D view's chase frame and the body axes shrink with the altitude
    expected = np.maximum(traj["altitude_m"].to_numpy(), 2e3) / 150e3
    np.testing.assert_allclose(world.chase_scale(traj["altitude_m"].to_numpy()), expected)
    for entity in (world.CHASE_ENTITY, "/world/spacecraft/axes"):
        scale = columns(path, entity)[f"{entity}:Transform3D:scale"]
        np.testing.assert_allclose([v[0] for v in scale], expected[:, None] * np.ones(3))


def test_estimation_status_iterations_and_solve_time_are_separate_series(tmp_path, tables):
    traj, est, _ = tables
    path = tmp_path / "estimation.rrd"
    with layout.recording("r", path) as rec:
        estimation.log_estimation(rec, est, pl.DataFrame(
            schema={"frame": pl.Int32, "det_index": pl.Int32, "c_matched_mcmf_x_m": pl.Float64,
                    "c_matched_mcmf_y_m": pl.Float64, "c_matched_mcmf_z_m": pl.Float64,
                    "diam_km": pl.Float64}),
            traj)
    for method in ("paper", "joint"):
        m = est.filter(pl.col("method") == method)
        for status, frames in m.group_by("status"):
            entity = f"/estimation/status/{method}/{status[0]}"
            cols = columns(path, entity)
            assert cols["frame"] == sorted(frames["frame"].to_list())
            np.testing.assert_array_equal(series(cols, entity), STATUS_CODES[status[0]])
            names = columns(path, entity, index=None)[f"{entity}:SeriesPoints:names"]
            assert names == [[f"{method}: {status[0]} ({STATUS_CODES[status[0]]})"]]
        cols = columns(path, f"/estimation/{method}/**")
        np.testing.assert_array_equal(series(cols, f"/estimation/{method}/iterations"),
                                      m["iterations"].to_numpy())
        np.testing.assert_allclose(series(cols, f"/estimation/{method}/solve_ms"),
                                   m["solve_ms"].to_numpy())
        np.testing.assert_array_equal(series(cols, f"/estimation/{method}/status"),
                                      [STATUS_CODES[s] for s in m["status"]])
    # no status of a method that never had it
    assert columns(path, "/estimation/status/paper/not_converged")["frame"] == []


def test_covariance_ellipsoids_shrink_with_altitude(tmp_path, tables):
    traj, est, _ = tables
    np.testing.assert_allclose(estimation.covariance_scale([300e3, 100e3, 10e3, 1e3, 50.0]),
                               [1000.0, 1000.0, 100.0, 10.0, 1.0])
    path = tmp_path / "estimation.rrd"
    with layout.recording("r", path) as rec:
        estimation.log_estimation(rec, est.filter(pl.col("method") == "paper"), pl.DataFrame(
            schema={"frame": pl.Int32, "det_index": pl.Int32, "c_matched_mcmf_x_m": pl.Float64,
                    "c_matched_mcmf_y_m": pl.Float64, "c_matched_mcmf_z_m": pl.Float64,
                    "diam_km": pl.Float64}),
            traj)
    cols = columns(path, "/world/estimate_cov/paper")
    ok = est.filter((pl.col("method") == "paper") & (pl.col("status") == "ok"))
    scale = estimation.covariance_scale(traj["altitude_m"].to_numpy()[ok["frame"].to_numpy()])
    half = np.array([np.sort(np.array(v[0])) for v in
                     cols["/world/estimate_cov/paper:Ellipsoids3D:half_sizes"]])
    sigma = np.sqrt(np.array([[4.0, 9.0, 16.0]]) * (1 + ok["frame"].to_numpy()[:, None]))
    np.testing.assert_allclose(half, 3 * sigma * scale[:, None], rtol=1e-6)


def test_scoring_has_errors_and_nees_with_its_reference_lines(tmp_path, tables):
    scores = tables[2]
    path = tmp_path / "scoring.rrd"
    with layout.recording("r", path) as rec:
        estimation.log_scoring(rec, scores)
    cols = columns(path, "/consistency/**")
    assert cols["frame"] == list(range(N))
    lo, hi = chi2.ppf([0.025, 0.975], STATE_DIM)
    np.testing.assert_array_equal(series(cols, "/consistency/reference/expected"), STATE_DIM)
    np.testing.assert_allclose(series(cols, "/consistency/reference/chi2_lower"), lo)
    np.testing.assert_allclose(series(cols, "/consistency/reference/chi2_upper"), hi)
    paper = scores.filter(pl.col("method") == "paper")
    np.testing.assert_array_equal(series(cols, "/consistency/paper/nees"),
                                  paper["nees"].to_numpy())
    err = columns(path, "/errors/position/x/**")
    np.testing.assert_array_equal(series(err, "/errors/position/x/paper"),
                                  paper["err_x_m"].to_numpy())
    np.testing.assert_array_equal(series(err, "/errors/position/x/crlb_3sigma_upper"),
                                  3 * paper["crlb_x_m"].to_numpy())


def _p99_best(scores: pl.DataFrame, column: str) -> float:
    """The smallest per-method 99th percentile of |error| over the `ok` estimates."""
    ok = scores.filter(pl.col("status") == "ok")
    return min(float(np.nanpercentile(np.abs(g[column].to_numpy()), 99))
               for _, g in ok.group_by("method"))


def test_error_ranges_follow_the_data_not_a_fixed_zoom(tables):
    scores = tables[2]
    big = scores.with_columns(pl.col("err_y_m") * 150.0)  # a real catalogue's 30-400 m errors
    r = estimation.error_ranges(big)
    p99 = _p99_best(big, "err_y_m")
    assert r["y_m"] == pytest.approx((-1.5 * p99, 1.5 * p99))
    assert r["y_m"][1] > 100.0 > r["x_m"][1]


def test_error_ranges_follow_the_best_method_not_the_worst(tables):
    # from pixels: the paper method kilometres off, the joint metres; the plot keeps the joint
    scores = tables[2]
    assert set(scores["method"].unique()) >= {"paper", "joint"}
    worse = scores.with_columns(pl.when(pl.col("method") == "paper").then(pl.col("err_x_m") * 1e3)
                                .otherwise(pl.col("err_x_m")).alias("err_x_m"))
    r = estimation.error_ranges(worse)
    joint = worse.filter((pl.col("method") == "joint") & (pl.col("status") == "ok"))
    p99_joint = float(np.nanpercentile(np.abs(joint["err_x_m"].to_numpy()), 99))
    crlb = 3.0 * float(np.nanmedian(worse["crlb_x_m"].to_numpy()))
    assert r["x_m"][1] == pytest.approx(1.5 * max(p99_joint, crlb))
    paper = worse.filter(pl.col("method") == "paper")
    assert np.nanpercentile(np.abs(paper["err_x_m"].to_numpy()), 50) > 10 * r["x_m"][1]


def test_catalogue_recording_is_static_with_its_own_recording_id(tmp_path):
    rng = np.random.default_rng(0)
    xyz = rng.normal(size=(500, 3))
    xyz *= R_MOON / np.linalg.norm(xyz, axis=1, keepdims=True)
    diam = rng.uniform(1, 50, 500)
    db = tmp_path / "catalogue" / "craters.duckdb"
    path = world.log_catalogue(base.catalogue_recording_path(db), xyz, diam, "craters")
    assert path == tmp_path / "catalogue" / "craters.rrd"
    [entry] = rr.chunk.RrdReader(path).recordings()
    assert entry.application_id == base.APP_ID
    assert entry.recording_id == base.catalogue_recording_id("craters")
    assert not list(tmp_path.glob("catalogue/.tmp-*"))
    static = columns(path, "/world/moon/**", index=None)
    points = np.array(static["/world/moon/craters:Points3D:positions"][0])
    np.testing.assert_allclose(points, xyz, rtol=1e-6)
    assert "/world/moon/surface:Ellipsoids3D:half_sizes" in static


# --- layout -------------------------------------------------------------------------------------


def blueprint_columns(path: Path) -> dict[str, list]:
    reader = rr.chunk.RrdReader(path)
    [bp] = reader.blueprints()
    table = reader.stream(store=bp).collect().reader(index="blueprint",
                                                     contents="/**").to_arrow_table()
    return {name: [v for v in table.column(name).to_pylist() if v is not None]
            for name in table.column_names}


def views(cols: dict[str, list]) -> dict[str, dict[str, object]]:
    """View id -> {name, origin, contents}."""
    out: dict[str, dict[str, object]] = {}
    for name, values in cols.items():
        if not name.startswith("/view/") or not values:
            continue
        view_id = name.split("/")[2].split(":")[0]
        for key, suffix in (("name", ":ViewBlueprint:display_name"),
                            ("origin", ":ViewBlueprint:space_origin"),
                            ("contents", ":ViewContents:query")):
            if name.endswith(suffix):
                out.setdefault(view_id, {})[key] = values[0]
    return out


def test_layout_has_one_unit_per_plot_and_the_eye_on_the_spacecraft(tmp_path):
    path = tmp_path / "layout.rbl"
    layout.blueprint().save(base.APP_ID, path)
    cols = blueprint_columns(path)
    by_name = {v["name"][0]: v for v in views(cols).values()}
    for name, contents in (("altitude (km)", ["/trajectory/altitude_km"]),
                           ("speed (m/s)", ["/trajectory/speed_m_s"]),
                           ("status (code)", ["/estimation/status/**"]),
                           ("iterations", [f"/estimation/{m}/iterations" for m in METHODS]),
                           ("solve time (ms)", [f"/estimation/{m}/solve_ms" for m in METHODS]),
                           ("candidates (tile query)", ["/counts/candidates"])):
        assert by_name[name]["contents"] == contents, name
    assert "/counts/candidates" not in by_name["craters per frame"]["contents"]
    # the rendered images and their rims have a view of their own (`just view images`)
    assert by_name["rendered image (px)"]["origin"] == [rendered.IMAGE_ENTITY]
    three_d = by_name["3D: spacecraft and footprint (body frame)"]
    assert three_d["origin"] == [world.CHASE_ENTITY]
    assert three_d["contents"] == ["/world/**", "- /world/spacecraft/camera/**"]
    eye = {k.rsplit(":", 1)[1]: v[0] for k, v in cols.items() if ":EyeControls3D:" in k}
    assert eye["position"] == [list(layout.EYE_POSITION_BODY_M)]
    assert eye["look_target"] == [list(layout.EYE_TARGET_BODY_M)]
    assert eye["eye_up"] == [[0.0, 0.0, -1.0]]


def test_layout_with_data_ranges_fixes_the_error_axes(tmp_path, tables):
    ranges = estimation.error_ranges(tables[2])
    path = tmp_path / "layout.rbl"
    layout.blueprint(ranges).save(base.APP_ID, path)
    cols = blueprint_columns(path)
    got = sorted(tuple(v[0][0]) for k, v in cols.items() if k.endswith("ScalarAxis:range"))
    for q in QUANTITIES:
        assert tuple(ranges[q.name]) in got
    # readable with polars too (no cursor-relative time ranges in this form)
    reader = rr.chunk.RrdReader(path)
    [bp] = reader.blueprints()
    reader.stream(store=bp).collect().reader(index="blueprint", contents="/**").to_polars()


# --- report -------------------------------------------------------------------------------------


def test_by_craters_used_on_a_hand_made_table():
    nan = np.nan
    scores = pl.DataFrame({
        "method": ["paper"] * 6 + ["joint"] * 2,
        "frame": [0, 1, 2, 3, 4, 5, 0, 1],
        "t_s": [0.0, 1, 2, 3, 4, 5, 0, 1],
        "status": ["too_few_craters", "ok", "ok", "ok", "ok", "ok", "ok", "ok"],
        "n_used": [2, 3, 5, 8, 250, 300, 4, 9],
        **{f"err_{q.name}": [nan, 3.0, -4.0, 1.0, 0.1, -0.3, 6.0, 2.0] for q in QUANTITIES},
        **{f"crlb_{q.name}": [nan, 2.0, 2.0, 1.0, 0.1, 0.1, 2.0, 1.0] for q in QUANTITIES},
        **{f"sigma_{q.name}": [nan, 2.0, 2.0, 1.0, 0.1, 0.1, 2.0, 1.0] for q in QUANTITIES},
        "nees": [nan, 5.0, 7.0, 6.0, 4.0, 8.0, 3.0, 9.0]})
    t = by_craters_used(scores).filter(pl.col("quantity") == "x_m")
    rows = {(r["method"], r["craters"]): r for r in t.iter_rows(named=True)}
    assert list(rows) == [("paper", "0-2"), ("paper", "3-5"), ("paper", "6-10"),
                          ("paper", ">200"), ("joint", "3-5"), ("joint", "6-10")]
    r = rows[("paper", "0-2")]
    assert (r["frames"], r["estimated"]) == (1, 0) and np.isnan(r["rmse"])
    r = rows[("paper", "3-5")]
    assert (r["frames"], r["estimated"], r["n_min"], r["n_max"]) == (2, 2, 3, 5)
    assert r["rmse"] == pytest.approx(np.sqrt((9 + 16) / 2))
    assert r["median_abs"] == pytest.approx(3.5)
    assert r["crlb_rms"] == pytest.approx(2.0)
    assert r["ratio_to_crlb"] == pytest.approx(np.sqrt(12.5) / 2)
    assert r["median_ratio"] == pytest.approx(1.75)
    assert r["mean_nees"] == pytest.approx(6.0)
    r = rows[("paper", ">200")]
    assert (r["frames"], r["n_max"]) == (2, None)
    assert r["rmse"] == pytest.approx(np.sqrt((0.01 + 0.09) / 2))
    assert r["median_abs"] == pytest.approx(0.2)
    assert r["ratio_to_crlb"] == pytest.approx(np.sqrt(0.05) / 0.1)
    assert rows[("joint", "6-10")]["rmse"] == pytest.approx(2.0)
    md = md_tables.craters_used_table(by_craters_used(scores))
    assert "| paper | 3-5 | 2 | 2 | 3.54 / 3.5 (1.77) |" in md
    assert "| paper | 0-2 | 1 | 0 | - |" in md


def test_report_figures_of_craters_used_and_counts(tmp_path, tables):
    scores = tables[2]
    figures.fig_craters_used(by_craters_used(scores), tmp_path / "f.png", "t")
    assert (tmp_path / "f.png").read_bytes()[:4] == b"\x89PNG"
    frames = pl.DataFrame({"t_s": np.arange(0, 3000, 100.0), "n_visible": np.arange(30) * 20,
                           "n_identified": np.arange(30) * 17, "n_used": np.arange(30) * 15,
                           "altitude_km": np.linspace(300, 0, 30)})
    figures.fig_counts(frames, tmp_path / "c.png", "t")
    facts = run_report.count_facts(frames)
    assert "paper: < 150 before 1,500 s" in facts and "max visible craters in start-1,500 s: 280" \
        in facts


def test_study_holds_the_papers_numbers():
    s = suslu2025.STUDY
    assert s.table1[None]["x_m"] == 0.6111 and s.table1[10]["psi_deg"] == 0.0066
    assert s.table1[50]["theta_deg"] == 0.0025 and set(s.table1) == {10, 20, 50, 100, 200, None}
    assert [(w.figure, w.start_s, w.end_s) for w in s.cap_figure_windows] == [
        ("7", 0.0, 1500.0), ("8", 1800.0, 2400.0)]
    assert [r.value for r in s.count_refs] == [150.0, 900.0]
    assert s.table_window == (1800.0, 2400.0)


# --- viewer -------------------------------------------------------------------------------------


def write_run(root: Path, tables, run: str = "r") -> tuple[Path, Path]:
    """A run with committed trajectory and score stages (their recordings) and an ingest stage
    whose catalogue.json names a catalogue recording beside catalogue/craters.duckdb."""
    from pipeline.io.store import RunStore

    traj, _, scores = tables
    rng = np.random.default_rng(0)
    xyz = rng.normal(size=(20_000, 3))
    xyz *= R_MOON / np.linalg.norm(xyz, axis=1, keepdims=True)
    cat = world.log_catalogue(root / "catalogue" / "craters.rrd", xyz,
                                  rng.uniform(1, 30, len(xyz)), "craters")
    db = root / "catalogue" / "craters.duckdb"
    build_catalogue("synthetic", db_path=db, key="catalogue-key", min_diam_km=100.0)
    store = RunStore(run, root / "runs")
    with store.lock():
        tx = store.begin("ingest", "k", {}, "c", "h")
        tx.output("catalogue.json").write_text(json.dumps(
            {"db_path": str(db), "key": "catalogue-key", "recording": str(cat)}))
        tx.commit()
        tx = store.begin("trajectory", "k", {}, "c", "h")
        with layout.recording(run, tx.output("trajectory.rrd")) as rec:
            log_trajectory(rec, traj)
        tx.commit()
        tx = store.begin("score", "k", {}, "c", "h")
        with layout.recording(run, tx.output("scoring.rrd")) as rec:
            estimation.log_scoring(rec, scores)
        tx.commit()
    return store.run_dir, cat


def test_view_finds_the_runs_recordings_and_the_catalogue(workdir, tables):
    run_dir, cat = write_run(workdir, tables)
    found_dir, files, catalogue = viewer.run_recordings("r")
    assert found_dir.resolve() == run_dir.resolve()
    assert [f.name for f in files] == ["scoring.rrd", "trajectory.rrd"]
    assert catalogue.resolve() == cat.resolve()
    args = viewer.viewer_args(files, catalogue)
    assert args[:2] == ["--asset", str(catalogue)] and args[2:] == [str(f) for f in files]


def test_view_without_a_display_says_to_use_screenshot(workdir, tables, monkeypatch, capsys):
    from pipeline import cli

    write_run(workdir, tables)
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    monkeypatch.setattr(cli.os, "execv", lambda *a: pytest.fail("the viewer was started"))
    monkeypatch.setattr("sys.argv", ["crater-nav", "view", "r"])
    with pytest.raises(SystemExit) as exc:
        cli.main()
    assert exc.value.code == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--screenshot" in err[0] and "no display" in err[0]


def test_headless_screenshot_is_not_empty(workdir, tables):
    """The real viewer, headless, with the software Vulkan driver (about 3 s on 2 cores; not
    marked slow)."""
    if not viewer.vulkan_available():
        pytest.skip("no Vulkan driver (Debian: apt-get install mesa-vulkan-drivers libvulkan1)")
    import matplotlib.image

    write_run(workdir, tables)
    _, files, catalogue = viewer.run_recordings("r")
    out = workdir / "shot.png"
    shot = viewer.screenshot(files, out, catalogue=catalogue, timeout_s=90)
    assert shot.frame == (N - 1) // 2 and shot.frames == (0, N - 1)
    image = matplotlib.image.imread(out)
    assert image.shape[:2] == (viewer.WINDOW_SIZE[1], viewer.WINDOW_SIZE[0])
    assert image[..., :3].std() > 0.02  # not one colour
    assert len(np.unique(image[..., :3].reshape(-1, 3)[::97], axis=0)) > 50
    # the viewer's process group is gone
    left = subprocess.run(["pgrep", "-f", f"rerun --headless.*{out.parent}"],
                          capture_output=True, text=True)
    assert left.stdout.strip() == ""




def test_images_scale_their_bits_to_the_jpeg(tmp_path):
    """An image quantised to 12 bits is shown at its grey level, not at 1/16 of it."""
    import io

    from PIL import Image

    from pipeline.viz import images

    for bits in (8, 12, 16):
        grey = np.full((32, 32), round(0.5 * (2**bits - 1)),
                       dtype=np.uint8 if bits == 8 else np.uint16)
        jpeg = images.encode_jpeg(grey, 16, bits)
        assert jpeg[:2] == b"\xff\xd8"
        level = np.asarray(Image.open(io.BytesIO(jpeg)), dtype=float)
        assert level.shape == (16, 16) and abs(level.mean() - 127.5) < 2.0, (bits, level.mean())
