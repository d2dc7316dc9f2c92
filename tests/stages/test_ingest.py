"""Stage `ingest`: real catalogues, a USGS-style Robbins file with bad rows, failures that keep the
previous catalogue, the stage's cache and recording, and read-only SQL over the result."""

from __future__ import annotations

import csv
import datetime as dt
import hashlib
import io
import json
import math
from pathlib import Path

import healpy as hp
import numpy as np
import polars as pl
import pytest
import rerun as rr
from conftest import REPO, query, run_stages, shared_file
from typer.testing import CliRunner

from pipeline.cli import app
from pipeline.config import load_config, to_dict
from pipeline.errors import StageInputError
from pipeline.io.catalogue import CatalogueError
from pipeline.io.catalogue.db import run_catalogue_db
from pipeline.io.store import RunStore
from pipeline.stages import ingest
from pipeline.viz.rerun import base

R_M = 1_737_400.0
COLUMNS = ["crater_id", "source_id", "lat_deg", "lon_deg", "diam_km", "x_m", "y_m", "z_m", "tile",
           "source"]
DEFAULT_TOML = str(REPO / "runs" / "scenarios" / "default.toml")
SMALL = {"synthetic_min_diam_km": 20.0}  # ~7,000 synthetic craters


# --- helpers --------------------------------------------------------------------------------------


def build(source: Path | str, db_path: Path, **catalogue) -> dict:
    """Ingest `source` into `db_path` without a run (the stage's build step)."""
    cfg = load_config(DEFAULT_TOML, "t", {"catalogue": {"source": str(source),
                                                        "db_path": str(db_path), **catalogue}})
    return ingest.build(cfg, "test-key")


def craters(db_path: Path) -> pl.DataFrame:
    """The craters table in storage order."""
    return query(db_path, "SELECT * FROM craters ORDER BY rowid")


def meta(db_path: Path) -> dict:
    return query(db_path, "SELECT * FROM catalogue_meta").to_dicts()[0]


def assert_conventions(table: pl.DataFrame, order: int = 6) -> None:
    """Columns, wrapped longitudes, MCMF on the 1737.4 km sphere, tiles, rows ordered by tile."""
    assert table.columns == COLUMNS
    lat, lon = table["lat_deg"].to_numpy(), table["lon_deg"].to_numpy()
    x, y, z = (table[c].to_numpy() for c in ("x_m", "y_m", "z_m"))
    assert np.all((lon >= -180.0) & (lon < 180.0))
    assert np.all(np.abs(lat) <= 90.0)
    assert np.all(table["diam_km"].to_numpy() > 0)
    np.testing.assert_allclose(np.sqrt(x**2 + y**2 + z**2), R_M, rtol=1e-12)
    lat_r, lon_r = np.radians(lat), np.radians(lon)
    np.testing.assert_allclose(x, R_M * np.cos(lat_r) * np.cos(lon_r), rtol=0, atol=1e-6)
    np.testing.assert_allclose(y, R_M * np.cos(lat_r) * np.sin(lon_r), rtol=0, atol=1e-6)
    np.testing.assert_allclose(z, R_M * np.sin(lat_r), rtol=0, atol=1e-6)
    tiles = table["tile"].to_numpy()
    np.testing.assert_array_equal(tiles, hp.ang2pix(2**order, lon, lat, lonlat=True, nest=True))
    assert np.all(np.diff(tiles) >= 0)
    assert table["crater_id"].n_unique() == table.height


def assert_position(row: dict, lat_deg: float, lon_deg: float) -> None:
    """One crater's stored position against a scalar evaluation of the formula."""
    la, lo = math.radians(lat_deg), math.radians(lon_deg)
    assert row["lat_deg"] == pytest.approx(lat_deg, abs=1e-12)
    assert row["lon_deg"] == pytest.approx(lon_deg, abs=1e-9)
    assert row["x_m"] == pytest.approx(R_M * math.cos(la) * math.cos(lo), abs=1e-6)
    assert row["y_m"] == pytest.approx(R_M * math.cos(la) * math.sin(lo), abs=1e-6)
    assert row["z_m"] == pytest.approx(R_M * math.sin(la), abs=1e-6)


def by_crater_id(table: pl.DataFrame, crater_id: int) -> dict:
    return table.filter(pl.col("crater_id") == crater_id).row(0, named=True)


def sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


# --- the real catalogues --------------------------------------------------------------------------


@pytest.mark.slow
def test_lu1319381(tmp_path):
    path = shared_file("lu1319381_partial.parquet")
    db = tmp_path / "lu.duckdb"
    m = build(path, db)
    assert (m["rows_read"], m["rows_kept"], m["rows_rejected"]) == (1_319_381, 731_819, 587_562)
    assert m["format"] == "lu1319381" and m["sha256"] == sha256(path)
    stored = meta(db)
    assert (stored["rows_read"], stored["rows_kept"], stored["rows_rejected"]) == (
        1_319_381, 731_819, 587_562)
    assert Path(stored["source_path"]) == path.resolve()
    assert stored["healpix_order"] == 6 and stored["generator_seed"] is None

    reasons = query(db, "SELECT reason, count(*) AS n FROM rejects GROUP BY reason")
    assert reasons.height == 1 and reasons["n"][0] == 587_562
    assert "diameter" in reasons["reason"][0] and "diam_km" in reasons["reason"][0]

    table = craters(db)
    assert table.height == 731_819
    assert_conventions(table)
    source = pl.read_parquet(path).with_row_index("crater_id", offset=1)
    known = source.filter(pl.col("diam_km").is_not_null())
    labels = {0: "lu1319381:wang_wu", 1: "lu1319381:robbins2018", 2: "lu1319381:head2010"}
    want = {labels[code]: n for code, n in known.group_by("source").len().iter_rows()}
    assert dict(table.group_by("source").len().iter_rows()) == want
    assert len(want) == 3
    joined = table.join(known, on="crater_id", how="inner", suffix="_src")
    assert joined.height == 731_819  # crater_id is the source row number
    assert (joined["source_id"] == joined["id"].cast(pl.String)).all()
    np.testing.assert_array_equal(joined["diam_km"], joined["diam_km_src"].cast(pl.Float64))


def test_robbins_ge20km_csv_wraps_longitudes(tmp_path):
    path = shared_file("robbins2018_ge20km.csv")
    db = tmp_path / "robbins.duckdb"
    m = build(path, db)
    assert (m["format"], m["rows_read"], m["rows_kept"], m["rows_rejected"]) == (
        "robbins2018_ge20km", 6_973, 6_973, 0)
    table = craters(db)
    assert_conventions(table)
    # first data row: -19.8304, 264.757 (0..360), 940.96 km -> lon -95.243
    first = by_crater_id(table, 1)
    assert_position(first, -19.8304, -95.243)
    assert first["diam_km"] == 940.96
    assert_position(by_crater_id(table, 3), 57.0866, 82.0995)  # below 180: unchanged
    raw = pl.read_csv(path)
    lon_360 = raw["lon"].to_numpy()[table["crater_id"].to_numpy() - 1]
    assert lon_360.max() > 180 and lon_360.min() >= 0
    dlon = (table["lon_deg"].to_numpy() - lon_360 + 180.0) % 360.0 - 180.0
    np.testing.assert_allclose(dlon, 0.0, atol=1e-9)


def test_robbins_parquet_twin_gives_the_same_craters(tmp_path):
    build(shared_file("robbins2018_ge20km.csv"), tmp_path / "a.duckdb")
    from_csv = craters(tmp_path / "a.duckdb")
    m = build(shared_file("robbins2018_ge20km.parquet"), tmp_path / "b.duckdb")
    assert (m["format"], m["rows_kept"], m["rows_rejected"]) == (
        "robbins2018_ge20km_parquet", 6_973, 0)
    from_pq = craters(tmp_path / "b.duckdb")
    assert_conventions(from_pq)
    a = from_csv.sort("crater_id")
    b = from_pq.sort("crater_id")
    assert a["crater_id"].to_list() == b["crater_id"].to_list()
    f32 = 2.0**-24  # the Parquet twin stores float32: half an ulp, relative
    for col in ("lat_deg", "diam_km"):
        x, y = a[col].to_numpy(), b[col].to_numpy()
        assert np.all(np.abs(x - y) <= f32 * np.abs(y) + 1e-12), col
    dlon = (a["lon_deg"].to_numpy() - b["lon_deg"].to_numpy() + 180.0) % 360.0 - 180.0
    assert np.all(np.abs(dlon) <= f32 * np.abs(b["lon_deg"].to_numpy()) + 1e-9)


def test_head2010_cr_only_line_endings(tmp_path):
    path = shared_file("head2010_ge20km.csv")
    assert b"\n" not in path.read_bytes()  # the case under test: CR-only endings
    db = tmp_path / "head.duckdb"
    m = build(path, db)
    assert (m["format"], m["rows_read"], m["rows_kept"], m["rows_rejected"]) == (
        "head2010", 5_185, 5_185, 0)
    table = craters(db)
    assert_conventions(table)
    lines = path.read_bytes().decode().split("\r")
    first, last = lines[1].split(","), [ln for ln in lines if ln][-1].split(",")
    for crater_id, (lon, lat, diam) in ((1, first), (5_185, last)):
        row = by_crater_id(table, crater_id)
        assert_position(row, float(lat), float(lon))
        assert row["diam_km"] == float(diam)


def test_povilaitis2018_messy_header_quoted_newline_and_tags(tmp_path):
    path = shared_file("povilaitis2018_5to20km.csv")
    db = tmp_path / "pov.duckdb"
    m = build(path, db)
    assert (m["format"], m["rows_read"], m["rows_kept"], m["rows_rejected"]) == (
        "povilaitis2018", 19_335, 19_335, 0)
    table = craters(db)
    assert_conventions(table)
    assert table["source_id"].n_unique() == 19_335

    records = list(csv.DictReader(io.StringIO(path.read_text(), newline="")))
    assert len(records) == 19_335
    quoted = [i for i, r in enumerate(records) if "\n" in r["tag"]]
    assert len(quoted) == 1
    # the record with the newline and the one after it: one row each, numbered by record
    for i in (quoted[0], quoted[0] + 1):
        rec = records[i]
        row = by_crater_id(table, i + 1)
        assert row["source_id"] == rec[""]
        assert_position(row, float(rec["Lat"]), float(rec["Long"]))
        assert row["diam_km"] == float(rec["Diameter (km)"])
    tagged = {r[""] for r in records if "?" in r["tag"]}
    assert len(tagged) > 4_000
    assert tagged <= set(table["source_id"].to_list())


# --- a USGS-style Robbins (2018) file -------------------------------------------------------------

USGS_HEADER = ("CRATER_ID,LAT_CIRC_IMG,LON_CIRC_IMG,LAT_ELLI_IMG,LON_ELLI_IMG,DIAM_CIRC_IMG,"
               "DIAM_CIRC_SD_IMG,DIAM_ELLI_MAJOR_IMG,DIAM_ELLI_MINOR_IMG,DIAM_ELLI_ECCEN_IMG,"
               "DIAM_ELLI_ELLIP_IMG,DIAM_ELLI_ANGLE_IMG,ARC_IMG,PTS_RIM_IMG")


def usgs_line(crater_id: str, lat: str, lon: str, diam: str) -> str:
    """A record with the circle fit given and plausible ellipse columns."""
    return f"{crater_id},{lat},{lon},{lat},{lon},{diam},0.1,{diam},{diam},0.2,1.02,45.0,0.9,32"


def good_lines(n: int, seed: int = 0, start: int = 1) -> list[str]:
    rng = np.random.default_rng(seed)
    return [usgs_line(f"00-1-{start + i:06d}", f"{rng.uniform(-89, 89):.5f}",
                      f"{rng.uniform(0, 360):.5f}", f"{rng.uniform(1, 50):.4f}")
            for i in range(n)]


BAD_ROWS = [  # (line, reason words, column named in the reason)
    (usgs_line("00-1-900001", "", "10.0", "5.0"), "missing or unparseable lat", "LAT_CIRC_IMG"),
    (usgs_line("00-1-900002", "95.0", "10.0", "5.0"), "lat out of", "LAT_CIRC_IMG"),
    (usgs_line("00-1-900003", "10.0", "400.0", "5.0"), "lon out of", "LON_CIRC_IMG"),
    (usgs_line("00-1-900004", "10.0", "-10.0", "5.0"), "lon out of", "LON_CIRC_IMG"),
    (usgs_line("00-1-900005", "10.0", "20.0", "0"), "non-positive diameter", "DIAM_CIRC_IMG"),
    (usgs_line("00-1-900006", "10.0", "20.0", "-3.5"), "non-positive diameter", "DIAM_CIRC_IMG"),
    (usgs_line("00-1-900007", "10.0", "20.0", "abc"), "unparseable diameter", "DIAM_CIRC_IMG"),
    (usgs_line("00-1-000001", "11.0", "21.0", "6.0"), "duplicate id", "CRATER_ID"),
    (usgs_line("", "12.0", "22.0", "7.0"), "missing id", "CRATER_ID"),
]
EDGE_ROWS = [  # (line, stored lat, stored lon): kept, longitudes wrapped to [-180, 180)
    (usgs_line("00-2-000001", "90.0", "0.0", "3.0"), 90.0, 0.0),
    (usgs_line("00-2-000002", "-90.0", "360.0", "3.0"), -90.0, 0.0),
    (usgs_line("00-2-000003", "0.0", "180.0", "3.0"), 0.0, -180.0),
    (usgs_line("00-2-000004", "-45.5", "359.9", "3.0"), -45.5, -0.1),
    (usgs_line("00-2-000005", " 12.5 ", "90.0", "0.01"), 12.5, 90.0),
]


def write_usgs(path: Path, lines: list[str]) -> Path:
    path.write_text("\n".join([USGS_HEADER, *lines]) + "\n")
    return path


@pytest.fixture
def usgs_file(tmp_path) -> tuple[Path, dict[int, tuple], dict[int, tuple]]:
    """200 good rows with the bad and edge rows spread among them (9 of 214 rejected, 4.2 %)."""
    lines = good_lines(200)
    for k, (line, *_) in enumerate(BAD_ROWS):
        lines.insert(10 + 20 * k, line)
    for k, (line, *_) in enumerate(EDGE_ROWS):
        lines.insert(15 + 30 * k, line)
    bad = {i: b for i, line in enumerate(lines, start=1) for b in BAD_ROWS if b[0] == line}
    edge = {i: e for i, line in enumerate(lines, start=1) for e in EDGE_ROWS if e[0] == line}
    return write_usgs(tmp_path / "robbins2018_usgs.csv", lines), bad, edge


def test_usgs_robbins_bad_rows_rejected_with_reason_and_raw_text(tmp_path, usgs_file):
    path, bad, edge = usgs_file
    db = tmp_path / "usgs.duckdb"
    m = build(path, db)
    assert (m["format"], m["rows_read"], m["rows_kept"], m["rows_rejected"]) == (
        "robbins2018", 214, 205, 9)
    rejects = query(db, "SELECT * FROM rejects ORDER BY row_number")
    assert rejects["row_number"].to_list() == sorted(bad)
    for row in rejects.iter_rows(named=True):
        line, words, column = bad[row["row_number"]]
        assert words in row["reason"] and column in row["reason"], row
        assert row["raw"] == line
    dup = rejects.filter(pl.col("reason").str.contains("duplicate"))["reason"][0]
    assert "of row 1" in dup  # names the row it duplicates

    table = craters(db)
    assert_conventions(table)
    assert by_crater_id(table, 1)["source_id"] == "00-1-000001"  # the first occurrence is kept
    assert set(table["source"].to_list()) == {"robbins2018"}
    for row_number, (line, lat, lon) in edge.items():
        row = by_crater_id(table, row_number)
        assert row["source_id"] == line.split(",")[0]
        assert_position(row, lat, lon)


def test_usgs_robbins_with_bom_and_crlf(tmp_path):
    path = tmp_path / "excel.csv"
    text = "\r\n".join([USGS_HEADER, *good_lines(20)]) + "\r\n"
    path.write_bytes(b"\xef\xbb\xbf" + text.encode())
    m = build(path, tmp_path / "excel.duckdb")
    assert (m["format"], m["rows_kept"], m["rows_rejected"]) == ("robbins2018", 20, 0)


def test_usgs_robbins_good_rows_kept_exactly(tmp_path):
    lines = good_lines(50, seed=3)
    path = write_usgs(tmp_path / "good.csv", lines)
    build(path, tmp_path / "good.duckdb")
    table = craters(tmp_path / "good.duckdb").sort("crater_id")
    want = [ln.split(",") for ln in lines]
    assert table["source_id"].to_list() == [w[0] for w in want]
    np.testing.assert_array_equal(table["lat_deg"], [float(w[1]) for w in want])
    np.testing.assert_allclose(table["lon_deg"], [(float(w[2]) + 180) % 360 - 180 for w in want],
                               rtol=0, atol=1e-12)
    np.testing.assert_array_equal(table["diam_km"], [float(w[5]) for w in want])


# --- failures keep the previous catalogue ---------------------------------------------------------


def run_ingest(run_id: str, force: bool = False, **catalogue) -> tuple[object, RunStore, bool]:
    cfg = load_config("default", run_id, {"catalogue": catalogue})
    store = RunStore(run_id)
    ran = run_stages(cfg, store.root, ["ingest"], force=["ingest"] if force else [])
    return cfg, store, ran == ["ingest"]


def snapshot(workdir: Path) -> tuple:
    db = workdir / "catalogue" / "craters.duckdb"
    store = RunStore("r")
    return meta(db), craters(db), store.entry("ingest"), store.token("ingest")


def missing_column_file(tmp_path: Path) -> tuple[Path, dict, list[str]]:
    path = tmp_path / "no_diam.csv"
    path.write_text("CRATER_ID,LAT_CIRC_IMG,LON_CIRC_IMG,LAT_ELLI_IMG\n"
                    "00-1-000042,12.25,300.5,12.3\n")
    return path, {"format": "robbins2018"}, ["DIAM_CIRC_IMG", "00-1-000042", "12.25"]


def unknown_format_file(tmp_path: Path) -> tuple[Path, dict, list[str]]:
    path = tmp_path / "mystery.csv"
    path.write_text("name,latitude,longitude,size_km\nTycho,-43.31,-11.36,85.0\n")
    return path, {}, ["latitude", "Tycho", "-43.31"]


def too_many_rejects_file(tmp_path: Path) -> tuple[Path, dict, list[str]]:
    lines = good_lines(80)
    lines += [usgs_line(f"00-3-{i:06d}", "99.5", "10.0", "5.0") for i in range(20)]
    return write_usgs(tmp_path / "bad_lats.csv", lines), {}, [
        "LAT_CIRC_IMG", "20.0%", "00-3-000000,99.5,10.0"]


def header_only_file(tmp_path: Path) -> tuple[Path, dict, list[str]]:
    return write_usgs(tmp_path / "empty.csv", []), {}, ["no data rows"]


def unknown_format_name(tmp_path: Path) -> tuple[Path, dict, list[str]]:
    path = write_usgs(tmp_path / "fine.csv", good_lines(10))
    return path, {"format": "robins2018"}, ["robins2018", "robbins2018", "head2010"]


@pytest.mark.parametrize("make", [missing_column_file, unknown_format_file, too_many_rejects_file,
                                  header_only_file, unknown_format_name])
def test_failed_ingest_names_the_problem_and_keeps_the_catalogue(workdir, tmp_path, make):
    run_ingest("r", **SMALL)
    before = snapshot(workdir)
    path, options, expected = make(tmp_path)
    with pytest.raises(CatalogueError) as exc:
        run_ingest("r", source=str(path), **options)
    message = str(exc.value)
    assert str(path) in message
    for text in expected:
        assert text in message, (text, message)
    after = snapshot(workdir)
    assert after[0] == before[0]
    assert after[1].equals(before[1])
    assert after[2] == before[2]
    assert sorted(p.name for p in (workdir / "catalogue").iterdir()) == [
        "craters.duckdb", "craters.rrd", "craters.rrd.key"]


def test_max_reject_share_is_configurable(workdir, tmp_path):
    path, _, _ = too_many_rejects_file(tmp_path)
    with pytest.raises(CatalogueError):
        run_ingest("r", source=str(path), max_reject_share=0.19)
    cfg, _, ran = run_ingest("r", source=str(path), max_reject_share=0.2)  # share <= limit
    assert ran
    m = meta(Path(cfg.catalogue.db_path))
    assert (m["rows_read"], m["rows_kept"], m["rows_rejected"]) == (100, 80, 20)


# --- the stage: synthetic ingest, recording, cache ------------------------------------------------


def rrd_entities(path: Path) -> pl.DataFrame:
    store = rr.chunk.RrdReader(path).stream().collect()
    return store.reader(index=None, contents="/world/**").to_polars()


def test_synthetic_ingest_stage_outputs(workdir):
    cfg, store, ran = run_ingest("r", **SMALL)
    assert ran
    db = workdir / "catalogue" / "craters.duckdb"
    m = meta(db)
    assert m["key"] == ingest.catalogue_key(cfg)
    assert (m["format"], m["source_path"], m["sha256"]) == ("synthetic", "synthetic", None)
    assert m["generator_seed"] == 2018 and m["healpix_order"] == 6
    assert m["rows_read"] == m["rows_kept"] > 6_000 and m["rows_rejected"] == 0
    assert dt.datetime.fromisoformat(m["ingest_time"]).tzinfo is not None
    table = craters(db)
    assert table.height == m["rows_kept"]
    assert_conventions(table)
    assert table["diam_km"].min() >= 20.0
    assert query(db, "SELECT count(*) AS n FROM rejects")["n"][0] == 0

    # the catalogue's recording lives beside the database, once for every run of it
    rrd = workdir / "catalogue" / "craters.rrd"
    [entry] = rr.chunk.RrdReader(rrd).recordings()
    assert entry.recording_id == base.catalogue_recording_id("craters")
    assert entry.application_id == base.APP_ID
    df = rrd_entities(rrd)
    points = np.array(df["/world/moon/craters:Points3D:positions"][0].to_list())
    assert points.shape == (table.height, 3)
    xyz = table.select("x_m", "y_m", "z_m").to_numpy()
    order_p, order_t = np.lexsort(points.T), np.lexsort(xyz.T)
    np.testing.assert_allclose(points[order_p], xyz[order_t], rtol=0, atol=R_M * 2.0**-24)
    # points are drawn at half the crater radius
    radii = np.sort(np.array(df["/world/moon/craters:Points3D:radii"][0].to_list()))
    np.testing.assert_allclose(radii, np.sort(table["diam_km"].to_numpy()) * 250.0, rtol=1e-6)
    half_sizes = np.array(df["/world/moon/surface:Ellipsoids3D:half_sizes"][0].to_list())
    np.testing.assert_array_equal(half_sizes, [[R_M] * 3])

    entry = store.entry("ingest")
    facts = json.loads(store.path("catalogue.json").read_text())
    assert (facts["db_path"], facts["key"], facts["recording"]) == (str(db), m["key"], str(rrd))
    assert set(entry["outputs"]) == {"catalogue.json"}
    assert entry["rows"] == {"craters": table.height, "rejects": 0}
    assert entry["wall_time_s"] > 0 and entry["info"]["rebuilt"] is True
    assert json.loads((store.run_dir / "config.json").read_text()) == json.loads(
        json.dumps(to_dict(cfg)))


def test_ingest_stage_cache(workdir, tmp_path):
    db = workdir / "catalogue" / "craters.duckdb"
    _, store, ran = run_ingest("r", **SMALL)
    assert ran
    token = store.token("ingest")
    assert not run_ingest("r", **SMALL)[2]  # unchanged: skipped
    assert store.token("ingest") == token

    assert run_ingest("r", **SMALL, healpix_order=5)[2]  # a config value changed
    assert meta(db)["healpix_order"] == 5
    assert_conventions(craters(db), order=5)
    assert not run_ingest("r", **SMALL, healpix_order=5)[2]

    path = write_usgs(tmp_path / "cat.csv", good_lines(30))
    assert run_ingest("r", source=str(path))[2]  # another source
    assert (meta(db)["format"], meta(db)["rows_kept"]) == ("robbins2018", 30)
    assert not run_ingest("r", source=str(path))[2]
    write_usgs(path, good_lines(31))  # same path, new content
    assert run_ingest("r", source=str(path))[2]
    assert meta(db)["rows_kept"] == 31

    rrd = workdir / "catalogue" / "craters.rrd"
    inode = rrd.stat().st_ino
    assert run_ingest("r", force=True, source=str(path))[2]
    assert rrd.stat().st_ino != inode  # forced: rebuilt, a new recording was published
    inode, db_inode = rrd.stat().st_ino, db.stat().st_ino
    rrd.with_name("craters.rrd.key").write_text("another build")  # killed before the recording
    _, store2, ran = run_ingest("r2", source=str(path))  # another run of the same catalogue
    assert ran and store2.entry("ingest")["info"]["rebuilt"] is False
    assert db.stat().st_ino == db_inode and rrd.stat().st_ino != inode  # recording rewritten

    (store.stage_dir("ingest") / "catalogue.json").write_text("{}")  # a damaged output
    assert run_ingest("r", source=str(path))[2]
    db.unlink()  # so does a missing (or replaced) catalogue database
    assert run_ingest("r", source=str(path))[2]
    assert store.entry("ingest")["info"]["rebuilt"] is True
    assert meta(db)["rows_kept"] == 31


def test_runs_share_the_catalogue_database(workdir):
    db = workdir / "catalogue" / "craters.duckdb"
    run_ingest("a", **SMALL)
    built_at = meta(db)["ingest_time"], db.stat().st_ino
    _, store_b, ran = run_ingest("b", **SMALL)
    assert ran  # run b has no catalogue.json yet
    assert store_b.entry("ingest")["info"]["rebuilt"] is False
    assert (meta(db)["ingest_time"], db.stat().st_ino) == built_at


def test_cli_ingest_with_source_and_db(workdir, tmp_path):
    path = write_usgs(tmp_path / "cli.csv", good_lines(12))
    result = CliRunner().invoke(app, ["ingest", "--run-id", "c", "--source", str(path),
                                      "--format", "robbins2018", "--db", "catalogue/cli.duckdb"])
    assert result.exit_code == 0, result.output
    assert meta(workdir / "catalogue" / "cli.duckdb")["rows_kept"] == 12
    assert (workdir / "catalogue" / "cli.rrd").is_file()
    assert run_catalogue_db(RunStore("c")) == workdir / "catalogue" / "cli.duckdb"


@pytest.mark.slow
def test_cli_ingest_of_a_file_never_replaces_the_default_catalogue(workdir, tmp_path):
    """Without --db a source file goes to catalogue/<stem>.duckdb and run <stem>: the shared
    default catalogue and the default run are untouched."""
    assert CliRunner().invoke(app, ["ingest", "default"]).exit_code == 0
    default_db = workdir / "catalogue" / "craters.duckdb"
    before = (meta(default_db), RunStore("default").token("ingest"))
    path = write_usgs(tmp_path / "mine.csv", good_lines(12))
    result = CliRunner().invoke(app, ["ingest", "--source", str(path)])
    assert result.exit_code == 0, result.output
    assert meta(workdir / "catalogue" / "mine.duckdb")["rows_kept"] == 12
    assert run_catalogue_db(RunStore("mine")) == workdir / "catalogue" / "mine.duckdb"
    assert (meta(default_db), RunStore("default").token("ingest")) == before


def test_a_runs_catalogue_rebuilt_by_another_run_is_refused_not_joined(workdir, capsys):
    """Run a's tables must never be joined against another catalogue: once run b rebuilds the
    shared database with another config (saying so), `sql --run a` and `view a` say so in one
    line."""
    run_ingest("a", **SMALL)
    assert run_catalogue_db(RunStore("a")) == workdir / "catalogue" / "craters.duckdb"
    assert "held another catalogue" not in capsys.readouterr().out
    run_ingest("b", **SMALL, healpix_order=5)  # same database file, another catalogue
    assert "held another catalogue" in " ".join(capsys.readouterr().out.split())
    with pytest.raises(CatalogueError, match="no longer holds the catalogue this run used"):
        run_catalogue_db(RunStore("a"))
    for command in (["sql", "--run", "a", "SELECT count(*) FROM craters"], ["view", "a"]):
        result = CliRunner().invoke(app, command)
        assert result.exit_code != 0
        text = result.output + str(result.exception or "")
        assert "no longer holds the catalogue this run used" in text, text
    # a catalogue.json replaced since its commit is refused before it is read
    (RunStore("b").stage_dir("ingest") / "catalogue.json").write_text("{not json")
    with pytest.raises(StageInputError, match=r"catalogue\.json: .* \(replaced or truncated\)"):
        run_catalogue_db(RunStore("b"))
