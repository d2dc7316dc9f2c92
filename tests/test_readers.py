"""The readers of a run (`just sql --run`, `just compare`, `just view`) check what they read as a
stage checks its inputs: each output a plain name inside the run's .stages/ folder, with the size
and sha256 its stage committed; else one line naming the file. And `just compare` of a physical
run in which nothing was detected beside one with detections writes its report."""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

import pytest
from conftest import REPO
from test_cli import TINY, assert_clear_error, main
from typer.testing import CliRunner

from pipeline.cli import app
from pipeline.workspace import workspace

PHYSICAL = """
[trajectory]
epoch_utc = "2026-01-30T08:40:00Z"

[detection]
sensor = "physical"
range_source = "apparent_size"
detect_min_diameter_px = {min_px}
"""


@pytest.fixture(scope="module")
def project(tmp_path_factory) -> Path:
    """A project with three runs of six frames: `tiny` (the paper's sensor), `cam` (the physical
    one) and `blind` (the physical one seeing nothing: no crater reaches 1,000 px)."""
    root = tmp_path_factory.mktemp("readers")
    shutil.copytree(REPO / "runs" / "scenarios", root / "runs" / "scenarios")
    scenarios = root / "runs" / "scenarios"
    (scenarios / "tiny.toml").write_text(TINY)
    (scenarios / "cam.toml").write_text('extends = "tiny"\n' + PHYSICAL.format(min_px=5.0))
    (scenarios / "blind.toml").write_text('extends = "tiny"\n' + PHYSICAL.format(min_px=1000.0))
    (root / "catalogue").mkdir()
    mp = pytest.MonkeyPatch()
    mp.chdir(root)
    mp.setenv("CRATER_NAV_ROOT", str(root))
    workspace.cache_clear()
    try:
        for run in ("tiny", "cam", "blind"):
            result = CliRunner().invoke(app, ["run", run], catch_exceptions=False)
            assert result.exit_code == 0, result.output
    finally:
        mp.undo()
        workspace.cache_clear()
    return root


@pytest.fixture
def here(project, monkeypatch) -> Path:
    monkeypatch.chdir(project)
    monkeypatch.setenv("CRATER_NAV_ROOT", str(project))
    workspace.cache_clear()
    yield project
    workspace.cache_clear()


def copy_run(project: Path, run: str, name: str) -> Path:
    """A copy of run `run` as `name` (its stage links, relative, point into the copy)."""
    dst = project / "runs" / name
    shutil.rmtree(dst, ignore_errors=True)
    shutil.copytree(project / "runs" / run, dst, symlinks=True)
    return dst


def flip_a_byte(path: Path) -> None:
    data = bytearray(path.read_bytes())
    data[len(data) // 2] ^= 0x01
    path.write_bytes(bytes(data))


READERS = {
    "sql": lambda run: ("sql", "--run", run, "SELECT count(*) FROM summary"),
    "compare": lambda run: ("compare", run),
    "view": lambda run: ("view", run),
}


@pytest.mark.parametrize("reader", READERS)
@pytest.mark.parametrize("damage", ["flipped", "replaced", "missing"])
def test_readers_refuse_an_output_not_as_committed(here, monkeypatch, capsys, reader, damage):
    run = f"r-{reader}-{damage}"
    folder = copy_run(here, "tiny", run)
    target = folder / ("estimate/estimation.rrd" if reader == "view" else "score/summary.parquet")
    if damage == "flipped":  # same size, other bytes
        flip_a_byte(target)
    elif damage == "replaced":  # another file of the run in its place
        other = folder / ("trajectory/trajectory.rrd" if reader == "view"
                          else "score/scores.parquet")
        shutil.copyfile(other, target)
    else:
        target.unlink()
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    code, _, err = main(monkeypatch, capsys, *READERS[reader](run))
    assert_clear_error(code, err, target.name, run)


def run_naming_an_outside_file(project: Path, run: str, stem: str) -> tuple[Path, str]:
    """A copy of `tiny` as `run` whose score stage.json also lists `<stem>.parquet` outside the
    run (a copy of its summary, with the right size and sha256): the folder and that name."""
    secret = project / f"{stem}.parquet"
    shutil.copyfile(project / "runs" / "tiny" / "score" / "summary.parquet", secret)
    folder = copy_run(project, "tiny", run)
    entry_path = folder / "score" / "stage.json"
    entry = json.loads(entry_path.read_text())
    name = os.path.relpath(secret, (folder / "score").resolve())
    entry["outputs"][name] = entry["outputs"]["summary.parquet"]
    entry_path.write_text(json.dumps(entry))
    return folder, name


def test_sql_does_not_register_an_output_outside_the_run(here, monkeypatch, capsys):
    """A stage.json naming a file outside its folder, or a stage link pointing outside the run,
    is refused before any table is registered (the lockdown comes after the registration)."""
    run_naming_an_outside_file(here, "r-escape", "secret")
    code, _, err = main(monkeypatch, capsys, "sql", "--run", "r-escape",
                          "SELECT count(*) FROM secret")
    assert_clear_error(code, err, "stage.json", "not a file name")
    # a stage link to a copy of the stage's folder outside the run
    folder = copy_run(here, "tiny", "r-link")
    outside = here / "outside-score"
    shutil.rmtree(outside, ignore_errors=True)
    shutil.copytree((folder / "score").resolve(), outside)
    (folder / "score").unlink()
    (folder / "score").symlink_to(outside)
    code, _, err = main(monkeypatch, capsys, "sql", "--run", "r-link",
                          "SELECT count(*) FROM summary")
    assert_clear_error(code, err, "points outside the run")


@pytest.mark.parametrize("reader", READERS)
@pytest.mark.parametrize("record", ["{bad json", "[1]", "link"])
def test_readers_refuse_a_run_whose_stage_record_is_damaged(here, monkeypatch, capsys, reader,
                                                            record):
    """A stage.json that is not a commit record (or a link to one elsewhere) made the stage
    vanish: sql had no `detections`, view opened the run without its recording. Refused."""
    run = f"r-rec-{reader}-{len(record)}"
    folder = copy_run(here, "tiny", run)
    entry = folder / "detect" / "stage.json"
    if record == "link":
        outside = here / f"outside-{run}.json"
        shutil.copyfile(entry, outside)
        entry.unlink()
        entry.symlink_to(outside)
    else:
        entry.write_text(record)
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    code, _, err = main(monkeypatch, capsys, *READERS[reader](run))
    assert_clear_error(code, err, "detect/stage.json", "damaged")


def test_the_viewer_refuses_a_run_with_any_output_not_as_committed(here, monkeypatch, capsys):
    """Not only the recordings it opens: a run whose tables were altered is not the run shown."""
    folder = copy_run(here, "tiny", "r-view-table")
    flip_a_byte(folder / "score" / "summary.parquet")
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    code, _, err = main(monkeypatch, capsys, "view", "r-view-table")
    assert_clear_error(code, err, "summary.parquet", "r-view-table")


def test_a_stage_naming_an_output_outside_its_folder_is_run_again(here, monkeypatch, capsys):
    """`just run`'s freshness check holds the names as the readers do: a stage whose record
    names a file outside its folder is not fresh, and its new commit no longer names it."""
    folder, name = run_naming_an_outside_file(here, "r-escape-run", "secret-run")
    code, _, err = main(monkeypatch, capsys, "run", "tiny", "--run-id", "r-escape-run")
    assert code == 0, err
    assert name not in json.loads((folder / "score" / "stage.json").read_text())["outputs"]


def test_an_intact_copy_is_read(here, monkeypatch, capsys):
    copy_run(here, "tiny", "r-intact")
    result = CliRunner().invoke(app, ["sql", "--run", "r-intact", "--format", "csv",
                                      "SELECT count(*) AS n FROM scores"])
    assert result.exit_code == 0, result.output
    assert result.output.splitlines() == ["n", "12"]


def test_compare_of_a_run_with_no_detections_writes_the_report(here, monkeypatch, capsys):
    """A physical run that detected nothing has no centre-bias rows: the comparison with one
    that has them writes its report (it raised polars' ShapeError)."""
    code, _, err = main(monkeypatch, capsys, "compare", "cam", "blind", "--name", "nothing")
    assert code in (0, None), err
    text = (here / "runs" / "compare-nothing" / "report.md").read_text()
    assert "| cam |" in text and "| blind |" in text


def test_a_campaigns_record_vouches_only_for_its_own_files(tmp_path):
    """`verified_file`: a file as its folder's record promises it (size, sha256), not a link,
    a damaged or unrecorded file, nor a damaged record."""
    from pipeline.io.files import file_records, verified_file

    (tmp_path / "a.duckdb").write_bytes(b"0123456789")
    record = tmp_path / "campaign.json"
    record.write_text(json.dumps({"outputs": file_records(tmp_path, ["a.duckdb"])}))
    assert verified_file(tmp_path, "a.duckdb", "campaign.json") == tmp_path / "a.duckdb"
    (tmp_path / "b.rrd").symlink_to(tmp_path / "a.duckdb")
    with pytest.raises(ValueError, match=r"b\.rrd: not recorded"):
        verified_file(tmp_path, "b.rrd", "campaign.json")
    flip_a_byte(tmp_path / "a.duckdb")
    with pytest.raises(ValueError, match=r"a\.duckdb: not the file .*records"):
        verified_file(tmp_path, "a.duckdb", "campaign.json")
    record.write_text(json.dumps({"outputs": {"a.duckdb": [1]}}))
    with pytest.raises(ValueError, match="not recorded"):
        verified_file(tmp_path, "a.duckdb", "campaign.json")
