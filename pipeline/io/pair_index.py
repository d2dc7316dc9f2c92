"""The lost-in-space pair-invariant indexes on disk: one .npz per catalogue, region and size
range, beside the catalogue (config `identification.index_dir`), written atomically and read
back when the same region is asked for again (`pipeline.core.vision.crater_index`). Each file
holds the sha256 of its arrays (names, dtypes, shapes, bytes): a damaged file with the right key
and shapes is rebuilt, not trusted (it identified no crater, for ever)."""

from __future__ import annotations

import hashlib
import io
import json
import zipfile
from pathlib import Path

import numpy as np

from pipeline.core.vision.crater_index import PairIndex
from pipeline.io.files import atomic_write_bytes


def arrays_digest(arrays: dict[str, np.ndarray]) -> str:
    """sha256 over the arrays' names, dtypes, shapes and bytes (in name order)."""
    h = hashlib.sha256()
    for name in sorted(arrays):
        a = np.ascontiguousarray(arrays[name])
        h.update(f"{name}|{a.dtype.str}|{a.shape}|".encode())
        h.update(a.tobytes())
    return h.hexdigest()


class PairIndexStore:
    """Indexes of one catalogue (its key) in a folder."""

    def __init__(self, directory: Path, catalogue_key: str) -> None:
        self.directory = directory
        self.catalogue_key = catalogue_key

    def _key(self, params: dict[str, float]) -> dict[str, float | str]:
        return {"catalogue": self.catalogue_key, **params}

    def path(self, params: dict[str, float]) -> Path:
        """The file of the index built with `params` (region, size range, separation)."""
        text = json.dumps(self._key(params), sort_keys=True)
        return self.directory / f"pairs-{hashlib.sha256(text.encode()).hexdigest()[:20]}.npz"

    def load(self, params: dict[str, float]) -> PairIndex | None:
        """The index, or None when not built, unreadable or not the one `params` describe (a
        damaged or foreign file is rebuilt, not trusted)."""
        path = self.path(params)
        if not path.is_file():
            return None
        try:
            with np.load(path) as z:
                arrays = {k: z[k] for k in z.files}
            stored = json.loads(str(arrays.pop("params")))
            digest = str(arrays.pop("digest"))
            if digest != arrays_digest(arrays):
                return None
            index = PairIndex.from_arrays(arrays)
        except (OSError, ValueError, KeyError, EOFError, IndexError, TypeError,
                zipfile.BadZipFile):
            return None
        n = index.diam_m.size
        sane = (stored == self._key(params) and index.c_m.shape == (n, 3)
                and index.pair_ij.ndim == 2 and index.pair_ij.shape[1] == 2
                and (index.pair_ij.size == 0 or (index.pair_ij.min() >= 0
                                                 and index.pair_ij.max() < n))
                and bool(np.all(index.diam_m >= params["diam_min_m"]))
                and bool(np.all(index.diam_m <= params["diam_max_m"])))
        return index if sane else None

    def save(self, params: dict[str, float], index: PairIndex) -> Path:
        path = self.path(params)
        buf = io.BytesIO()
        data = index.to_arrays()
        arrays = {"params": np.array(json.dumps(self._key(params))),
                  "digest": np.array(arrays_digest(data)), **data}
        np.savez(buf, allow_pickle=False, **arrays)
        self.directory.mkdir(parents=True, exist_ok=True)
        atomic_write_bytes(path, buf.getvalue())
        return path
