"""Writing a Rerun recording so that its failure is the stage's: the SDK streams into memory and
the bytes are written with ordinary file I/O (a full disk or a file-size limit raises OSError at
once). rerun-sdk's own file sink writes from a background thread and, on ENOSPC, was seen to block
forever in 3 of 5 trials (and in 2 of 2 here under RLIMIT_FSIZE); the in-memory stream costs
about the recording's size in RAM (< 25 MiB for the largest recording of the default run). The
layout goes in as the default blueprint (a Blueprint store in the same file), as `save` does.

`CRATER_NAV_VISUALS=off` in the environment switches a run's visual outputs off (what a
campaign's runs do by default): its recordings here, its report's figures in `viz.report`. Every
stream is a null one (its calls do nothing, and rerun-sdk is not asked:
a disabled stream of its own warns on stderr) and each `.rrd` is written empty, so a stage still
commits the outputs it declares. A campaign gives the command that reruns one of its runs with
its recordings.
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any, cast

import rerun as rr

from pipeline.errors import PipelineError
from pipeline.io.files import atomic_write_bytes


@contextmanager
def recording_file(application_id: str, recording_id: str, path: Path,
                   blueprint: Any | None = None) -> Iterator[rr.RecordingStream]:
    """A recording stream whose bytes are written to `path` (atomically) when the block ends
    without error; OSError (ENOSPC, EFBIG) propagates from the write. With recordings off
    (`visuals_enabled()`), a null stream and an empty file."""
    if not visuals_enabled():
        yield cast(rr.RecordingStream, _Off())
        atomic_write_bytes(Path(path), b"")
        return
    rec = rr.RecordingStream(application_id, recording_id=recording_id)
    rec.set_log_time_enabled(False)
    stream = rr.binary_stream(rec)
    if blueprint is not None:
        rec.send_blueprint(blueprint, make_active=False, make_default=True)
    ok = False
    try:
        yield rec
        ok = True
    finally:
        rec.flush()
        data = stream.read() or b""
        rec.disconnect()
        data += stream.read() or b""
        if ok:
            atomic_write_bytes(Path(path), data)


VISUALS_ENV = "CRATER_NAV_VISUALS"


class _Off:
    """A recording stream with recordings off: every method call does nothing."""

    def __getattr__(self, name: str) -> Any:
        return lambda *args, **kwargs: None


def visuals_enabled() -> bool:
    """A run's recordings and figures are made unless the environment says
    `CRATER_NAV_VISUALS=off` (or 0, false, no); a value that is neither on nor off is refused."""
    value = os.environ.get(VISUALS_ENV, "on").strip().lower()
    if value in ("off", "0", "false", "no"):
        return False
    if value in ("on", "1", "true", "yes", ""):
        return True
    raise PipelineError(f"{VISUALS_ENV}={os.environ[VISUALS_ENV]!r} in the environment: must be "
                        "on or off (1/0, true/false, yes/no)")
