"""Crater catalogues: source formats, validation, the DuckDB database and the in-memory index.

`build_catalogue` is the one entry point of the ingest stage. It reads a source file once (the
sha256 and the parse use the same bytes), detects its format (`catalogue/sources.toml`, then the
user's `catalogue/formats.local.toml`), checks it at the door (column types, record shapes, UTF-8),
validates every row (rejected rows keep their reason, line and raw text), reports positional
duplicates, puts positions in MCMF on the 1737.4 km sphere (paper Eq. 3, ERRATA 1) and in a
HEALPix nested tile, and builds the database into a new file that replaces the old one only when
complete. Later stages load it as a `Catalogue` and query it through its `TileIndex`.

Every `CatalogueError` is one line naming the file, the line or row, and the column or key.
"""

from __future__ import annotations

from pipeline.errors import CatalogueError
from pipeline.io.catalogue.build import build_catalogue, build_from_config
from pipeline.io.catalogue.db import (
    Catalogue,
    check_catalogue_unchanged,
    load_catalogue,
    load_recorded_catalogue,
    read_meta,
    recorded_catalogue_db,
    recorded_facts,
    share_catalogue,
)
from pipeline.io.catalogue.formats import format_fingerprint, load_formats
from pipeline.io.catalogue.source import source_sha256
from pipeline.io.catalogue.validate import default_db_path, site_tier_table, source_key

__all__ = [
    "Catalogue", "CatalogueError", "build_catalogue", "build_from_config",
    "check_catalogue_unchanged", "default_db_path", "format_fingerprint", "load_catalogue",
    "load_formats", "load_recorded_catalogue", "read_meta", "recorded_catalogue_db",
    "recorded_facts", "share_catalogue", "site_tier_table", "source_key", "source_sha256",
]
