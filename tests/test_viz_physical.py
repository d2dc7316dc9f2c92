"""pipeline.viz.recording for the physical sensor (log_detection with the rim-ellipse and Sun
columns): recordings written from small synthetic tables and read back with rerun's RrdReader.
The Sun's arrow and the lit side's frame (MCI), the Sun's elevation and the ground sample
distance series, the rim ellipses per frame (measured in their state's colour, true in grey, the
largest per frame), the polygons on their ellipses; and a default (paper) detection table that
still gives the old entities only."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import polars as pl
import pytest
import rerun as rr
from test_viz import blueprint_columns, columns, views

from pipeline.core.math import frames, rotations
from pipeline.core.sensors import camera, conics
from pipeline.core.sensors.detection import DetectionModel
from pipeline.viz.rerun import base, detection, ellipses, layout
from pipeline.viz.rerun import sun as rerun_sun
from pipeline.vocab import COUNT_COLORS

R_MOON = 1_737_400.0
SIZE_PX = 1024
COUNTS = [3, 0, 5, 2]  # detections per frame (frame 1 sees none)
F = len(COUNTS)
CAM = "/world/spacecraft/camera"

rr.set_strict_mode(True)


# --- synthetic tables -------------------------------------------------------------------------


def model() -> DetectionModel:
    return DetectionModel(
        fov=camera.FieldOfView.from_config(45.0, "full_angle"), image_size_px=SIZE_PX,
        visibility_a=1.0, visibility_b_per_km=0.0, visibility_diam_unit="km", p_identify=0.9,
        max_craters=None, selection="random", false_match_share=0.0, sigma_bearing=1e-4,
        sigma_range_m=10.0, moon_radius_m=R_MOON)


def trajectory_table() -> pl.DataFrame:
    """Nadir-pointing over the north pole, 100 km down to 70 km."""
    t = np.arange(F) * 10.0
    alt = np.linspace(100e3, 70e3, F)
    return pl.DataFrame({
        "frame": np.arange(F, dtype=np.int32), "t_s": t,
        "r_mci_x_m": np.linspace(0, 30e3, F), "r_mci_y_m": np.zeros(F),
        "r_mci_z_m": R_MOON + alt,
        "q_mci_from_body_x": np.zeros(F), "q_mci_from_body_y": np.ones(F),
        "q_mci_from_body_z": np.zeros(F), "q_mci_from_body_w": np.zeros(F),  # z down (nadir)
        "altitude_m": alt, "theta_m_rad": t * 2.66e-6})


# Per detection of the frames above, in order: identified, used, false match.
FLAGS = [(True, True, False), (True, False, False), (False, False, False),  # frame 0
         (True, True, True), (True, True, False), (True, False, True), (False, False, False),
         (True, True, False),  # frame 2
         (True, True, False), (False, False, False)]  # frame 3
STATE = ["used", "identified", "detected",
         "false_match", "used", "false_match", "detected", "used",
         "used", "detected"]


def detections_table(physical: bool) -> pl.DataFrame:
    """Craters below the spacecraft; with `physical`, the rim ellipses (the measured one off the
    true one by ~0.3 px; detection 6's measured ellipse not finite)."""
    n = sum(COUNTS)
    frame = np.repeat(np.arange(F), COUNTS)
    first = np.repeat(np.cumsum(COUNTS) - COUNTS, COUNTS)
    rng = np.random.default_rng(3)
    u_body = np.column_stack([rng.uniform(-0.2, 0.2, (n, 2)), np.ones(n)])
    u_body /= np.linalg.norm(u_body, axis=1, keepdims=True)
    identified, used, false = (np.array(c) for c in zip(*FLAGS, strict=True))
    c_mci = rng.normal(0, 10e3, (n, 3)) + np.array([0.0, 0.0, R_MOON])
    c_mcmf = frames.mcmf_from_mci(c_mci, trajectory_table()["theta_m_rad"].to_numpy()[frame])
    table = pl.DataFrame({
        "frame": frame.astype(np.int32), "t_s": frame * 10.0,
        "det_index": (np.arange(n) - first).astype(np.int32),
        "crater_id": np.arange(n, dtype=np.int64), "diam_km": rng.uniform(2, 20, n),
        "matched_id": np.arange(n, dtype=np.int64) + 1000 * false,
        **{f"c_matched_mcmf_{c}_m": c_mcmf[:, i] for i, c in enumerate("xyz")},
        **{f"c_true_mcmf_{c}_m": c_mcmf[:, i] for i, c in enumerate("xyz")},
        **{f"u_meas_body_{c}": u_body[:, i] for i, c in enumerate("xyz")},
        "rho_meas_m": np.full(n, 90e3),
        "pixel_u": rng.uniform(100, 900, n), "pixel_v": rng.uniform(100, 900, n),
        "identified": identified, "used": used, "false_match": false})
    if not physical:
        return table
    a = np.array([30.0, 12.0, 8.0, 60.0, 7.0, 20.0, 9.0, 100.0, 15.0, 25.0])
    b = 0.8 * a
    angle = np.linspace(-1.2, 1.4, n)
    u, v = table["pixel_u"].to_numpy(), table["pixel_v"].to_numpy()
    measured_u = u + 0.3
    measured_u[6] = np.nan
    return table.with_columns(
        ellipse_u_px=measured_u, ellipse_v_px=v - 0.2, semi_major_px=a + 0.3,
        semi_minor_px=b - 0.1, ellipse_angle_rad=angle + 0.01,
        true_ellipse_u_px=u, true_ellipse_v_px=v, true_semi_major_px=a, true_semi_minor_px=b,
        true_ellipse_angle_rad=angle, apparent_diam_px=2 * a, rho_size_m=np.full(n, 9e4),
        incidence_deg=np.full(n, 60.0), emission_deg=np.full(n, 10.0),
        phase_deg=np.full(n, 70.0), p_detect=np.full(n, 0.9),
        true_diam_km=table["diam_km"].to_numpy() * 1.01)


def sun_directions() -> np.ndarray:
    """The Sun's unit direction per frame (MCI); the last one along -z (the shortest rotation's
    singular case)."""
    s = np.array([[1.0, 0.0, 0.2], [0.9, 0.3, 0.1], [0.0, 1.0, 0.0], [0.0, 0.0, -1.0]])
    return s / np.linalg.norm(s, axis=1, keepdims=True)


SUN_ELEVATION_DEG = np.array([-5.0, 3.5, 30.0, 44.0])
GSD_M = np.array([120.0, 110.0, 100.0, 90.0])


def frames_table(detections: pl.DataFrame, sun: bool) -> pl.DataFrame:
    counts = detections.group_by("frame").agg(
        pl.len().alias("n_visible"), pl.col("identified").sum().alias("n_identified"),
        pl.col("used").sum().alias("n_used"),
        (pl.col("false_match") & pl.col("identified")).sum().alias("n_false_match"))
    table = (pl.DataFrame({"frame": np.arange(F, dtype=np.int32), "t_s": np.arange(F) * 10.0,
                           "altitude_km": np.linspace(100, 70, F), "d_min_km": np.full(F, 2.0),
                           "n_candidates": np.full(F, 40)})
             .join(counts, on="frame", how="left").fill_null(0).sort("frame")
             .with_columns(pl.col("n_visible", "n_identified", "n_used", "n_false_match")
                           .cast(pl.Int64)))
    if not sun:
        return table
    s = sun_directions()
    return table.with_columns(sun_mci_x=s[:, 0], sun_mci_y=s[:, 1], sun_mci_z=s[:, 2],
                              sun_elevation_deg=SUN_ELEVATION_DEG, gsd_m=GSD_M)


def write(path: Path, physical: bool) -> Path:
    det = detections_table(physical)
    with layout.recording("r", path) as rec:
        detection.log_detection(rec, model(), trajectory_table(), det,
                                frames_table(det, sun=physical))
    return path


@pytest.fixture(scope="module")
def physical_rrd(tmp_path_factory) -> Path:
    return write(tmp_path_factory.mktemp("physical") / "detection.rrd", physical=True)


@pytest.fixture(scope="module")
def paper_rrd(tmp_path_factory) -> Path:
    return write(tmp_path_factory.mktemp("paper") / "detection.rrd", physical=False)


# --- reading back -------------------------------------------------------------------------------


def entities(path: Path) -> set[str]:
    """Every entity with data (temporal or static) in a recording."""
    names = [*columns(path, "/**"), *columns(path, "/**", index=None)]
    return {n.split(":")[0] for n in names if n.startswith("/") and not n.startswith("/__")}


def rgba(color: tuple[int, ...]) -> int:
    """Rerun's packed 0xRRGGBBAA of an RGB(A) colour."""
    r, g, b, *a = color
    return (r << 24) | (g << 16) | (b << 8) | (a[0] if a else 255)


OLD_ENTITIES = {CAM, f"{CAM}/unused", f"{CAM}/used", "/world/frustum", "/world/footprint",
                "/world/moon/unused", "/world/moon/used", "/world/moon/false_matches",
                "/counts/candidates", "/counts/visible", "/counts/identified", "/counts/used",
                "/detection/d_min_km"}
NEW_ENTITIES = {rerun_sun.SUN_ENTITY, rerun_sun.SUNLIGHT_ENTITY,
                f"{rerun_sun.SUNLIGHT_ENTITY}/day_side", f"{rerun_sun.SUNLIGHT_ENTITY}/terminator",
                rerun_sun.SUN_ELEVATION_ENTITY, rerun_sun.GSD_ENTITY,
                f"{ellipses.ELLIPSES_ENTITY}/measured", f"{ellipses.ELLIPSES_ENTITY}/true"}


# --- the Sun ------------------------------------------------------------------------------------


def test_sun_arrow_points_from_the_moon_centre_to_the_sun_per_frame(physical_rrd):
    cols = columns(physical_rrd, rerun_sun.SUN_ENTITY)
    assert cols["frame"] == list(range(F))
    vectors = np.array([v[0] for v in cols[f"{rerun_sun.SUN_ENTITY}:Arrows3D:vectors"]])
    np.testing.assert_allclose(vectors / rerun_sun.SUN_ARROW_LENGTH_M, sun_directions(),
                               atol=1e-6)
    # on the line from the Moon's centre, from where it leaves the surface (the subsolar point)
    origins = np.array([v[0] for v in cols[f"{rerun_sun.SUN_ENTITY}:Arrows3D:origins"]])
    np.testing.assert_allclose(origins / (R_MOON + rerun_sun.SUNLIGHT_LIFT_M), sun_directions(),
                               atol=1e-6)
    static = columns(physical_rrd, rerun_sun.SUN_ENTITY, index=None)
    assert static[f"{rerun_sun.SUN_ENTITY}:Arrows3D:labels"] == [["Sun"]]


def test_lit_side_turns_with_the_sun(physical_rrd):
    base = rerun_sun.SUNLIGHT_ENTITY
    cols = columns(physical_rrd, base)
    q = np.array([v[0] for v in cols[f"{base}:Transform3D:quaternion"]])
    np.testing.assert_allclose(np.linalg.norm(q, axis=1), 1.0, rtol=1e-6)
    # the Sun frame's +z is the Sun's direction in MCI (frame 3: the Sun along -z)
    np.testing.assert_allclose(rotations.dcm_from_q(q)[:, :, 2], sun_directions(), atol=1e-6)
    static = columns(physical_rrd, f"{base}/**", index=None)
    day = np.array(static[f"{base}/day_side:Points3D:positions"][0])
    assert len(day) == rerun_sun.DAY_SIDE_POINTS
    r = np.linalg.norm(day, axis=1)
    np.testing.assert_allclose(r, R_MOON + rerun_sun.SUNLIGHT_LIFT_M, rtol=1e-6)
    assert (day[:, 2] > 0).all()  # the lit hemisphere only
    colors = np.array(static[f"{base}/day_side:Points3D:colors"][0], dtype=np.int64)
    red = colors >> 24
    assert red[np.argmax(day[:, 2])] > red[np.argmin(day[:, 2])]  # brighter under the Sun
    ring = np.array(static[f"{base}/terminator:LineStrips3D:strips"][0][0])
    np.testing.assert_allclose(ring[:, 2], 0.0, atol=1e-6)
    np.testing.assert_allclose(np.hypot(ring[:, 0], ring[:, 1]),
                               R_MOON + rerun_sun.SUNLIGHT_LIFT_M, rtol=1e-6)


def test_sun_elevation_and_ground_sample_distance_series(physical_rrd):
    cols = columns(physical_rrd, "/trajectory/**")
    assert cols["frame"] == list(range(F))
    for entity, expected in ((rerun_sun.SUN_ELEVATION_ENTITY, SUN_ELEVATION_DEG),
                             (rerun_sun.GSD_ENTITY, GSD_M)):
        got = np.array([v[0] for v in cols[f"{entity}:Scalars:scalars"]])
        np.testing.assert_allclose(got, expected)
    names = columns(physical_rrd, "/trajectory/**", index=None)
    assert names[f"{rerun_sun.SUN_ELEVATION_ENTITY}:SeriesLines:names"] == [
        ["Sun elevation at the sub-spacecraft point (deg)"]]
    assert names[f"{rerun_sun.GSD_ENTITY}:SeriesLines:names"] == [
        ["ground sample distance at nadir (m/px)"]]


# --- rim ellipses -------------------------------------------------------------------------------


def test_measured_ellipses_per_frame_in_their_state_colour(physical_rrd):
    entity = f"{ellipses.ELLIPSES_ENTITY}/measured"
    cols = columns(physical_rrd, entity)
    assert cols["frame"] == list(range(F))
    strips = cols[f"{entity}:LineStrips2D:strips"]
    finite = np.ones(sum(COUNTS), bool)
    finite[6] = False  # its measured ellipse is NaN: left out
    frame_of = np.repeat(np.arange(F), COUNTS)
    assert [len(s) for s in strips] == np.bincount(frame_of[finite], minlength=F).tolist()
    expected = [rgba(ellipses.ELLIPSE_STATE_COLORS[s]) for s, ok in zip(STATE, finite,
                                                                             strict=True) if ok]
    got = [c for frame_colors in cols[f"{entity}:LineStrips2D:colors"] for c in frame_colors]
    assert got == expected
    assert ellipses.ELLIPSE_STATE_COLORS == {
        "false_match": COUNT_COLORS["false_match"], "used": COUNT_COLORS["used"],
        "identified": COUNT_COLORS["identified"], "detected": COUNT_COLORS["visible"]}
    # each strip is a closed polygon on its ellipse
    det = detections_table(True).filter(pl.Series(finite))
    conic = conics.conic_from_ellipse(
        np.stack([det["ellipse_u_px"].to_numpy(), det["ellipse_v_px"].to_numpy()], 1),
        det["semi_major_px"].to_numpy(), det["semi_minor_px"].to_numpy(),
        det["ellipse_angle_rad"].to_numpy())
    polygons = [np.array(s) for frame_strips in strips for s in frame_strips]
    segments = ellipses.ellipse_segments(det["semi_major_px"].to_numpy())
    for poly, c, n, a in zip(polygons, conic, segments, det["semi_major_px"], strict=True):
        assert len(poly) == n + 1
        np.testing.assert_array_equal(poly[0], poly[-1])
        h = np.column_stack([poly, np.ones(len(poly))])
        centre = np.array([*np.linalg.solve(c[:2, :2], -c[:2, 2]), 1.0])
        # conic value relative to the centre's: 0 on the ellipse (float32 points)
        np.testing.assert_allclose(np.einsum("ni,ij,nj->n", h, c, h) / (centre @ c @ centre),
                                   0.0, atol=2e-4 * max(1.0, 100.0 / a))


def test_true_ellipses_are_grey_and_thin_under_the_measured_ones(physical_rrd):
    entity = f"{ellipses.ELLIPSES_ENTITY}/true"
    cols = columns(physical_rrd, entity)
    assert [len(s) for s in cols[f"{entity}:LineStrips2D:strips"]] == COUNTS  # under the cap
    static = columns(physical_rrd, f"{ellipses.ELLIPSES_ENTITY}/**", index=None)
    assert static[f"{entity}:LineStrips2D:colors"] == [[rgba(ellipses.TRUE_ELLIPSE_COLOR)]]
    thin, thick = (static[f"{ellipses.ELLIPSES_ENTITY}/{k}:LineStrips2D:radii"][0][0]
                   for k in ("true", "measured"))
    assert thin < 0 and thick < 0 and abs(thin) < abs(thick)  # UI points
    order = {k: static[f"{ellipses.ELLIPSES_ENTITY}/{k}:LineStrips2D:draw_order"][0][0]
             for k in ("true", "measured")}
    assert order["true"] < order["measured"]


def test_true_ellipses_keep_the_largest_per_frame(tmp_path):
    det = detections_table(True)
    path = tmp_path / "capped.rrd"
    with layout.recording("r", path) as rec:
        ellipses.log_rim_ellipses(rec, det, frames_table(det, sun=True), true_per_frame=2)
    entity = f"{ellipses.ELLIPSES_ENTITY}/true"
    strips = columns(path, entity)[f"{entity}:LineStrips2D:strips"]
    assert [len(s) for s in strips] == [2, 0, 2, 2]
    # frame 2's two largest: a = 100 and 60 px (detections 7 and 3); a polygon's vertices
    # (uniform in the parameter, the closing one left out) average to its ellipse's centre
    centres = sorted(tuple(np.array(s)[:-1].mean(axis=0)) for s in strips[2])
    expected = sorted((det["true_ellipse_u_px"][i], det["true_ellipse_v_px"][i]) for i in (3, 7))
    np.testing.assert_allclose(centres, expected, atol=1e-3)


def test_ellipses_sent_in_several_batches_are_the_same(tmp_path, physical_rrd, monkeypatch):
    monkeypatch.setattr(ellipses, "STRIP_POINTS_PER_SEND", 40)  # a frame or two per send
    det = detections_table(True)
    path = tmp_path / "batches.rrd"
    with layout.recording("r", path) as rec:
        ellipses.log_rim_ellipses(rec, det, frames_table(det, sun=True))
    for kind in ("measured", "true"):
        entity = f"{ellipses.ELLIPSES_ENTITY}/{kind}"
        assert columns(path, entity) == columns(physical_rrd, entity)


def test_fewer_segments_for_small_ellipses():
    n = ellipses.ellipse_segments(np.array([0.0, 3.0, 7.0, 20.0, 60.0, 1e4, np.nan]))
    assert n.tolist()[0] == n.tolist()[1] == ellipses.ELLIPSE_SEGMENTS[0]
    assert n[-2] == ellipses.ELLIPSE_SEGMENTS[1] and n[-1] == ellipses.ELLIPSE_SEGMENTS[0]
    assert (np.diff(n[:-1]) >= 0).all()
    a = np.array([7.0, 20.0, 60.0])
    sag = a * (1 - np.cos(np.pi / n[2:5]))  # the chords' largest distance to the ellipse
    assert (sag <= ellipses.ELLIPSE_TOLERANCE_PX + 1e-12).all()


# --- the default (paper) run ----------------------------------------------------------------------


def test_paper_detections_keep_the_old_entities_only(paper_rrd, physical_rrd):
    assert entities(paper_rrd) == OLD_ENTITIES
    assert entities(physical_rrd) == OLD_ENTITIES | NEW_ENTITIES
    assert not rerun_sun.has_sun(frames_table(detections_table(False), sun=False))
    assert not ellipses.has_rim_ellipses(detections_table(False))


def test_camera_points_are_crater_discs_without_ellipses_and_dots_with_them(paper_rrd,
                                                                           physical_rrd):
    entity = f"{CAM}/unused"
    det = detections_table(False).filter(~pl.col("used"))
    disc_px = (det["diam_km"] * 500.0 / det["rho_meas_m"]).to_numpy() * model().k[0, 0]
    paper = [r for frame_radii in columns(paper_rrd, entity)[f"{entity}:Points2D:radii"]
             for r in frame_radii]
    assert len(paper) > 0
    np.testing.assert_allclose(paper, disc_px, rtol=1e-6)  # scene units: the crater's size
    dots = [r for frame_radii in columns(physical_rrd, entity)[f"{entity}:Points2D:radii"]
            for r in frame_radii]
    np.testing.assert_array_equal(dots, -ellipses.BEARING_DOT_UI)  # UI points


def test_layout_has_the_sun_and_gsd_plots_without_new_origins(tmp_path):
    path = tmp_path / "layout.rbl"
    layout.blueprint().save(base.APP_ID, path)
    by_name = {v["name"][0]: v for v in views(blueprint_columns(path)).values() if "name" in v}
    sun = by_name["Sun elevation at the sub-spacecraft point (deg)"]
    gsd = by_name["ground sample distance (m/px)"]
    assert sun["contents"] == [rerun_sun.SUN_ELEVATION_ENTITY]
    assert gsd["contents"] == [rerun_sun.GSD_ENTITY]
    assert sun["origin"] == gsd["origin"] == ["/trajectory"]


def test_no_nan_reaches_the_recording_from_false_detections(tmp_path):
    """A false detection has no true crater (NaN size and true point): its points are
    left out of the 3D views, its camera dot drawn at the UI size; no NaN is logged (the viewer
    warned "Found NaN radius in entity /world/moon/visible")."""
    det = detections_table(True)
    false = np.arange(det.height) % 5 == 0
    det = det.with_columns(
        diam_km=pl.when(pl.Series(false)).then(np.nan).otherwise(pl.col("diam_km")),
        **{c: pl.when(pl.Series(false)).then(np.nan).otherwise(pl.col(c))
           for c in ("c_true_mcmf_x_m", "c_true_mcmf_y_m", "c_true_mcmf_z_m")})
    path = tmp_path / "detection.rrd"
    with layout.recording("r", path) as rec:
        detection.log_detection(rec, model(), trajectory_table(), det,
                                frames_table(det, sun=True))
    for entity, kind in (("/world/moon/unused", "Points3D"), ("/world/moon/used", "Points3D"),
                         (f"{CAM}/unused", "Points2D")):
        cols = columns(path, entity)
        for part in ("radii", "positions"):
            values = np.array([v for row in cols[f"{entity}:{kind}:{part}"] for v in row],
                              dtype=float)
            assert values.size and np.isfinite(values).all(), (entity, part)
    unused = columns(path, "/world/moon/unused")["/world/moon/unused:Points3D:positions"]
    real_unused = ~false & ~det["used"].to_numpy()
    assert sum(len(row) for row in unused) == int(real_unused.sum())
