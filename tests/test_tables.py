"""The stage tables' Parquet codec: every value back as written (polars and DuckDB), the floats
byte-stream-split and zstd-compressed, and smaller than polars' default for noisy float64."""

from __future__ import annotations

import duckdb
import numpy as np
import polars as pl
import pyarrow.parquet as pq

from pipeline.io.tables import write_parquet


def _frame(n: int, rng: np.random.Generator) -> pl.DataFrame:
    x = rng.standard_normal(n)
    x[::7] = np.nan
    return pl.DataFrame({
        "frame": np.arange(n, dtype=np.int32), "id": rng.integers(-1, 50, n),
        "x": x, "y32": rng.standard_normal(n).astype(np.float32),
        "name": rng.choice(["a", "bb", "ccc"], n), "ok": rng.random(n) < 0.5,
        "cov": [list(rng.standard_normal(3)) for _ in range(n)],
        "maybe": [None if i % 3 else float(i) for i in range(n)],
    })


def test_round_trip_is_exact_and_duckdb_reads_it(tmp_path):
    frame = _frame(1000, np.random.default_rng(1))
    path = tmp_path / "t.parquet"
    write_parquet(frame, path)
    back = pl.read_parquet(path)
    assert back.schema == frame.schema
    assert back.equals(frame)  # NaN and null kept apart, bit for bit
    rel = duckdb.sql(f"SELECT sum(x) FILTER (WHERE NOT isnan(x)), count(maybe) FROM '{path}'")
    assert rel is not None
    total = rel.fetchall()[0]
    expected = float(frame["x"].fill_nan(None).sum())
    assert np.isclose(float(total[0]), expected, rtol=1e-12, atol=0)
    assert total[1] == frame["maybe"].count()


def test_floats_are_byte_stream_split_zstd(tmp_path):
    path = tmp_path / "t.parquet"
    write_parquet(_frame(200, np.random.default_rng(2)), path)
    meta = pq.ParquetFile(path).metadata.row_group(0)
    cols = {meta.column(i).path_in_schema: meta.column(i) for i in range(meta.num_columns)}
    for name in ("x", "y32"):
        assert "BYTE_STREAM_SPLIT" in cols[name].encodings
        assert cols[name].compression == "ZSTD"
    assert "BYTE_STREAM_SPLIT" not in cols["id"].encodings


def test_empty_frame(tmp_path):
    frame = pl.DataFrame(schema={"a": pl.Float64, "b": pl.Int64})
    write_parquet(frame, tmp_path / "e.parquet")
    assert pl.read_parquet(tmp_path / "e.parquet").equals(frame)


def test_smaller_than_polars_default_on_noisy_floats(tmp_path):
    rng = np.random.default_rng(3)
    frame = pl.DataFrame({f"u_{c}": rng.normal(0.0, 0.3, 50_000) for c in "xyz"})
    write_parquet(frame, tmp_path / "ours.parquet")
    frame.write_parquet(tmp_path / "polars.parquet")
    ours, theirs = ((tmp_path / n).stat().st_size for n in ("ours.parquet", "polars.parquet"))
    assert ours < 0.95 * theirs
