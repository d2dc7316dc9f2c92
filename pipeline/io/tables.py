"""Column conventions of the stage tables: vectors as <prefix>_x<unit>, _y, _z columns and
quaternions as <prefix>_x, _y, _z, _w (scalar-last), flat so that SQL reads them directly; and how
a table is written to Parquet (`write_parquet`, one codec for every stage table)."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np
import polars as pl

from pipeline.errors import StageInputError

# Parquet codec, chosen by measurement on the default run's tables (issue 26): the float columns
# byte-stream-split (each value's 8 bytes in 8 streams, so the exponent and high mantissa bytes
# compress), zstd level 3. Lossless; the detections table 48.8 -> 44.5 MB and the IMU increments
# 14.1 -> 12.8 MB (polars' default zstd: 48.8 and 14.1), written about as fast; zstd 9 saves a
# further 1 % at twice the time, 19 takes 30 s for 1 %.
PARQUET_ZSTD_LEVEL = 3


def write_parquet(frame: pl.DataFrame, path: Path | str) -> None:
    """Write `frame` to Parquet at `path` with the project's codec (`PARQUET_ZSTD_LEVEL`): the
    same values, dtypes and column order back from `pl.read_parquet`, DuckDB reads it."""
    import pyarrow.parquet as pq  # polars writes no byte-stream-split; pyarrow only when writing

    floats = [c for c, t in frame.schema.items() if t in (pl.Float64, pl.Float32)]
    pq.write_table(frame.to_arrow(), path, compression="zstd",
                   compression_level=PARQUET_ZSTD_LEVEL, use_byte_stream_split=floats,
                   use_dictionary=[c for c in frame.columns if c not in floats])


def reduced(value: object, default: float = math.nan) -> float:
    """A numeric column's reduction as a float (polars types `Series.mean()`, `.max()`,
    `.median()` as any Python value): `default` for None (an empty or all-null column)."""
    if value is None:
        return default
    if not isinstance(value, int | float):
        raise TypeError(f"expected a number, got {value!r}")
    return float(value)


def xyz_columns(prefix: str, unit: str, a: np.ndarray) -> dict[str, np.ndarray]:
    """{<prefix>_x<unit>: a[:, 0], ...} for an (N, 3) array."""
    return {f"{prefix}_{c}{unit}": a[:, i] for i, c in enumerate("xyz")}


def xyz(table: pl.DataFrame, prefix: str, unit: str) -> np.ndarray:
    """(N, 3) float64 array of the columns <prefix>_x<unit>, _y<unit>, _z<unit> (float32 ones
    widened: arithmetic in float64 whatever the storage)."""
    return np.stack([table[f"{prefix}_{c}{unit}"].to_numpy() for c in "xyz"],
                    axis=1).astype(np.float64, copy=False)


def quat_columns(prefix: str, q: np.ndarray) -> dict[str, np.ndarray]:
    """{<prefix>_x: q[:, 0], ..., <prefix>_w: q[:, 3]} for (N, 4) scalar-last quaternions."""
    return {f"{prefix}_{c}": q[:, i] for i, c in enumerate("xyzw")}


def quats(table: pl.DataFrame, prefix: str) -> np.ndarray:
    """(N, 4) scalar-last quaternions from the columns <prefix>_x, _y, _z, _w."""
    return np.stack([table[f"{prefix}_{c}"].to_numpy() for c in "xyzw"], axis=1)


def read_table(path: Path, **kwargs: Any) -> pl.DataFrame:
    """A Parquet table, or StageInputError naming the file when it cannot be read."""
    try:
        return pl.read_parquet(path, **kwargs)
    except (OSError, pl.exceptions.PolarsError) as exc:
        text = " ".join(str(exc).split())[:300]
        raise StageInputError(f"{path}: not a readable Parquet table ({text})") from None
