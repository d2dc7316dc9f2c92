"""Recordings are written so that a full disk or a file-size limit fails the stage at once."""

from __future__ import annotations

import subprocess
import sys
import textwrap
from pathlib import Path

import rerun as rr
import rerun.blueprint as rrb

from pipeline.io.rrd import recording_file

REPO = Path(__file__).resolve().parents[1]


def test_a_recording_is_complete_readable_and_carries_its_layout(tmp_path):
    path = tmp_path / "r.rrd"
    layout = rrb.Blueprint(rrb.TimeSeriesView(origin="/p"))
    with recording_file("crater-nav", "rid", path, layout) as rec:
        rec.log("/p", rr.Points3D([[0.0, 0.0, 1.0]]), static=True)
    reader = rr.chunk.RrdReader(path)
    assert [(e.kind, e.application_id, e.recording_id) for e in reader.recordings()] == [
        ("recording", "crater-nav", "rid")]
    assert [b.application_id for b in reader.blueprints()] == ["crater-nav"]
    table = reader.stream().collect().reader(index=None, contents="/p").to_polars()
    assert table.height == 1
    verify = subprocess.run([str(Path(sys.executable).parent / "rerun"), "rrd", "verify",
                             str(path)], capture_output=True, text=True)
    assert verify.returncode == 0, verify.stderr


def test_nothing_is_written_when_the_block_fails(tmp_path):
    path = tmp_path / "r.rrd"
    try:
        with recording_file("crater-nav", "rid", path) as rec:
            rec.log("/p", rr.Points3D([[0.0, 0.0, 1.0]]))
            raise RuntimeError("stage failed")
    except RuntimeError:
        pass
    assert not path.exists()
    assert not list(tmp_path.iterdir())


def test_a_file_size_limit_raises_at_once_instead_of_hanging(tmp_path):
    """Under RLIMIT_FSIZE (as on a full disk) the write raises EFBIG within the timeout; rerun's own
    file sink blocked forever in this situation."""
    script = textwrap.dedent(f"""
        import resource, signal, sys
        import numpy as np, rerun as rr
        sys.path.insert(0, {str(REPO)!r})
        from pipeline.io.rrd import recording_file
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
        resource.setrlimit(resource.RLIMIT_FSIZE, (1 << 20, 1 << 20))
        try:
            with recording_file("x", "y", {str(tmp_path / "big.rrd")!r}) as rec:
                rec.log("p", rr.Points3D(np.random.default_rng(0).random((300_000, 3))))
        except OSError as exc:
            print("errno", exc.errno)
            sys.exit(3)
    """)
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True,
                          timeout=60)
    assert done.returncode == 3, done.stderr
    assert "errno 27" in done.stdout
    assert not (tmp_path / "big.rrd").exists()
