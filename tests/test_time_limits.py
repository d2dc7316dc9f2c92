"""Every blocking call has a time limit: the viewer layout's save (rerun-sdk's, seen to block for
ever on a full disk) gives up with an OSError naming the file; an ordinary save is unchanged."""

from __future__ import annotations

import threading
import time

import pytest
import rerun as rr
import rerun.blueprint as rrb

from pipeline.viz.rerun import layout


def test_the_layout_save_is_the_sdks_file_moved_in(tmp_path):
    path = layout.save_layout(tmp_path / "layout.rbl")
    reader = rr.chunk.RrdReader(path)
    [bp] = reader.blueprints()
    assert reader.stream(store=bp).collect().reader(index="blueprint", contents="/**") \
        .to_arrow_table().num_rows
    assert sorted(p.name for p in tmp_path.iterdir()) == ["layout.rbl"]


def test_a_layout_save_that_blocks_is_an_oserror_naming_the_file(tmp_path, monkeypatch):
    release = threading.Event()
    monkeypatch.setattr(rrb.Blueprint, "save", lambda self, app, path: release.wait(30))
    monkeypatch.setattr(layout, "SAVE_TIMEOUT_S", 0.5)
    t0 = time.monotonic()
    try:
        with pytest.raises(OSError) as err:
            layout.save_layout(tmp_path / "layout.rbl")
    finally:
        release.set()
    assert time.monotonic() - t0 < 5
    assert err.value.filename == str(tmp_path / "layout.rbl")
    assert "did not finish within 0.5 s" in err.value.strerror
    assert not list(tmp_path.iterdir())


def test_a_layout_save_that_fails_names_the_file(tmp_path, monkeypatch):
    def full(self, app, path):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(rrb.Blueprint, "save", full)
    with pytest.raises(OSError) as err:
        layout.save_layout(tmp_path / "layout.rbl")
    assert err.value.errno == 28 and err.value.filename == str(tmp_path / "layout.rbl")
