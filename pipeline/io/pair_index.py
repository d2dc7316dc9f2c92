"""The lost-in-space pair-invariant indexes on disk: one .npz per catalogue, region and size
range, beside the catalogue (config `identification.index_dir`), written atomically and read
back when the same region is asked for again (`pipeline.core.crater_index`)."""

from __future__ import annotations

import hashlib
import io
import json
from pathlib import Path

import numpy as np

from pipeline.core.crater_index import PairIndex
from pipeline.io.store import atomic_write_bytes


class PairIndexStore:
    """Indexes of one catalogue (its key) in a folder."""

    def __init__(self, directory: Path, catalogue_key: str) -> None:
        self.directory = directory
        self.catalogue_key = catalogue_key

    def path(self, params: dict[str, float]) -> Path:
        """The file of the index built with `params` (region, size range, separation)."""
        text = json.dumps({"catalogue": self.catalogue_key, **params}, sort_keys=True)
        return self.directory / f"pairs-{hashlib.sha256(text.encode()).hexdigest()[:20]}.npz"

    def load(self, params: dict[str, float]) -> PairIndex | None:
        """The index, or None when not built (or unreadable)."""
        path = self.path(params)
        if not path.is_file():
            return None
        try:
            with np.load(path) as z:
                return PairIndex.from_arrays({k: z[k] for k in z.files})
        except (OSError, ValueError, KeyError):  # a damaged file is rebuilt, not trusted
            return None

    def save(self, params: dict[str, float], index: PairIndex) -> Path:
        path = self.path(params)
        buf = io.BytesIO()
        np.savez(buf, **index.to_arrays())
        self.directory.mkdir(parents=True, exist_ok=True)
        atomic_write_bytes(path, buf.getvalue())
        return path
