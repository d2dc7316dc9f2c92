"""The stage tables' declared schemas (`pipeline.vocab.tables`): every stage's table declared, and
the check a transaction makes when a table is written (missing, undeclared and mistyped columns,
an optional group in part), one line naming the table and the column. That the declarations
match what the stages write is held by every stage test (each write is checked) and asserted in
tests/stages (test_detect, test_estimate, test_score, test_trajectory: the columns and dtypes;
test_physical, test_identify: which optional groups each sensor and identification mode write).
"""

from __future__ import annotations

from pathlib import Path

import polars as pl
import pytest

from pipeline.errors import PipelineError, TableSchemaError
from pipeline.io.store import RunStore
from pipeline.stages import DAG
from pipeline.vocab import METHOD_COLORS, METHODS
from pipeline.vocab.tables import DETECTIONS, FRAMES, TABLES, check_table


def detections(*groups: str, rows: int = 2) -> pl.DataFrame:
    """A detections table of `rows` rows with the declared columns of `groups`."""
    cols = DETECTIONS.columns(*groups)
    return pl.DataFrame({c: pl.Series(c, [None] * rows, dtype=t) for c, t in cols.items()})


def refusal(frame: pl.DataFrame, name: str = "detections") -> str:
    with pytest.raises(TableSchemaError) as exc:
        check_table(name, frame)
    message = str(exc.value)
    assert "\n" not in message and message.startswith(f"table {name!r}: ")
    return message


def test_every_stage_table_is_declared_and_every_declaration_written():
    written = {o.removesuffix(".parquet") for s in DAG.stages.values() for o in s.outputs
               if o.endswith(".parquet")}
    assert written == set(TABLES)
    assert all(name == t.name for name, t in TABLES.items())


def test_a_table_as_declared_passes_with_any_whole_groups():
    for groups in ((), ("physical",), ("identification",), ("physical", "identification")):
        check_table("detections", detections(*groups))
    assert DETECTIONS.present(tuple(detections("identification").columns)) == ("identification",)
    check_table("detections", detections("physical").select(  # the order is not checked
        reversed(DETECTIONS.columns("physical"))))


def test_missing_undeclared_and_mistyped_columns_are_refused():
    assert "column 'used' is missing" in refusal(detections().drop("used"))
    assert "column 'extra' (Float64) is not declared" in refusal(
        detections().with_columns(extra=pl.lit(1.0)))
    assert "column 'frame' is Int64, declared Int32" in refusal(
        detections().with_columns(pl.col("frame").cast(pl.Int64)))
    two = refusal(detections().drop("used", "pixel_u"))
    assert two.endswith("(and 1 more); the declaration is in pipeline/vocab/tables.py")


def test_an_optional_group_is_written_whole():
    part = detections("physical").drop("p_detect")
    assert "column 'p_detect' of the optional group 'physical'" in refusal(part)
    sun = FRAMES.groups["sun"]
    frames = pl.DataFrame(schema=FRAMES.columns()).with_columns(
        pl.lit(None, pl.Float64).alias(next(iter(sun.columns))))
    assert "of the optional group 'sun' (trajectory.epoch_utc set)" in refusal(frames, "frames")


def test_a_null_column_passes_in_an_empty_table_only():
    empty = detections(rows=0).with_columns(pl.lit(None).alias("used"))
    assert empty.schema["used"] == pl.Null
    check_table("detections", empty)
    assert "column 'used' is Null, declared Boolean" in refusal(
        detections().with_columns(pl.lit(None).alias("used")))


def test_a_name_no_stage_writes_is_not_held_to_a_schema():
    check_table("not_a_stage_table", pl.DataFrame({"anything": [1]}))


def test_the_transaction_refuses_a_table_before_writing_it(tmp_path: Path):
    store = RunStore("r", tmp_path)
    with store.lock():
        tx = store.begin("detect", "key", {}, "config-hash", "code-hash")
        with pytest.raises(PipelineError, match="table 'detections': column 'used' is missing"):
            tx.table("detections", detections().drop("used"))
        assert tx.tables == [] and not (tx.folder / "detections.parquet").exists()
        path = tx.table("detections", detections("physical"))
        assert dict(pl.read_parquet_schema(path)) == DETECTIONS.columns("physical")
        tx.abort()


def test_every_registered_method_has_its_colour():
    assert set(METHODS) <= set(METHOD_COLORS)
