"""Files written so that a failure is the writer's: sha256 (remembered per file state), atomic
writes through a temporary name, fsync, and the sweep of dead processes' leftovers."""

from __future__ import annotations

import datetime as dt
import errno
import hashlib
import os
import re
import shutil
from functools import cache
from pathlib import Path


def sha256_file(path: Path, chunk: int = 1 << 22) -> str:
    """Hex sha256 of a file's bytes, remembered in this process while the file's size, mtime and
    ctime are unchanged (any write, and any utime that restores the mtime, changes the ctime)."""
    st = Path(path).stat()
    return _sha256(str(Path(path).resolve()), st.st_size, st.st_mtime_ns, st.st_ctime_ns, chunk)


@cache
def _sha256(path: str, size: int, mtime_ns: int, ctime_ns: int, chunk: int) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        while block := f.read(chunk):
            h.update(block)
    return h.hexdigest()


def write_failure(exc: BaseException, path: Path) -> OSError:
    """The OSError naming `path` of a failed write: an OSError's own errno (a write's ENOSPC
    names no file), or a library's error carrying "(os error N)" (polars, rerun), else EIO."""
    if isinstance(exc, OSError):
        return OSError(exc.errno, exc.strerror or str(exc), str(path))
    text = " ".join(str(exc).split())
    m = re.search(r"os error (\d+)", text)
    code = int(m.group(1)) if m else errno.EIO
    return OSError(code, os.strerror(code) if m else text[:300], str(path))


def atomic_write_bytes(path: Path, data: bytes) -> None:
    """Write bytes to `path` through a temporary name, fsync and a rename (ENOSPC/EFBIG raise,
    naming `path`)."""
    tmp = path.with_name(f".tmp-{os.getpid()}-{path.name}")
    try:
        with open(tmp, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except OSError as exc:
        tmp.unlink(missing_ok=True)
        raise write_failure(exc, path) from None
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def atomic_write_text(path: Path, text: str) -> None:
    """Write text to `path` through a temporary name and a rename."""
    atomic_write_bytes(path, text.encode())


def now_iso() -> str:
    return dt.datetime.now(dt.UTC).isoformat(timespec="seconds")


def pid_alive(pid: int) -> bool:
    """True when a process `pid` exists on this machine."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def sweep_dead_temporaries(folder: Path) -> list[Path]:
    """Remove `.tmp-<pid>-*` files and folders in `folder` whose process is gone."""
    removed = []
    for p in folder.glob(".tmp-*"):
        m = re.match(r"\.tmp-(\d+)-", p.name)
        if m and not pid_alive(int(m.group(1))):
            if p.is_dir() and not p.is_symlink():
                shutil.rmtree(p, ignore_errors=True)
            else:
                p.unlink(missing_ok=True)
            removed.append(p)
    return removed


def _fsync_dir(path: Path) -> None:
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def file_records(folder: Path, names: list[str]) -> dict[str, dict[str, object]]:
    """Size and sha256 of each named file in `folder` that exists: what a folder's record
    (e.g. campaign.json's `outputs`) promises its readers."""
    out: dict[str, dict[str, object]] = {}
    for name in names:
        p = folder / name
        if p.is_file():
            out[name] = {"size": p.stat().st_size, "sha256": sha256_file(p)}
    return out


def verified_file(folder: Path, name: str, record: str) -> Path:
    """folder/name as `folder/record` (a JSON file with `outputs`: name -> size, sha256)
    promises it: a plain file (not a link), of that size and sha256; else ValueError naming
    the file (a reader refuses what was replaced, damaged or never recorded)."""
    import json

    path, rec = folder / name, folder / record
    try:
        promised = json.loads(rec.read_text())["outputs"][name]
        if not isinstance(promised, dict):
            raise TypeError(name)
    except (OSError, UnicodeDecodeError, ValueError, KeyError, TypeError):
        raise ValueError(f"{path}: not recorded in {rec} (written by another version, or the "
                         "record is damaged)") from None
    if path.is_symlink() or not path.is_file():
        raise ValueError(f"{path}: {'a link' if path.is_symlink() else 'missing'}, not the "
                         f"file {rec} records")
    if path.stat().st_size != promised.get("size") or sha256_file(path) != promised.get("sha256"):
        raise ValueError(f"{path}: not the file {rec} records (replaced or damaged since)")
    return path
