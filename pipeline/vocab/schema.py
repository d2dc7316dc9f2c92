"""A table's schema: its columns and their polars types, always-written columns apart from the
optional groups a config adds whole (the physical sensor's, identification's, ...), and the
check of a frame against it. The declarations are in `pipeline.vocab.tables`."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field

import polars as pl

from pipeline.errors import TableSchemaError

Dtype = pl.DataType | type[pl.DataType]
F64, F32, I32, I64, BOOL, STR = (pl.Float64, pl.Float32, pl.Int32, pl.Int64, pl.Boolean,
                                  pl.String)


def xyz(prefix: str, unit: str = "", dtype: Dtype = F64) -> dict[str, Dtype]:
    """The columns `<prefix>_x<unit>`, `_y`, `_z` of a vector (`pipeline.io.tables.xyz_columns`)."""
    return {f"{prefix}_{c}{unit}": dtype for c in "xyz"}


def quat(prefix: str) -> dict[str, Dtype]:
    """The columns `<prefix>_x`, `_y`, `_z`, `_w` of a scalar-last quaternion."""
    return {f"{prefix}_{c}": F64 for c in "xyzw"}


@dataclass(frozen=True)
class Group:
    """Columns a table carries all together or not at all; `when`: the config that adds them."""

    when: str
    columns: Mapping[str, Dtype]


@dataclass(frozen=True)
class TableSchema:
    """A table's columns: `base` always, and each of `groups` (name -> Group) whole or not at
    all. The order of the columns is not part of the schema."""

    name: str
    base: Mapping[str, Dtype]
    groups: Mapping[str, Group] = field(default_factory=dict)

    def columns(self, *groups: str) -> dict[str, Dtype]:
        """Column -> dtype with the optional `groups` written (KeyError for an unknown group)."""
        out = dict(self.base)
        for g in groups:
            out.update(self.groups[g].columns)
        return out

    @property
    def names(self) -> tuple[str, ...]:
        """Every column the table can have: the base ones, then each group's."""
        return tuple(self.columns(*self.groups))

    def present(self, columns: list[str] | tuple[str, ...]) -> tuple[str, ...]:
        """The optional groups of which `columns` holds at least one column."""
        return tuple(g for g, grp in self.groups.items() if set(grp.columns) & set(columns))

    def problems(self, schema: Mapping[str, pl.DataType], empty: bool = False) -> list[str]:
        """What differs between a frame's `schema` and the declaration: missing, undeclared and
        mistyped columns, and optional groups written in part. An `empty` frame may have a
        column of type Null (polars' type of a column with no values)."""
        out = []
        for g in self.present(tuple(schema)):
            grp = self.groups[g]
            out += [f"column {c!r} of the optional group {g!r} ({grp.when}) is missing: the "
                    "group is written whole" for c in grp.columns if c not in schema]
        groups = self.present(tuple(schema))
        declared = self.columns(*groups)
        out += [f"column {c!r} is missing" for c in self.base if c not in schema]
        out += [f"column {c!r} ({schema[c]}) is not declared" for c in schema
                if c not in declared]
        out += [f"column {c!r} is {schema[c]}, declared {declared[c]}" for c in schema
                if c in declared and schema[c] != declared[c]
                and not (empty and schema[c] == pl.Null)]
        return out

    def check(self, frame: pl.DataFrame) -> None:
        """Raise TableSchemaError (one line: the table, the first column at fault, how many
        more) unless `frame` matches the declaration."""
        found = self.problems(frame.schema, frame.height == 0)
        if found:
            more = f" (and {len(found) - 1} more)" if len(found) > 1 else ""
            raise TableSchemaError(f"table {self.name!r}: {found[0]}{more}; the declaration is "
                                   "in pipeline/vocab/tables.py")
