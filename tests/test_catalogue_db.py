"""Catalogue inputs validated at the door (pipeline/io/catalogue_db.py): wrong column types,
absurd diameters, ragged rows, bytes that are not UTF-8, pandas index columns, positional
duplicates, a locked database, the user's own format file, one read per build, and the real
catalogues of ../shared/data."""

from __future__ import annotations

import hashlib
import io
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import polars as pl
import pytest
from conftest import REPO, query, shared_file

from pipeline.errors import CatalogueError
from pipeline.io import catalogue as cat
from pipeline.io.catalogue import build as catalogue_build
from pipeline.io.catalogue import formats as catalogue_formats
from pipeline.workspace import Workspace

R_M = 1_737_400.0


# --- helpers --------------------------------------------------------------------------------------


def build(source: Path | str, db: Path, **options) -> dict:
    return cat.build_catalogue(source, db_path=db, key="test-key", **options)


def rejects(db: Path) -> list[dict]:
    return query(db, "SELECT * FROM rejects ORDER BY row_number").to_dicts()


def fails(source: Path, db: Path, *expected: str, **options) -> str:
    """Build must fail with a one-line CatalogueError naming the file and `expected`; the database
    is not written."""
    existed = db.read_bytes() if db.is_file() else None
    with pytest.raises(CatalogueError) as exc:
        build(source, db, **options)
    message = str(exc.value)
    assert "\n" not in message, message
    assert str(source) in message, message
    for text in expected:
        assert text in message, (text, message)
    assert (db.read_bytes() if db.is_file() else None) == existed
    assert not [p for p in db.parent.iterdir() if p.name.startswith(".tmp-")]
    return message


def good_rows(n: int, seed: int = 0) -> list[str]:
    """`lat,lon,diam` rows (robbins2018_ge20km: lon 0..360, km), well apart."""
    rng = np.random.default_rng(seed)
    return [f"{rng.uniform(-80, 80):.5f},{rng.uniform(0, 360):.5f},{rng.uniform(20, 90):.3f}"
            for _ in range(n)]


def write_csv(path: Path, rows: list[str], header: str = "lat,lon,diam") -> Path:
    path.write_text("\n".join([header, *rows]) + "\n")
    return path


# --- wrong column types ---------------------------------------------------------------------------

WRONG_TYPES = {  # case -> (columns of a robbins2018_ge20km_parquet file, bad column, type named)
    "bool_lat": ({"lat": [True, False, True]}, "lat", "Boolean"),
    "list_lat": ({"lat": [[1.0], [2.0, 3.0], []]}, "lat", "List"),
    "struct_lat": ({"lat": [{"v": 1.0}, {"v": 2.0}, {"v": 3.0}]}, "lat", "Struct"),
    "bool_diam": ({"diam_km": [True, True, False]}, "diam_km", "Boolean"),
}


@pytest.mark.parametrize("case", sorted(WRONG_TYPES))
def test_wrong_column_type_is_an_error_not_a_cast(tmp_path, case):
    columns, bad, type_name = WRONG_TYPES[case]
    frame = {"lat": [10.0, 20.0, 30.0], "lon": [1.0, 2.0, 3.0], "diam_km": [30.0, 40.0, 50.0]}
    path = tmp_path / f"{case}.parquet"
    pl.DataFrame({**frame, **columns}).write_parquet(path)
    db = tmp_path / "cat.duckdb"
    build("synthetic", db, min_diam_km=100.0)
    fails(path, db, f"column {bad!r}", type_name, "row 1", "not converted")


def test_csv_text_in_a_numeric_column_is_a_rejected_row_not_an_error(tmp_path):
    path = write_csv(tmp_path / "t.csv", [*good_rows(30), "true,10,30"])
    m = build(path, tmp_path / "t.duckdb")
    assert (m["rows_kept"], m["rows_rejected"]) == (30, 1)
    [r] = rejects(tmp_path / "t.duckdb")
    assert (r["row_number"], r["line"], r["raw"]) == (31, 32, "true,10,30")
    assert "unparseable lat" in r["reason"] and "'lat'" in r["reason"]


# --- absurd diameters -----------------------------------------------------------------------------


def test_diameters_above_the_largest_basin_are_rejected(tmp_path):
    rows = good_rows(40)
    rows[5] = "10.0,20.0,5000"
    rows[9] = "11.0,21.0,2600.001"
    rows[12] = "-50.0,190.0,2500"  # South Pole-Aitken size: kept
    path = write_csv(tmp_path / "d.csv", rows)
    db = tmp_path / "d.duckdb"
    m = build(path, db)
    assert (m["rows_read"], m["rows_kept"], m["rows_rejected"]) == (40, 38, 2)
    got = rejects(db)
    assert [(r["row_number"], r["line"], r["raw"]) for r in got] == [
        (6, 7, "10.0,20.0,5000"), (10, 11, "11.0,21.0,2600.001")]
    for r in got:
        assert "diameter above 2,600 km" in r["reason"] and "'diam'" in r["reason"]
    assert query(db, "SELECT max(diam_km) AS m FROM craters")["m"][0] == 2500.0


def test_a_file_of_absurd_diameters_fails_naming_the_line(tmp_path):
    rows = [f"{i * 0.5},{i},{5000 + i}" for i in range(20)]
    fails(write_csv(tmp_path / "huge.csv", rows), tmp_path / "h.duckdb",
          "20 of 20 rows rejected", "diameter above 2,600 km", "row 1 (line 2)", "'diam'")


# --- ragged rows and undecodable bytes ------------------------------------------------------------


def test_ragged_rows_are_rejected_with_their_line(tmp_path):
    header = ",Unnamed: 0,Diameter (km),Long,Lat,tag"  # povilaitis2018, quoted newline in a tag
    rows = [f"{i},{i},{6 + i % 9},{i - 50}.5,{i % 50}.25,standard" for i in range(60)]
    rows[3] = '3,3,7.5,-40.0,12.0,"two\nlines"'  # record 4 spans lines 5-6
    rows[10] = "10,10,7.5,-40.0"  # too few fields: record 11, line 13
    rows[20] = "20,20,7.5,-41.0,12.0,standard,extra"  # too many: record 21, line 23
    path = write_csv(tmp_path / "pov.csv", rows, header)
    db = tmp_path / "pov.duckdb"
    m = build(path, db)
    assert (m["format"], m["rows_read"], m["rows_kept"], m["rows_rejected"]) == (
        "povilaitis2018", 60, 58, 2)
    got = rejects(db)
    assert [(r["row_number"], r["line"], r["raw"]) for r in got] == [
        (11, 13, rows[10]), (21, 23, rows[20])]
    assert got[0]["reason"] == "ragged row: 4 fields, the header has 6"
    assert got[1]["reason"] == "ragged row: 7 fields, the header has 6"
    kept = query(db, "SELECT crater_id, source_id FROM craters WHERE crater_id IN (4, 12)")
    assert sorted(kept.rows()) == [(4, "3"), (12, "11")]  # numbering follows the records


def test_too_many_ragged_rows_fail_naming_the_line(tmp_path):
    rows = good_rows(20) + ["1.0,2.0"] * 5
    fails(write_csv(tmp_path / "rag.csv", rows), tmp_path / "r.duckdb",
          "ragged row: 2 fields, the header has 3", "row 21 (line 22)", "'1.0,2.0'")


def test_blank_line_inside_the_file_is_a_rejected_row(tmp_path):
    rows = good_rows(30)
    rows.insert(10, "")
    path = tmp_path / "blank.csv"
    path.write_text("\n".join(["lat,lon,diam", *rows]) + "\n\n\n")  # trailing blank lines: ignored
    db = tmp_path / "b.duckdb"
    m = build(path, db)
    assert (m["rows_read"], m["rows_kept"], m["rows_rejected"]) == (31, 30, 1)
    assert [(r["row_number"], r["line"], r["reason"]) for r in rejects(db)] == [
        (11, 12, "blank line")]


def test_undecodable_bytes_are_rejected_with_their_line(tmp_path):
    rows = [r.encode() for r in good_rows(40)]
    rows[7] = b"10.5,20\xff,30"
    rows[30] = b"-5.0,100.0,4\xc3"  # a truncated two-byte sequence
    path = tmp_path / "latin.csv"
    path.write_bytes(b"\r\n".join([b"lat,lon,diam", *rows]) + b"\r\n")  # CRLF too
    db = tmp_path / "l.duckdb"
    m = build(path, db)
    assert (m["rows_read"], m["rows_kept"], m["rows_rejected"]) == (40, 38, 2)
    got = rejects(db)
    assert [(r["row_number"], r["line"]) for r in got] == [(8, 9), (31, 32)]
    assert {r["reason"] for r in got} == {"undecodable bytes (not UTF-8; shown as U+FFFD in raw)"}
    assert (got[0]["raw"], got[1]["raw"]) == ("10.5,20\ufffd,30", "-5.0,100.0,4\ufffd")


def test_a_latin1_file_fails_naming_the_first_bad_line(tmp_path):
    rows = [f"{r},Cr\u00e8ve" for r in good_rows(20)]
    rows[:3] = [f"{r},plain" for r in good_rows(3, seed=1)]
    path = tmp_path / "latin1.csv"
    path.write_bytes("\n".join(["lat,lon,diam,name", *rows]).encode("latin-1"))
    fails(path, tmp_path / "l1.duckdb", "17 of 20 rows rejected", "not UTF-8", "row 4 (line 5)")


def test_undecodable_header_or_unclosed_quote_fails_naming_the_line(tmp_path):
    path = tmp_path / "h.csv"
    path.write_bytes(b"lat,l\xf6n,diam\n1,2,30\n")
    fails(path, tmp_path / "h.duckdb", "line 1", "not UTF-8", "byte 6")
    path = write_csv(tmp_path / "q.csv", [*good_rows(5), '1.0,"2.0,30', *good_rows(3)])
    fails(path, tmp_path / "q.duckdb", "line 7", "never closed")


def test_stray_quote_inside_a_field_is_read_literally(tmp_path):
    rows = good_rows(60)
    rows[4] = '1.0,2"5,30'
    rows[9] = '3.0,4.0,6"'
    db = tmp_path / "s.duckdb"
    m = build(write_csv(tmp_path / "s.csv", rows), db)
    assert (m["rows_read"], m["rows_kept"], m["rows_rejected"]) == (60, 58, 2)
    got = rejects(db)
    assert [(r["row_number"], r["line"], r["raw"]) for r in got] == [
        (5, 6, rows[4]), (10, 11, rows[9])]
    assert "lon" in got[0]["reason"] and "diameter" in got[1]["reason"]
    del rows[9]  # one quote in the whole file: still a literal, not an unclosed field
    m = build(write_csv(tmp_path / "s1.csv", rows), db)
    assert (m["rows_read"], m["rows_kept"], m["rows_rejected"]) == (59, 58, 1)
    assert [(r["row_number"], r["line"]) for r in rejects(db)] == [(5, 6)]


# --- pandas index columns and repeated header names -----------------------------------------------


@pytest.mark.parametrize("index_header", ["", "Unnamed: 0"])
def test_pandas_index_column_ingests_unedited(tmp_path, index_header):
    rows = good_rows(25, seed=4)
    path = write_csv(tmp_path / "pandas.csv", [f"{i},{r}" for i, r in enumerate(rows)],
                     f"{index_header},lat,lon,diam")
    db = tmp_path / "p.duckdb"
    m = build(path, db)
    assert (m["format"], m["rows_kept"], m["rows_rejected"]) == ("robbins2018_ge20km", 25, 0)
    table = query(db, "SELECT lat_deg, lon_deg, diam_km FROM craters ORDER BY crater_id")
    want = np.array([[float(v) for v in r.split(",")] for r in rows])
    np.testing.assert_array_equal(table["lat_deg"], want[:, 0])
    np.testing.assert_allclose(table["lon_deg"], (want[:, 1] + 180) % 360 - 180, atol=1e-12)
    np.testing.assert_array_equal(table["diam_km"], want[:, 2])


def test_repeated_mapped_column_is_an_error(tmp_path):
    path = write_csv(tmp_path / "twice.csv", ["1,2,3,40"], "lat,lat,lon,diam")
    fails(path, tmp_path / "t.duckdb", "line 1", "column 'lat'", "more than once")


# --- positional duplicates ------------------------------------------------------------------------


def test_positional_duplicates_are_kept_and_reported(tmp_path):
    rows = good_rows(40, seed=7)
    base = rows[2].split(",")
    rows.append(",".join(base))  # row 41: the same lat/lon and diameter as row 3
    rows.append(f"{float(base[0]) + 5e-7},{base[1]},55.0")  # row 42: within 1e-6 deg of row 3
    rows.append("89.99999,10.0,30")  # rows 43 and 44: 1e-5 deg from the pole,
    rows.append("89.99999,190.0,31")  # 180 deg of longitude apart: ~0.6 m (MCMF)
    rows.append("0.0,100.0,25")  # rows 45, 46: 2 m apart: not duplicates
    rows.append(f"0.0,{float(100.0 + np.degrees(2.0 / R_M))!r},25")
    db = tmp_path / "dup.duckdb"
    m = build(write_csv(tmp_path / "dup.csv", rows), db)
    assert (m["rows_read"], m["rows_kept"], m["rows_rejected"], m["rows_duplicate"]) == (
        46, 46, 0, 3)
    dups = query(db, "SELECT * FROM duplicates ORDER BY crater_id").to_dicts()
    assert [(d["crater_id"], d["duplicate_of"]) for d in dups] == [(41, 3), (42, 3), (44, 43)]
    assert dups[0]["distance_m"] == 0.0
    assert 0 < dups[1]["distance_m"] < 0.03 and 0.5 < dups[2]["distance_m"] < 0.7
    assert query(db, "SELECT count(*) AS n FROM craters")["n"][0] == 46


# --- the catalogue database -----------------------------------------------------------------------


def test_read_meta_tells_a_locked_database_from_no_catalogue(tmp_path):
    db = tmp_path / "locked.duckdb"
    assert cat.read_meta(db) is None  # no file
    (tmp_path / "junk.duckdb").write_text("not a database")
    assert cat.read_meta(tmp_path / "junk.duckdb") is None
    build("synthetic", db, min_diam_km=100.0)
    assert cat.read_meta(db)["format"] == "synthetic"
    holder = subprocess.Popen(
        [sys.executable, "-c", "import duckdb, sys; con = duckdb.connect(sys.argv[1]); "
         "print('ready', flush=True); sys.stdin.read()", str(db)],
        stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "ready"
        for call in (cat.read_meta, cat.load_catalogue):
            with pytest.raises(CatalogueError) as exc:
                call(db)
            message = str(exc.value)
            assert "\n" not in message and str(db) in message
            assert "locked by another process" in message and f"PID {holder.pid}" in message
    finally:
        holder.stdin.close()
        holder.wait(timeout=30)
    assert cat.read_meta(db)["format"] == "synthetic"


def test_a_failed_build_keeps_the_previous_catalogue(tmp_path):
    db = tmp_path / "keep.duckdb"
    build("synthetic", db, min_diam_km=100.0)
    before = db.read_bytes()
    path = tmp_path / "bad.parquet"
    pl.DataFrame({"lat": [True], "lon": [1.0], "diam_km": [3.0]}).write_parquet(path)
    fails(path, db, "'lat'")
    assert db.read_bytes() == before


def test_default_db_path_per_source():
    assert cat.default_db_path("synthetic") == "catalogue/craters.duckdb"
    assert cat.default_db_path("../shared/data/head2010_ge20km.csv") == (
        "catalogue/head2010_ge20km.duckdb")
    assert cat.default_db_path(Path("/x/My Robbins (2018).csv")) == (
        "catalogue/My_Robbins_2018.duckdb")
    assert cat.default_db_path("/x/craters.parquet") == "catalogue/craters_file.duckdb"
    assert cat.default_db_path("/x/..csv") == "catalogue/catalogue.duckdb"


# --- the file is read once ------------------------------------------------------------------------


@pytest.mark.parametrize("kind", ["csv", "parquet"])
def test_build_reads_the_file_once_and_hashes_what_it_parsed(tmp_path, monkeypatch, kind):
    path = write_csv(tmp_path / "once.csv", good_rows(30))
    if kind == "parquet":
        pl.read_csv(path).rename({"diam": "diam_km"}).with_columns(
            (pl.col("lon") + 180) % 360 - 180).write_parquet(tmp_path / "once.parquet")
        path = tmp_path / "once.parquet"
    opened = []
    real_open = io.open

    def counting_open(file, *args, **kwargs):
        if Path(str(file)).resolve() == path.resolve():
            opened.append(args[0] if args else kwargs.get("mode", "r"))
        return real_open(file, *args, **kwargs)

    def no_paths(reader):
        def check(source, *args, **kwargs):
            assert not isinstance(source, str | Path), f"{reader.__name__} read {source}"
            return reader(source, *args, **kwargs)
        return check

    monkeypatch.setattr(io, "open", counting_open)
    for name in ("read_csv", "read_parquet", "scan_csv", "scan_parquet"):
        monkeypatch.setattr(pl, name, no_paths(getattr(pl, name)))
    m = build(path, tmp_path / "once.duckdb")
    monkeypatch.undo()
    assert opened == ["rb"]
    assert m["rows_kept"] == 30
    digest = hashlib.sha256(path.read_bytes()).hexdigest()
    assert m["sha256"] == digest == cat.source_sha256(path)
    assert cat.source_key(path)["sha256"] == digest
    with pytest.raises(CatalogueError, match="changed while the ingest ran"):
        build(path, tmp_path / "once.duckdb", expected_sha256="0" * 64)
    assert build(path, tmp_path / "once.duckdb", expected_sha256=digest)["sha256"] == digest


# --- the user's own formats -----------------------------------------------------------------------

LOCAL_FORMAT = """
[my_survey]
title = "My survey: diameters in metres, degrees east 0..360"
file = "csv"
columns = { id = "name", lat = "latitude", lon = "longitude", diam = "size_m" }
lon_convention = "0..360"
diam_unit = "m"
max_reject_share = 0.1
"""


@pytest.fixture
def project(tmp_path, monkeypatch) -> Workspace:
    """A project folder with the shipped sources.toml; the catalogue's workspace points at it."""
    ws = Workspace(tmp_path / "project")
    ws.catalogue_dir.mkdir(parents=True)
    shutil.copy(REPO / "catalogue" / "sources.toml", ws.sources_toml)
    for module in (catalogue_formats, catalogue_build):
        monkeypatch.setattr(module, "workspace", lambda: ws)
    return ws


def test_user_format_file_is_loaded_and_keys_the_ingest(tmp_path, project):
    shipped = cat.load_formats()
    assert "my_survey" not in shipped
    project.local_formats_toml.write_text(LOCAL_FORMAT)
    formats = cat.load_formats()
    assert set(formats) == {*shipped, "my_survey"}
    assert formats["my_survey"].defined_in == str(project.local_formats_toml)
    assert formats["robbins2018"].defined_in == str(project.sources_toml)

    path = write_csv(tmp_path / "survey.csv",
                     ["A,10.0,350.0,1500", "B,-20.0,10.0,2600000", "C,5.0,20.0,3000000"],
                     "name,latitude,longitude,size_m")
    db = tmp_path / "survey.duckdb"
    m = build(path, db, max_reject_share=0.5)
    assert (m["format"], m["rows_kept"], m["rows_rejected"]) == ("my_survey", 2, 1)
    assert m["format_file"] == str(project.local_formats_toml)
    assert m["format_sha256"] == cat.format_fingerprint(formats["my_survey"])
    assert m["format_sha256"] == cat.source_key(path)["format_sha256"]
    stored = cat.read_meta(db)
    assert stored["format_sha256"] == m["format_sha256"] and '"diam_unit": "m"' in (
        stored["format_spec"])
    table = query(db, "SELECT source_id, lon_deg, diam_km FROM craters ORDER BY crater_id")
    assert table.rows() == [("A", pytest.approx(-10.0), 1.5), ("B", 10.0, 2600.0)]
    assert "diameter above 2,600 km" in rejects(db)[0]["reason"]  # 3,000 km (in metres)


def test_format_fingerprint_follows_the_format_used_not_the_file(project):
    project.local_formats_toml.write_text(LOCAL_FORMAT)
    before = cat.load_formats()
    project.local_formats_toml.write_text(
        LOCAL_FORMAT.replace("My survey", "Renamed survey") + LOCAL_FORMAT.replace(
            "my_survey", "other").replace('"m"', '"km"'))
    after = cat.load_formats()
    fp = cat.format_fingerprint
    assert fp(after["my_survey"]) == fp(before["my_survey"])  # the title does not count
    assert fp(after["other"]) != fp(before["my_survey"])
    assert all(fp(after[n]) == fp(before[n]) for n in before)
    project.local_formats_toml.write_text(LOCAL_FORMAT.replace("0.1", "0.2"))
    assert fp(cat.load_formats()["my_survey"]) != fp(before["my_survey"])


def test_a_format_reading_one_column_as_two_fields_is_refused(project):
    """lat = lon = diam from one column would ingest every crater as lat = lon = diam."""
    project.local_formats_toml.write_text(LOCAL_FORMAT.replace(
        'lon = "longitude", diam = "size_m"', 'lon = "latitude", diam = "latitude"'))
    with pytest.raises(cat.CatalogueError, match="each field to its own column") as exc:
        cat.load_formats()
    assert str(project.local_formats_toml) in str(exc.value)


def test_shipped_formats_come_from_the_checkout_when_the_workspace_has_none(project):
    project.sources_toml.unlink()
    project.local_formats_toml.write_text(LOCAL_FORMAT)
    formats = cat.load_formats()
    assert formats["head2010"].defined_in == str(REPO / "catalogue" / "sources.toml")
    assert formats["my_survey"].defined_in == str(project.local_formats_toml)


def test_user_format_name_clash_names_both_files(project):
    project.local_formats_toml.write_text(LOCAL_FORMAT + LOCAL_FORMAT.replace(
        "my_survey", "head2010"))
    with pytest.raises(CatalogueError) as exc:
        cat.load_formats()
    message = str(exc.value)
    assert "\n" not in message
    assert str(project.local_formats_toml) in message and str(project.sources_toml) in message
    assert "[head2010]" in message and "line 10" in message


@pytest.mark.parametrize(("text", "expected"), [
    (LOCAL_FORMAT.replace('diam_unit = "m"', 'diam_unit = "mile"'), ["line 2", "'diam_unit'"]),
    (LOCAL_FORMAT.replace("max_reject_share = 0.1\n", ""), ["missing key 'max_reject_share'"]),
    (LOCAL_FORMAT + "colour = 'red'\n", ["unknown key 'colour'"]),
    (LOCAL_FORMAT.replace('lat = "latitude", ', ""), ["'columns'", "lat, lon, diam"]),
    (LOCAL_FORMAT.replace("file = ", "file == "), ["not a valid TOML file", "line 4"]),
])
def test_invalid_user_format_names_file_line_and_key(project, text, expected):
    project.local_formats_toml.write_text(text)
    with pytest.raises(CatalogueError) as exc:
        cat.load_formats()
    message = str(exc.value)
    assert "\n" not in message and str(project.local_formats_toml) in message
    for word in expected:
        assert word in message, (word, message)


# --- the real catalogues --------------------------------------------------------------------------

REAL = {  # file -> (format, rows read, kept, rejected, positional duplicates)
    "lu1319381_partial.parquet": ("lu1319381", 1_319_381, 731_819, 587_562, 4),
    "robbins2018_ge20km.csv": ("robbins2018_ge20km", 6_973, 6_973, 0, 0),
    "robbins2018_ge20km.parquet": ("robbins2018_ge20km_parquet", 6_973, 6_973, 0, 0),
    "head2010_ge20km.csv": ("head2010", 5_185, 5_185, 0, 0),
    "povilaitis2018_5to20km.csv": ("povilaitis2018", 19_335, 19_335, 0, 0),
}


@pytest.mark.parametrize("name", [pytest.param(n, marks=pytest.mark.slow)  # 1.3 M rows
                                  if n.startswith("lu1319381") else n for n in sorted(REAL)])
def test_real_catalogue_still_ingests(tmp_path, name):
    path = shared_file(name)
    db = tmp_path / "real.duckdb"
    m = build(path, db)
    want = REAL[name]
    assert (m["format"], m["rows_read"], m["rows_kept"], m["rows_rejected"],
            m["rows_duplicate"]) == want
    assert cat.source_key(path)["format_sha256"] == m["format_sha256"]
    assert m["sha256"] == cat.source_sha256(path)
    stored = cat.read_meta(db)
    assert {k: stored[k] for k in m} == m
    counts = query(db, "SELECT (SELECT count(*) FROM craters) AS c, (SELECT count(*) FROM "
                       "rejects) AS r, (SELECT count(*) FROM duplicates) AS d").row(0)
    assert counts == want[2:]
    if path.suffix == ".csv":
        assert query(db, "SELECT count(*) AS n FROM rejects WHERE line IS NULL")["n"][0] == 0


def test_a_target_that_is_not_a_catalogue_is_never_overwritten(tmp_path):
    """A mistyped --db naming another file or a folder is refused by its own name; the file
    stays as it was and no recording or temporary is left beside it."""
    victim = tmp_path / "notes.txt"
    victim.write_text("precious")
    with pytest.raises(CatalogueError) as exc:
        build("synthetic", victim, min_diam_km=50.0)
    assert str(victim) in str(exc.value) and "not a catalogue database" in str(exc.value)
    assert victim.read_text() == "precious"
    folder = tmp_path / "folder"
    folder.mkdir()
    with pytest.raises(CatalogueError) as exc:
        build("synthetic", folder, min_diam_km=50.0)
    message = str(exc.value)
    assert str(folder) in message and "is a folder" in message and ".tmp-" not in message
    assert sorted(p.name for p in tmp_path.iterdir()) == ["folder", "notes.txt"]
    db = tmp_path / "c.duckdb"  # a catalogue is replaced by a new build, as it should be
    first = build("synthetic", db, min_diam_km=50.0)["rows_kept"]
    assert 0 < build("synthetic", db, min_diam_km=60.0)["rows_kept"] < first
